"""Read a COLMAP sparse model (cameras/images/points3D, .bin or .txt) into a Reconstruction."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dualnerf.confine import check_file_name, confine
from dualnerf.io.errors import InputError
from dualnerf.io.reconstruction import Reconstruction

# COLMAP model name -> how its params map to (fx, fy, cx, cy) and OpenCV distortion (k1, k2, p1, p2, k3).
_MODELS = {
    "SIMPLE_PINHOLE": lambda p: ((p[0], p[0], p[1], p[2]), (0, 0, 0, 0, 0)),
    "PINHOLE": lambda p: ((p[0], p[1], p[2], p[3]), (0, 0, 0, 0, 0)),
    "SIMPLE_RADIAL": lambda p: ((p[0], p[0], p[1], p[2]), (p[3], 0, 0, 0, 0)),
    "RADIAL": lambda p: ((p[0], p[0], p[1], p[2]), (p[3], p[4], 0, 0, 0)),
    "OPENCV": lambda p: ((p[0], p[1], p[2], p[3]), (p[4], p[5], p[6], p[7], 0)),
}

SUPPORTED_MODELS = tuple(_MODELS)


def load_pycolmap():
    """The pycolmap module, imported so that SIGTERM keeps the handler Python had.

    On import pycolmap installs glog's failure signal handler, SIGTERM included: a terminated worker
    would print a native stack dump and die without unwinding (no clean stop, lease not released).
    glog keeps its handlers for real crashes (SIGSEGV, SIGABRT, ...); only SIGTERM is given back.
    COLMAP's own INFO logging is turned off (warnings and errors still print).
    """
    import signal
    import threading

    # Python still records its own handler after glog replaced it at the C level: setting it again
    # restores it, also when pycolmap was imported before.
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGTERM) if main_thread else None
    import pycolmap

    if previous is not None:
        signal.signal(signal.SIGTERM, previous)
    # COLMAP's INFO lines (hundreds per reconstruction) flooded the terminal of every run; keep its
    # warnings and errors. The SfM step reports what matters in sfm_report.json and its log.
    pycolmap.logging.minloglevel = pycolmap.logging.WARNING
    return pycolmap


def find_model(source: Path) -> Path | None:
    """The sparse model folder in `source` (itself, sparse/0 or sparse), else None."""
    source = Path(source)
    for candidate in (source, source / "sparse" / "0", source / "sparse"):
        if any((candidate / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return candidate
    return None


def find_image_folder(source: Path, model_dir: Path) -> Path:
    for candidate in (Path(source) / "images", model_dir.parent / "images", model_dir.parent.parent / "images"):
        if candidate.is_dir():
            return candidate
    raise InputError(f"{model_dir}: found a COLMAP model but no images/ folder next to it (looked in "
                     f"{Path(source) / 'images'} and the model's parent folders); put the images there.")


def reconstruction_from_pycolmap(model, image_dir: Path, total: int | None = None,
                                 root: Path | None = None) -> Reconstruction:
    """Convert a pycolmap.Reconstruction (COLMAP world->camera poses) into our Reconstruction.
    With `root` (the scene folder) every image the model names must lie inside it."""
    names, paths, c2w, intrinsics, sizes, distortion = [], [], [], [], [], []
    for image_id in sorted(model.images, key=lambda k: model.images[k].name):
        image = model.images[image_id]
        if not image.has_pose:
            continue
        camera = model.cameras[image.camera_id]
        model_name = camera.model.name
        if model_name not in _MODELS:
            raise InputError(f"{image_dir}: camera model {model_name} is not supported (supported: "
                             f"{', '.join(_MODELS)}); undistort with `colmap image_undistorter` first.")
        k, dist = _MODELS[model_name](np.asarray(camera.params, dtype=np.float64))
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        image_path = image_dir / image.name
        if root is not None:
            where = f"{image_dir.parent}: COLMAP model image {image_id}"
            image_path = confine(image_path, root, error=InputError, where=where, field="image name",
                                 value=image.name)
            check_file_name(Path(image.name).name, error=InputError, where=where, field="image file name")
        names.append(Path(image.name).name)
        paths.append(image_path)
        c2w.append(np.linalg.inv(w2c))
        # COLMAP puts pixel centres at integer + 0.5 too, so cx, cy carry over unchanged.
        intrinsics.append(k)
        sizes.append([camera.width, camera.height])
        distortion.append(dist)
    points = np.array([p.xyz for p in model.points3D.values()], dtype=np.float64).reshape(-1, 3)
    registered = len(names)
    errors = [p.error for p in model.points3D.values()]
    report = {"registered": registered, "total": total if total is not None else registered,
              "points": len(points),
              "mean_reprojection_error": float(np.mean(errors)) if errors else None}
    return Reconstruction(names=names, image_paths=paths, c2w=np.array(c2w).reshape(-1, 4, 4),
                          intrinsics=np.array(intrinsics).reshape(-1, 4),
                          sizes=np.array(sizes, dtype=np.int64).reshape(-1, 2),
                          distortion=np.array(distortion, dtype=np.float64).reshape(-1, 5),
                          points=points if len(points) else None, report=report)


def import_colmap_model(source: Path) -> Reconstruction:
    pycolmap = load_pycolmap()

    model_dir = find_model(source)
    if model_dir is None:
        raise InputError(f"{source}: no COLMAP model (cameras.bin/.txt) in it, in sparse/0 or in sparse.")
    try:
        model = pycolmap.Reconstruction(str(model_dir))
    except (RuntimeError, ValueError) as err:    # pycolmap raises plain RuntimeError on malformed files
        raise InputError(f"{model_dir}: the COLMAP model could not be read ({err}); re-export it.") from None
    found = find_image_folder(source, model_dir)
    image_dir = confine(found, source, error=InputError, where=str(model_dir), field="images folder", value=found)
    recon = reconstruction_from_pycolmap(model, image_dir, root=source)
    recon.report["total"] = len(model.images)
    recon.report["unregistered"] = sorted(Path(model.images[i].name).name for i in model.images
                                          if not model.images[i].has_pose)
    missing = [str(p) for p in recon.image_paths if not p.is_file()]
    if missing:
        raise InputError(f"{model_dir}: {len(missing)} image(s) of the model are missing: "
                         f"{', '.join(missing[:10])}; copy them into {image_dir}.")
    recon.method = "colmap"
    recon.validate(str(model_dir))
    return recon
