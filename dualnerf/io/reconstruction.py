"""Cameras recovered from any source (SfM, nerfstudio, a COLMAP model), before normalisation."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualnerf.io.errors import InputError


@dataclass
class Reconstruction:
    """Registered views in a common world frame (arbitrary scale), OpenCV camera axes.

    `distortion` holds OpenCV coefficients (k1, k2, p1, p2[, k3 ...]) per view, or zeros for pinhole.
    """

    names: list[str]
    image_paths: list[Path]
    c2w: np.ndarray                 # (N, 4, 4)
    intrinsics: np.ndarray          # (N, 4) fx, fy, cx, cy in pixels of the source image
    sizes: np.ndarray               # (N, 2) width, height of the source image
    distortion: np.ndarray          # (N, K)
    points: np.ndarray | None = None    # (M, 3) sparse scene points, world frame
    report: dict = field(default_factory=dict)
    method: str = ""

    def validate(self, where: str) -> None:
        n = len(self.names)
        if n < 3:
            raise InputError(f"{where}: only {n} registered image(s); at least 3 are needed.")
        bad = [self.names[i] for i in range(n)
               if not (np.all(np.isfinite(self.c2w[i])) and np.all(np.isfinite(self.intrinsics[i])))]
        if bad:
            raise InputError(f"{where}: non-finite pose or intrinsics for {', '.join(bad)}; fix or remove "
                             f"these frames.")
        non_rigid = []
        for i in range(n):
            r = self.c2w[i, :3, :3]
            if (not np.allclose(r.T @ r, np.eye(3), atol=1e-3) or abs(np.linalg.det(r) - 1.0) > 1e-3
                    or not np.allclose(self.c2w[i, 3], [0, 0, 0, 1], atol=1e-6)):
                non_rigid.append(self.names[i])
        if non_rigid:
            raise InputError(f"{where}: the pose of {', '.join(non_rigid)} is not a rigid transform (its "
                             f"rotation is not orthonormal with determinant +1, or the last row is not "
                             f"0 0 0 1); export camera-to-world poses without scale or shear.")
        if np.any(self.intrinsics[:, :2] <= 0):
            raise InputError(f"{where}: focal lengths must be positive.")
