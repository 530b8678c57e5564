"""The report's convergence figure: per edited row, the edit stage's probe PSNRs against the iteration.

The edit stage's curves.json carries "convergence" (dualnerf.convergence, procedural scenes only):
psnr_in (renders of a few training views vs the ground-truth edit inside its mask) and psnr_out (vs the
original outside it) at regular iterations. `write_convergence(rows, out_dir)` draws one panel per row
into curves/convergence.png and titles it with `late_change_share`: the share of the in-mask curve's
total change made during the last 10% of the iterations (small: the row has converged).
"""
from __future__ import annotations

import json
import math
from pathlib import Path


def load_convergence(edit_dir: Path | None) -> dict | None:
    """The "convergence" columns of an edit result's curves.json, or None when there are none."""
    if edit_dir is None:
        return None
    path = Path(edit_dir) / "curves.json"
    try:
        doc = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None           # report.load_curves reports a corrupt file; a missing one is an unedited row
    conv = doc.get("convergence")
    if not isinstance(conv, dict) or len(conv.get("iteration", [])) < 2:
        return None
    return conv


def late_change_share(iterations, values, tail: float = 0.1) -> float | None:
    """|v(T) - v(T - tail T)| / (max v - min v) over the curve (None when flat or unknown): how much of the
    curve's movement still happens in its last `tail` share of iterations."""
    points = [(it, v) for it, v in zip(iterations, values) if v is not None and math.isfinite(v)]
    if len(points) < 2:
        return None
    last_it, last_v = points[-1]
    cut = last_it - tail * (last_it - points[0][0])
    before = [v for it, v in points if it <= cut]
    span = max(v for _, v in points) - min(v for _, v in points)
    if not before or span <= 0:
        return None
    return abs(last_v - before[-1]) / span


def write_convergence(rows, out_dir: Path) -> list[str]:
    """curves/convergence.png (one panel per edited row that has probe data); returns [its path] or []."""
    panels = []
    for row in rows:
        conv = load_convergence(row.edit_dir)
        if conv is not None:
            name = row.label if row.seed is None else f"{row.label} (seed {row.seed})"
            panels.append((name, conv))
    if not panels:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(panels))
    n_rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(4.2 * cols, 3.0 * n_rows), squeeze=False, sharey=True)
    for ax, (name, conv) in zip(axes.flat, panels):
        it = conv["iteration"]
        nan = [math.nan if v is None else v for v in conv["psnr_in"]]
        ax.plot(it, nan, "-o", ms=2, label="in mask vs GT edit")
        ax.plot(it, [math.nan if v is None else v for v in conv["psnr_out"]], "--", label="outside vs original")
        share = late_change_share(it, conv["psnr_in"])
        ax.set_title(name + ("" if share is None else f"\nlast 10% of iterations: {share:.0%} of the change"),
                     fontsize=8)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes[0, 0].set_ylabel("PSNR (dB)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    (Path(out_dir) / "curves").mkdir(exist_ok=True)
    rel = "curves/convergence.png"
    fig.savefig(Path(out_dir) / rel, dpi=90)
    plt.close(fig)
    return [rel]
