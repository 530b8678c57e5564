"""CLIP image and text encoders run with onnxruntime from a model folder written by `export_clip`.

Folder layout (format "dualnerf-clip-onnx" v1):
    image_encoder.onnx    pixel_values (B,3,S,S) float32 -> image_embeds (B,D) (projected, not normalised)
    text_encoder.onnx     input_ids, attention_mask (B,L) int64 -> text_embeds (B,D)
    tokenizer.json        a `tokenizers` tokenizer with CLIP's special tokens, padding and truncation to L
    preprocess.json       resize_shortest_edge, crop_size, mean, std, interpolation, context_length
    manifest.json         format, version, source, embedding_dim, sha256 of every other file (written last)
Every file's sha256 is checked against the manifest on load, so a truncated or swapped file is an error.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dualnerf.encoders.base import EncoderError, images_to_float, l2_normalise
from dualnerf.file_hash import file_sha256

CLIP_FORMAT = "dualnerf-clip-onnx"
CLIP_FORMAT_VERSION = 1
IMAGE_ONNX, TEXT_ONNX = "image_encoder.onnx", "text_encoder.onnx"
TOKENIZER_FILE, PREPROCESS_FILE, MANIFEST_FILE = "tokenizer.json", "preprocess.json", "manifest.json"


def read_verified_manifest(folder: Path) -> dict:
    """The folder's manifest after checking format and every listed file's sha256."""
    path = folder / MANIFEST_FILE
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise EncoderError(f"{path} is missing: {folder} is not a CLIP model folder; create one with "
                           f"`dualnerf models export-clip --from HUB_ID_OR_DIR --out {folder}`.") from None
    except json.JSONDecodeError as err:
        raise EncoderError(f"{path} is not valid JSON ({err}); re-export the CLIP model folder.") from None
    if manifest.get("format") != CLIP_FORMAT or manifest.get("version") != CLIP_FORMAT_VERSION:
        raise EncoderError(f"{path}: expected format {CLIP_FORMAT} v{CLIP_FORMAT_VERSION}, got "
                           f"{manifest.get('format')} v{manifest.get('version')}; re-export the model folder.")
    for name in (IMAGE_ONNX, TEXT_ONNX, TOKENIZER_FILE, PREPROCESS_FILE):
        expected = manifest.get("files", {}).get(name)
        file = folder / name
        if expected is None or not file.exists():
            raise EncoderError(f"{file} is missing (or not in {path}); re-export the CLIP model folder with "
                               f"`dualnerf models export-clip`.")
        actual = file_sha256(file)
        if actual != expected:
            raise EncoderError(f"{file} has sha256 {actual[:12]}... but {path} expects {expected[:12]}...: the "
                               f"file is corrupt or was replaced; re-export the CLIP model folder.")
    return manifest


def preprocess_images(images: np.ndarray, config: dict) -> np.ndarray:
    """CLIP preprocessing: resize the shortest edge (bicubic, antialiased), centre crop, normalise."""
    import torch

    x = torch.from_numpy(images_to_float(images)).permute(0, 3, 1, 2)
    height, width = x.shape[-2:]
    short = int(config["resize_shortest_edge"])
    scale = short / min(height, width)
    size = (max(short, round(height * scale)), max(short, round(width * scale)))
    x = torch.nn.functional.interpolate(x, size=size, mode=config.get("interpolation", "bicubic"),
                                        antialias=True, align_corners=False).clamp(0.0, 1.0)
    crop = int(config["crop_size"])
    top, left = (size[0] - crop) // 2, (size[1] - crop) // 2
    x = x[:, :, top:top + crop, left:left + crop]
    mean = torch.tensor(config["mean"], dtype=torch.float32)[None, :, None, None]
    std = torch.tensor(config["std"], dtype=torch.float32)[None, :, None, None]
    return ((x - mean) / std).contiguous().numpy()


class ClipOnnxEncoder:
    """CLIP E_I / E_T through onnxruntime; outputs are L2-normalised like CLIP's image_embeds/text_embeds."""

    def __init__(self, folder: Path, num_threads: int = 0):
        import onnxruntime as ort
        from tokenizers import Tokenizer

        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise EncoderError(f"CLIP model folder {self.folder} does not exist; create it with "
                               f"`dualnerf models export-clip --from HUB_ID_OR_DIR --out {self.folder}`.")
        self.manifest = read_verified_manifest(self.folder)
        self._manifest_sha256 = file_sha256(self.folder / MANIFEST_FILE)
        self.preprocess = json.loads((self.folder / PREPROCESS_FILE).read_text())
        self.tokenizer = Tokenizer.from_file(str(self.folder / TOKENIZER_FILE))
        options = ort.SessionOptions()
        options.intra_op_num_threads = num_threads
        options.inter_op_num_threads = 1
        self._image = ort.InferenceSession(str(self.folder / IMAGE_ONNX), options,
                                           providers=["CPUExecutionProvider"])
        self._text = ort.InferenceSession(str(self.folder / TEXT_ONNX), options,
                                          providers=["CPUExecutionProvider"])

    @property
    def identity(self) -> dict:
        return {"kind": "clip", "model": self.manifest.get("source", "unknown"),
                "embedding_dim": self.manifest.get("embedding_dim"), "sha256": self._manifest_sha256}

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        pixels = preprocess_images(images, self.preprocess)
        return l2_normalise(self._image.run(None, {"pixel_values": pixels})[0])

    def tokenize(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
        encodings = self.tokenizer.encode_batch(list(texts))
        ids = np.array([e.ids for e in encodings], dtype=np.int64)
        mask = np.array([e.attention_mask for e in encodings], dtype=np.int64)
        return ids, mask

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        if isinstance(texts, str):
            texts = [texts]
        ids, mask = self.tokenize(texts)
        return l2_normalise(self._text.run(None, {"input_ids": ids, "attention_mask": mask})[0])
