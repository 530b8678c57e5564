"""Structure from motion with COLMAP (pycolmap 4.x): SIFT, exhaustive or sequential matching,
incremental mapping; keeps the largest model.

The input images are first read, checked and converted (EXIF orientation, 16-bit, RGBA, grayscale) to
8-bit PNG copies in the scratch folder, so COLMAP sees exactly the pixels the dataset will store and the
user's folder is never touched. Seeds are set explicitly and every COLMAP step runs on one thread:
with several, the result depends on how the threads are scheduled. Feature extraction with 2 threads
moved camera centres by up to 0.07 in normalised units between runs on `tiny`; matching and mapping
with 2 threads agreed with 1 thread on a quiet machine but not in a CI run (centres moved by ~0.002;
not reproduced here, so the cause, probably thread scheduling in RANSAC or bundle adjustment, is a guess).
A preprocess is computed once per scene and cached, so the lost speed costs little.

Accuracy (max camera-centre error after a similarity alignment, % of the camera-circle radius, measured
on `tiny` and a 40-view 200-degree arc of the tiny world with other radius, height and FOV, seeds 0-2):
COLMAP's defaults gave 1.1-1.3% and 1.9-2.0%; a lower SIFT peak threshold (more features on small,
low-contrast images) with observations beyond 2 px filtered out of the model gives 0.50-0.56% and
0.80-0.92%. Lens distortion is only kept when the data supports it (`camera_model = "auto"`): the model
is fitted as a pinhole camera, then refined once more with a radial term, and the radial term is kept
only if it lowers the mean reprojection error by at least `DISTORTION_MIN_GAIN`. On distortion-free
images it otherwise takes an arbitrary small k1 that changes nothing (0.06% lower error on `tiny`),
and undistorting with it would resample every image for nothing.
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
SIFT_PEAK_THRESHOLD = 0.002  # COLMAP's default 0.0067 finds too few features on small images (see above)
FILTER_MAX_REPROJ_ERROR = 2.0   # px; COLMAP's default 4 keeps poorly localised matches in the model
DISTORTION_MIN_GAIN = 0.02  # relative drop of the mean reprojection error a radial term must give
UNIFORM_STD = 2.0           # grey-level standard deviation (of 255) below which an image is "nearly uniform"
AUTO_MODEL = "auto"
log = logging.getLogger(__name__)


def prepare_images(source: Path, folder: Path, warnings: list[str] | None = None
                   ) -> tuple[list[str], list[Path], np.ndarray]:
    """Validated 8-bit RGB PNG copies of the source images in `folder`; returns the original file names,
    the original paths and the (N, 2) sizes. Raises InputError for too few or unreadable images; nearly
    uniform images are warned about (and the warning appended to `warnings`)."""
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
    uniform = []
    for path in paths:
        image = read_image(path)
        names.append(path.name)
        std = float(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).std())
        if std < UNIFORM_STD:
            uniform.append(f"{path.name} (grey-level std {std:.2f})")
        sizes.append(image.shape[1::-1])
        if not cv2.imwrite(str(folder / (path.stem + ".png")), image[..., ::-1]):
            raise OSError(f"could not write {folder / (path.stem + '.png')}")
    sizes = np.array(sizes, dtype=np.int64)
    check_uniform_size(names, sizes, str(source))
    if uniform:
        _warn(warnings, f"{source}: {len(uniform)} image(s) are nearly uniform (no texture SfM can match; black, "
             f"blank or overexposed frames): {', '.join(uniform[:20])}{' ...' if len(uniform) > 20 else ''}. "
             f"They will not register and can pull neighbouring views out; remove them.")
    return names, paths, sizes


def _warn(warnings: list[str] | None, message: str) -> None:
    """Log a warning and keep it for the SfM report (the stage repeats the report's warnings in its log)."""
    log.warning(message)
    if warnings is not None:
        warnings.append(message)


def run_sfm(source: Path, scratch: Path, config) -> Reconstruction:
    """Reconstruct the cameras of the images in `source`; `config` is a PreprocessConfig."""
    from dualnerf.io.colmap import SUPPORTED_MODELS, load_pycolmap

    pycolmap = load_pycolmap()

    if config.matcher not in ("auto", "exhaustive", "sequential"):
        raise InputError(f"unknown matcher '{config.matcher}'; use auto, exhaustive or sequential.")
    if config.camera_model not in (AUTO_MODEL, *SUPPORTED_MODELS):
        raise InputError(f"camera_model '{config.camera_model}' is not supported for SfM; use one of "
                         f"{', '.join((AUTO_MODEL, *SUPPORTED_MODELS))}.")
    warnings: list[str] = []
    scratch = Path(scratch)
    if scratch.exists():
        shutil.rmtree(scratch)      # a retried attempt starts clean: COLMAP appends to databases
    work_images = scratch / "images"
    names, paths, _sizes = prepare_images(Path(source), work_images, warnings)
    database = scratch / "database.db"
    threads = 1                     # deterministic results (see the module docstring)
    pycolmap.set_random_seed(int(config.seed))

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE" if config.camera_model == AUTO_MODEL else config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.use_gpu = False
    extraction.max_image_size = SFM_MAX_IMAGE_SIZE
    extraction.sift.max_num_features = 8192
    extraction.sift.peak_threshold = SIFT_PEAK_THRESHOLD
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
    mapping.mapper.filter_max_reproj_error = FILTER_MAX_REPROJ_ERROR
    models = pycolmap.incremental_mapping(database, work_images, scratch / "sparse", options=mapping)
    best = max(models.values(), key=lambda m: m.num_reg_images(), default=None)
    model_choice = None
    if best is not None and config.camera_model == AUTO_MODEL:
        best, model_choice = _radial_if_supported(pycolmap, best, threads)
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
    if unregistered:
        _warn(warnings, f"{source}: SfM could not register {len(unregistered)} of {len(names)} image(s), which are "
             f"left out of the dataset: {', '.join(unregistered[:30])}{' ...' if len(unregistered) > 30 else ''}."
             f" Check that they overlap their neighbours (at most ~10-15 degrees apart) and show texture.")
    camera_model = next(iter(best.cameras.values())).model.name
    recon.report.update({"unregistered": unregistered, "matcher": matcher, "camera_model": camera_model,
                         "camera_model_requested": config.camera_model, "models_found": len(models),
                         "warnings": warnings})
    if model_choice is not None:
        recon.report["camera_model_choice"] = model_choice
    recon.validate(str(source))
    return recon


def _radial_if_supported(pycolmap, model, threads: int):
    """(model, why): the pinhole `model`, or a copy refined with a radial term (SIMPLE_RADIAL) when that
    lowers the mean reprojection error by at least DISTORTION_MIN_GAIN: a simpler model that explains
    the matches equally well is kept, so no distortion is estimated or undone that the data lacks."""
    pinhole_error = model.compute_mean_reprojection_error()
    radial = pycolmap.Reconstruction(model)
    for camera_id, camera in list(radial.cameras.items()):
        f, cx, cy = camera.params
        radial.cameras[camera_id] = pycolmap.Camera(model="SIMPLE_RADIAL", width=camera.width,
                                                    height=camera.height, params=[f, cx, cy, 0.0],
                                                    camera_id=camera_id)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_extra_params = True
    options.print_summary = False
    # Ceres defaults to every core (num_threads -1); its multi-threaded sums moved the refined k1 and the
    # errors in their last bits between two runs of one key (campsite), and could flip the model choice.
    options.ceres.solver_options.num_threads = threads
    pycolmap.bundle_adjustment(radial, options)
    radial_error = radial.compute_mean_reprojection_error()
    gain = (pinhole_error - radial_error) / pinhole_error if pinhole_error > 0 else 0.0
    k1 = float(next(iter(radial.cameras.values())).params[3])
    why = {"pinhole_reprojection_error": float(pinhole_error), "radial_reprojection_error": float(radial_error),
           "radial_k1": k1, "gain": float(gain), "min_gain": DISTORTION_MIN_GAIN}
    if gain >= DISTORTION_MIN_GAIN:
        return radial, {**why, "chosen": "SIMPLE_RADIAL"}
    return model, {**why, "chosen": "SIMPLE_PINHOLE"}
