"""The report's parameter-axis figures: each metric against a parameter, error bars = std over seeds."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dualnerf.metrics import METRICS
from experiments.report.rows import display_label, slug


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
        rel = f"params/{slug(key, empty='param')}.png"
        fig.savefig(out_dir / rel, dpi=90)
        plt.close(fig)
        written.append(rel)
    return written

