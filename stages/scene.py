"""Stage "scene": render a procedural scene (synthetic views + ground-truth edits) into a scene folder.

The folder layout is the contract in `dualnerf.scenes.spec`. Overrides left at 0 keep the scene's
defaults (`dualnerf.scenes.SCENES[name]`).
"""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.stage import Resources, Stage, StageContext
from stages.numerics import NumpyNumerics


@dataclass(frozen=True)
class SceneParams:
    name: str = "tiny"      # the procedural scene (`dualnerf scene list`)
    seed: int = 0           # texture seed
    width: int = 0          # 0: the scene's default
    height: int = 0         # 0: the scene's default
    n_views: int = 0        # cameras on the scene's arc (0: the scene's default)
    supersample: int = 0    # samples per pixel side, for anti-aliasing (0: the scene's default)
    workers: int = 0        # non-semantic: render processes (0: the threads the engine grants)


class SceneStage(NumpyNumerics, Stage):
    name = "scene"
    # 2: campsite gained the geometry edit 'canoe' (gt/edits/canoe) and scene.toml records each edit's
    # kind; the views and the earlier edits render byte-identically. 3: every edit's alternative modes
    # (gt/edits/<edit>.<mode>/, listed as `modes` in scene.toml) for the emulator's mode lock-in; the
    # views and the ground-truth edits render byte-identically.
    version = "3"
    Params = SceneParams
    resources = Resources(cpus=2, gpus=0, memory_gb=2)
    nonsemantic_params = frozenset({"workers"})
    packages = ("numpy", "opencv-contrib-python-headless")

    def run(self, ctx: StageContext) -> None:
        from dualnerf.scenes import generate_scene, scene_config
        from dualnerf.scenes.generate import GENERATOR

        p = ctx.params
        overrides = {k: v for k, v in (("width", p.width), ("height", p.height), ("n_views", p.n_views),
                                       ("supersample", p.supersample)) if v}
        config = scene_config(p.name, **overrides)
        workers = p.workers or max(1, ctx.threads)
        ctx.log.info("rendering synthetic scene '%s' (%d views, %dx%d) with %d process(es)", p.name,
                     config.n_views, config.width, config.height, workers)
        with ctx.progress(config.n_views, f"render {p.name}") as bar:
            generate_scene(p.name, ctx.out_dir, seed=p.seed, workers=workers,
                           progress=lambda done, total: bar.update(1), **overrides)
        ctx.record(seed=p.seed, synthetic=True, generator=GENERATOR, n_views=config.n_views,
                   width=config.width, height=config.height)
