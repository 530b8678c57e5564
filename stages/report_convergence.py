"""The report's convergence figure: per edited row, the edit stage's probe PSNRs against the iteration.

The edit stage's curves.json carries "convergence" (dualnerf.convergence, procedural scenes only):
psnr_in (renders of a few training views vs the ground-truth edit inside its mask) and psnr_out (vs the
original outside it) at regular iterations. `write_convergence(rows, out_dir)` draws one panel per row
into curves/convergence.png and titles it with `remaining_change`: the in-mask curve's fitted plateau
and the share of its change still to come (<= 10%: converged; the plateau is a dotted line).
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


def remaining_change(iterations, values) -> dict | None:
    """How far a probe curve still is from its plateau: the least-squares fit of the saturating curve
    v(t) = a - b exp(-t / tau) (tau searched on a log grid from 1/50 to 10x the span), whose plateau a is
    where the curve is heading. Returns {"plateau": a, "end": the fitted value at the last iteration,
    "remaining": a - end, "share": (a - end) / (a - fitted start)} (the share of the fitted change still
    to come: <= 0.1 reads "converged"), or None without a change to measure. A straight line fits with
    tau at the top of the grid, i.e. a distant plateau and a large share; noise around a level curve
    fits a tiny change, reported as such."""
    import numpy as np

    points = [(it, v) for it, v in zip(iterations, values) if v is not None and math.isfinite(v)]
    if len(points) < 4:
        return None
    t = np.array([p[0] for p in points], np.float64)
    v = np.array([p[1] for p in points], np.float64)
    t = t - t[0]
    span = float(t[-1])
    if span <= 0:
        return None
    def fit(tau):
        basis = np.stack([np.ones_like(t), np.exp(-t / tau)], axis=1)
        coef, *_ = np.linalg.lstsq(basis, v, rcond=None)
        return float(np.sum((basis @ coef - v) ** 2)), tau, coef

    grid = np.geomspace(span / 50.0, 10.0 * span, 200)
    best = min((fit(tau) for tau in grid), key=lambda r: r[0])
    ratio = grid[1] / grid[0]                      # refine between the best point's neighbours
    best = min((fit(tau) for tau in np.geomspace(best[1] / ratio, best[1] * ratio, 200)), key=lambda r: r[0])
    _, tau, (plateau, amplitude) = best
    start, end = plateau + amplitude, plateau + amplitude * math.exp(-span / tau)
    if abs(plateau - start) < 1e-9:
        return None
    return {"plateau": float(plateau), "end": float(end), "remaining": float(plateau - end),
            "share": float((plateau - end) / (plateau - start)), "tau": float(tau)}


def convergence_note(fit: dict) -> str:
    """One line for a fitted in-mask curve: converged or not, and what is left."""
    verdict = "converged" if fit["share"] <= 0.1 else "NOT converged"
    return (f"{verdict}: {fit['remaining']:+.1f} dB to the fitted plateau {fit['plateau']:.1f} dB "
            f"({fit['share']:.0%} of the change)")


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
        fit = remaining_change(it, conv["psnr_in"])
        if fit is not None:
            ax.axhline(fit["plateau"], color="tab:blue", lw=0.6, ls=":")
        ax.set_title(name + ("" if fit is None else "\n" + convergence_note(fit)), fontsize=8)
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
