"""PNG files of stage results and checkpoints: RGB uint8 arrays in, RGB uint8 arrays out (OpenCV stores
BGR). The one place stages write and read their images."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an RGB (H, W, 3) uint8 image, creating its folder; OSError if OpenCV cannot."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(image[..., ::-1])):
        raise OSError(f"could not write {path}")


def read_png(path: Path) -> np.ndarray | None:
    """An RGB (H, W, 3) uint8 image, or None when the file is missing or unreadable (the caller says
    what that means)."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if image is None else np.ascontiguousarray(image[..., ::-1])
