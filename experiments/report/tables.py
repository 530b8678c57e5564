"""The metrics table: rows grouped by method and parameters, mean ± std over seeds, best value per column;
written as table.md, table.csv and table.json."""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualnerf.metrics import METRICS, json_value
from experiments.methods import Method
from experiments.report import differences as RS
from experiments.report.rows import ReportError, ReportRow, display_label, metric_value, row_key
from experiments.statistics import summarize_over_seeds


@dataclass
class TableRow:
    label: str
    method: Method
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
    """Group rows by method and parameters (Original first, then grid order), mean ± sample std over seeds of each
    seed's mean over scenes and edits (experiments/statistics.py), and mark the best mean per column in the
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
        groups.setdefault(row.method_key, []).append(i)
    ordered = sorted(groups.items(), key=lambda kv: (not rows[kv[1][0]].is_original, kv[1][0]))
    table = []
    for _, members in ordered:
        first = rows[members[0]]
        mean, std, n = {}, {}, {}
        for column in columns:
            summary = summarize_over_seeds([metric_value(docs[i]["metrics"].get(column)) for i in members],
                                           [rows[i].seed for i in members])
            mean[column], std[column], n[column] = summary.mean, summary.std, summary.n
        table.append(TableRow(first.label, first.method,
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


def write_tables(columns: list[str], table: list[TableRow], docs: list[dict], out_dir: Path,
                 paired: dict | None = None, reference: str | None = None) -> dict:
    """table.md/csv/json; `paired` ({(label, params): {column: PairedDifference}}, from
    report_statistics.paired_differences) adds the difference-to-`reference` columns."""
    paired = paired or {}
    headers = [column_header(c, docs) for c in columns]
    lines = ["| Variant | DF | SA | CCI | seeds | n | " + " | ".join(headers) + " |",
             "|---|:-:|:-:|:-:|---|---:|" + "---:|" * len(columns)]
    for row in table:
        label = display_label(row.label, row.params, original=row.method.is_original)
        seeds = ", ".join("-" if s is None else str(s) for s in row.seeds)
        cells = [f"**{format_cell(row, c)}**" if row.best[c] else format_cell(row, c) for c in columns]
        lines.append(f"| {label} | " + " | ".join(row.method.marks()) + f" | {seeds} | {row.runs} | "
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
                head += [f"{column}_diff", f"{column}_ci_low", f"{column}_ci_high", f"{column}_ci_contains_zero",
                         f"{column}_t_ci_low", f"{column}_t_ci_high", f"{column}_ci_excludes_zero"]
        writer.writerow(head)
        for row in table:
            record = [row.label, *("" if t is None else int(t) for t in _flags(row.method)),
                      " ".join("" if s is None else str(s) for s in row.seeds),
                      " ".join(f"{k}={v}" for k, v in row.params), row.runs]
            for column in columns:
                record += [_csv_number(row.mean[column]), _csv_number(row.std[column]), row.n[column],
                           int(row.best[column])]
                if paired:
                    diff = paired.get(row_key(row), {}).get(column)
                    record += [""] * 7 if diff is None else [
                        _csv_number(diff.mean), _csv_number(diff.low), _csv_number(diff.high),
                        "" if diff.contains_zero is None else int(diff.contains_zero),
                        _csv_number(diff.t_low), _csv_number(diff.t_high),
                        "" if diff.excludes_zero is None else int(diff.excludes_zero)]
            writer.writerow(record)

    doc = {
        "columns": [{"name": c, "symbol": METRICS[c].symbol, "higher_is_better": METRICS[c].higher_is_better,
                     "encoder": _encoder_tags(docs, c) if METRICS[c].uses_encoder else None,
                     "lpips": _encoder_tags(docs, c, "lpips") if METRICS[c].uses_lpips else None} for c in columns],
        "rows": [{"label": r.label, "kind": r.method.kind, "dual_field": _flags(r.method)[0],
                  "annealing": _flags(r.method)[1], "consistency": _flags(r.method)[2], "seeds": r.seeds, "params": [list(p) for p in r.params],
                  "runs": r.runs,
                  "metrics": {c: {"mean": json_value(r.mean[c]), "std": json_value(r.std[c]),
                                  "n": r.n[c], "best": r.best[c],
                                  **({"paired": RS.diff_json(paired[row_key(r)][c])}
                                     if c in paired.get(row_key(r), {}) else {})} for c in columns}}
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


def _flags(method: Method) -> tuple:
    """DF, SA, CCI of an IDU row; None (not applicable) for the per-frame baseline and the unedited scene."""
    return method.flags or (None, None, None)
