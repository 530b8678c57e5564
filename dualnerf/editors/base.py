"""What every editor shares: the Editor interface, its error and the image conversions (the package's
__init__ re-exports them; the editor modules import them from here)."""
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
