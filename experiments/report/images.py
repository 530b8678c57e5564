"""The report's image grids: fixed views per row (grid.png) and camera-path frames (path_strip.png)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from experiments.report.rows import ReportRow, display_label
from stages import layout
from stages.images import read_png as _read_rgb

GRID_VIEWS = 4
PATH_STRIP_FRAMES = 6


def _first_per_method(rows: list[ReportRow]) -> list[ReportRow]:
    seen, out = set(), []
    for row in rows:
        if not row.is_original and row.method_key not in seen:
            seen.add(row.method_key)
            out.append(row)
    return out


def _plot_grid(grid: list[tuple[str, list[np.ndarray | None]]], titles: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(grid), len(titles), figsize=(2.2 * len(titles), 2.0 * len(grid)),
                             squeeze=False)
    for r, (label, images) in enumerate(grid):
        for c, image in enumerate(images):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if image is None:
                ax.text(0.5, 0.5, "missing", ha="center", va="center", transform=ax.transAxes)
            else:
                ax.imshow(image)
            if c == 0:
                ax.set_ylabel(label, fontsize=9)
            if r == 0:
                ax.set_title(titles[c], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_image_grid(rows: list[ReportRow], docs: list[dict], path: Path) -> list[str] | None:
    """A grid of fixed views (columns) for the original scene, the ground-truth edit where the scene
    has one, and the first seed of every edited method. Returns the row labels, or None without views."""
    names = None
    for doc in docs:
        listed = doc.get("views", {}).get("names", [])
        names = listed if names is None else [n for n in names if n in listed]
    names = (names or [])[:GRID_VIEWS]
    if not names:
        return None
    source = rows[0].evaluate_dir
    grid: list[tuple[str, list[np.ndarray | None]]] = [
        ("Original", [_read_rgb(layout.view_path(source, layout.ORIGINAL, n)) for n in names])]
    gt = [_read_rgb(layout.view_path(source, layout.GT_EDIT, n)) for n in names]
    if any(image is not None for image in gt):
        grid.append(("GT edit", gt))
    for row in _first_per_method(rows):
        grid.append((display_label(row.label, row.params),
                     [_read_rgb(layout.view_path(row.evaluate_dir, layout.EDITED, n)) for n in names]))
    _plot_grid(grid, names, path)
    return [label for label, _ in grid]


def write_path_strip(rows: list[ReportRow], path: Path) -> list[str] | None:
    """Camera-path frames at evenly spaced positions (columns) for the original scene and the first seed
    of every method: the videos' content as a still, for print and for a quick look."""
    source = rows[0].evaluate_dir / layout.FRAMES / layout.ORIGINAL
    count = len(list(source.glob("*.png"))) if source.is_dir() else 0
    if count == 0:
        return None
    picks = sorted({int(i) for i in np.round(np.linspace(0, count - 1, min(PATH_STRIP_FRAMES, count)))})
    grid = [("Original", [_read_rgb(layout.frame_path(rows[0].evaluate_dir, layout.ORIGINAL, i)) for i in picks])]
    for row in _first_per_method(rows):
        grid.append((display_label(row.label, row.params),
                     [_read_rgb(layout.frame_path(row.evaluate_dir, layout.EDITED, i)) for i in picks]))
    _plot_grid(grid, [f"frame {i}" for i in picks], path)
    return [label for label, _ in grid]
