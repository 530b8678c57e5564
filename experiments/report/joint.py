"""The report's joint reading of the edit and the background, and the metrics that see the ground truth.

`write_joint_scatter`: in-mask PSNR to the ground-truth edit (did the edit arrive?) against outside-mask
PSNR to the original views (was the rest kept?), one point per row and seed, one panel per scene edit;
the unedited scene's in-mask PSNR is a dashed vertical line (its outside-mask PSNR is infinite). A row
that edits less moves toward that line: it cannot pass as preserving more without showing it.

`ground_truth_section`: every reported metric whose computation used the ground-truth edit, from
metrics.json `sees_ground_truth` (stages/evaluate.py), plus the two places that see it by construction.
"""
from __future__ import annotations

import html
import math
from pathlib import Path

from dualnerf.metrics import METRICS
from experiments.report.rows import display_label, metric_value, row_key, scene_edits

X_METRIC, Y_METRIC = "gt_psnr_inside", "gt_psnr_background"
SCATTER = "joint_psnr.png"
MARKERS = "osD^vP*Xph<>"


def scatter_points(rows, docs) -> dict[tuple, dict[tuple, list]]:
    """{(scene, edit): {table-row key: [(seed, x, y), ...]}} for edited rows with both values finite."""
    out: dict[tuple, dict[tuple, list]] = {}
    for row, doc in zip(rows, docs):
        if row.is_original:
            continue
        x = metric_value(doc["metrics"].get(X_METRIC))
        y = metric_value(doc["metrics"].get(Y_METRIC))
        if math.isfinite(x) and math.isfinite(y):
            out.setdefault((row.scene, row.edit), {}).setdefault(row_key(row), []).append((row.seed, x, y))
    return out


def write_joint_scatter(rows, docs, out_dir: Path) -> str | None:
    """joint_psnr.png (relative path returned), or None when no row has both PSNRs."""
    points = scatter_points(rows, docs)
    if not points:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = [p for p in scene_edits(rows) if p in points]
    keys = list(dict.fromkeys(k for p in pairs for k in points[p]))
    cmap = plt.get_cmap("tab10" if len(keys) <= 10 else "tab20")
    style = {k: (cmap(i % cmap.N), MARKERS[i % len(MARKERS)]) for i, k in enumerate(keys)}
    fig, axes = plt.subplots(1, len(pairs), figsize=(6.4 * len(pairs), 5.2), squeeze=False)
    for ax, pair in zip(axes[0], pairs):
        for key, pts in points[pair].items():
            colour, marker = style[key]
            xs, ys = [p[1] for p in pts], [p[2] for p in pts]
            ax.scatter(xs, ys, color=colour, marker=marker, s=36, label=display_label(*key))
            ax.scatter([sum(xs) / len(xs)], [sum(ys) / len(ys)], color=colour, marker=marker, s=160,
                       facecolors="none", linewidths=1.5)
            for seed, x, y in pts:
                if seed is not None:
                    ax.annotate(str(seed), (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7,
                                color=colour)
        for row, doc in zip(rows, docs):
            if row.is_original and (row.scene, row.edit) == pair:
                x = metric_value(doc["metrics"].get(X_METRIC))
                if math.isfinite(x):
                    ax.axvline(x, linestyle="--", color="0.4", label="unedited scene (in-mask)")
                break
        ax.set_title(f"{pair[0]} / {pair[1]}", fontsize=10)
        ax.set_xlabel(f"{METRICS[X_METRIC].symbol}: in-mask PSNR to the GT edit (dB) →", fontsize=9)
        ax.set_ylabel(f"{METRICS[Y_METRIC].symbol}: outside-mask PSNR to the original (dB) →", fontsize=9)
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    seen = dict(zip(labels, handles))
    fig.legend(list(seen.values()), list(seen.keys()), loc="lower center", ncol=min(4, len(seen)), fontsize=8)
    fig.suptitle("In-mask vs outside-mask PSNR per row and seed\n(small: one seed, labelled; large hollow: "
                 "the row's mean)", fontsize=10)
    fig.tight_layout(rect=(0, 0.04 + 0.03 * math.ceil(len(seen) / 4), 1, 0.93))
    fig.savefig(out_dir / SCATTER, dpi=90)
    plt.close(fig)
    return SCATTER


SCATTER_CAPTION = ("In-mask PSNR to the ground-truth edit (did the edit arrive?) against outside-mask PSNR "
                   "to the original views (was the rest kept?), one point per row and seed. Outside-mask "
                   "PSNR alone is best for the unedited scene (dashed line: its in-mask PSNR): a row that "
                   "edits less moves left, so read the two together.")

BY_CONSTRUCTION = [("the InstructPix2Pix emulator (it simulates an editor that knows what the instruction "
                   "means; no component reads it)"),
                   ("the edit stage's convergence probe (training curves; a diagnostic, not a metric of the "
                   "table)")]


def ground_truth_metrics(rows, docs) -> list[dict]:
    """Per metric named in any result's `sees_ground_truth`: its symbol and the rows where it does."""
    found: dict[str, list] = {}
    for row, doc in zip(rows, docs):
        for name in doc.get("sees_ground_truth") or []:
            label = display_label(*row_key(row), original=row.is_original)
            found.setdefault(name, [])
            if label not in found[name]:
                found[name].append(label)
    all_labels = list(dict.fromkeys(display_label(*row_key(r), original=r.is_original) for r in rows))
    return [{"metric": name, "symbol": METRICS[name].symbol if name in METRICS else name,
             "rows": "all" if labels == all_labels else labels}
            for name, labels in sorted(found.items(), key=lambda kv: list(METRICS).index(kv[0])
                                       if kv[0] in METRICS else len(METRICS))]


def _entry_text(entry: dict) -> str:
    rows = "every row" if entry["rows"] == "all" else "rows " + ", ".join(entry["rows"])
    return f"{entry['symbol']} ({entry['metric']}): {rows}"


def ground_truth_markdown(entries: list[dict]) -> list[str]:
    lines = ["", "## Metrics that see the ground truth", ""]
    lines += [f"- {_entry_text(e)}" for e in entries] or ["- none of the reported metrics"]
    lines += ["", "By construction, also: " + "; ".join(BY_CONSTRUCTION) + ". CCI's scores never see it."]
    return lines


def ground_truth_html(entries: list[dict]) -> str:
    esc = html.escape
    items = "".join(f"<li>{esc(_entry_text(e))}</li>" for e in entries) or "<li>none of the reported metrics</li>"
    return (f"<h2>Metrics that see the ground truth</h2><p>From each result's metrics.json "
            f"<code>sees_ground_truth</code>:</p><ul>{items}</ul><p>By construction, also: "
            f"{esc('; '.join(BY_CONSTRUCTION))}. CCI's scores never see it.</p>")
