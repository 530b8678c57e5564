"""Reading the results that the evaluation of a scene edit is built from: the unedited scene's evaluation
(its camera path, view names and f_S renders: reused by edited rows, edited by the per-frame baseline),
the per-frame baseline's images and the ground-truth views (stages.gtviews). Shared by evaluate,
perframe and gtviews; file names in stages.layout."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages import layout
from stages.images import read_png


class PerFrameError(ValueError):
    """An input of the per-frame baseline (the evaluation it edits, the ground-truth views) that cannot be
    used; the message says what to change."""

    user_error = True


def read_image(path: Path, error: type[Exception], hint: str) -> np.ndarray:
    """The RGB image at `path`, or `error` naming the file and what to rerun (`hint`)."""
    image = read_png(path)
    if image is None:
        raise error(f"{path} is missing or unreadable; {hint}")
    return image


class OriginalEvaluation:
    """The unedited scene's evaluate result (the "original" input of edited rows and of the per-frame
    baseline): its camera path, fixed-view names and f_S renders. `error` is the reading stage's error."""

    def __init__(self, folder: Path, error: type[Exception]):
        self.folder, self.error = Path(folder), error
        try:
            self.camera_path = json.loads((self.folder / layout.CAMERA_PATH).read_text())
            metrics = json.loads((self.folder / layout.METRICS).read_text())
        except (FileNotFoundError, json.JSONDecodeError) as err:
            raise error(f"{folder} is not an evaluate result ({err}); the 'original' input must be the "
                        f"unedited scene's evaluation.") from None
        self.edited = bool(metrics.get("edited"))
        self.view_names: list[str] = list(metrics["views"]["names"])

    @property
    def path_c2w(self) -> np.ndarray:
        return np.asarray(self.camera_path["c2w"])

    @property
    def path_size(self) -> tuple[int, int]:
        return int(self.camera_path["width"]), int(self.camera_path["height"])

    def _read(self, path: Path) -> np.ndarray:
        return read_image(path, self.error, "rerun the unedited-scene evaluation.")

    def frames(self) -> list[np.ndarray]:
        return [self._read(layout.frame_path(self.folder, layout.ORIGINAL, n)) for n in range(len(self.path_c2w))]

    def views(self, names: list[str] | None = None) -> list[np.ndarray]:
        return [self._read(layout.view_path(self.folder, layout.ORIGINAL, name))
                for name in (self.view_names if names is None else names)]


def evaluation_cameras(original_dir: Path, dataset) -> list[tuple]:
    """Every image the evaluate stage scores: the path frames, then the fixed views, as (group, name, c2w
    in the dataset frame, (width, height), f_S render), all read from the unedited evaluation."""
    original = OriginalEvaluation(original_dir, PerFrameError)
    if original.edited:
        raise PerFrameError(f"{original_dir} evaluates an edited model; 'original' must be the unedited scene.")
    size = original.path_size
    jobs = [(layout.FRAMES, layout.frame_name(n), c2w, size, render)
            for n, (c2w, render) in enumerate(zip(original.path_c2w, original.frames()))]
    index = {name: i for i, name in enumerate(dataset.names)}
    for name in original.view_names:
        if name not in index:
            raise PerFrameError(f"view {name} of {original_dir} is not in the dataset; 'original' must come "
                                f"from the same dataset.")
    for name, render in zip(original.view_names, original.views()):
        jobs.append((layout.VIEWS, name, dataset.c2w[index[name]], (dataset.width, dataset.height), render))
    return jobs


def read_ground_truth(folder: Path, group: str, name: str):
    """(original, gt_edit, mask) of one evaluation image from a gtviews result."""
    images = [read_image(layout.image_path(folder, group, kind, name), PerFrameError,
                         "the gtviews result does not match this evaluation's cameras; rerun the gtviews step.")
              for kind in layout.GROUND_TRUTH_KINDS]
    return images[0], images[1], images[2][..., 0] > 127


def per_frame_images(folder: Path, n_frames: int, view_names, error: type[Exception]) -> tuple[list, list]:
    """The per-frame baseline's edited path frames and views (stages.perframe output layout)."""
    hint = "the per-frame result does not match this evaluation's camera path and views (rerun the perframe step)."
    return ([read_image(layout.frame_path(folder, layout.EDITED, n), error, hint) for n in range(n_frames)],
            [read_image(layout.view_path(folder, layout.EDITED, name), error, hint) for name in view_names])
