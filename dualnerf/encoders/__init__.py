"""Image-text encoders E_I, E_T: CLIP through onnxruntime, or the weight-free `proxy` stand-in.

One interface (`ImageTextEncoder`), used by the CLIP consistency indicator during editing and by the
metrics stage:
    encode_images(images: (B,H,W,3) uint8 or float in [0,1]) -> (B,D) float32, L2-normalised
    encode_texts(texts: list[str]) -> (B,D) float32, L2-normalised
    identity -> dict    e.g. {"kind": "clip", "model": ..., "sha256": ...} or {"kind": "proxy", ...}
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dualnerf.encoders.base import EncoderError, ImageTextEncoder

ENCODER_KINDS = ("proxy", "clip")

__all__ = ["ENCODER_KINDS", "EncoderError", "ImageTextEncoder", "load_encoder"]


def load_encoder(kind: str, model_dir: str | Path | None = None,
                 vocabulary: Mapping[str, np.ndarray] | None = None, vocabulary_source: str = ""
                 ) -> ImageTextEncoder:
    """Build an encoder.

    kind "clip": `model_dir` is a folder written by `dualnerf models export-clip` (ONNX files, tokenizer,
    preprocessing config, sha256 manifest, all verified on load); `vocabulary` is ignored.
    kind "proxy": `vocabulary` maps each text the caller will encode to the images that define its
    embedding (dualnerf.encoders.vocabulary); `vocabulary_source` says where they came from (recorded in
    the identity); `model_dir` must be empty.
    """
    if kind == "clip":
        if not model_dir:
            raise EncoderError("encoder 'clip' needs a model folder (the parameters edit.encoder_model and "
                               "evaluate.encoder_model, e.g. --set edit.encoder_model=DIR); create one with "
                               "`dualnerf models export-clip --from openai/clip-vit-base-patch32 --out DIR`.")
        from dualnerf.encoders.clip_onnx import ClipOnnxEncoder

        return ClipOnnxEncoder(Path(model_dir))
    if kind == "proxy":
        from dualnerf.encoders.proxy import ProxyEncoder

        return ProxyEncoder(vocabulary or {}, vocabulary_source)
    raise EncoderError(f"unknown encoder kind '{kind}'; choose one of: {', '.join(ENCODER_KINDS)}.")
