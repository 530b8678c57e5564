"""Preprocess any supported source into the normalised dataset folder, with an SfM report.

Sources: a folder of images (COLMAP SfM via pycolmap), a nerfstudio dataset (transforms.json: known
cameras) or a COLMAP sparse model. The source is only read; all work happens in `out` and `scratch`.
"""
from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

from dualnerf.dataset import save_dataset
from dualnerf.io.build import UNDISTORT_MIN_PIXELS, build_dataset, carry_scene_files, distortion_pixels
from dualnerf.io.colmap import find_model, import_colmap_model
from dualnerf.io.errors import InputError
from dualnerf.io.nerfstudio import find_transforms, import_nerfstudio

METHODS = ("auto", "sfm", "nerfstudio", "colmap")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PreprocessConfig:
    method: str = "auto"            # auto | sfm | nerfstudio | colmap
    max_size: int = 512             # long side of the stored images, pixels
    holdout_every: int = 8          # every k-th view is held out (0: none)
    seed: int = 0                   # SfM RANSAC / mapper seed
    matcher: str = "auto"           # auto | exhaustive | sequential
    min_registered_fraction: float = 0.5
    single_camera: bool = True      # one shared camera for all images (same device, same zoom)
    camera_model: str = "auto"      # COLMAP model fitted by SfM ("auto": pinhole unless a radial term pays)


def detect_method(source: Path) -> str:
    if find_transforms(source) is not None:
        return "nerfstudio"
    if find_model(source) is not None:
        return "colmap"
    return "sfm"


def preprocess(source: Path, out: Path, config: PreprocessConfig, scratch: Path | None = None) -> dict:
    """Write the dataset for `source` into `out` (created); returns the SfM report (also sfm_report.json)."""
    source, out = Path(source), Path(out)
    if config.method not in METHODS:
        raise InputError(f"unknown preprocess method '{config.method}'; use one of {', '.join(METHODS)}.")
    if not source.exists():
        raise InputError(f"{source} does not exist; pass a folder of images, a nerfstudio dataset or a "
                         f"COLMAP model folder.")
    method = detect_method(source) if config.method == "auto" else config.method
    if method == "nerfstudio":
        transforms = find_transforms(source)
        if transforms is None and (source / "gt" / "transforms.json").is_file():
            transforms = source / "gt" / "transforms.json"    # a procedural scene's ground-truth cameras
        if transforms is None:
            raise InputError(f"{source}: method 'nerfstudio' needs a transforms.json in it.")
        recon = import_nerfstudio(transforms, root=source if source.is_dir() else source.parent)
    elif method == "colmap":
        recon = import_colmap_model(source)
    else:
        from dualnerf.io.sfm import run_sfm

        if scratch is None:
            import tempfile

            with tempfile.TemporaryDirectory(prefix="dualnerf-sfm-") as tmp:
                recon = run_sfm(source, Path(tmp), config)
        else:
            recon = run_sfm(source, Path(scratch), config)
    recon = _sorted_by_name(recon)
    dataset = build_dataset(recon, config.max_size, config.holdout_every,
                            source={"method": method, "name": source.resolve().name, "config": asdict(config)})
    out.mkdir(parents=True, exist_ok=True)
    save_dataset(dataset, out)
    carried = carry_scene_files(source, out, dataset.names, (dataset.width, dataset.height))
    report = {"method": method, "registered": recon.report.get("registered", len(recon.names)),
              "total": recon.report.get("total", len(recon.names)),
              "unregistered": recon.report.get("unregistered", []),
              "mean_reprojection_error": recon.report.get("mean_reprojection_error"),
              "points": recon.report.get("points", 0 if recon.points is None else len(recon.points)),
              "focal_px": float(recon.intrinsics[0, 0]), "distortion": [float(v) for v in recon.distortion[0]],
              "undistorted": bool(distortion_pixels(recon.distortion[0], recon.intrinsics[0], *recon.sizes[0])
                                  > UNDISTORT_MIN_PIXELS),
              "gt_edits": carried,
              **{k: v for k, v in recon.report.items() if k not in ("registered", "total", "unregistered",
                                                                   "mean_reprojection_error", "points")}}
    (out / "sfm_report.json").write_text(json.dumps(report, indent=1))
    return report


def _sorted_by_name(recon):
    import numpy as np

    order = np.argsort(recon.names, kind="stable")
    recon.names = [recon.names[i] for i in order]
    recon.image_paths = [recon.image_paths[i] for i in order]
    for attr in ("c2w", "intrinsics", "sizes", "distortion"):
        setattr(recon, attr, getattr(recon, attr)[order])
    return recon
