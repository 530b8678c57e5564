"""The experiment report: a Table-2-style metrics table, an image grid, training curves and index.html.

`build_report(rows, out_dir, title_info=...)` reads finished evaluate results (their `metrics.json`,
`views/`, `path.mp4`) and edit results (`curves.json`) and writes, into `out_dir`:
    table.md, table.csv, table.json    one row per method (mean ± std over seeds, n), best value marked,
                                       paired difference to a reference row with a bootstrap CI
    scenes/<scene>_<edit>/table.*      the same per scene and edit (only when there are several)
    joint_psnr.png                     in-mask vs outside-mask PSNR per row and seed (experiments/report/joint.py)
                                       table.md and index.html also hold each component's effect against
                                       the row without it per failure-mode setting (components.py),
                                       CCI's precision/recall at flagging
                                       the emulator's failed calls (flagging.py) and the metrics that see
                                       the ground truth
    params/<axis>.png                  each metric against a parameter axis, error bars = std over seeds
    grid.png                           rows: original, ground-truth edit (procedural scenes), methods
    path_strip.png                     camera-path frames at evenly spaced positions, per method
    curves/<series>.png                training curves of every edited row, one plot per series
    videos/<row>.mp4                   copies of the camera-path videos
    index.html                         everything above, with relative links only
It knows nothing about workflows or the cache: callers (the CLI, `dualnerf run`) resolve the folders.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from experiments.report import components as CE
from experiments.report import differences as RS
from experiments.report import flagging as FL
from experiments.report import joint as J
from experiments.report.convergence import convergence_html, convergence_summary, write_convergence
from experiments.report.curves import CURVE_FIGURES, load_curves, write_curves
from experiments.report.images import write_image_grid, write_path_strip
from experiments.report.page import metrics_table_html, statistics_html, title_rows, write_html
from experiments.report.parameter_plots import write_parameter_plots
from experiments.report.rows import (
    ReportError,
    ReportRow,
    display_label,
    load_metrics,
    metric_value,
    scene_edits,
    slug,
)
from experiments.report.tables import TableRow, aggregate, column_header, format_cell, write_tables
from stages import layout

__all__ = ["CURVE_FIGURES", "ReportError", "ReportRow", "TableRow", "aggregate", "build_report", "column_header",
           "format_cell", "load_curves", "load_metrics", "metric_value", "metrics_table_html", "write_tables"]


def _paired(rows, docs, table, columns, reference: str | None) -> tuple[dict, str]:
    """Paired differences to the reference label; {} when the default reference is absent."""
    label = reference or RS.DEFAULT_REFERENCE
    if label not in {r.label for r in table}:
        if reference is None:
            return {}, label
        raise ReportError(f"reference row {reference!r} is not among the report's rows "
                          f"({', '.join(sorted({r.label for r in table}))}); pass one of those labels.")
    try:
        return RS.paired_differences(rows, docs, table, columns, label, metric_value), label
    except ValueError as err:
        raise ReportError(f"report: {err}") from None


def _per_scene_tables(rows, docs, reference: str | None, out_dir: Path) -> list[tuple]:
    """With several (scene, edit) pairs: each one's table (and differences) in scenes/<scene>_<edit>/."""
    pairs = scene_edits(rows)
    if len(pairs) < 2:
        return []
    written = []
    for scene, edit in pairs:
        members = [i for i, r in enumerate(rows) if (r.scene, r.edit) == (scene, edit)]
        sub_rows, sub_docs = [rows[i] for i in members], [docs[i] for i in members]
        columns, table = aggregate(sub_rows, sub_docs)
        if reference is not None and reference not in {r.label for r in table}:
            paired, label = {}, reference                   # this scene did not run the reference
        else:
            paired, label = _paired(sub_rows, sub_docs, table, columns, reference)
        rel = f"scenes/{slug(f'{scene}_{edit}')}"
        (out_dir / rel).mkdir(parents=True, exist_ok=True)
        doc = write_tables(columns, table, sub_docs, out_dir / rel, paired, label)
        effects = CE.component_effects(sub_rows, sub_docs, table, columns)
        if effects:
            with open(out_dir / rel / "table.md", "a") as handle:
                handle.write("\n".join(CE.markdown_section(effects)) + "\n")
        written.append((scene, edit, rel, columns, table, sub_docs, paired, label, doc))
    return written


def build_report(rows: list[ReportRow], out_dir: Path, *, title_info: dict, reference: str | None = None) -> Path:
    """Write the report for `rows` (Original row first if present) into `out_dir`; returns index.html.
    `reference`: the row label that differences are taken to (default "baseline" where present)."""
    if not rows:
        raise ReportError("nothing to report: no evaluate results were given; run the workflow first.")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = sorted(rows, key=lambda r: not r.is_original)          # stable: grid order kept
    docs = [load_metrics(row.evaluate_dir) for row in rows]
    columns, table = aggregate(rows, docs)
    paired, reference_label = _paired(rows, docs, table, columns, reference)
    table_doc = write_tables(columns, table, docs, out_dir, paired, reference_label)
    flag_entries = FL.flagging_rows(rows, table)
    gt_entries = J.ground_truth_metrics(rows, docs)
    effects = CE.component_effects(rows, docs, table, columns)
    with open(out_dir / "table.md", "a") as handle:
        handle.write("\n".join(CE.markdown_section(effects) + FL.markdown_section(flag_entries)
                               + J.ground_truth_markdown(gt_entries)) + "\n")
    scatter = J.write_joint_scatter(rows, docs, out_dir)
    per_scene = _per_scene_tables(rows, docs, reference, out_dir)
    param_plots = write_parameter_plots(table, columns, out_dir, reference_label)
    pairs = scene_edits(rows)
    shown = [i for i, r in enumerate(rows) if (r.scene, r.edit) == pairs[0]]   # images: one scene
    grid_labels = write_image_grid([rows[i] for i in shown], [docs[i] for i in shown], out_dir / "grid.png")
    strip_labels = write_path_strip([rows[i] for i in shown], out_dir / "path_strip.png")
    curves = write_curves(rows, out_dir) + write_convergence(rows, out_dir)
    convergence = convergence_summary(rows)
    videos = []
    for row in rows:
        source = row.evaluate_dir / layout.PATH_VIDEO
        if source.exists():
            name = display_label(row.label, row.params)
            name += f" {row.scene}/{row.edit}" if len(pairs) > 1 else ""
            name += "" if row.seed is None else f" seed {row.seed}"
            rel = f"videos/{slug(name)}.mp4"
            (out_dir / "videos").mkdir(exist_ok=True)
            shutil.copyfile(source, out_dir / rel)
            videos.append((name, rel))
    title = title_rows(docs, title_info)
    (out_dir / "report.json").write_text(json.dumps({
        "title": dict(title), "table": table_doc, "grid_rows": grid_labels,
        "per_scene": [{"scene": sc, "edit": ed, "folder": rel, "table": doc}
                      for sc, ed, rel, *_, doc in per_scene], "parameter_plots": param_plots,
        "path_strip_rows": strip_labels, "curves": curves, "convergence": convergence,
        "videos": [rel for _, rel in videos], "joint_scatter": scatter, "cci_flagging": flag_entries,
        "component_effects": CE.entries_json(effects),
        "sees_ground_truth": gt_entries,
        "rows": [{"label": r.label, "seed": r.seed, "scene": r.scene, "edit": r.edit,
                  "params": [list(p) for p in r.params], "evaluate_key": Path(r.evaluate_dir).name,
                  "edit_key": None if r.edit_dir is None else Path(r.edit_dir).name} for r in rows]}, indent=1))
    stats = statistics_html(columns, table, docs, paired, reference_label, per_scene, param_plots)
    first = 1 if paired else 0                                   # after the differences to the reference
    joint = [(f"<h2>Edit and background together</h2><img src='{scatter}' alt='in-mask vs outside-mask PSNR'>"
             f"<p>{J.SCATTER_CAPTION}</p>")] if scatter else []
    joint += [CE.html_section(effects), FL.html_section(flag_entries), J.ground_truth_html(gt_entries)]
    return write_html(out_dir, title_rows=title, columns=columns, table=table, docs=docs,
                      grid_labels=grid_labels, strip_labels=strip_labels, curves=curves, videos=videos,
                      sections=[*stats[:first], *joint, *stats[first:], *convergence_html(convergence)])
