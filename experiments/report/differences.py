"""The report's statistics sections: paired differences to a reference row (Markdown and HTML). The
numbers come from experiments/statistics.py; this module groups report rows and formats them.

Rows with equal (label, params) are one table row; (scene, edit, seed) is the pairing unit.
"""
from __future__ import annotations

import html
import math

from dualnerf.metrics import json_value
from experiments import statistics as S
from experiments.report.rows import display_label, row_key

DEFAULT_REFERENCE = "baseline"          # the single-field Instruct-NeRF2NeRF row of the shipped workflows


def unit_values(rows, docs, column: str, metric_value) -> dict[tuple, dict]:
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
        values = unit_values(rows, docs, column, metric_value)
        for trow in table:
            key = row_key(trow)
            if key in ref_keys or trow.method.is_original:     # the unedited scene is not a method to compare
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
            "verdict": f"paired t interval ({S.T_LEVEL:.0%}, mean ± t_(n-1) sd/sqrt(n)): t_ci_low, t_ci_high, "
                       f"ci_excludes_zero",
            "unit": ["scene", "edit", "seed"], "resamples": S.BOOTSTRAP_RESAMPLES, "level": S.BOOTSTRAP_LEVEL,
            "seed": S.BOOTSTRAP_SEED, "generator": "numpy.random.default_rng(seed), fresh per comparison",
            "min_pairs": S.MIN_PAIRS}


def diff_json(diff: S.PairedDifference) -> dict:
    return {"mean": json_value(diff.mean), "ci_low": json_value(diff.low), "ci_high": json_value(diff.high),
            "n_pairs": diff.n_pairs, "ci_contains_zero": diff.contains_zero,
            "t_ci_low": json_value(diff.t_low), "t_ci_high": json_value(diff.t_high),
            "ci_excludes_zero": diff.excludes_zero,
            "unpaired": [list(u) for u in diff.unpaired],
            "unpaired_reference": [list(u) for u in diff.unpaired_reference],
            "non_finite": [list(u) for u in diff.non_finite]}


def verdict(diff: S.PairedDifference) -> str:
    """'excl. 0' / 'incl. 0' from the paired t interval; '' without an interval."""
    if diff.excludes_zero is None:
        return ""
    return "excl. 0" if diff.excludes_zero else "incl. 0"


def format_diff(diff: S.PairedDifference | None, column: str) -> str:
    """'+0.0400 [+0.0200, +0.0600] excl. 0': the mean paired difference, its paired 95% t interval and
    whether that interval excludes 0; 'n/a' without pairs, '(n=1, no CI)' with one pair."""
    if diff is None or math.isnan(diff.mean):
        return "n/a"
    digits = 2 if "psnr" in column else 4
    text = f"{diff.mean:+.{digits}f}"
    if diff.excludes_zero is None:
        return text + f" (n={diff.n_pairs}, no CI)"
    return text + f" [{diff.t_low:+.{digits}f}, {diff.t_high:+.{digits}f}] {verdict(diff)}"


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
            f"with its paired {S.T_LEVEL:.0%} t interval (mean ± t_(n−1)·sd/√n; t = 4.30 at 3 units). "
            f"'excl. 0': the interval excludes zero, a difference beyond seed noise at this n; 'incl. 0': "
            f"no difference shown. The {S.BOOTSTRAP_LEVEL:.0%} {S.BOOTSTRAP_METHOD} bootstrap interval "
            f"(B = {S.BOOTSTRAP_RESAMPLES}, numpy default_rng({S.BOOTSTRAP_SEED})) is in table.json/csv; "
            f"with few units it is too narrow (3 seeds give at most 10 distinct resamples).")


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
        lines.append(f"| {display_label(*key, original=trow.method.is_original)} | {pairs} | "
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
        parts.append(f"<tr><td style='text-align:left'>{esc(display_label(*key, original=trow.method.is_original))}"
                     f"</td><td>{max(d.n_pairs for d in diffs.values())}</td>")
        for c in columns:
            diff = diffs.get(c)
            cls = " class='ns'" if diff is not None and diff.excludes_zero is False else ""
            parts.append(f"<td{cls}>{esc(format_diff(diff, c))}</td>")
        parts.append("</tr>")
    parts.append(f"</table><p>{esc(caption(reference))}</p>")
    if all(d.n_pairs < 2 for diffs in paired.values() for d in diffs.values()):
        parts.append("<p class='warn'>One unit per comparison: these differences say nothing about seed noise. "
                     "Run more seeds (e.g. --set seeds=[0,1,2]; each adds one run of every row) for "
                     "intervals.</p>")
    parts += [f"<p class='note'>{esc(note)}</p>" for note in _unpaired_note(paired)]
    return "".join(parts)
