"""Turn a Reconstruction into the normalised dataset: read, undistort, resize, normalise, split."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from dualnerf.confine import check_plain_name, confine
from dualnerf.dataset import Dataset
from dualnerf.io.errors import InputError
from dualnerf.io.images import read_image, resize_long_side
from dualnerf.io.normalise import apply_normalisation, fit_normalisation, near_far
from dualnerf.io.reconstruction import Reconstruction


def split_for(n: int, holdout_every: int) -> list[str]:
    """Every `holdout_every`-th view (0, k, 2k, ...) is held out; 0 disables the held-out set."""
    if holdout_every <= 0:
        return ["train"] * n
    return ["heldout" if i % holdout_every == 0 else "train" for i in range(n)]


def check_uniform_size(names: list[str], sizes: np.ndarray, where: str) -> None:
    """The dataset stores one image size; name the views whose size differs from the majority."""
    keys, counts = np.unique(sizes, axis=0, return_counts=True)
    if len(keys) <= 1:
        return
    common = keys[np.argmax(counts)]
    odd = [f"{names[i]} ({sizes[i][0]}x{sizes[i][1]})" for i in range(len(names))
           if not np.array_equal(sizes[i], common)]
    raise InputError(f"{where}: images must all have the same resolution; most are {common[0]}x{common[1]} "
                     f"but these differ: {', '.join(odd[:20])}{' ...' if len(odd) > 20 else ''}. Resize or "
                     f"remove them.")


# Below this corner displacement the image is kept as is: resampling would blur every pixel by more
# than the geometric error it removes (SfM's own reprojection error is ~0.3 px).
UNDISTORT_MIN_PIXELS = 0.2


def distortion_pixels(coeffs: np.ndarray, intrinsics: np.ndarray, width: int, height: int) -> float:
    """How far (pixels) the lens distortion moves the farthest image corner (first-order estimate)."""
    k1, k2, p1, p2, k3 = (list(coeffs) + [0.0] * 5)[:5]
    fx, fy, cx, cy = intrinsics
    x, y = max(cx, width - cx) / fx, max(cy, height - cy) / fy
    r2 = x * x + y * y
    radial = abs(k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) * np.sqrt(r2)
    tangential = 2 * abs(p1) * x * y + abs(p2) * (r2 + 2 * x * x) + abs(p1) * (r2 + 2 * y * y) + 2 * abs(p2) * x * y
    return float((radial + tangential) * max(fx, fy))


def build_dataset(recon: Reconstruction, max_size: int, holdout_every: int, source: dict) -> Dataset:
    import cv2

    check_uniform_size(recon.names, recon.sizes, "input")
    images, intrinsics = [], []
    for i, path in enumerate(recon.image_paths):
        image = read_image(path)
        w, h = int(recon.sizes[i][0]), int(recon.sizes[i][1])
        if image.shape[:2] != (h, w):
            raise InputError(f"{path} is {image.shape[1]}x{image.shape[0]} but its camera says {w}x{h}; fix "
                             f"the intrinsics (w, h) or the image.")
        fx, fy, cx, cy = recon.intrinsics[i]
        if distortion_pixels(recon.distortion[i], recon.intrinsics[i], w, h) > UNDISTORT_MIN_PIXELS:
            # Undistort to a pinhole camera with the same K: the dataset format is pinhole only.
            k = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])   # OpenCV: pixel centre = integer
            image = cv2.undistort(image, k, recon.distortion[i])
        image = resize_long_side(image, max_size)
        sx, sy = image.shape[1] / w, image.shape[0] / h
        images.append(image)
        intrinsics.append([fx * sx, fy * sy, cx * sx, cy * sy])
    scale, offset = fit_normalisation(recon.c2w[:, :3, 3], recon.points)
    c2w = apply_normalisation(recon.c2w, scale, offset)
    points = None if recon.points is None else scale * (recon.points + offset)
    intrinsics = np.array(intrinsics)
    height, width = images[0].shape[:2]
    sizes = np.tile([width, height], (len(images), 1))
    near, far = near_far(c2w, intrinsics, sizes, points)
    return Dataset(images=np.stack(images), c2w=c2w, intrinsics=intrinsics, near=near, far=far,
                   names=list(recon.names), split=split_for(len(images), holdout_every),
                   normalisation={"scale": float(scale), "offset": [float(v) for v in offset]},
                   source=source)


def carry_scene_files(source: Path, out: Path, names: list[str], size: tuple[int, int]) -> list[str]:
    """Copy scene.toml and gt/edits/<id>/{images,masks}/<name> of the registered views into `out`,
    resized to the dataset's (width, height) exactly as the views were. Returns the edit ids carried.

    A resized mask marks a pixel changed when any source pixel under it changed, so the ground-truth
    edited view still equals the original wherever the mask is 0.
    """
    import cv2

    source, out = Path(source), Path(out)
    if not source.is_dir():
        return []
    if (source / "scene.toml").is_file():
        confine(source / "scene.toml", source, error=InputError, where=str(source), field="file", value="scene.toml")
        shutil.copyfile(source / "scene.toml", out / "scene.toml")
    edits_dir = source / "gt" / "edits"
    carried = []
    if not edits_dir.is_dir():
        return carried
    for edit_dir in sorted(p for p in edits_dir.iterdir() if p.is_dir()):
        check_plain_name(edit_dir.name, error=InputError, where=str(edits_dir), field="edit folder")
        for kind in ("images", "masks"):
            (out / "gt" / "edits" / edit_dir.name / kind).mkdir(parents=True, exist_ok=True)
        for name in names:
            src_img, src_mask = edit_dir / "images" / name, edit_dir / "masks" / name
            if not src_img.is_file():
                continue
            for path in (src_img, src_mask):
                confine(path, source, error=InputError, where=str(edit_dir), field="ground-truth file",
                        value=path.relative_to(source).as_posix())
            image = read_image(src_img)
            mask = cv2.imread(str(src_mask), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise InputError(f"{src_mask} is missing or unreadable; every ground-truth edited view needs "
                                 f"a mask.")
            if image.shape[1::-1] != tuple(size):
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
                mask = cv2.resize((mask > 127).astype(np.float32), size, interpolation=cv2.INTER_AREA)
                mask = (mask > 0).astype(np.uint8) * 255
            cv2.imwrite(str(out / "gt/edits" / edit_dir.name / "images" / name), image[..., ::-1])
            cv2.imwrite(str(out / "gt/edits" / edit_dir.name / "masks" / name), mask)
        carried.append(edit_dir.name)
    return carried
