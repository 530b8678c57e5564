"""The report's training curves: the edit stage's curves.json per edited row, one figure per series."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from experiments.report.rows import ReportError, ReportRow
from stages import layout

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
    path = Path(edit_dir) / layout.CURVES
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
