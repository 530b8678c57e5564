"""The normalised dataset: what preprocess writes and every later stage reads.

Folder layout:
    images/0000.png ...   8-bit RGB, all the same size, in frame order
    cameras.json          frames (see below), the normalisation applied, and provenance

Pose convention (one for the whole project): `c2w` is a 4x4 camera-to-world matrix with OpenCV camera
axes (x right, y down, z forward, looking along +z). The world is normalised so that camera centres and
the scene's sparse points lie inside the cube [-1, 1]^3. Intrinsics are pinhole (fx, fy, cx, cy) in
pixels of the stored image; pixel centres are at integer + 0.5.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualnerf.confine import check_file_name, confine

FORMAT = "dualnerf-dataset"
FORMAT_VERSION = 1
CONVENTION = "c2w 4x4, OpenCV camera axes (x right, y down, z forward); world normalised into [-1,1]^3"


class DatasetError(ValueError):
    """A dataset folder that cannot be used; the message names the file and what to do."""

    user_error = True   # the CLI prints the message and exits 2 (rule in pipeline.errors)


@dataclass
class Dataset:
    images: np.ndarray          # (N, H, W, 3) uint8
    c2w: np.ndarray             # (N, 4, 4) float64
    intrinsics: np.ndarray      # (N, 4) float64: fx, fy, cx, cy
    near: np.ndarray            # (N,) float64
    far: np.ndarray             # (N,) float64
    names: list[str]            # original image file names (stable ids across stages)
    split: list[str]            # "train" or "heldout" per frame
    normalisation: dict = field(default_factory=dict)   # {"scale": s, "offset": [3]}: x_norm = s * (x + offset)
    source: dict = field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def indices(self, split: str) -> np.ndarray:
        return np.array([i for i, s in enumerate(self.split) if s == split], dtype=np.int64)

    def validate(self) -> None:
        n = len(self.images)
        if self.images.ndim != 4 or self.images.shape[-1] != 3 or self.images.dtype != np.uint8:
            raise DatasetError(f"images must be (N,H,W,3) uint8, got {self.images.shape} {self.images.dtype}")
        for name, arr, shape in (("c2w", self.c2w, (n, 4, 4)), ("intrinsics", self.intrinsics, (n, 4)),
                                 ("near", self.near, (n,)), ("far", self.far, (n,))):
            if arr.shape != shape:
                raise DatasetError(f"{name} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise DatasetError(f"{name} contains non-finite values")
        if len(self.names) != n or len(self.split) != n:
            raise DatasetError("names and split must have one entry per image")
        if not np.all(self.far > self.near) or not np.all(self.near >= 0):
            raise DatasetError("every frame needs 0 <= near < far")


def save_dataset(dataset: Dataset, folder: Path) -> None:
    import cv2

    dataset.validate()
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i, image in enumerate(dataset.images):
        rel = f"images/{i:04d}.png"
        if not cv2.imwrite(str(folder / rel), image[..., ::-1]):
            raise OSError(f"could not write {folder / rel}")
        fx, fy, cx, cy = (float(v) for v in dataset.intrinsics[i])
        frames.append({
            "file": rel, "name": dataset.names[i], "split": dataset.split[i],
            "width": dataset.width, "height": dataset.height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "c2w": dataset.c2w[i].tolist(), "near": float(dataset.near[i]), "far": float(dataset.far[i]),
        })
    doc = {"format": FORMAT, "version": FORMAT_VERSION, "convention": CONVENTION,
           "normalisation": dataset.normalisation, "source": dataset.source, "frames": frames}
    (folder / "cameras.json").write_text(json.dumps(doc, indent=1))


def load_dataset(folder: Path) -> Dataset:
    import cv2

    folder = Path(folder)
    path = folder / "cameras.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path} is missing: this is not a preprocessed dataset folder") from None
    except json.JSONDecodeError as err:
        raise DatasetError(f"{path} is not valid JSON ({err}); rerun preprocess") from None
    if doc.get("format") != FORMAT or doc.get("version") != FORMAT_VERSION:
        raise DatasetError(f"{path}: expected format {FORMAT} v{FORMAT_VERSION}, got "
                           f"{doc.get('format')} v{doc.get('version')}; rerun preprocess")
    frames = doc["frames"]
    images = []
    for i, frame in enumerate(frames):
        # Names become output file names (views/<name>) and files are read: both stay in the folder.
        check_file_name(frame.get("name"), error=DatasetError, where=f"{path}: frame {i}", field="name")
        confine(folder / str(frame["file"]), folder, error=DatasetError, where=f"{path}: frame {i}", field="file",
                value=frame["file"])
        image = cv2.imread(str(folder / frame["file"]), cv2.IMREAD_COLOR)
        if image is None:
            raise DatasetError(f"{folder / frame['file']} is missing or unreadable; rerun preprocess")
        images.append(image[..., ::-1])
    dataset = Dataset(
        images=np.ascontiguousarray(np.stack(images)),
        c2w=np.array([f["c2w"] for f in frames], dtype=np.float64),
        intrinsics=np.array([[f["fx"], f["fy"], f["cx"], f["cy"]] for f in frames], dtype=np.float64),
        near=np.array([f["near"] for f in frames], dtype=np.float64),
        far=np.array([f["far"] for f in frames], dtype=np.float64),
        names=[f["name"] for f in frames],
        split=[f["split"] for f in frames],
        normalisation=doc.get("normalisation", {}),
        source=doc.get("source", {}),
    )
    dataset.validate()
    return dataset
