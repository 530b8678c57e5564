"""Image editors for the dataset-update step of IDU. One interface:

    edit(render, original, instruction, seed, step) -> edited image (HxWx3 uint8 or float in [0,1])

`render` is the current (or SA-retreated) model's render of the view, `original` the view's original
training image, `seed` the per-call seed the loop records, `step` the training iteration.

- "ip2p": InstructPix2Pix through diffusers, as Instruct-NeRF2NeRF uses it (needs the weights).
- "synthetic": an InstructPix2Pix EMULATOR for procedural scenes with ground-truth edits. It is a
  simulator, named as such in its class name, its `identity`, and every log line and record.
Editors expose `identity` (dict, with "is_simulator") and `last_details` (dict about the latest call).
"""
from __future__ import annotations

from dualnerf.editors.base import EDITOR_KINDS, Editor, EditorError, to_float_image, to_uint8_image

__all__ = ["EDITOR_KINDS", "Editor", "EditorError", "load_editor", "to_float_image", "to_uint8_image"]


def load_editor(kind: str, *, instruction: str, model: str | None = None, device: str = "cpu",
                scene_folder=None, edit_id: str | None = None, names=None, originals=None,
                emulator_config=None, c2w=None) -> Editor:
    """Build an editor. "ip2p" needs `model` (a local diffusers folder or hub id); "synthetic" (the
    InstructPix2Pix EMULATOR) needs the folder with scene.toml + gt/edits/, the edit id, and the training
    views' names and original images (and optionally their cameras `c2w`, for the view-dependent
    background cast)."""
    if kind == "ip2p":
        from dualnerf.editors.ip2p import IP2P_HUB_ID, InstructPix2PixConfig, InstructPix2PixEditor

        return InstructPix2PixEditor(model or IP2P_HUB_ID, InstructPix2PixConfig(device=device))
    if kind == "synthetic":
        from dualnerf.editors.emulator import EmulatorConfig, InstructPix2PixEmulator

        if scene_folder is None or edit_id is None or names is None or originals is None:
            raise EditorError("editor 'synthetic' (InstructPix2Pix emulator) needs a scene folder with "
                              "scene.toml and gt/edits/, an edit_id, and the training views.")
        return InstructPix2PixEmulator.from_scene_folder(scene_folder, edit_id, instruction, names, originals,
                                                         emulator_config or EmulatorConfig(), c2w=c2w)
    raise EditorError(f"unknown editor '{kind}'; choose one of: {', '.join(EDITOR_KINDS)}.")
