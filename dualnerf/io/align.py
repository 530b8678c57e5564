"""Similarity alignment (Umeyama 1991) of estimated camera centres to ground truth, for pose error."""
from __future__ import annotations

import numpy as np


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |target - (s R source + t)|^2 over similarities (Umeyama, Eq. 40-42)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0            # a reflection would fit better; force a proper rotation
    rotation = u @ sign @ vt
    var_s = np.mean(np.sum(xs * xs, axis=1))
    scale = float(np.trace(np.diag(d) @ sign) / var_s)
    translation = mu_t - scale * rotation @ mu_s
    return scale, rotation, translation


def aligned_centre_errors(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-camera distance between ground-truth centres and similarity-aligned estimated centres."""
    s, r, t = umeyama(estimated, truth)
    return np.linalg.norm(truth - (s * estimated @ r.T + t), axis=1)
