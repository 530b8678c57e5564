"""Camera path: through the key poses, orthonormal rotations, smooth, deterministic."""
import numpy as np
import pytest

from dualnerf import camera_path as cp


def look_at(centre, target=(0.0, 0.0, 0.0)):
    """c2w with OpenCV axes (z forward, y down) looking from `centre` at `target`, world up +z."""
    centre = np.asarray(centre, dtype=np.float64)
    z = np.asarray(target) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = centre
    return pose


def ring(n, radius=1.0, height=0.3, start=0.0, stop=2 * np.pi, endpoint=False):
    angles = np.linspace(start, stop, n, endpoint=endpoint)
    return np.array([look_at([radius * np.cos(a), radius * np.sin(a), height]) for a in angles])


def test_quaternion_round_trip_covers_every_branch():
    rng = np.random.default_rng(0)
    # Rotations by pi about each axis exercise the non-trace branches of matrix_to_quaternion.
    rotations = [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    for _ in range(20):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        rotations.append(q * np.sign(np.linalg.det(q)))
    for rotation in rotations:
        back = cp.quaternion_to_matrix(cp.matrix_to_quaternion(rotation))
        np.testing.assert_allclose(back, rotation, atol=1e-12)


def test_interpolation_hits_key_poses_exactly():
    keys = ring(6)
    for closed in (True, False):
        poses = cp.interpolate_poses(keys, np.arange(6.0), closed)
        np.testing.assert_allclose(poses, keys, atol=1e-9)


def test_ring_path_is_closed_passes_keys_and_stays_on_the_ring():
    poses = ring(24)
    shuffled = poses[np.random.default_rng(1).permutation(24)]   # capture order scrambled
    path = cp.smooth_camera_path(shuffled, n_frames=60)
    assert path.closed
    assert len(path.c2w) == 60 and len(set(path.key_indices)) == 8
    centres = path.c2w[:, :3, 3]
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=-1)
    # Every key camera lies within one step of the path.
    for k in path.key_indices:
        assert np.min(np.linalg.norm(centres - shuffled[k, :3, 3], axis=-1)) <= steps.max()
    # The spline through points of a circle stays close to the circle and at its height.
    assert np.abs(np.linalg.norm(centres[:, :2], axis=-1) - 1.0).max() < 0.02
    np.testing.assert_allclose(centres[:, 2], 0.3, atol=1e-9)
    # Constant speed, and the loop closes with the same step.
    assert steps.max() / steps.min() < 1.02
    assert np.linalg.norm(centres[0] - centres[-1]) == pytest.approx(steps.mean(), rel=0.05)
    # Rotations interpolate look-at poses: each camera still looks at the ring centre.
    to_centre = -centres / np.linalg.norm(centres, axis=-1, keepdims=True)
    assert np.min(np.sum(path.c2w[:, :3, 2] * to_centre, axis=-1)) > 0.999


def test_rotations_orthonormal_and_smooth():
    path = cp.smooth_camera_path(ring(30), n_frames=45)
    rotations = path.c2w[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3),
                               rotations.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    np.testing.assert_allclose(path.c2w[:, 3], np.broadcast_to([0, 0, 0, 1.0], (45, 4)))
    centres = path.c2w[:, :3, 3]
    # Bounded second differences: on a unit circle with step h, |c''| ~ h^2.
    h = np.linalg.norm(np.diff(centres, axis=0), axis=-1).mean()
    second = np.linalg.norm(centres[2:] - 2 * centres[1:-1] + centres[:-2], axis=-1)
    assert second.max() < 2 * h ** 2
    # Rotation steps change gradually from frame to frame (no jerks at the keys, which here are unevenly
    # spaced: 30 poses, 8 keys). Positions move at constant speed; the rotation speed varies smoothly.
    relative = rotations[1:] @ rotations[:-1].transpose(0, 2, 1)
    angles = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert np.abs(np.diff(angles)).max() < 0.2 * angles.mean()
    assert angles.max() < 1.5 * angles.min()


def test_forward_facing_arc_is_open_from_end_to_end():
    poses = ring(10, start=0.0, stop=np.pi / 2, endpoint=True)
    path = cp.smooth_camera_path(poses, n_frames=20)
    assert not path.closed
    ends = {path.key_indices[0], path.key_indices[-1]}
    assert ends == {0, 9}
    np.testing.assert_allclose(path.c2w[0], poses[path.key_indices[0]], atol=1e-9)
    np.testing.assert_allclose(path.c2w[-1], poses[path.key_indices[-1]], atol=1e-9)


def test_path_is_deterministic():
    poses = ring(16)[np.random.default_rng(2).permutation(16)]
    a = cp.smooth_camera_path(poses, n_frames=30)
    b = cp.smooth_camera_path(poses.copy(), n_frames=30)
    assert a.key_indices == b.key_indices
    np.testing.assert_array_equal(a.c2w, b.c2w)
    assert a.describe()["n_frames"] == 30


def test_bad_inputs_are_explained():
    with pytest.raises(cp.CameraPathError, match="at least 2 training poses"):
        cp.smooth_camera_path(ring(1), n_frames=10)
    with pytest.raises(cp.CameraPathError, match="n_frames"):
        cp.smooth_camera_path(ring(5), n_frames=1)
    assert issubclass(cp.CameraPathError, ValueError)
