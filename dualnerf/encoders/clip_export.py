"""Export Hugging Face transformers CLIP weights to the ONNX model folder `ClipOnnxEncoder` reads.

The source is a hub id or a local folder with a CLIPModel (config + weights), a fast tokenizer
(tokenizer.json) and optionally preprocessor_config.json. Needs transformers and onnx (the `models` extra).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

from dualnerf.encoders.base import EncoderError
from dualnerf.encoders.clip_onnx import (
    CLIP_FORMAT,
    CLIP_FORMAT_VERSION,
    IMAGE_ONNX,
    MANIFEST_FILE,
    PREPROCESS_FILE,
    TEXT_ONNX,
    TOKENIZER_FILE,
    file_sha256,
)

# OpenAI CLIP's published normalisation, used when the source has no preprocessor_config.json.
OPENAI_CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
ONNX_OPSET = 17


def _preprocess_config(source: str, image_size: int, context_length: int) -> dict:
    config = {"resize_shortest_edge": image_size, "crop_size": image_size, "mean": list(OPENAI_CLIP_MEAN),
              "std": list(OPENAI_CLIP_STD), "interpolation": "bicubic", "context_length": context_length}
    try:
        from transformers import CLIPImageProcessor

        processor = CLIPImageProcessor.from_pretrained(source)
    except (OSError, ValueError, ImportError):
        return config
    size = processor.size or {}
    crop = processor.crop_size or {}
    config["resize_shortest_edge"] = int(size.get("shortest_edge", size.get("height", image_size)))
    config["crop_size"] = int(crop.get("height", image_size))
    config["mean"] = [float(v) for v in processor.image_mean]
    config["std"] = [float(v) for v in processor.image_std]
    return config


def export_clip(source: str, out_dir: Path, log=print) -> dict:
    """Write the ONNX CLIP model folder for `source` into `out_dir` (must not exist or be empty).

    Files are written into a temporary sibling folder and renamed into place, manifest last; returns the
    manifest."""
    import torch
    from transformers import AutoTokenizer, CLIPModel

    out_dir = Path(out_dir)
    if str(source).startswith("open_clip:"):
        # open_clip checkpoints are not supported by this exporter (open_clip is not a dependency here).
        raise EncoderError(f"'{source}': open_clip models cannot be exported by this version; use the Hugging "
                           f"Face transformers version of the weights (e.g. laion/CLIP-ViT-B-32-laion2B-s34B-b79K "
                           f"or openai/clip-vit-base-patch32).")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise EncoderError(f"{out_dir} exists and is not empty; choose a new --out folder (existing model "
                           f"folders are never overwritten).")
    try:
        model = CLIPModel.from_pretrained(source).eval()
        tokenizer = AutoTokenizer.from_pretrained(source)
    except OSError as err:
        raise EncoderError(f"could not load a transformers CLIPModel and tokenizer from '{source}' ({err}). "
                           f"Pass a hub id such as openai/clip-vit-base-patch32 (needs internet) or a local "
                           f"folder containing config.json, the weights and tokenizer.json.") from None
    if not getattr(tokenizer, "is_fast", False):
        raise EncoderError(f"'{source}' has no fast tokenizer (tokenizer.json); save one with "
                           f"transformers' CLIPTokenizerFast.save_pretrained into that folder.")
    context_length = int(model.config.text_config.max_position_embeddings)
    image_size = int(model.config.vision_config.image_size)
    backend = tokenizer.backend_tokenizer
    backend.enable_truncation(max_length=context_length)
    backend.enable_padding(length=context_length, pad_id=int(tokenizer.pad_token_id), pad_token=tokenizer.pad_token)

    def features(output):
        return output if torch.is_tensor(output) else output.pooler_output

    class ImageEncoder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.clip = model

        def forward(self, pixel_values):
            return features(self.clip.get_image_features(pixel_values=pixel_values))

    class TextEncoder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.clip = model

        def forward(self, input_ids, attention_mask):
            return features(self.clip.get_text_features(input_ids=input_ids, attention_mask=attention_mask))

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        pixels = torch.zeros(2, 3, image_size, image_size)
        encoded = backend.encode_batch(["a photo", "a"])
        ids = torch.tensor([e.ids for e in encoded], dtype=torch.int64)
        mask = torch.tensor([e.attention_mask for e in encoded], dtype=torch.int64)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            # The TorchScript exporter (dynamo=False) handles CLIP's data-dependent EOS pooling by tracing.
            torch.onnx.export(ImageEncoder(), (pixels,), str(work / IMAGE_ONNX), input_names=["pixel_values"],
                              output_names=["image_embeds"], dynamic_axes={"pixel_values": {0: "batch"}},
                              opset_version=ONNX_OPSET, dynamo=False)
            torch.onnx.export(TextEncoder(), (ids, mask), str(work / TEXT_ONNX),
                              input_names=["input_ids", "attention_mask"], output_names=["text_embeds"],
                              dynamic_axes={"input_ids": {0: "batch"}, "attention_mask": {0: "batch"}},
                              opset_version=ONNX_OPSET, dynamo=False)
        backend.save(str(work / TOKENIZER_FILE))
        (work / PREPROCESS_FILE).write_text(json.dumps(_preprocess_config(source, image_size, context_length),
                                                       indent=1))
        files = {name: file_sha256(work / name) for name in (IMAGE_ONNX, TEXT_ONNX, TOKENIZER_FILE, PREPROCESS_FILE)}
        manifest = {"format": CLIP_FORMAT, "version": CLIP_FORMAT_VERSION, "source": str(source),
                    "embedding_dim": int(model.config.projection_dim), "context_length": context_length,
                    "image_size": image_size, "onnx_opset": ONNX_OPSET, "torch": torch.__version__,
                    "files": files}
        (work / MANIFEST_FILE).write_text(json.dumps(manifest, indent=1))
        if out_dir.exists():
            out_dir.rmdir()
        os.replace(work, out_dir)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    log(f"exported CLIP '{source}' to {out_dir} (embedding dim {manifest['embedding_dim']}, "
        f"image {image_size}px, context {context_length} tokens)")
    return manifest


def check_export(source: str, folder: Path) -> float:
    """Max |ONNX - torch| over image and text embeddings of a few fixed inputs (both L2-normalised)."""
    import numpy as np
    import torch
    from transformers import CLIPModel

    from dualnerf.encoders.clip_onnx import ClipOnnxEncoder, preprocess_images

    encoder = ClipOnnxEncoder(Path(folder))
    model = CLIPModel.from_pretrained(source).eval()
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(2, 64, 80, 3), dtype=np.uint8)
    texts = ["a photo of a campsite", "make it look like it just snowed"]
    ids, mask = encoder.tokenize(texts)
    with torch.no_grad():
        out = model(pixel_values=torch.from_numpy(preprocess_images(images, encoder.preprocess)),
                    input_ids=torch.from_numpy(ids), attention_mask=torch.from_numpy(mask))
    return float(max(np.abs(encoder.encode_images(images) - out.image_embeds.numpy()).max(),
                     np.abs(encoder.encode_texts(texts) - out.text_embeds.numpy()).max()))
