"""The report's convergence figure: per edited row, the edit stage's probe PSNRs against the iteration.

The edit stage's curves.json carries "convergence" (dualnerf.convergence, procedural scenes only):
psnr_in (renders of a few training views vs the ground-truth edit inside its mask) and psnr_out (vs the
original outside it) at regular iterations. `write_convergence(rows, out_dir)` draws one panel per row
into curves/convergence.png and titles it with `remaining_change`: the in-mask curve's fitted plateau
and the share of its change still to come (<= 10%: converged; the plateau is a dotted line), or, for a
curve still near-straight, its current slope.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from stages import layout


def load_convergence(edit_dir: Path | None) -> dict | None:
    """The "convergence" columns of an edit result's curves.json, or None when there are none."""
    if edit_dir is None:
        return None
    path = Path(edit_dir) / layout.CURVES
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
    "remaining": a - end, "share": (a - end) / (a - fitted start) (the share of the fitted change still
    to come: <= 0.1 reads "converged"), "tau", "late_slope": the measured slope over the last quarter of
    the span, per 1000 iterations}, or None without a change to measure. A straight line fits with
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
    late = t >= 0.75 * span                          # the measured slope over the last quarter (per 1000 it)
    slope = float(np.polyfit(t[late], v[late], 1)[0]) * 1000.0 if late.sum() >= 2 else None
    return {"plateau": float(plateau), "end": float(end), "remaining": float(plateau - end),
            "share": float((plateau - end) / (plateau - start)), "tau": float(tau), "late_slope": slope}


def convergence_note(fit: dict, span: float) -> str:
    """Two short lines on a fitted in-mask curve probed over `span` iterations: converged or not, and
    what is left (a time constant beyond twice the span means the curve is still near-straight: its
    extrapolated plateau says nothing, the current slope does)."""
    if fit["share"] <= 0.1:
        return f"converged: {fit['remaining']:+.1f} dB to the plateau\n{fit['plateau']:.1f} dB ({fit['share']:.0%} left)"
    if fit["tau"] > 2.0 * span:
        slope = fit["late_slope"] if fit["late_slope"] is not None else fit["remaining"] / fit["tau"] * 1000.0
        return f"NOT converged: still {slope:+.1f} dB per\n1000 iterations, no plateau in sight"
    return (f"NOT converged: {fit['remaining']:+.1f} dB to the fitted\nplateau {fit['plateau']:.1f} dB "
            f"({fit['share']:.0%} of the change left)")


def _panels(rows) -> list[tuple[str, dict]]:
    panels = []
    for row in rows:
        conv = load_convergence(row.edit_dir)
        if conv is not None:
            name = row.label if row.seed is None else f"{row.label} (seed {row.seed})"
            panels.append((name, conv))
    return panels


def convergence_summary(rows) -> list[dict]:
    """Per edited row with probe data: the last probe's in-mask and outside PSNR, the fitted plateau and the
    share of the change left, and the verdict (report.json "convergence" and the page's table)."""
    out = []
    for name, conv in _panels(rows):
        it = conv["iteration"]
        fit = remaining_change(it, conv["psnr_in"])
        span = float(it[-1] - it[0])
        in_sight = fit is not None and fit["tau"] <= 2.0 * span     # else the plateau is an extrapolation
        entry = {"row": name, "iterations": it[-1], "psnr_in": conv["psnr_in"][-1], "psnr_out": conv["psnr_out"][-1],
                 "fit": fit, "plateau": fit["plateau"] if in_sight else None,
                 "share_left": fit["share"] if in_sight else None,
                 "converged": None if fit is None else fit["share"] <= 0.1,
                 "note": "no change to fit" if fit is None else convergence_note(fit, span).replace("\n", " ")}
        out.append(entry)
    return out


def convergence_html(summary: list[dict]) -> list[str]:
    """The page's convergence table (empty without probe data)."""
    import html

    if not summary:
        return []

    def number(value, fmt):
        return "-" if value is None else format(value, fmt)

    parts = [("<h2>Convergence</h2><p>In-mask PSNR of the edit stage's probe renders to the ground-truth "
              "edit (training views, half size), the saturating curve fitted to it, and the share of its "
              "change still to come (converged: &le; 10%; docs/metrics.md). Outside: PSNR to the original "
              "outside the edit mask. Curves: <a href='curves/convergence.png'>curves/convergence.png</a>.</p>"),
             ("<table><tr><th>row</th><th>iterations</th><th>PSNR in (dB)</th><th>PSNR outside (dB)</th>"
              "<th>fitted plateau (dB)</th><th>change left</th><th style='text-align:left'>verdict</th></tr>")]
    for e in summary:
        parts.append(f"<tr><td>{html.escape(e['row'])}</td><td>{e['iterations']}</td>"
                     f"<td>{number(e['psnr_in'], '.2f')}</td><td>{number(e['psnr_out'], '.2f')}</td>"
                     f"<td>{number(e['plateau'], '.1f')}</td><td>{number(e['share_left'], '.0%')}</td>"
                     f"<td style='text-align:left'>{html.escape(e['note'])}</td></tr>")
    parts.append("</table>")
    return parts


def write_convergence(rows, out_dir: Path) -> list[str]:
    """curves/convergence.png (one panel per edited row that has probe data); returns [its path] or []."""
    panels = _panels(rows)
    if not panels:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(panels))
    n_rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(4.4 * cols, 3.4 * n_rows), squeeze=False, sharey=True)
    for ax, (name, conv) in zip(axes.flat, panels):
        it = conv["iteration"]
        nan = [math.nan if v is None else v for v in conv["psnr_in"]]
        ax.plot(it, nan, "-o", ms=2, label="in mask vs GT edit")
        ax.plot(it, [math.nan if v is None else v for v in conv["psnr_out"]], "--", label="outside vs original")
        fit = remaining_change(it, conv["psnr_in"])
        span = float(it[-1] - it[0])
        if fit is not None and fit["tau"] <= 2.0 * span:      # a plateau the curve is visibly heading to
            ax.axhline(fit["plateau"], color="tab:blue", lw=0.6, ls=":", label="fitted plateau (in mask)")
        ax.set_title(name + ("" if fit is None else "\n" + convergence_note(fit, span)), fontsize=7)
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
