"""A weight-free PROXY for CLIP: colour and structure statistics, with text embeddings defined by images.

This is not CLIP and its scores are not CLIP scores; every identity, log line and manifest says "proxy".
It exists so that the consistency indicator and the metrics run offline on procedural scenes.

Image feature (signed, so cosine similarity discriminates; each block is L2-normalised, then weighted):
  - colour layout: mean of opponent colours (L - 1/2, R - G, (R + G)/2 - B) over a 4x4 grid
  - global colour moments: mean and standard deviation of the opponent colours
  - texture: standard deviation of L and mean gradient magnitude of L over the 4x4 grid, minus constants
    typical of smooth renders (so blur and noise move the feature in opposite directions)
Text embedding: a text only has an embedding if the caller's vocabulary defines it by a stack of images
(dualnerf.encoders.vocabulary: the target caption / instruction <- caption images made from the edit's
specification; the source caption <- original views); its embedding is the normalised mean of those
images' features. Unknown text is an error. `vocabulary_source` (in the identity) says where the target
caption's images came from, so a record shows whether the proxy saw the ground truth.
"""
from __future__ import annotations

import hashlib
from collections.abc import Mapping

import numpy as np

from dualnerf.encoders.base import EncoderError, images_to_float, l2_normalise

PROXY_FEATURE_VERSION = 1
_GRID = 4
_SIZE = 64
_TEXTURE_STD_OFFSET = 0.05
_TEXTURE_GRAD_OFFSET = 0.02
_BLOCK_WEIGHTS = {"layout": 1.0, "moments": 1.0, "texture": 0.5}


def _resize(images: np.ndarray) -> np.ndarray:
    import torch

    x = torch.from_numpy(images).permute(0, 3, 1, 2)
    x = torch.nn.functional.interpolate(x, size=(_SIZE, _SIZE), mode="area")
    return x.permute(0, 2, 3, 1).numpy()


def _grid_mean(values: np.ndarray) -> np.ndarray:
    """(B,H,W,C) -> (B, GRID*GRID*C) cell means (H, W divisible by GRID)."""
    b, h, w, c = values.shape
    cells = values.reshape(b, _GRID, h // _GRID, _GRID, w // _GRID, c)
    return cells.mean(axis=(2, 4)).reshape(b, -1)


def proxy_image_features(images: np.ndarray) -> np.ndarray:
    x = _resize(images_to_float(images))
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    lum = (r + g + b) / 3.0
    opponent = np.stack([lum - 0.5, r - g, (r + g) / 2.0 - b], axis=-1)
    layout = _grid_mean(opponent)
    moments = np.concatenate([opponent.mean(axis=(1, 2)), opponent.std(axis=(1, 2))], axis=-1)
    gy, gx = np.gradient(lum, axis=(1, 2))
    grad = np.sqrt(gx ** 2 + gy ** 2)[..., None]
    cell_mean_lum = _grid_mean(lum[..., None])
    cell_sq = _grid_mean((lum ** 2)[..., None])
    cell_std = np.sqrt(np.maximum(cell_sq - cell_mean_lum ** 2, 0.0))
    texture = np.concatenate([cell_std - _TEXTURE_STD_OFFSET, _grid_mean(grad) - _TEXTURE_GRAD_OFFSET], axis=-1)
    blocks = [("layout", layout), ("moments", moments), ("texture", texture)]
    return l2_normalise(np.concatenate([_BLOCK_WEIGHTS[n] * l2_normalise(v) for n, v in blocks], axis=-1))


class ProxyEncoder:
    """Weight-free proxy encoder (see module docstring); not CLIP."""

    def __init__(self, vocabulary: Mapping[str, np.ndarray], vocabulary_source: str = ""):
        self._texts: dict[str, np.ndarray] = {}
        self.vocabulary_source = vocabulary_source
        digest = hashlib.sha256()
        for text in sorted(vocabulary):
            images = np.asarray(vocabulary[text])
            if images.ndim != 4 or len(images) == 0:
                raise EncoderError(f"proxy encoder: the vocabulary entry for '{text}' must be a non-empty "
                                   f"(N,H,W,3) stack of images that define it, got shape {images.shape}.")
            feature = proxy_image_features(images).mean(axis=0)
            self._texts[text] = l2_normalise(feature)
            digest.update(text.encode() + self._texts[text].tobytes())
        self._vocabulary_sha256 = digest.hexdigest()

    @property
    def identity(self) -> dict:
        return {"kind": "proxy", "model": "colour/structure statistics (NOT CLIP)",
                "feature_version": PROXY_FEATURE_VERSION, "vocabulary": sorted(self._texts),
                "vocabulary_sha256": self._vocabulary_sha256, "vocabulary_source": self.vocabulary_source}

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        return proxy_image_features(images)

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        if isinstance(texts, str):
            texts = [texts]
        unknown = [t for t in texts if t not in self._texts]
        if unknown:
            known = "; ".join(f"'{t}'" for t in sorted(self._texts)) or "none"
            raise EncoderError(
                f"proxy encoder: no embedding for text {unknown[0]!r}. The proxy (not CLIP) only knows texts "
                f"defined by the scene's own views (scene.toml edit captions/instructions); known: {known}. "
                f"Use a scene edit's instruction or captions, or use encoder 'clip' with a CLIP model folder.")
        return np.stack([self._texts[t] for t in texts]) if texts else np.zeros((0, self.dim), np.float32)

    @property
    def dim(self) -> int:
        return int(proxy_image_features(np.zeros((1, _SIZE, _SIZE, 3), np.uint8)).shape[1])
