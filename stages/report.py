"""The experiment report: a Table-2-style metrics table, an image grid, training curves and index.html.

`build_report(rows, out_dir, title_info=...)` reads finished evaluate results (their `metrics.json`,
`views/`, `path.mp4`) and edit results (`curves.json`) and writes, into `out_dir`:
    table.md, table.csv, table.json    one row per variant (mean ± std over seeds, n), best value marked,
                                       paired difference to a reference row with a bootstrap CI
    scenes/<scene>_<edit>/table.*      the same per scene and edit (only when there are several)
    params/<axis>.png                  each metric against a parameter axis, error bars = std over seeds
    grid.png                           rows: original, ground-truth edit (procedural scenes), variants
    path_strip.png                     camera-path frames at evenly spaced positions, per variant
    curves/<series>.png                training curves of every edited row, one plot per series
    videos/<row>.mp4                   copies of the camera-path videos
    index.html                         everything above, with relative links only
It knows nothing about workflows or the cache: callers (the CLI, `dualnerf run`) resolve the folders.
"""
from __future__ import annotations

import csv
import html
import json
import math
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualnerf.metrics import METRICS, METRICS_FORMAT, METRICS_VERSION, json_value, parse_json_value
from stages import report_statistics as RS
from stages.report_convergence import convergence_html, convergence_summary, write_convergence
from stages.statistics import summarize_over_seeds

GRID_VIEWS = 4
PATH_STRIP_FRAMES = 6
SIMULATED_EDITORS = {"synthetic"}
SIMULATED_ENCODERS = {"proxy"}


class ReportError(ValueError):
    """A report input that cannot be used; the message names the folder/file and what to do."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


@dataclass(frozen=True)
class ReportRow:
    """One evaluated result. Toggles are None for the unedited "Original Scene" row."""

    label: str
    dual_field: bool | None
    annealing: bool | None
    consistency: bool | None
    seed: int | None
    evaluate_dir: Path
    edit_dir: Path | None = None
    scene: str = ""
    edit: str = ""                     # the scene edit id
    params: tuple = ()                 # parameter-axis values of this row: ((axis name, value), ...)

    @property
    def is_original(self) -> bool:
        return self.dual_field is None

    @property
    def variant_key(self) -> tuple:
        return (self.label, self.dual_field, self.annealing, self.consistency, tuple(self.params))


def load_metrics(evaluate_dir: Path) -> dict:
    """Read and check an evaluate result's metrics.json."""
    path = Path(evaluate_dir) / "metrics.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ReportError(f"{path} is missing: {evaluate_dir} is not a finished evaluate result; "
                          f"rerun the workflow (dualnerf run) before building the report.") from None
    except json.JSONDecodeError as err:
        raise ReportError(f"{path} is not valid JSON ({err}); verify the cache (dualnerf cache verify).") from None
    if doc.get("format") != METRICS_FORMAT or doc.get("version") != METRICS_VERSION:
        raise ReportError(f"{path}: expected format {METRICS_FORMAT} v{METRICS_VERSION}, got "
                          f"{doc.get('format')} v{doc.get('version')}; rerun the evaluate stage.")
    return doc


def metric_value(entry: dict | None) -> float:
    """A metrics.json value as a float: null -> nan, the string "inf" -> inf."""
    return math.nan if entry is None else parse_json_value(entry.get("value"))


# ---------------------------------------------------------------------------------------------- table

@dataclass
class TableRow:
    label: str
    toggles: tuple[bool | None, bool | None, bool | None]
    seeds: list[int | None]
    mean: dict[str, float]
    std: dict[str, float]
    best: dict[str, bool]
    params: tuple = ()
    runs: int = 0                               # results behind the row (scenes x edits x seeds)
    n: dict[str, int] = field(default_factory=dict)    # per column: results with a value (not null)


def _column_names(docs: list[dict]) -> list[str]:
    present = {name for doc in docs for name in doc.get("metrics", {})}
    return [name for name in METRICS if name in present]


def _encoder_tags(docs: list[dict], column: str, key: str = "encoder") -> str:
    tags = sorted({doc["metrics"][column].get(key, "?") for doc in docs if column in doc["metrics"]})
    return ", ".join(tags)


def column_header(column: str, docs: list[dict]) -> str:
    info = METRICS[column]
    arrow = "↑" if info.higher_is_better else "↓"
    tag = f" [{_encoder_tags(docs, column)}]" if info.uses_encoder else ""
    tag = f" [{_encoder_tags(docs, column, 'lpips')}]" if info.uses_lpips else tag
    return f"{info.symbol} {arrow}{tag}"


def aggregate(rows: list[ReportRow], docs: list[dict]) -> tuple[list[str], list[TableRow]]:
    """Group rows by variant (Original first, then grid order), mean ± sample std over seeds of each
    seed's mean over scenes and edits (stages/statistics.py), and mark the best mean per column in the
    direction the metric improves."""
    columns = _column_names(docs)
    for column in columns:
        tags = _encoder_tags(docs, column)
        if METRICS[column].uses_encoder and "," in tags:
            raise ReportError(f"the results mix encoders for {METRICS[column].symbol} ({tags}); numbers from "
                              f"different encoders cannot share a column. Evaluate every row with one encoder.")
        if METRICS[column].uses_lpips and "," in _encoder_tags(docs, column, "lpips"):
            raise ReportError(f"the results mix LPIPS backbones for {METRICS[column].symbol}; evaluate every "
                              f"row with one evaluate.lpips_net.")
    groups: dict[tuple, list[int]] = {}
    for i, row in enumerate(rows):
        groups.setdefault(row.variant_key, []).append(i)
    ordered = sorted(groups.items(), key=lambda kv: (not rows[kv[1][0]].is_original, kv[1][0]))
    table = []
    for _, members in ordered:
        first = rows[members[0]]
        mean, std, n = {}, {}, {}
        for column in columns:
            summary = summarize_over_seeds([metric_value(docs[i]["metrics"].get(column)) for i in members],
                                           [rows[i].seed for i in members])
            mean[column], std[column], n[column] = summary.mean, summary.std, summary.n
        table.append(TableRow(first.label, (first.dual_field, first.annealing, first.consistency),
                              list(dict.fromkeys(rows[i].seed for i in members)), mean, std, {},
                              params=tuple(first.params), runs=len(members), n=n))
    for column in columns:
        means = np.array([r.mean[column] for r in table])
        valid = ~np.isnan(means)
        if not valid.any():
            best_value = None
        else:
            best_value = np.max(means[valid]) if METRICS[column].higher_is_better else np.min(means[valid])
        for r in table:
            value = r.mean[column]
            r.best[column] = best_value is not None and not math.isnan(value) and \
                math.isclose(value, best_value, rel_tol=1e-12, abs_tol=1e-12)
    return columns, table


def _digits(column: str) -> int:
    return 2 if "psnr" in column else 4


def format_cell(row: TableRow, column: str) -> str:
    mean, std = row.mean[column], row.std[column]
    if math.isnan(mean):
        return "n/a"
    if math.isinf(mean):
        return "∞" if mean > 0 else "-∞"
    text = f"{mean:.{_digits(column)}f}"
    if len(row.seeds) > 1 and not math.isnan(std):
        text += f" ± {std:.{_digits(column)}f}"
    return text


def _mark(flag: bool | None) -> str:
    return "" if flag is None else ("✓" if flag else "✗")


def write_tables(columns: list[str], table: list[TableRow], docs: list[dict], out_dir: Path,
                 paired: dict | None = None, reference: str | None = None) -> dict:
    """table.md/csv/json; `paired` ({(label, params): {column: PairedDifference}}, from
    report_statistics.paired_differences) adds the difference-to-`reference` columns."""
    paired = paired or {}
    headers = [column_header(c, docs) for c in columns]
    lines = ["| Variant | DF | SA | CCI | seeds | n | " + " | ".join(headers) + " |",
             "|---|:-:|:-:|:-:|---|---:|" + "---:|" * len(columns)]
    for row in table:
        label = RS.display_label(row.label, row.params, original=row.toggles[0] is None)
        seeds = ", ".join("-" if s is None else str(s) for s in row.seeds)
        cells = [f"**{format_cell(row, c)}**" if row.best[c] else format_cell(row, c) for c in columns]
        lines.append(f"| {label} | " + " | ".join(_mark(t) for t in row.toggles) + f" | {seeds} | {row.runs} | "
                     + " | ".join(cells) + " |")
    lines.append("")
    lines.append("Mean ± sample std over seeds (of each seed's mean over scenes and edits); n: results per "
                 "row. Best value per column in bold (↑ higher is better, ↓ lower). Bracketed tags name the "
                 "encoder behind CLIP-space numbers; `proxy` is a weight-free stand-in, NOT CLIP.")
    if paired:
        lines += RS.markdown_section(table, columns, headers, paired, reference)
    (out_dir / "table.md").write_text("\n".join(lines) + "\n")

    with open(out_dir / "table.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        head = ["variant", "dual_field", "annealing", "consistency", "seeds", "params", "runs"]
        for column in columns:
            head += [f"{column}_mean", f"{column}_std", f"{column}_n", f"{column}_best"]
            if paired:
                head += [f"{column}_diff", f"{column}_ci_low", f"{column}_ci_high", f"{column}_ci_contains_zero"]
        writer.writerow(head)
        for row in table:
            record = [row.label, *("" if t is None else int(t) for t in row.toggles),
                      " ".join("" if s is None else str(s) for s in row.seeds),
                      " ".join(f"{k}={v}" for k, v in row.params), row.runs]
            for column in columns:
                record += [_csv_number(row.mean[column]), _csv_number(row.std[column]), row.n[column],
                           int(row.best[column])]
                if paired:
                    diff = paired.get(RS.row_key(row), {}).get(column)
                    record += ["", "", "", ""] if diff is None else [
                        _csv_number(diff.mean), _csv_number(diff.low), _csv_number(diff.high),
                        "" if diff.contains_zero is None else int(diff.contains_zero)]
            writer.writerow(record)

    doc = {
        "columns": [{"name": c, "symbol": METRICS[c].symbol, "higher_is_better": METRICS[c].higher_is_better,
                     "encoder": _encoder_tags(docs, c) if METRICS[c].uses_encoder else None,
                     "lpips": _encoder_tags(docs, c, "lpips") if METRICS[c].uses_lpips else None} for c in columns],
        "rows": [{"label": r.label, "dual_field": r.toggles[0], "annealing": r.toggles[1],
                  "consistency": r.toggles[2], "seeds": r.seeds, "params": [list(p) for p in r.params],
                  "runs": r.runs,
                  "metrics": {c: {"mean": json_value(r.mean[c]), "std": json_value(r.std[c]),
                                  "n": r.n[c], "best": r.best[c],
                                  **({"paired": RS.diff_json(paired[RS.row_key(r)][c])}
                                     if c in paired.get(RS.row_key(r), {}) else {})} for c in columns}}
                 for r in table],
    }
    if paired:
        doc["paired"] = RS.bootstrap_record(reference)
    (out_dir / "table.json").write_text(json.dumps(doc, indent=1))
    return doc


def _csv_number(value: float) -> str:
    if math.isnan(value):
        return ""
    return "inf" if math.isinf(value) else repr(value)


# ---------------------------------------------------------------------------------------------- images

def _read_rgb(path: Path) -> np.ndarray | None:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if image is None else image[..., ::-1]


def _first_per_variant(rows: list[ReportRow]) -> list[ReportRow]:
    seen, out = set(), []
    for row in rows:
        if not row.is_original and row.variant_key not in seen:
            seen.add(row.variant_key)
            out.append(row)
    return out


def _plot_grid(grid: list[tuple[str, list[np.ndarray | None]]], titles: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(grid), len(titles), figsize=(2.2 * len(titles), 2.0 * len(grid)),
                             squeeze=False)
    for r, (label, images) in enumerate(grid):
        for c, image in enumerate(images):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if image is None:
                ax.text(0.5, 0.5, "missing", ha="center", va="center", transform=ax.transAxes)
            else:
                ax.imshow(image)
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
            if r == 0:
                ax.set_title(titles[c], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_image_grid(rows: list[ReportRow], docs: list[dict], path: Path) -> list[str] | None:
    """A grid of fixed views (columns) for the original scene, the ground-truth edit where the scene
    has one, and the first seed of every edited variant. Returns the row labels, or None without views."""
    names = None
    for doc in docs:
        listed = doc.get("views", {}).get("names", [])
        names = listed if names is None else [n for n in names if n in listed]
    names = (names or [])[:GRID_VIEWS]
    if not names:
        return None
    source = rows[0].evaluate_dir
    grid: list[tuple[str, list[np.ndarray | None]]] = [
        ("Original", [_read_rgb(source / "views" / "original" / n) for n in names])]
    gt = [_read_rgb(source / "views" / "gt_edit" / n) for n in names]
    if any(image is not None for image in gt):
        grid.append(("GT edit", gt))
    for row in _first_per_variant(rows):
        grid.append((RS.display_label(row.label, row.params),
                     [_read_rgb(row.evaluate_dir / "views" / "edited" / n) for n in names]))
    _plot_grid(grid, names, path)
    return [label for label, _ in grid]


def write_path_strip(rows: list[ReportRow], path: Path) -> list[str] | None:
    """Camera-path frames at evenly spaced positions (columns) for the original scene and the first seed
    of every variant: the videos' content as a still, for print and for a quick look."""
    source = rows[0].evaluate_dir / "frames" / "original"
    count = len(list(source.glob("*.png"))) if source.is_dir() else 0
    if count == 0:
        return None
    picks = sorted({int(i) for i in np.round(np.linspace(0, count - 1, min(PATH_STRIP_FRAMES, count)))})
    names = [f"{i:04d}.png" for i in picks]
    grid = [("Original", [_read_rgb(source / n) for n in names])]
    for row in _first_per_variant(rows):
        grid.append((RS.display_label(row.label, row.params),
                     [_read_rgb(row.evaluate_dir / "frames" / "edited" / n) for n in names]))
    _plot_grid(grid, [f"frame {i}" for i in picks], path)
    return [label for label, _ in grid]


# ---------------------------------------------------------------------------------------------- curves

def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "row"


# Figures of the report: title -> per-iteration series of the edit stage's curves.json drawn in it.
CURVE_FIGURES = {
    "loss": ("loss",),
    "psnr": ("psnr",),
    "blend_weights": ("blend_density", "blend_color"),
    "sa_temperature": ("temperature",),
    "sa_acceptance_rate": ("sa_acceptance_rate",),
    "cci_weights": ("cci_weight_min", "cci_weight_max"),
}


def load_curves(edit_dir: Path) -> dict[str, tuple[list[float], list[float | None]]]:
    """Series from an edit result's curves.json (columns keyed by name, with "iteration" as the x axis
    and an "updates" table of view updates): {series: (iterations, values)}. SA acceptances become the
    running acceptance rate over the updates that drew a retreat (accepted not null)."""
    path = Path(edit_dir) / "curves.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except json.JSONDecodeError as err:
        raise ReportError(f"{path} is not valid JSON ({err}); verify the cache (dualnerf cache verify).") from None
    iterations = doc.get("iteration", [])
    curves = {}
    for series in {name for names in CURVE_FIGURES.values() for name in names}:
        values = doc.get(series)
        if isinstance(values, list) and len(values) == len(iterations) and any(v is not None for v in values):
            curves[series] = (iterations, values)
    updates = doc.get("updates", {})
    drawn = [(it, bool(acc)) for it, acc in zip(updates.get("iteration", []), updates.get("accepted", []))
             if acc is not None]
    if drawn:
        accepted = np.cumsum([acc for _, acc in drawn])
        curves["sa_acceptance_rate"] = ([it for it, _ in drawn],
                                        (accepted / np.arange(1, len(drawn) + 1)).tolist())
    return curves


def write_curves(rows: list[ReportRow], out_dir: Path) -> list[str]:
    """One PNG per figure of CURVE_FIGURES, with a line per edited row (and per series in the figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loaded = []
    for row in rows:
        if row.edit_dir is not None:
            name = row.label if row.seed is None else f"{row.label} (seed {row.seed})"
            loaded.append((name, load_curves(row.edit_dir)))
    written = []
    for title, names in CURVE_FIGURES.items():
        lines = [(f"{row} {series}" if len(names) > 1 else row, *curves[series])
                 for row, curves in loaded for series in names if series in curves]
        if not lines:
            continue
        (out_dir / "curves").mkdir(exist_ok=True)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        for label, steps, values in lines:
            values = [math.nan if v is None else v for v in values]
            style = "--" if label.endswith(("blend_color", "cci_weight_max")) else "-"
            ax.plot(steps, values, style, label=label, marker="o" if len(steps) < 30 else None, markersize=3)
        ax.set_xlabel("iteration")
        ax.set_title(title.replace("_", " "))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        rel = f"curves/{title}.png"
        fig.savefig(out_dir / rel, dpi=90)
        plt.close(fig)
        written.append(rel)
    return written


# ---------------------------------------------------------------------------------------------- html

def _identities(docs: list[dict], key: str) -> list[str]:
    found = set()
    for doc in docs:
        entry = doc.get(key) or {}
        if entry.get("kind"):
            found.add(entry["kind"])
    return sorted(found)


def _title_rows(docs: list[dict], title_info: dict) -> list[tuple[str, str]]:
    editors = _identities(docs, "editor") or ["none (no edited rows)"]
    encoders = _identities(docs, "encoder") or ["unknown"]
    editor_text = ", ".join(f"{e} (InstructPix2Pix EMULATOR, not IP2P)" if e in SIMULATED_EDITORS else e
                            for e in editors)
    encoder_text = ", ".join(f"{e} (weight-free stand-in, NOT CLIP)" if e in SIMULATED_ENCODERS else e
                             for e in encoders)
    rows = [(str(k), str(v)) for k, v in title_info.items()]
    lpips = sorted({(doc.get("lpips") or {}).get("tag") for doc in docs} - {None})
    return rows + [("editor", editor_text), ("encoder", encoder_text)] + \
        ([("LPIPS metrics", ", ".join(lpips) + " (pretrained, v0.1 linear layers)")] if lpips else [])


def metrics_table_html(columns, table, docs) -> list[str]:
    esc = html.escape
    parts = ["<table><tr><th>Variant</th><th>DF</th><th>SA</th><th>CCI</th><th>seeds</th><th>n</th>"]
    parts += [f"<th>{esc(column_header(c, docs))}</th>" for c in columns]
    parts.append("</tr>")
    for row in table:
        label = RS.display_label(row.label, row.params, original=row.toggles[0] is None)
        seeds = ", ".join("-" if s is None else str(s) for s in row.seeds)
        parts.append(f"<tr><td style='text-align:left'>{esc(label)}</td>"
                     + "".join(f"<td style='text-align:center'>{_mark(t)}</td>" for t in row.toggles)
                     + f"<td>{esc(seeds)}</td><td>{row.runs}</td>")
        for c in columns:
            cls = " class='best'" if row.best[c] else ""
            parts.append(f"<td{cls}>{esc(format_cell(row, c))}</td>")
        parts.append("</tr>")
    parts.append("</table>")
    return parts


def write_html(out_dir: Path, *, title_rows, columns, table, docs, grid_labels, strip_labels, curves,
               videos, sections=()) -> Path:
    """index.html; `sections` are ready HTML fragments (statistics) placed after the metrics table."""
    esc = html.escape
    parts = ["<!DOCTYPE html>", "<html><head><meta charset='utf-8'><title>DualNeRF report</title>",
             ("<style>body{font-family:sans-serif;margin:2em;max-width:1200px}table{border-collapse:collapse}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}th{background:#eee}"
             ".best{font-weight:bold;background:#e6f4e6}.warn{color:#a00;font-weight:bold}.ns{color:#777}.paired td{white-space:nowrap}"
             "img{max-width:100%}</style></head><body>"), "<h1>DualNeRF experiment report</h1>",
             "<table class='title'>"]
    for key, value in title_rows:
        cls = " class='warn'" if ("EMULATOR" in value or "NOT CLIP" in value) else ""
        parts.append(f"<tr><th>{esc(key)}</th><td{cls} style='text-align:left'>{esc(value)}</td></tr>")
    parts.append("</table>")
    parts.append("<h2>Metrics</h2>")
    parts += metrics_table_html(columns, table, docs)
    parts.append("<p>Mean ± sample std over seeds; n: results per row. Best value per column highlighted. "
                 "Downloads: <a href='table.md'>table.md</a>, "
                 "<a href='table.csv'>table.csv</a>, <a href='table.json'>table.json</a>. Metric "
                 "definitions: docs/metrics.md in the repository.</p>")
    parts += list(sections)
    if grid_labels:
        parts.append(f"<h2>Views</h2><p>Rows: {esc(', '.join(grid_labels))}.</p>"
                     "<img src='grid.png' alt='image grid'>")
    if strip_labels:
        parts.append(f"<h2>Camera path</h2><p>Rows: {esc(', '.join(strip_labels))}.</p>"
                     "<img src='path_strip.png' alt='camera path frames'>")
    if curves:
        parts.append("<h2>Training curves</h2>")
        parts += [f"<img src='{esc(rel)}' alt='{esc(rel)}'>" for rel in curves]
    if videos:
        parts.append("<h2>Camera-path videos</h2>")
        for label, rel in videos:
            parts.append(f"<figure><figcaption>{esc(label)}</figcaption><video controls loop "
                         f"src='{esc(rel)}' width='480'></video><br><a href='{esc(rel)}'>{esc(rel)}</a>"
                         f"</figure>")
    parts.append("</body></html>")
    path = out_dir / "index.html"
    path.write_text("\n".join(parts) + "\n")
    return path


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
    pairs = RS.scene_edits(rows)
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
        rel = f"scenes/{_slug(f'{scene}_{edit}')}"
        (out_dir / rel).mkdir(parents=True, exist_ok=True)
        doc = write_tables(columns, table, sub_docs, out_dir / rel, paired, label)
        written.append((scene, edit, rel, columns, table, sub_docs, paired, label, doc))
    return written


def _statistics_html(columns, table, docs, paired, reference, per_scene, param_plots) -> list[str]:
    esc = html.escape
    parts = []
    if paired:
        headers = [column_header(c, docs) for c in columns]
        parts.append(RS.html_section(table, columns, headers, paired, reference))
    if param_plots:
        parts.append("<h2>Parameter axes</h2><p>Each metric against the parameter: mean ± std over seeds "
                     "(error bars), averaged over scenes and edits.</p>")
        parts += [f"<img src='{esc(rel)}' alt='{esc(rel)}'>" for rel in param_plots]
    if per_scene:
        parts.append("<h2>Per scene and edit</h2>")
        for scene, edit, rel, sub_columns, sub_table, sub_docs, sub_paired, label, _ in per_scene:
            parts.append(f"<h3>{esc(scene)} / {esc(edit)}</h3>")
            parts += metrics_table_html(sub_columns, sub_table, sub_docs)
            if sub_paired:
                headers = [column_header(c, sub_docs) for c in sub_columns]
                parts.append(RS.html_section(sub_table, sub_columns, headers, sub_paired, label)
                             .replace("<h2>", "<h4>").replace("</h2>", "</h4>"))
            parts.append(f"<p>Downloads: <a href='{esc(rel)}/table.md'>table.md</a>, "
                         f"<a href='{esc(rel)}/table.csv'>table.csv</a>, "
                         f"<a href='{esc(rel)}/table.json'>table.json</a>.</p>")
    return parts


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
    per_scene = _per_scene_tables(rows, docs, reference, out_dir)
    param_plots = RS.write_parameter_plots(table, columns, out_dir, reference_label)
    scene_edits = RS.scene_edits(rows)
    shown = [i for i, r in enumerate(rows) if (r.scene, r.edit) == scene_edits[0]]   # images: one scene
    grid_labels = write_image_grid([rows[i] for i in shown], [docs[i] for i in shown], out_dir / "grid.png")
    strip_labels = write_path_strip([rows[i] for i in shown], out_dir / "path_strip.png")
    curves = write_curves(rows, out_dir) + write_convergence(rows, out_dir)
    convergence = convergence_summary(rows)
    videos = []
    for row in rows:
        source = row.evaluate_dir / "path.mp4"
        if source.exists():
            name = RS.display_label(row.label, row.params)
            name += f" {row.scene}/{row.edit}" if len(scene_edits) > 1 else ""
            name += "" if row.seed is None else f" seed {row.seed}"
            rel = f"videos/{_slug(name)}.mp4"
            (out_dir / "videos").mkdir(exist_ok=True)
            shutil.copyfile(source, out_dir / rel)
            videos.append((name, rel))
    title_rows = _title_rows(docs, title_info)
    (out_dir / "report.json").write_text(json.dumps({
        "title": dict(title_rows), "table": table_doc, "grid_rows": grid_labels,
        "per_scene": [{"scene": sc, "edit": ed, "folder": rel, "table": doc}
                      for sc, ed, rel, *_, doc in per_scene], "parameter_plots": param_plots,
        "path_strip_rows": strip_labels, "curves": curves, "convergence": convergence,
        "videos": [rel for _, rel in videos],
        "rows": [{"label": r.label, "seed": r.seed, "scene": r.scene, "edit": r.edit,
                  "params": [list(p) for p in r.params], "evaluate_dir": str(r.evaluate_dir),
                  "edit_dir": None if r.edit_dir is None else str(r.edit_dir)} for r in rows]}, indent=1))
    return write_html(out_dir, title_rows=title_rows, columns=columns, table=table, docs=docs,
                      grid_labels=grid_labels, strip_labels=strip_labels, curves=curves, videos=videos,
                      sections=[*_statistics_html(columns, table, docs, paired, reference_label, per_scene,
                                                  param_plots), *convergence_html(convergence)])
