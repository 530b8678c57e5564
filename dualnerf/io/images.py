"""Reading user images robustly: 8-bit RGB out of grayscale, 16-bit, RGBA, EXIF-rotated or odd files."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dualnerf.confine import confine
from dualnerf.io.errors import InputError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr"}
log = logging.getLogger(__name__)


def list_images(folder: Path) -> list[Path]:
    """Image files in `folder` (its `images/` subfolder when present), sorted by name.

    Other files are skipped with a warning; hidden files are ignored silently. Every image must lie
    inside `folder` once links are followed.
    """
    root = folder = Path(folder)
    if (folder / "images").is_dir():
        folder = folder / "images"
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder; pass a folder of images, a nerfstudio dataset or a "
                         f"COLMAP model folder.")
    images, skipped = [], []
    for path in sorted(folder.iterdir()):
        if path.name.startswith(".") or path.is_dir():
            continue
        if path.suffix.lower() in IMAGE_SUFFIXES:
            confine(path, root, error=InputError, where=str(folder), field="image", value=path.name)
            images.append(path)
        else:
            skipped.append(path)
    if skipped:
        log.warning("skipping %d non-image file(s) in %s: %s", len(skipped), folder,
                    ", ".join(p.name for p in skipped[:10]) + (" ..." if len(skipped) > 10 else ""))
    return images


def read_image(path: Path) -> np.ndarray:
    """An (H, W, 3) uint8 RGB image; EXIF orientation applied, gray expanded, alpha composited on
    black, 16-bit and float images scaled to 8 bits. Raises InputError naming the file otherwise."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist; check the file list (transforms.json or the folder).")
    if path.stat().st_size == 0:
        raise InputError(f"{path} is empty (0 bytes); re-copy or remove it.")
    # IMREAD_UNCHANGED keeps the bit depth and alpha but ignores EXIF; orientation is applied below.
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None or image.size == 0:
        raise InputError(f"{path} could not be decoded (truncated, corrupt or not an image); "
                         f"re-export it or remove it from the input folder.")
    if _looks_truncated(path):
        raise InputError(f"{path} is truncated (its file ends before the image data does); "
                         f"re-copy or remove it.")
    image = _to_uint8(image, path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    elif image.shape[2] == 4:
        alpha = image[..., 3:4].astype(np.float32) / 255.0
        image = np.round(image[..., :3].astype(np.float32) * alpha).astype(np.uint8)
    elif image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    image = np.ascontiguousarray(image[..., ::-1])          # OpenCV is BGR
    return apply_exif_orientation(image, exif_orientation(path))


def _to_uint8(image: np.ndarray, path: Path) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return np.round(image.astype(np.float32) / 257.0).astype(np.uint8)
    if image.dtype in (np.float32, np.float64):
        # Linear HDR (EXR): clip and apply the sRGB transfer curve.
        x = np.clip(image.astype(np.float32), 0.0, 1.0)
        srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
        return np.round(srgb * 255).astype(np.uint8)
    raise InputError(f"{path} has unsupported pixel type {image.dtype}; convert it to 8- or 16-bit PNG/JPEG.")


def _looks_truncated(path: Path) -> bool:
    """OpenCV decodes some truncated files silently (grey fill); check that the format's end marker
    follows the image data. Data appended after the image (motion photos) is allowed."""
    data = path.read_bytes()
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        scan = _jpeg_first_scan(data)
        return scan < 0 or data.find(b"\xff\xd9", scan) < 0
    if suffix == ".png":
        return data.find(b"IEND", 8) < 0
    return False


def _jpeg_first_scan(data: bytes) -> int:
    """Offset of the main image's first start-of-scan segment (walking the marker segments, so an
    EXIF thumbnail's own markers inside APP1 are skipped), or -1."""
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return -1
        marker = data[pos + 1]
        if marker == 0xFF:              # fill byte
            pos += 1
            continue
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker == 0xDA:
            return pos + 2 + length
        pos += 2 + length
    return -1


def exif_orientation(path: Path) -> int:
    """The EXIF Orientation tag (1..8) as OpenImageIO reads it, 1 when absent or unreadable."""
    try:
        import OpenImageIO as oiio
    except ImportError:
        oiio = None
    if oiio is not None:
        inp = oiio.ImageInput.open(str(path))
        if inp is not None:
            try:
                value = inp.spec().get_int_attribute("Orientation", 1)
            finally:
                inp.close()
            return int(value) if 1 <= int(value) <= 8 else 1
    return 1


def apply_exif_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Turn stored pixels upright following EXIF orientation codes 1..8."""
    ops = {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1, :],
        5: lambda a: np.transpose(a, (1, 0, 2)),
        6: lambda a: np.rot90(a, k=-1),
        7: lambda a: np.rot90(a, k=1)[:, ::-1],
        8: lambda a: np.rot90(a, k=1),
    }
    return np.ascontiguousarray(ops.get(orientation, ops[1])(image))


def resize_long_side(image: np.ndarray, max_size: int) -> np.ndarray:
    """Downscale (area filter) so the long side is at most `max_size`; never upscales."""
    import cv2

    h, w = image.shape[:2]
    factor = max_size / max(h, w)
    if factor >= 1.0:
        return image
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def resized_shape(width: int, height: int, max_size: int) -> tuple[int, int]:
    factor = max_size / max(width, height)
    if factor >= 1.0:
        return width, height
    return max(1, round(width * factor)), max(1, round(height * factor))
