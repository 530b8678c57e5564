"""Camera rigs for procedural scenes: views on a circle or arc, looking at the scene centre."""
from __future__ import annotations

import numpy as np

# OpenCV camera axes (x right, y down, z forward) -> OpenGL/nerfstudio axes (x right, y up, z back).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def look_at(position: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """c2w (4x4) with OpenCV camera axes for a camera at `position` looking at `target`."""
    forward = np.asarray(target, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, position
    return c2w


def orbit(n_views: int, radius: float, height: float, arc_degrees: float, target,
          height_wobble: float = 0.0, start_degrees: float = -90.0) -> np.ndarray:
    """(n_views, 4, 4) OpenCV c2w on an arc of `arc_degrees` (360 = full circle, no repeated view).

    `height_wobble` varies the camera height sinusoidally so the centres are not coplanar, which
    constrains self-calibration better than a perfectly flat ring.
    """
    if arc_degrees >= 360.0:
        angles = np.deg2rad(start_degrees + 360.0 * np.arange(n_views) / n_views)
    else:
        angles = np.deg2rad(start_degrees + np.linspace(-arc_degrees / 2, arc_degrees / 2, n_views))
    poses = []
    for i, a in enumerate(angles):
        z = height + height_wobble * np.sin(3.0 * a + 0.5)
        position = np.array([radius * np.cos(a), radius * np.sin(a), z])
        poses.append(look_at(position, np.asarray(target, float)))
    return np.stack(poses)


def neighbour_angles_degrees(c2w: np.ndarray) -> np.ndarray:
    """Angle between the viewing directions of consecutive views (for the <= 10 degree rule)."""
    forward = c2w[:, :3, 2]
    cos = np.clip(np.einsum("ij,ij->i", forward[:-1], forward[1:]), -1.0, 1.0)
    return np.rad2deg(np.arccos(cos))
