"""Stage "preprocess": any input (image folder -> COLMAP SfM, nerfstudio dataset, COLMAP model) into the
normalised dataset (`dualnerf.dataset`), plus sfm_report.json, and scene.toml / gt/edits/ carried over.

Inputs: upstream "scene" (a scene-stage result) or external "source" (a user folder), exactly one.
The input is only read; SfM works on converted copies in the scratch folder.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.stage import Resources, Stage, StageContext
from stages.numerics import NumpyNumerics


class PreprocessInputError(ValueError):
    """The step was wired with no input or with both inputs."""

    user_error = True


@dataclass(frozen=True)
class PreprocessParams:
    method: str = "auto"                    # auto | sfm | nerfstudio | colmap
    max_size: int = 512                     # long side of the stored images (pixels)
    holdout_every: int = 8                  # every k-th view held out for evaluation (0: none)
    seed: int = 0                           # SfM RANSAC / mapper seed
    matcher: str = "auto"                   # auto (exhaustive up to 150 images) | exhaustive | sequential
    camera_model: str = "auto"              # COLMAP camera model fitted by SfM; auto: pinhole unless the
                                            # matches support a radial term (see dualnerf.io.sfm)
    single_camera: bool = True              # one camera shared by all images
    min_registered_fraction: float = 0.5    # fail when SfM registers fewer images than this


class PreprocessStage(NumpyNumerics, Stage):
    name = "preprocess"
    # 2: SfM with more SIFT features, 2 px filter, pinhole unless distortion pays; 3: the radial trial's
    # bundle adjustment on one thread (its report's numbers were thread-scheduling dependent)
    version = "3"
    Params = PreprocessParams
    upstream = ("scene",)
    external = ("source",)
    resources = Resources(cpus=1, gpus=0, memory_gb=3)     # SfM runs on one thread (dualnerf.io.sfm)
    packages = ("pycolmap", "opencv-contrib-python-headless", "numpy", "OpenImageIO")

    def run(self, ctx: StageContext) -> None:
        import dataclasses

        from dualnerf.io import PreprocessConfig, preprocess

        given = [name for name in ("scene", "source") if name in ctx.inputs]
        if len(given) != 1:
            raise PreprocessInputError(
                f"preprocess needs exactly one input, 'scene' (a procedural scene step) or 'source' (a user "
                f"folder); got {given or 'none'}.")
        source = ctx.inputs[given[0]]
        if given == ["source"] and not Path(source).is_dir():
            raise PreprocessInputError(
                f"preprocess: input 'source' must be a folder, got the file {source}. Pass the folder holding "
                f"it (its whole content enters the cache key, so every image the file names must be in it).")
        p = ctx.params
        values = dataclasses.asdict(p)
        config = PreprocessConfig(**values)
        ctx.log.info("preprocessing %s (method %s)", source, p.method)
        report = preprocess(source, ctx.out_dir, config, scratch=ctx.scratch_dir / "sfm")
        for warning in report.get("warnings", []):
            ctx.log.warning(warning)
        ctx.log.info("registered %d/%d images, %s points, mean reprojection error %s px",
                     report["registered"], report["total"], report["points"], report["mean_reprojection_error"])
        ctx.record(source=str(source), seed=p.seed, method=report["method"], registered=report["registered"], total=report["total"],
                   points=report["points"], mean_reprojection_error=report["mean_reprojection_error"],
                   unregistered=report["unregistered"])
