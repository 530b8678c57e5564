"""The encoder interface and input normalisation shared by every encoder."""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


class EncoderError(ValueError):
    """An encoder that cannot be loaded or asked for: the message names the file or text and what to do."""

    user_error = True   # the CLI prints the message (exit 2) instead of a traceback


@runtime_checkable
class ImageTextEncoder(Protocol):
    @property
    def identity(self) -> dict: ...

    def encode_images(self, images: np.ndarray) -> np.ndarray: ...

    def encode_texts(self, texts: list[str]) -> np.ndarray: ...


def images_to_float(images: np.ndarray) -> np.ndarray:
    """(B,H,W,3) uint8 or float in [0,1] -> float32 in [0,1]; a single HxWx3 image is promoted to B=1."""
    images = np.asarray(images)
    if images.ndim == 3:
        images = images[None]
    if images.ndim != 4 or images.shape[-1] != 3:
        raise EncoderError(f"images must be (B,H,W,3) RGB, got shape {images.shape}.")
    if images.dtype == np.uint8:
        return images.astype(np.float32) / 255.0
    if not np.issubdtype(images.dtype, np.floating):
        raise EncoderError(f"images must be uint8 or float in [0,1], got dtype {images.dtype}.")
    return np.clip(images.astype(np.float32), 0.0, 1.0)


def l2_normalise(features: np.ndarray) -> np.ndarray:
    features = np.asarray(features, dtype=np.float32)
    return features / np.maximum(np.linalg.norm(features, axis=-1, keepdims=True), 1e-12)
