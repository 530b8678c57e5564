"""Stage "perframe": the per-frame InstructPix2Pix baseline (paper Table 1, first row). No 3D editing:
every evaluation view (the camera-path frames and the fixed views of the unedited evaluation) is the
editor's output for f_S's render of that view, edited independently of all others. The evaluate stage
then scores these images with the same metrics as every other row (its "perframe" input).

Inputs: "dataset" (preprocess result), "original" (the unedited scene's evaluate result: its f_S renders,
camera path and view names, so the baseline edits exactly the images the other rows are compared on)
and, for the emulator, "gtviews" (stages.gtviews: the scene re-rendered, original and edited, at those
cameras).

Editors: "ip2p" is the real baseline (InstructPix2Pix conditioned on, and starting from, f_S's render).
"synthetic" is the InstructPix2Pix EMULATOR (a simulator), built per view from that view's ground truth.

Outputs:
    frames/edited/0000.png ...     the edited path frames
    views/edited/<name>            the edited fixed views
    edit.json                      method, editor identity (simulator flag), instruction, seeds, per-image
                                   editor details

Editor seeds: image k (path frames first, then views) is edited with seed `seed` and step k, i.e. the
editor's generator is seeded by (seed, k); recorded in the manifest.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from pipeline.stage import Resources, Stage, StageContext
from stages import layout
from stages.checkpoints import resume_images, save_images
from stages.evaluation_io import PerFrameError, evaluation_cameras, read_ground_truth
from stages.images import write_png
from stages.numerics import TorchNumerics, semantic_values, use_step_threads

CHECKPOINT_EVERY = 16          # edited images between in-stage checkpoints

__all__ = ["PerFrameError", "PerFrameParams", "PerFrameStage"]


@dataclass(frozen=True)
class PerFrameParams:
    instruction: str = ""          # default: the edit's instruction from the dataset's scene.toml
    edit_id: str = ""              # the scene edit (the emulator's ground truth)
    editor: str = "synthetic"      # "synthetic" (InstructPix2Pix EMULATOR, a simulator) or "ip2p"
    editor_model: str = ""         # ip2p: local diffusers folder or hub id
    seed: int = 0                  # editor seed: image k is edited with (seed, k)
    device: str = "cpu"            # "cpu" or "cuda" (the editor's)
    num_threads: int = 0           # non-semantic; 0: the threads the engine grants


class PerFrameStage(TorchNumerics, Stage):
    name = "perframe"
    # 2: renders on kernels that flush subnormals (fit 8)
    version = "2"
    Params = PerFrameParams
    upstream = ("dataset", "original", "gtviews")
    resources = Resources(cpus=1, gpus=0, memory_gb=3)
    nonsemantic_params = frozenset({"num_threads"})
    packages = ("torch", "numpy", "opencv-contrib-python-headless", "diffusers", "transformers")

    def run(self, ctx: StageContext) -> None:
        from dualnerf.dataset import load_dataset
        from dualnerf.editors import EDITOR_KINDS, to_float_image, to_uint8_image

        p = ctx.params
        if p.editor not in EDITOR_KINDS:
            raise PerFrameError(f"perframe: unknown editor '{p.editor}'; choose one of {', '.join(EDITOR_KINDS)}.")
        if "original" not in ctx.inputs or "dataset" not in ctx.inputs:
            raise PerFrameError("perframe needs the inputs 'dataset' and 'original' (the unedited evaluation).")
        use_step_threads(ctx, p.num_threads)
        data_dir, original_dir = Path(ctx.inputs["dataset"]), Path(ctx.inputs["original"])
        dataset = load_dataset(data_dir)
        instruction = p.instruction or _scene_instruction(data_dir, p.edit_id)
        if not instruction:
            raise PerFrameError(f"perframe: no instruction; set 'instruction', or 'edit_id' naming an edit of "
                                f"{data_dir / 'scene.toml'}.")
        editor, ground_truth = _editor(p, data_dir, instruction, ctx.inputs.get("gtviews"))
        jobs = evaluation_cameras(original_dir, dataset)      # (group, name, c2w, (w, h), f_S render)

        images, details = resume_images(ctx, len(jobs), with_details=True, restart="editing from the start")
        done = list(zip(images, details))
        if done:
            ctx.log.info("resuming after %d of %d edited images (checkpoint)", len(done), len(jobs))
        with ctx.progress(len(jobs), f"per-frame {p.editor} edits", initial=len(done)) as bar:
            for k, (group, name, c2w, size, render) in enumerate(jobs):
                if k < len(done):
                    continue
                if ground_truth is not None:
                    original, gt_edit, mask = ground_truth(group, name)
                    edited = editor(render, original, gt_edit, mask, instruction, p.seed, k)
                else:
                    edited = editor(render, render, None, None, instruction, p.seed, k)
                edited = to_uint8_image(to_float_image(edited, "edited image"))
                done.append((edited, dict(editor.last_details)))
                bar.update()
                if len(done) % CHECKPOINT_EVERY == 0 and len(done) < len(jobs):
                    save_images(ctx, [image for image, _ in done], [detail for _, detail in done])

        out = ctx.out_dir
        details = []
        for (group, name, *_), (edited, detail) in zip(jobs, done):
            write_png(layout.image_path(out, group, layout.EDITED, name), edited)
            details.append({"group": group, "name": name, "editor_step": len(details), **detail})
        identity = editor.identity
        (out / layout.EDIT_RECORD).write_text(json.dumps({
            "method": "per-frame", "instruction": instruction, "edit_id": p.edit_id, "editor": identity,
            "editor_is_simulator": bool(identity.get("is_simulator")), "params": semantic_values(p, self.nonsemantic_params),
            "images": details}, indent=1))
        ctx.record(editor=identity, editor_is_simulator=bool(identity.get("is_simulator")),
                   seeds={"seed": p.seed, "editor_seed": "(seed, k) for image k: path frames, then views"},
                   images=len(jobs))
        if identity.get("is_simulator"):
            ctx.log.info("per-frame editor: InstructPix2PixEmulator (a SIMULATOR of InstructPix2Pix)")


class _EmulatorPerView:
    """The InstructPix2Pix emulator for one view at a time, from ground truth rendered for that view."""

    def __init__(self, edit_id: str, instruction: str, config):
        from dualnerf.editors.emulator import InstructPix2PixEmulator

        self.edit_id = edit_id
        self.config = config
        self.last_details: dict = {}
        self.identity = {**InstructPix2PixEmulator([], instruction, edit_id, config).identity,
                         "use": "per-frame: built per view from ground truth rendered at that view"}

    def __call__(self, render, original, gt_edit, mask, instruction, seed, step):
        from dualnerf.editors.emulator import EmulatedView, InstructPix2PixEmulator

        emulator = InstructPix2PixEmulator([EmulatedView(original, gt_edit, mask)], instruction,
                                           self.edit_id, self.config)
        edited = emulator.edit(render, original, instruction, seed, step)
        self.last_details = emulator.last_details
        return edited


class _Editor:
    def __init__(self, editor):
        self.editor = editor

    @property
    def identity(self) -> dict:
        return self.editor.identity

    @property
    def last_details(self) -> dict:
        return self.editor.last_details

    def __call__(self, render, original, gt_edit, mask, instruction, seed, step):
        return self.editor.edit(render, original, instruction, seed, step)


def _editor(p: PerFrameParams, data_dir: Path, instruction: str, gtviews):
    """(editor callable, ground-truth reader (group, name) -> (original, gt_edit, mask) or None)."""
    from dualnerf.editors import load_editor

    if p.editor == "ip2p":
        return _Editor(load_editor("ip2p", instruction=instruction, model=p.editor_model or None,
                                   device=p.device)), None
    from dualnerf.editors.emulator import EmulatorConfig
    from dualnerf.scenes.spec import load_scene_spec

    if not p.edit_id:
        raise PerFrameError("perframe: editor 'synthetic' (the InstructPix2Pix emulator) needs edit_id, the "
                            "scene edit whose ground truth it emulates; or use editor 'ip2p'.")
    if gtviews is None:
        raise PerFrameError("perframe: editor 'synthetic' (the InstructPix2Pix emulator) needs the 'gtviews' "
                            "input (the scene's ground truth at the evaluation cameras); or use editor 'ip2p'.")
    spec = load_scene_spec(data_dir).edit(p.edit_id)
    if instruction != spec.instruction:
        raise PerFrameError(f"perframe: the InstructPix2Pix emulator can only emulate edit '{p.edit_id}' "
                            f"('{spec.instruction}'), got instruction '{instruction}'; use editor 'ip2p'.")
    return (_EmulatorPerView(p.edit_id, instruction, EmulatorConfig()),
            lambda group, name: read_ground_truth(Path(gtviews), group, name))


def _scene_instruction(data_dir: Path, edit_id: str) -> str:
    if not edit_id or not (data_dir / "scene.toml").is_file():
        return ""
    from dualnerf.scenes.spec import load_scene_spec

    return load_scene_spec(data_dir).edit(edit_id).instruction
