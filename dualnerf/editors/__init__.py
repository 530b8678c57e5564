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

from typing import Protocol, runtime_checkable

import numpy as np

EDITOR_KINDS = ("synthetic", "ip2p")


class EditorError(ValueError):
    """An editor that cannot be built or called: the message names the file/field and what to do."""

    user_error = True   # the CLI prints the message (exit 2) instead of a traceback


@runtime_checkable
class Editor(Protocol):
    @property
    def identity(self) -> dict: ...

    last_details: dict

    def edit(self, render: np.ndarray, original: np.ndarray, instruction: str, seed: int, step: int
             ) -> np.ndarray: ...


def to_float_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    """HxWx3 uint8 or float in [0,1] -> float32 in [0,1]."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise EditorError(f"{what} must be an HxWx3 RGB image, got shape {image.shape}.")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    return np.clip(image.astype(np.float32), 0.0, 1.0)


def to_uint8_image(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def load_editor(kind: str, *, instruction: str, model: str | None = None, device: str = "cpu",
                scene_folder=None, edit_id: str | None = None, names=None, originals=None,
                emulator_config=None) -> Editor:
    """Build an editor. "ip2p" needs `model` (a local diffusers folder or hub id); "synthetic" (the
    InstructPix2Pix EMULATOR) needs the folder with scene.toml + gt/edits/, the edit id, and the training
    views' names and original images."""
    if kind == "ip2p":
        from dualnerf.editors.ip2p import IP2P_HUB_ID, InstructPix2PixConfig, InstructPix2PixEditor

        return InstructPix2PixEditor(model or IP2P_HUB_ID, InstructPix2PixConfig(device=device))
    if kind == "synthetic":
        from dualnerf.editors.emulator import EmulatorConfig, InstructPix2PixEmulator

        if scene_folder is None or edit_id is None or names is None or originals is None:
            raise EditorError("editor 'synthetic' (InstructPix2Pix emulator) needs a scene folder with "
                              "scene.toml and gt/edits/, an edit_id, and the training views.")
        return InstructPix2PixEmulator.from_scene_folder(scene_folder, edit_id, instruction, names, originals,
                                                         emulator_config or EmulatorConfig())
    raise EditorError(f"unknown editor '{kind}'; choose one of: {', '.join(EDITOR_KINDS)}.")
