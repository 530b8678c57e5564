"""The folder layout of the stage results that other stages and the report read: one place for the names.

    evaluate   metrics.json, camera_path.json, path.mp4,
               frames/{original,edited}/0000.png ...       the camera path, rendered
               views/{original,edited,gt_edit,gt_mask}/<name>   the fixed views (and their ground truth)
    perframe   frames/edited/..., views/edited/..., edit.json
    gtviews    frames/{original,gt_edit,gt_mask}/..., views/{...}/..., gtviews.json
    edit       model/, edited/<stem>.png, updates.jsonl, curves.json, curves.png, edit.json
    fit        model/, heldout/<stem>.png, metrics.json, curve.json, curve.png
"""
from __future__ import annotations

from pathlib import Path

# Image groups: the camera-path frames and the fixed (held-out) views.
FRAMES = "frames"
VIEWS = "views"
# Image kinds within a group.
ORIGINAL = "original"             # f_S's renders (gtviews: the scene's own render)
EDITED = "edited"                 # the edited model's renders, or the per-frame baseline's edits
GT_EDIT = "gt_edit"               # the procedural scene's ground-truth edit
GT_MASK = "gt_mask"               # where that edit changes the scene (white)
GROUND_TRUTH_KINDS = (ORIGINAL, GT_EDIT, GT_MASK)

METRICS = "metrics.json"
CAMERA_PATH = "camera_path.json"
PATH_VIDEO = "path.mp4"
EDIT_RECORD = "edit.json"         # edit and perframe: what edited (editor identity, instruction, ...)
CURVES = "curves.json"            # edit: per-iteration series and convergence probes
MODEL = "model"                   # fit and edit: the saved field (dualnerf.model)


def frame_name(n: int) -> str:
    """The file name of camera-path frame n."""
    return f"{n:04d}.png"


def image_path(folder: Path | str, group: str, kind: str, name: str) -> Path:
    return Path(folder) / group / kind / name


def frame_path(folder: Path | str, kind: str, n: int) -> Path:
    return image_path(folder, FRAMES, kind, frame_name(n))


def view_path(folder: Path | str, kind: str, name: str) -> Path:
    return image_path(folder, VIEWS, kind, name)
