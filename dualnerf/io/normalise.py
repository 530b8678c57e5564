"""Normalise a reconstruction's world into [-1, 1]^3 and bound every view's depth range (near, far).

x_norm = scale * (x + offset). The box is fitted to camera centres and the sparse points (0.5/99.5
percentiles, so a few SfM outliers cannot shrink the scene), then padded by `margin`. Without points,
the scene is assumed to extend to twice the camera spread around the cameras' centre.
"""
from __future__ import annotations

import numpy as np

MIN_NEAR = 0.01


def fit_normalisation(centres: np.ndarray, points: np.ndarray | None, margin: float = 1.05
                      ) -> tuple[float, np.ndarray]:
    """(scale, offset) mapping cameras and points into [-1, 1]^3, isotropically."""
    if points is not None and len(points) >= 10:
        lo = np.minimum(np.percentile(points, 0.5, axis=0), centres.min(axis=0))
        hi = np.maximum(np.percentile(points, 99.5, axis=0), centres.max(axis=0))
        centre = 0.5 * (lo + hi)
        half = 0.5 * np.max(hi - lo)
    else:
        centre = centres.mean(axis=0)
        half = 2.0 * np.max(np.abs(centres - centre))
    half = max(float(half) * margin, 1e-9)
    return 1.0 / half, -centre


def apply_normalisation(c2w: np.ndarray, scale: float, offset: np.ndarray) -> np.ndarray:
    out = c2w.copy()
    out[:, :3, 3] = scale * (c2w[:, :3, 3] + offset)
    return out


def near_far(c2w: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray, points: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Per-view depth bounds in normalised units.

    far is the distance to the farthest corner of the [-1, 1]^3 cube (nothing modelled lies beyond it);
    near comes from the visible sparse points (0.6 x their 1st depth percentile: surfaces without
    SfM points, such as the ground at the bottom of the image, can be nearer) when there are enough,
    else from the distance to the cube.
    """
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    near, far = [], []
    for i in range(len(c2w)):
        centre = c2w[i, :3, 3]
        far.append(float(np.max(np.linalg.norm(corners - centre, axis=1))))
        depth = _visible_depths(c2w[i], intrinsics[i], sizes[i], points) if points is not None else None
        if depth is not None and len(depth) >= 20:
            near.append(max(MIN_NEAR, 0.6 * float(np.percentile(depth, 1.0))))
        else:
            near.append(max(MIN_NEAR, float(np.linalg.norm(np.maximum(np.abs(centre) - 1.0, 0.0)))))
    near_arr, far_arr = np.array(near), np.array(far)
    return np.minimum(near_arr, 0.5 * far_arr), far_arr


def _visible_depths(c2w, intrinsics, size, points) -> np.ndarray:
    w2c = np.linalg.inv(c2w)
    p = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    front = z > 1e-6
    fx, fy, cx, cy = intrinsics
    u = fx * p[front, 0] / z[front] + cx
    v = fy * p[front, 1] / z[front] + cy
    inside = (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
    return z[front][inside]
