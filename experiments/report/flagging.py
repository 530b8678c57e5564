"""The report's CCI section: how well the consistency score S flags the emulator's failed calls.

From each edit result's updates.jsonl (one record per view update: S, `score_ratio` = S / mean S over the
training views, and the emulator's `failed` flag), `dualnerf.consistency.flagging_quality` gives one
confusion matrix per (scene, edit, seed) unit: a call is flagged when score_ratio < 1 (eq. 10 gives it a
weight below 1). Per table row the matrices are summed (pooled precision = flagged failed / flagged,
recall = flagged failed / failed), with the per-unit precision and recall beside them and the mean AUC.
S is logged whenever an encoder is given, so rows without CCI show what CCI would have flagged; only
rows with CCI train on it. Neither S nor the flag sees the ground truth; the `failed` label is the
emulator's own record, which only this evaluation reads.
"""
from __future__ import annotations

import html
import json
from pathlib import Path

from dualnerf.consistency import flagging_quality
from experiments.report.rows import display_label, row_key

UPDATES = "updates.jsonl"
COUNTS = ("calls", "failed", "flagged", "flagged_failed")


def read_updates(edit_dir: Path | None) -> list[dict] | None:
    """The update records of an edit result; None when there is no edit result or no updates.jsonl."""
    if edit_dir is None or not (Path(edit_dir) / UPDATES).is_file():
        return None
    lines = (Path(edit_dir) / UPDATES).read_text().splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def _ratio(num: int, den: int) -> float | None:
    return num / den if den else None


def flagging_rows(rows, table) -> list[dict]:
    """Per table row with scored emulator calls: pooled counts, precision, recall, base rate, the per-unit
    values and the mean AUC, in table order."""
    per_key: dict[tuple, list] = {}
    for row in rows:
        updates = read_updates(row.edit_dir)
        if updates is None:
            continue
        quality = flagging_quality(updates)
        if quality["calls"]:
            per_key.setdefault(row_key(row), []).append((row.scene, row.edit, row.seed, quality))
    out = []
    for trow in table:
        units = per_key.get(row_key(trow))
        if not units:
            continue
        total = {c: sum(q[c] for *_, q in units) for c in COUNTS}
        aucs = [q["auc"] for *_, q in units if q["auc"] is not None]
        flags = trow.method.flags
        out.append({
            "label": trow.label, "params": [list(p) for p in trow.params],
            "cci": None if flags is None else bool(flags[2]), **total,
            "precision": _ratio(total["flagged_failed"], total["flagged"]),
            "recall": _ratio(total["flagged_failed"], total["failed"]),
            "base_rate": _ratio(total["failed"], total["calls"]),
            "auc_mean": sum(aucs) / len(aucs) if aucs else None,
            "units": [{"scene": sc, "edit": ed, "seed": seed, **q} for sc, ed, seed, q in units]})
    return out


def _number(value) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def _per_unit(entry: dict, key: str) -> str:
    return ", ".join(_number(u[key]) for u in entry["units"])


def _cells(entry: dict) -> list[str]:
    label = display_label(entry["label"], tuple(tuple(p) for p in entry["params"]))
    cci = "-" if entry["cci"] is None else ("✓" if entry["cci"] else "✗ (logged only)")
    return [label, cci, str(len(entry["units"])), str(entry["calls"]), str(entry["failed"]),
            _number(entry["base_rate"]), str(entry["flagged"]), _number(entry["precision"]),
            _per_unit(entry, "precision"), _number(entry["recall"]), _per_unit(entry, "recall"),
            _number(entry["auc_mean"])]


HEADERS = ["Variant", "CCI", "units", "calls", "failed", "base rate", "flagged", "precision",
           "precision per unit", "recall", "recall per unit", "AUC (mean)"]
CAPTION = ("CCI's flagging of the emulator's failed calls, from updates.jsonl: a call is flagged when its "
           "score S is below the training views' mean (score_ratio < 1, a loss weight below 1 in eq. 10). "
           "Counts are summed over the row's (scene, edit, seed) units; precision = failed among flagged "
           "(compare with the base rate: a filter that flags at random has precision = base rate), recall = "
           "flagged among failed, per-unit values in seed order; AUC = P(S_failed < S_ok), 0.5 is chance. "
           "Rows without CCI log S but do not train on it.")


def markdown_section(entries: list[dict]) -> list[str]:
    if not entries:
        return []
    lines = ["", "## CCI: flagging the emulator's failed calls", "",
             "| " + " | ".join(HEADERS) + " |", "|---|:-:|" + "---:|" * (len(HEADERS) - 2)]
    lines += ["| " + " | ".join(_cells(e)) + " |" for e in entries]
    return lines + ["", CAPTION]


def html_section(entries: list[dict]) -> str:
    if not entries:
        return ""
    esc = html.escape
    parts = ["<h2>CCI: flagging the emulator's failed calls</h2><table class='flagging'><tr>"]
    parts += [f"<th>{esc(h)}</th>" for h in HEADERS] + ["</tr>"]
    for entry in entries:
        cells = _cells(entry)
        parts.append(f"<tr><td style='text-align:left'>{esc(cells[0])}</td>"
                     + "".join(f"<td>{esc(c)}</td>" for c in cells[1:]) + "</tr>")
    parts.append(f"</table><p>{esc(CAPTION)}</p>")
    return "".join(parts)
