"""Structure from motion with COLMAP (pycolmap 4.x): SIFT, exhaustive or sequential matching,
incremental mapping; keeps the largest model.

The input images are first read, checked and converted (EXIF orientation, 16-bit, RGBA, grayscale) to
8-bit PNG copies in the scratch folder, so COLMAP sees exactly the pixels the dataset will store and the
user's folder is never touched. Seeds are set explicitly. Feature extraction runs on one thread: with
several, COLMAP's result changed between runs (measured: camera centres moved by up to 0.07 in
normalised units on `tiny`), while matching and mapping gave identical results with 1 or 2 threads,
so `num_threads` only changes speed.
"""
from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np

from dualnerf.io.build import check_uniform_size
from dualnerf.io.colmap import reconstruction_from_pycolmap
from dualnerf.io.errors import InputError
from dualnerf.io.images import list_images, read_image
from dualnerf.io.reconstruction import Reconstruction

EXHAUSTIVE_LIMIT = 150      # beyond this many images, match each only with its neighbours in name order
SEQUENTIAL_OVERLAP = 12
SFM_MAX_IMAGE_SIZE = 1600   # SIFT runs on images downscaled to this long side (COLMAP rescales keypoints)
log = logging.getLogger(__name__)


def prepare_images(source: Path, folder: Path) -> tuple[list[str], list[Path], np.ndarray]:
    """Validated 8-bit RGB PNG copies of the source images in `folder`; returns the original file names,
    the original paths and the (N, 2) sizes. Raises InputError for too few or unreadable images."""
    import cv2

    paths = list_images(source)
    if len(paths) < 3:
        raise InputError(f"{source}: found {len(paths)} image(s); SfM needs at least 3 overlapping views "
                         f"(ideally 20+).")
    folder.mkdir(parents=True, exist_ok=True)
    names, sizes = [], []
    stems = [p.stem for p in paths]
    if len(set(stems)) != len(stems):
        dupes = sorted({s for s in stems if stems.count(s) > 1})
        raise InputError(f"{source}: several files share a name up to the extension ({', '.join(dupes[:10])});"
                         f" rename them so each view has a unique name.")
    for path in paths:
        image = read_image(path)
        names.append(path.name)
        sizes.append(image.shape[1::-1])
        if not cv2.imwrite(str(folder / (path.stem + ".png")), image[..., ::-1]):
            raise OSError(f"could not write {folder / (path.stem + '.png')}")
    sizes = np.array(sizes, dtype=np.int64)
    check_uniform_size(names, sizes, str(source))
    return names, paths, sizes


def run_sfm(source: Path, scratch: Path, config) -> Reconstruction:
    """Reconstruct the cameras of the images in `source`; `config` is a PreprocessConfig."""
    from dualnerf.io.colmap import SUPPORTED_MODELS, load_pycolmap

    pycolmap = load_pycolmap()

    if config.matcher not in ("auto", "exhaustive", "sequential"):
        raise InputError(f"unknown matcher '{config.matcher}'; use auto, exhaustive or sequential.")
    if config.camera_model not in SUPPORTED_MODELS:
        raise InputError(f"camera_model '{config.camera_model}' is not supported for SfM; use one of "
                         f"{', '.join(SUPPORTED_MODELS)}.")
    scratch = Path(scratch)
    if scratch.exists():
        shutil.rmtree(scratch)      # a retried attempt starts clean: COLMAP appends to databases
    work_images = scratch / "images"
    names, paths, _sizes = prepare_images(Path(source), work_images)
    database = scratch / "database.db"
    threads = max(1, int(config.num_threads))
    pycolmap.set_random_seed(int(config.seed))

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1      # deterministic results (see the module docstring)
    extraction.use_gpu = False
    extraction.max_image_size = SFM_MAX_IMAGE_SIZE
    extraction.sift.max_num_features = 8192
    camera_mode = pycolmap.CameraMode.SINGLE if config.single_camera else pycolmap.CameraMode.PER_IMAGE
    work_names = [Path(n).stem + ".png" for n in names]
    pycolmap.extract_features(database, work_images, image_names=work_names, camera_mode=camera_mode,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = False
    matcher = config.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= EXHAUSTIVE_LIMIT else "sequential"
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = int(config.seed)
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.num_threads = threads
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.random_seed = int(config.seed)
    mapping.mapper.random_seed = int(config.seed)
    mapping.mapper.num_threads = threads
    models = pycolmap.incremental_mapping(database, work_images, scratch / "sparse", options=mapping)
    best = max(models.values(), key=lambda m: m.num_reg_images(), default=None)
    registered = best.num_reg_images() if best is not None else 0
    recon = reconstruction_from_pycolmap(best, work_images, total=len(names)) if best is not None else None
    stem_to_name = {Path(n).stem: n for n in names}
    registered_names = set() if recon is None else {stem_to_name[Path(n).stem] for n in recon.names}
    unregistered = [n for n in names if n not in registered_names]
    if registered < config.min_registered_fraction * len(names) or registered < 3:
        raise InputError(
            f"{source}: SfM registered only {registered} of {len(names)} images (fewer than "
            f"{config.min_registered_fraction:.0%}). Unregistered: {', '.join(unregistered[:30])}"
            f"{' ...' if len(unregistered) > 30 else ''}. Hints: neighbouring photos need strong overlap "
            f"(at most ~10-15 degrees apart), the scene needs visible texture (plain walls, sky and "
            f"reflections do not match), and very long captures register better with matcher='sequential' "
            f"when the files are named in capture order.")
    # Map COLMAP's working copies back to the user's file names and paths.
    index = {n: i for i, n in enumerate(names)}
    recon.names = [stem_to_name[Path(n).stem] for n in recon.names]
    recon.image_paths = [paths[index[n]] for n in recon.names]
    recon.method = "sfm"
    recon.report.update({"unregistered": unregistered, "matcher": matcher, "camera_model": config.camera_model,
                         "models_found": len(models)})
    recon.validate(str(source))
    return recon
