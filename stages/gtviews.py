"""Stage "gtviews": the ground truth of a procedural scene at every evaluation camera, for the per-frame
baseline's InstructPix2Pix EMULATOR (stages.perframe), which needs each view's ground-truth edit.

The cameras are those of the unedited evaluation ("original" input: its camera path and fixed views),
given in the dataset's normalised frame; they are mapped back into the scene frame by the similarity
between the dataset's and the scene's cameras (dualnerf.scenes.views, checked on every view) and
rendered by the scene's own ray caster, original and edited, at the scene's resolution and area-resized
to the evaluation size as preprocess resizes the stored ground truth. One step per scene edit and
camera set: shared by every seed and editor setting of the per-frame rows.

Outputs:
    frames/{original,gt_edit,gt_mask}/0000.png ...    at the camera-path frames
    views/{original,gt_edit,gt_mask}/<name>            at the fixed views
    gtviews.json                                       scene, edit, alignment residuals

Rendered images go to the step's scratch folder one by one (renamed into place when complete), so a
killed run resumes after the last finished view.
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.stage import Resources, Stage, StageContext
from stages import layout
from stages.evaluation_io import PerFrameError, evaluation_cameras
from stages.images import write_png
from stages.numerics import NumpyNumerics

KINDS = layout.GROUND_TRUTH_KINDS


@dataclass(frozen=True)
class GroundTruthViewsParams:
    edit_id: str = ""              # the scene edit whose ground truth is rendered
    scene_supersample: int = 0     # the procedural scene's supersample (0: its default), to re-render it exactly


class GroundTruthViewsStage(NumpyNumerics, Stage):
    name = "gtviews"
    version = "1"
    Params = GroundTruthViewsParams
    upstream = ("dataset", "original")
    resources = Resources(cpus=1, gpus=0, memory_gb=2)
    packages = ("numpy", "opencv-contrib-python-headless")

    def run(self, ctx: StageContext) -> None:
        from threadpoolctl import threadpool_limits

        from dualnerf.dataset import load_dataset
        from dualnerf.scenes.spec import SceneSpecError
        from dualnerf.scenes.views import SceneViewRenderer

        p = ctx.params
        data_dir = Path(ctx.inputs["dataset"])
        dataset = load_dataset(data_dir)
        try:
            renderer = SceneViewRenderer(data_dir, dataset, supersample=p.scene_supersample)
            renderer.spec.edit(p.edit_id)
        except SceneSpecError as err:
            raise PerFrameError(f"gtviews: the per-frame baseline's emulator needs the procedural scene behind "
                                f"{data_dir}: {err} For real captures use editor 'ip2p'.") from None
        jobs = evaluation_cameras(Path(ctx.inputs["original"]), dataset)
        work = ctx.scratch_dir / "gt"
        done = sum(1 for group, name, *_ in jobs if all((work / group / k / name).is_file() for k in KINDS))
        if done:
            ctx.log.info("resuming after %d of %d ground-truth views", done, len(jobs))
        with ctx.progress(len(jobs), "render ground-truth views", initial=done) as bar:
            for group, name, c2w, size, _ in jobs:
                if all((work / group / k / name).is_file() for k in KINDS):
                    continue
                # The ray caster's small matrix products only contend with a threaded BLAS (scenes.generate).
                with threadpool_limits(limits=1, user_api="blas"):
                    original, edited, mask = renderer.render(c2w, p.edit_id, size)
                mask_image = np.repeat(mask[..., None], 3, -1).astype(np.uint8) * 255
                for kind, image in zip(KINDS, (original, edited, mask_image)):
                    final = work / group / kind / name
                    partial = final.with_name(f".partial-{name}")
                    write_png(partial, image)
                    os.replace(partial, final)
                bar.update()
        for group in (layout.FRAMES, layout.VIEWS):
            shutil.copytree(work / group, ctx.out_dir / group)
        similarity = renderer.to_scene
        (ctx.out_dir / "gtviews.json").write_text(json.dumps({
            "scene": renderer.spec.name, "edit_id": p.edit_id, "renderer": "dualnerf.scenes ray caster",
            "alignment": {"scale": similarity.scale, "rotation_residual_degrees": similarity.rotation_residual_degrees,
                          "centre_residual_of_radius": similarity.centre_residual},
            "images": len(jobs)}, indent=1))
        ctx.record(scene=renderer.spec.name, edit_id=p.edit_id, randomness="none: deterministic ray caster",
                   alignment_rotation_residual_degrees=similarity.rotation_residual_degrees)
