"""A fixed, smooth camera path through the training poses, for rendering evaluation videos.

Positions follow a centripetal Catmull-Rom spline through key camera centres (it passes through every
key and does not overshoot or self-intersect between close keys); rotations follow squad, the
quaternion analogue of a cubic spline (Shoemake 1987), through the key rotations. Frames are spaced
evenly by arc length so the video moves at constant speed. Poses are c2w 4x4 in the dataset
convention (OpenCV camera axes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Samples per spline segment used to measure arc length before resampling at constant speed.
_ARC_SAMPLES = 128
# A capture is treated as a closed loop unless closing it needs a jump this many times the median step.
_OPEN_GAP_RATIO = 3.0
_EPS = 1e-9


class CameraPathError(ValueError):
    """Poses a camera path cannot be built from; the message says what to change."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


@dataclass(frozen=True)
class CameraPath:
    c2w: np.ndarray                 # (n_frames, 4, 4)
    key_indices: tuple[int, ...]    # dataset frame indices of the key poses, in path order
    closed: bool

    def describe(self) -> dict:
        """JSON-ready facts for the manifest and metrics.json."""
        return {"n_frames": len(self.c2w), "key_indices": [int(i) for i in self.key_indices],
                "closed": self.closed, "positions": "centripetal Catmull-Rom, constant speed",
                "rotations": "quaternion squad"}


# ---------------------------------------------------------------------------------------------- quaternions
# Unit quaternions as (w, x, y, z) arrays.

def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion (w, x, y, z), via the largest-diagonal branch for stability."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def _qlog(q: np.ndarray) -> np.ndarray:
    """Log of a unit quaternion: the pure quaternion (0, theta * axis)."""
    vec_norm = np.linalg.norm(q[1:])
    if vec_norm < _EPS:
        return np.zeros(4)
    angle = np.arctan2(vec_norm, q[0])
    return np.concatenate([[0.0], q[1:] * (angle / vec_norm)])


def _qexp(v: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(v[1:])
    if angle < _EPS:
        return np.array([1.0, *v[1:]]) / np.linalg.norm([1.0, *v[1:]])
    return np.concatenate([[np.cos(angle)], v[1:] * (np.sin(angle) / angle)])


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation along the great arc between unit quaternions (no sign flip:
    squad needs the arc as given)."""
    dot = float(np.clip(np.dot(q0, q1), -1.0, 1.0))
    if dot > 1.0 - 1e-12:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - u) * angle) * q0 + np.sin(u * angle) * q1) / np.sin(angle)


def _squad_sequence(quats: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment-ready quaternions and squad controls: element j+1 of the returned arrays is key j.
    The sequence is sign-chained (each quaternion in the hemisphere of its predecessor) so every
    segment, including a closed loop's wrap-around segment, takes the short arc; the inner control is
    s_j = q_j exp(-(log(q_j^-1 q_{j+1}) + log(q_j^-1 q_{j-1})) / 4) (Shoemake's squad)."""
    k = len(quats)
    if closed:
        seq = np.concatenate([quats[-1:], quats, quats[:2]])        # q_{K-1}, q_0..q_{K-1}, q_0, q_1
    else:
        seq = np.concatenate([quats[:1], quats, quats[-1:], quats[-1:]])
    for j in range(2, len(seq)):
        if np.dot(seq[j], seq[j - 1]) < 0:
            seq[j] = -seq[j]
    if np.dot(seq[0], seq[1]) < 0:
        seq[0] = -seq[0]
    controls = seq.copy()
    for j in range(1, len(seq) - 1):
        if not closed and (j == 1 or j >= k):                   # open ends: no tangent to match
            continue
        inv = _qconj(seq[j])
        tangent = -(_qlog(_qmul(inv, seq[j + 1])) + _qlog(_qmul(inv, seq[j - 1]))) / 4.0
        controls[j] = _qmul(seq[j], _qexp(tangent))
    return seq, controls


# ---------------------------------------------------------------------------------------------- ordering

def order_along_capture(centres: np.ndarray, max_passes: int = 20) -> tuple[list[int], bool]:
    """Order camera centres into a short tour, starting from the capture (frame) order and improving it
    with 2-opt moves; returns (order, closed). A capture whose loop needs one long jump to close
    (a forward-facing arc) becomes an open path cut at that jump."""
    n = len(centres)
    order = list(range(n))
    if n < 4:
        return order, False
    dist = np.linalg.norm(centres[:, None, :] - centres[None, :, :], axis=-1)
    tour = np.arange(n)
    for _ in range(max_passes):
        improved = False
        for i in range(n - 2):
            a, b = tour[i], tour[i + 1]
            # Reversing tour[i+1 .. j] replaces edges (a, b), (c, d) by (a, c), (b, d).
            js = np.arange(i + 2, n)
            c, d = tour[js], tour[(js + 1) % n]
            gain = dist[a, b] + dist[c, d] - dist[a, c] - dist[b, d]
            best = int(np.argmax(gain))
            if gain[best] > 1e-12:
                j = int(js[best])
                tour[i + 1:j + 1] = tour[i + 1:j + 1][::-1].copy()
                improved = True
        if not improved:
            break
    order = [int(v) for v in tour]
    edges = np.array([dist[order[i], order[(i + 1) % n]] for i in range(n)])
    longest = int(np.argmax(edges))
    median = float(np.median(edges))
    if edges[longest] > _OPEN_GAP_RATIO * max(median, _EPS):
        # Cut the loop at its longest edge: the path runs from order[longest+1] round to order[longest].
        order = order[longest + 1:] + order[:longest + 1]
        return order, False
    return order, True


# ---------------------------------------------------------------------------------------------- splines

def _catmull_rom(p0, p1, p2, p3, u: np.ndarray) -> np.ndarray:
    """Centripetal (alpha = 0.5) Catmull-Rom between p1 and p2 at u in [0, 1] (Barry-Goldman form)."""
    def knot(t, a, b):
        return t + max(np.linalg.norm(b - a) ** 0.5, _EPS)

    t0 = 0.0
    t1 = knot(t0, p0, p1)
    t2 = knot(t1, p1, p2)
    t3 = knot(t2, p2, p3)
    t = (t1 + u * (t2 - t1))[:, None]
    a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
    a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
    a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
    b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
    b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
    return (t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2


def interpolate_poses(key_c2w: np.ndarray, t: np.ndarray, closed: bool) -> np.ndarray:
    """Poses at spline parameters t: key k sits at t = k; t in [0, K) for a closed path (wrapping),
    [0, K-1] for an open one. Returns (len(t), 4, 4) c2w matrices."""
    keys = np.asarray(key_c2w, dtype=np.float64)
    k = len(keys)
    if k < 2:
        raise CameraPathError("a camera path needs at least 2 distinct key poses.")
    centres = keys[:, :3, 3]
    quats = np.array([matrix_to_quaternion(c[:3, :3]) for c in keys])
    seq, controls = _squad_sequence(quats, closed)

    def point(i: int) -> np.ndarray:
        if closed:
            return centres[i % k]
        if i < 0:
            return 2 * centres[0] - centres[1]          # reflected phantom points for the open ends
        if i > k - 1:
            return 2 * centres[-1] - centres[-2]
        return centres[i]

    t = np.asarray(t, dtype=np.float64)
    span = k if closed else k - 1
    out = np.zeros((len(t), 4, 4))
    out[:, 3, 3] = 1.0
    for n, tn in enumerate(t):
        if closed:
            tn = tn % span
        tn = float(np.clip(tn, 0.0, span))
        seg = min(int(np.floor(tn)), span - 1)
        u = tn - seg
        out[n, :3, 3] = _catmull_rom(point(seg - 1), point(seg), point(seg + 1), point(seg + 2),
                                     np.array([u]))[0]
        q0, q1, s0, s1 = seq[seg + 1], seq[seg + 2], controls[seg + 1], controls[seg + 2]
        q = slerp(slerp(q0, q1, u), slerp(s0, s1, u), 2 * u * (1 - u))
        out[n, :3, :3] = quaternion_to_matrix(q)
    return out


def smooth_camera_path(c2w: np.ndarray, n_frames: int = 60, max_keys: int = 8) -> CameraPath:
    """The evaluation path through the training poses `c2w` (N, 4, 4): order them along the capture,
    take up to `max_keys` evenly spaced key poses, and sample `n_frames` poses at constant speed."""
    poses = np.asarray(c2w, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < 2:
        raise CameraPathError(f"need at least 2 training poses of shape (4, 4), got {poses.shape}; "
                              f"the dataset has too few training frames for a camera path.")
    if n_frames < 2:
        raise CameraPathError(f"n_frames must be at least 2, got {n_frames}.")
    order, closed = order_along_capture(poses[:, :3, 3])
    n_keys = min(max_keys, len(order))
    if n_keys < 3:
        closed = False
    if closed:
        picks = np.floor(np.arange(n_keys) * len(order) / n_keys).astype(int)
    else:
        picks = np.round(np.linspace(0, len(order) - 1, n_keys)).astype(int)
    key_indices = tuple(int(order[p]) for p in picks)
    keys = poses[list(key_indices)]
    span = n_keys if closed else n_keys - 1
    # Arc length along a dense sampling of the spline, then equal-length steps between frames.
    dense_t = np.linspace(0.0, span, span * _ARC_SAMPLES + 1)
    dense = interpolate_poses(keys, dense_t, closed)[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=-1))])
    if arc[-1] < _EPS:                          # cameras rotating in place: evenly in the parameter
        arc = dense_t.copy()
    targets = np.linspace(0.0, arc[-1], n_frames, endpoint=not closed)
    t = np.interp(targets, arc, dense_t)
    return CameraPath(c2w=interpolate_poses(keys, t, closed), key_indices=key_indices, closed=closed)
