"""The report's statistics sections: paired differences to a reference row, per-scene tables, parameter
plots. The numbers come from stages/statistics.py; this module groups report rows, formats and draws.

Rows with equal (label, params) are one table row; (scene, edit, seed) is the pairing unit.
"""
from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from dualnerf.metrics import METRICS, json_value
from stages import statistics as S

DEFAULT_REFERENCE = "baseline"          # the single-field Instruct-NeRF2NeRF row of the shipped workflows


def row_key(row) -> tuple:
    """What makes a table row: the method label and the parameter-axis values (ReportRow or TableRow)."""
    return (row.label, tuple(row.params))


def display_label(label: str, params: tuple, *, original: bool = False) -> str:
    text = "Original Scene" if original else label
    return text + (" [" + ", ".join(f"{k}={v}" for k, v in params) + "]" if params else "")


def scene_edits(rows) -> list[tuple[str, str]]:
    """The distinct (scene, edit) pairs of the rows, in first-seen order."""
    return list(dict.fromkeys((row.scene, row.edit) for row in rows))


def _unit_values(rows, docs, column: str, metric_value) -> dict[tuple, dict]:
    """{table-row key: {(scene, edit, seed): value}}; a repeated unit in one table row is an error."""
    out: dict[tuple, dict] = {}
    for row, doc in zip(rows, docs):
        units = out.setdefault(row_key(row), {})
        unit = (row.scene, row.edit, row.seed)
        if unit in units:
            raise ValueError(f"two results for row {display_label(*row_key(row))} at scene {row.scene!r}, "
                             f"edit {row.edit!r}, seed {row.seed}: give the cells distinct labels or params.")
        units[unit] = metric_value(doc["metrics"].get(column))
    return out


def paired_differences(rows, docs, table, columns, reference: str, metric_value) -> dict:
    """{table-row key: {column: PairedDifference}} against the rows labelled `reference`. Where several
    parameter settings carry the reference label, each row pairs with the one of equal params."""
    ref_keys = [key for key in (row_key(r) for r in table) if key[0] == reference]
    out: dict[tuple, dict] = {}
    for column in columns:
        values = _unit_values(rows, docs, column, metric_value)
        for trow in table:
            key = row_key(trow)
            if key in ref_keys:
                continue
            if len(ref_keys) == 1:
                ref = ref_keys[0]
            elif (reference, key[1]) in ref_keys:
                ref = (reference, key[1])
            else:
                continue
            out.setdefault(key, {})[column] = S.paired_difference(values[key], values[ref])
    return out


def bootstrap_record(reference: str) -> dict:
    return {"reference": reference, "method": f"{S.BOOTSTRAP_METHOD} bootstrap of the mean paired difference",
            "unit": ["scene", "edit", "seed"], "resamples": S.BOOTSTRAP_RESAMPLES, "level": S.BOOTSTRAP_LEVEL,
            "seed": S.BOOTSTRAP_SEED, "generator": "numpy.random.default_rng(seed), fresh per comparison",
            "min_pairs": S.MIN_PAIRS}


def diff_json(diff: S.PairedDifference) -> dict:
    return {"mean": json_value(diff.mean), "ci_low": json_value(diff.low), "ci_high": json_value(diff.high),
            "n_pairs": diff.n_pairs, "ci_contains_zero": diff.contains_zero,
            "unpaired": [list(u) for u in diff.unpaired],
            "unpaired_reference": [list(u) for u in diff.unpaired_reference],
            "non_finite": [list(u) for u in diff.non_finite]}


def format_diff(diff: S.PairedDifference | None, column: str) -> str:
    """'+0.0400 [+0.0200, +0.0600]', with † when the interval contains 0; 'n/a' without pairs."""
    if diff is None or math.isnan(diff.mean):
        return "n/a"
    digits = 2 if "psnr" in column else 4
    text = f"{diff.mean:+.{digits}f}"
    if diff.contains_zero is None:
        return text + f" (n={diff.n_pairs}, no CI)"
    text += f" [{diff.low:+.{digits}f}, {diff.high:+.{digits}f}]"
    return text + " †" if diff.contains_zero else text


def _unpaired_note(paired: dict) -> list[str]:
    notes = []
    for key, per_column in paired.items():
        first = next(iter(per_column.values()))
        if first.unpaired or first.unpaired_reference:
            notes.append(f"{display_label(*key)}: {len(first.unpaired)} unit(s) without a reference run, "
                         f"{len(first.unpaired_reference)} reference unit(s) it did not run "
                         f"({', '.join('/'.join(str(x) for x in u) for u in first.unpaired[:3])}"
                         f"{'…' if len(first.unpaired) > 3 else ''}); only shared units are compared.")
    return notes


def caption(reference: str) -> str:
    return (f"Mean paired difference (row − {reference}) over the (scene, edit, seed) units both rows ran, "
            f"with a {S.BOOTSTRAP_LEVEL:.0%} {S.BOOTSTRAP_METHOD} bootstrap interval (B = "
            f"{S.BOOTSTRAP_RESAMPLES}, numpy default_rng({S.BOOTSTRAP_SEED})). † the interval contains 0: "
            f"no difference shown at this n. With few units the bootstrap interval is too narrow "
            f"(3 seeds give at most 10 distinct resamples); read it as a screen, not a test.")


def markdown_section(table, columns, headers, paired: dict, reference: str) -> list[str]:
    lines = ["", f"## Difference to `{reference}`", "",
             "| Variant | pairs | " + " | ".join(f"Δ {h}" for h in headers) + " |",
             "|---|---:|" + "---:|" * len(columns)]
    for trow in table:
        key = row_key(trow)
        if key not in paired:
            continue
        diffs = paired[key]
        pairs = max(d.n_pairs for d in diffs.values())
        lines.append(f"| {display_label(*key, original=trow.toggles[0] is None)} | {pairs} | "
                     + " | ".join(format_diff(diffs.get(c), c) for c in columns) + " |")
    lines += ["", caption(reference)] + [f"- {note}" for note in _unpaired_note(paired)]
    return lines


def html_section(table, columns, headers, paired: dict, reference: str) -> str:
    esc = html.escape
    parts = [f"<h2>Difference to {esc(reference)}</h2><table class='paired'><tr><th>Variant</th><th>pairs</th>"]
    parts += [f"<th>Δ {esc(h)}</th>" for h in headers]
    parts.append("</tr>")
    for trow in table:
        key = row_key(trow)
        if key not in paired:
            continue
        diffs = paired[key]
        parts.append(f"<tr><td style='text-align:left'>{esc(display_label(*key, original=trow.toggles[0] is None))}"
                     f"</td><td>{max(d.n_pairs for d in diffs.values())}</td>")
        for c in columns:
            diff = diffs.get(c)
            cls = " class='ns'" if diff is not None and diff.contains_zero else ""
            parts.append(f"<td{cls}>{esc(format_diff(diff, c))}</td>")
        parts.append("</tr>")
    parts.append(f"</table><p>{esc(caption(reference))}</p>")
    if all(d.n_pairs < 2 for diffs in paired.values() for d in diffs.values()):
        parts.append("<p class='warn'>One unit per comparison: these differences say nothing about seed noise. "
                     "Run more seeds (e.g. --set seeds=[0,1,2]; each adds one run of every row) for "
                     "intervals.</p>")
    parts += [f"<p class='note'>{esc(note)}</p>" for note in _unpaired_note(paired)]
    return "".join(parts)


# ---------------------------------------------------------------------------------------------- plots

def parameter_keys(table) -> list[str]:
    return list(dict.fromkeys(k for trow in table for k, _ in trow.params))


def _axis_value(value):
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def write_parameter_plots(table, columns, out_dir: Path, reference: str | None = None) -> list[str]:
    """One figure per parameter axis: each metric (a panel) against the parameter's value, mean ± std over
    seeds as error bars, one line per method label and setting of the other axes. A `reference` row that
    does not vary along the axis is drawn as a dashed level with a ±std band."""
    keys = parameter_keys(table)
    if not keys or not columns:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for key in keys:
        series: dict[tuple, list] = {}
        for trow in table:
            params = dict(trow.params)
            if key not in params:
                continue
            rest = tuple((k, v) for k, v in trow.params if k != key)
            series.setdefault((trow.label, rest), []).append((params[key], trow))
        values = list(dict.fromkeys(v for points in series.values() for v, _ in points))
        levels = [t for t in table if t.label == reference and key not in dict(t.params)]
        numeric = all(_axis_value(v) is not None for v in values)
        position = {v: (_axis_value(v) if numeric else i) for i, v in enumerate(values)}
        width = min(4, len(columns))
        rows_n = math.ceil(len(columns) / width)
        fig, axes = plt.subplots(rows_n, width, figsize=(3.6 * width, 2.9 * rows_n), squeeze=False)
        for ax, column in zip(axes.flat, columns):
            for (label, rest), points in series.items():
                points = sorted(points, key=lambda p: position[p[0]])
                x = [position[v] for v, _ in points]
                y = [t.mean[column] for _, t in points]
                err = [0.0 if math.isnan(t.std[column]) else t.std[column] for _, t in points]
                if all(not np.isfinite(v) for v in y):
                    continue
                ax.errorbar(x, y, yerr=err, marker="o", markersize=3, capsize=3,
                            label=display_label(label, rest))
            if len(levels) == 1 and np.isfinite(levels[0].mean[column]):
                level, spread = levels[0].mean[column], levels[0].std[column]
                ax.axhline(level, linestyle="--", color="0.4", label=f"{reference} (reference)")
                if np.isfinite(spread):
                    ax.axhspan(level - spread, level + spread, color="0.6", alpha=0.2)
            info = METRICS[column]
            ax.set_title(f"{info.symbol} {'↑' if info.higher_is_better else '↓'}", fontsize=9)
            ax.set_xlabel(key, fontsize=8)
            if numeric and len(values) > 2 and min(position.values()) > 0 and \
                    max(position.values()) / min(position.values()) >= 10:
                ax.set_xscale("log")
                ax.minorticks_off()
            # Ticks at the grid's values, written as given in the workflow.
            ax.set_xticks([position[v] for v in values], [str(v) for v in values], fontsize=7)
            ax.grid(alpha=0.3)
        for ax in list(axes.flat)[len(columns):]:
            ax.axis("off")
        handles, labels = axes.flat[0].get_legend_handles_labels()
        if handles:
            fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=7)
        fig.suptitle(f"metrics against {key} (mean ± std over seeds)", fontsize=10)
        fig.tight_layout(rect=(0, 0.08 if handles else 0, 1, 0.95))
        (out_dir / "params").mkdir(exist_ok=True)
        rel = f"params/{_slug(key)}.png"
        fig.savefig(out_dir / rel, dpi=90)
        plt.close(fig)
        written.append(rel)
    return written


def _slug(text: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "param"
