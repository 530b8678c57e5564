"""Import a nerfstudio dataset (transforms.json): known cameras, no SfM.

nerfstudio convention: `transform_matrix` is camera-to-world with OpenGL camera axes (x right, y up,
z back); intrinsics fl_x, fl_y, cx, cy, w, h at the top level or per frame; OPENCV distortion k1 k2 p1
p2 (k3 k4 for fisheye are not supported); `ply_file_path` optionally names a sparse point cloud.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dualnerf.confine import check_file_name, confine
from dualnerf.io.errors import InputError
from dualnerf.io.ply import read_ply_points
from dualnerf.io.reconstruction import Reconstruction

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
SUPPORTED_MODELS = ("PINHOLE", "OPENCV", "SIMPLE_PINHOLE")


def find_transforms(source: Path) -> Path | None:
    """transforms.json of a nerfstudio dataset folder (or the file itself), else None."""
    source = Path(source)
    if source.is_file() and source.name.endswith(".json"):
        return source
    if (source / "transforms.json").is_file():
        return source / "transforms.json"
    return None


def import_nerfstudio(path: Path, root: Path | None = None) -> Reconstruction:
    """Cameras and image paths of `path`; every file it names must lie inside `root` (the scene
    folder; default the folder holding `path`)."""
    path = Path(path)
    root = path.parent if root is None else Path(root)
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise InputError(f"{path} is not valid JSON ({err}); fix the file.") from None
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{path}: no 'frames' list; a nerfstudio transforms.json needs one entry per image.")
    model = str(doc.get("camera_model", "OPENCV")).upper()
    if model not in SUPPORTED_MODELS:
        raise InputError(f"{path}: camera_model '{model}' is not supported (use one of "
                         f"{', '.join(SUPPORTED_MODELS)}); undistort the images first.")
    names, paths, c2w, intrinsics, sizes, distortion, missing = [], [], [], [], [], [], []
    for i, frame in enumerate(frames):
        where = f"{path}: frame {i}"
        file_path = frame.get("file_path")
        if not isinstance(file_path, str):
            raise InputError(f"{where} has no 'file_path'.")
        image_path = path.parent / file_path
        if not image_path.suffix and image_path.with_suffix(".png").exists():
            image_path = image_path.with_suffix(".png")    # old Blender-style entries omit the suffix
        image_path = confine(image_path, root, error=InputError, where=where, field="file_path", value=file_path)
        check_file_name(Path(file_path).name, error=InputError, where=where, field="file_path's file name")
        if not image_path.is_file():
            missing.append(file_path)
            continue
        values = {}
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            value = frame.get(key, doc.get(key))
            if key == "fl_y" and value is None:
                value = frame.get("fl_x", doc.get("fl_x"))
            if value is None:
                raise InputError(f"{where} ({file_path}): intrinsic '{key}' is missing (neither in the frame "
                                 f"nor at the top level); add fl_x, fl_y, cx, cy, w and h.")
            values[key] = float(value)
        matrix = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
        if matrix.shape == (3, 4):
            matrix = np.vstack([matrix, [0, 0, 0, 1]])
        if matrix.shape != (4, 4):
            raise InputError(f"{where} ({file_path}): transform_matrix must be 4x4, got shape {matrix.shape}.")
        names.append(Path(file_path).name)
        paths.append(image_path)
        c2w.append(matrix @ OPENGL_TO_OPENCV)
        intrinsics.append([values["fl_x"], values["fl_y"], values["cx"], values["cy"]])
        sizes.append([values["w"], values["h"]])
        distortion.append([float(frame.get(k, doc.get(k, 0.0))) for k in ("k1", "k2", "p1", "p2", "k3")])
    if missing:
        raise InputError(f"{path}: {len(missing)} image file(s) listed in frames do not exist: "
                         f"{', '.join(missing[:10])}{' ...' if len(missing) > 10 else ''}; "
                         f"copy them next to the transforms file or remove their frames.")
    if len(set(names)) != len(names):
        raise InputError(f"{path}: image file names must be unique (they identify views across stages).")
    points = None
    ply = doc.get("ply_file_path")
    if ply:
        ply_path = confine(path.parent / ply, root, error=InputError, where=str(path), field="ply_file_path",
                           value=ply)
        if not ply_path.is_file():
            raise InputError(f"{path}: ply_file_path '{ply}' does not exist; fix or remove the entry.")
        points = read_ply_points(ply_path)
    recon = Reconstruction(names=names, image_paths=paths, c2w=np.array(c2w), intrinsics=np.array(intrinsics),
                           sizes=np.array(sizes, dtype=np.int64), distortion=np.array(distortion),
                           points=points, method="nerfstudio",
                           report={"registered": len(names), "total": len(frames), "unregistered": []})
    recon.validate(str(path))
    return recon
