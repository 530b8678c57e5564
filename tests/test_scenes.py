"""Procedural scenes: ray-caster geometry against closed forms, camera conventions, determinism and
the ground-truth edit contract (masks non-empty, local edits local, unchanged outside the mask)."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from dualnerf.scenes import (
    SCENES,
    SceneConfigError,
    SceneSpecError,
    generate_scene,
    load_gt_edit,
    load_scene_spec,
    scene_cameras,
    scene_config,
)
from dualnerf.scenes.cameras import OPENCV_TO_OPENGL, look_at, orbit
from dualnerf.scenes.geometry import Cylinder, Disk, Dome, Ellipsoid, box, prism_tent, pyramid, rotation_y
from dualnerf.scenes.noise import fbm
from dualnerf.scenes.render import camera_rays, trace


def _ray(origin, direction):
    d = np.asarray(direction, float)
    return np.asarray([origin], float), np.asarray([d / np.linalg.norm(d)])


@pytest.mark.parametrize("primitive, origin, direction, t_expected, n_expected", [
    (Ellipsoid(centre=(0, 0, 1), radii=(1, 1, 1)), (0, -5, 1), (0, 1, 0), 4.0, (0, -1, 0)),
    (Ellipsoid(centre=(0, 0, 0), radii=(2, 1, 1)), (-6, 0, 0), (1, 0, 0), 4.0, (-1, 0, 0)),
    (box((0, 0, 0.5), (0.5, 0.5, 0.5)), (0, 0, 5), (0, 0, -1), 4.0, (0, 0, 1)),
    (box((0, 0, 0), (1, 1, 1), angle=np.pi / 4), (-5, 0, 0), (1, 0, 0), 5 - np.sqrt(2), (-1, -1, 0)),
    (Cylinder(centre=(0, 0, 0), radius=1.0, height=2.0), (3, 0, 1), (-1, 0, 0), 2.0, (1, 0, 0)),
    (Cylinder(centre=(0, 0, 0), radius=1.0, height=2.0), (0.2, 0, 5), (0, 0, -1), 3.0, (0, 0, 1)),
    # A log: a cylinder turned to lie along +x; hit from above at its top line.
    (Cylinder(centre=(0, 0, 0.5), rotation=rotation_y(np.pi / 2), radius=0.5, height=2.0),
     (1, 0, 4), (0, 0, -1), 3.0, (0, 0, 1)),
    (Disk(radius=3.0), (1, 1, 2), (0, 0, -1), 2.0, (0, 0, 1)),
    # Tent: width 2, height 1, so the sloped side z = 1 - |y| is hit from +y at 45 degrees.
    (prism_tent((0, 0, 0), length=2, width=2, height=1), (0, 3, 0.5), (0, -1, 0), 2.5, (0, 1, 1)),
    (pyramid((0, 0, 0), radius=1, height=2, sides=4), (0, 0, 5), (0, 0, -1), 3.0, None),
    (Dome(radius=10.0), (0, 0, 0), (0, 1, 0), 10.0, (0, -1, 0)),
])
def test_primitive_hits_match_closed_form(primitive, origin, direction, t_expected, n_expected):
    o, d = _ray(origin, direction)
    t, n = primitive.hit(o, d)
    assert t[0] == pytest.approx(t_expected, abs=1e-9)
    if n_expected is not None:
        expected = np.asarray(n_expected, float) / np.linalg.norm(n_expected)
        assert np.allclose(n[0], expected, atol=1e-9)


@pytest.mark.parametrize("primitive", [
    Ellipsoid(centre=(0, 0, 1), radii=(1, 1, 1)), box((0, 0, 0.5), (0.5, 0.5, 0.5)),
    Cylinder(centre=(0, 0, 0), radius=1.0, height=2.0), prism_tent((0, 0, 0), 2, 2, 1), Disk(radius=1.0)])
def test_rays_pointing_away_miss(primitive):
    o, d = _ray((0, -5, 1), (0, -1, 0.1))
    assert np.isinf(primitive.hit(o, d)[0][0])


def test_bounding_sphere_culling_matches_full_test():
    rng = np.random.default_rng(1)
    o = np.tile([[0.0, -6.0, 1.5]], (4000, 1))
    d = rng.normal(size=(4000, 3)) + [0, 4, -0.5]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    from dualnerf.scenes.render import _cone_candidates

    for prim in (box((0.3, 0, 0.4), (0.4, 0.3, 0.4), 0.3), Ellipsoid(centre=(0, 0.2, 0.5), radii=(0.5, 0.3, 0.4)),
                 prism_tent((0, 0, 0), 2, 1.5, 1.1, 0.3), pyramid((0.5, 0, 0.2), 0.7, 1.5, 9),
                 Cylinder(centre=(0, 0, 0.3), rotation=rotation_y(np.pi / 2), radius=0.2, height=1.5)):
        full = prim.hit(o, d)[0]
        culled = prim.hit(o, d, _cone_candidates(o[0], d, prim.bound()))[0]
        assert np.isfinite(full).sum() > 50
        assert np.array_equal(full, culled)


def test_look_at_is_a_rigid_opencv_pose_that_projects_the_target_to_the_centre():
    c2w = look_at(np.array([3.0, -4.0, 2.0]), np.array([0.0, 0.0, 0.5]))
    r = c2w[:3, :3]
    assert np.allclose(r.T @ r, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    assert r[2, 1] < 0          # image "down" (+y) points down in the z-up world
    _o, d = camera_rays(c2w, 100.0, 100.0, 50.0, 40.0, 100, 80)
    # The ray through the image centre (between the 4 central pixels) is the viewing direction.
    centre = d.reshape(80, 100, 3)[39:41, 49:51].mean(axis=(0, 1))
    to_target = np.array([0.0, 0.0, 0.5]) - [3.0, -4.0, 2.0]
    assert np.allclose(centre / np.linalg.norm(centre), to_target / np.linalg.norm(to_target), atol=1e-4)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_camera_rigs_keep_neighbouring_views_within_10_degrees(name):
    config = SCENES[name]
    c2w, _ = scene_cameras(config)
    centre = np.array([0.0, 0.0, config.target_height])
    v = c2w[:, :3, 3] - centre
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    steps = np.rad2deg(np.arccos(np.clip(np.einsum("ij,ij->i", v[:-1], v[1:]), -1, 1)))
    assert steps.max() <= 10.0
    assert len(c2w) == config.n_views


def test_orbit_full_circle_does_not_repeat_the_first_view():
    c2w = orbit(36, 5.0, 2.0, 360.0, (0, 0, 0))
    assert np.linalg.norm(c2w[0, :3, 3] - c2w[-1, :3, 3]) > 0.5


def test_noise_is_zero_mean_deterministic_and_prefiltered():
    p = np.random.default_rng(0).uniform(-20, 20, size=(20000, 3))
    a, b = fbm(p, 1.0, 6, seed=3), fbm(p, 1.0, 6, seed=3)
    assert np.array_equal(a, b)
    assert abs(float(a.mean())) < 0.01 and 0.05 < float(a.std()) < 0.3
    assert not np.array_equal(a, fbm(p, 1.0, 6, seed=4))
    # A pixel footprint wider than half the coarsest wavelength removes every octave.
    assert np.all(fbm(p, 1.0, 6, seed=3, footprint=np.full(len(p), 0.6)) == 0)


def test_scene_config_rejects_unknown_names_and_overrides():
    with pytest.raises(SceneConfigError, match="available scenes"):
        scene_config("nope")
    with pytest.raises(SceneConfigError, match="colour"):
        scene_config("tiny", colour=3)
    assert scene_config("tiny", width=64).width == 64


def _digest(folder):
    h = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(folder)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_generation_is_deterministic_for_a_seed_and_parallel_equals_serial(tmp_path):
    small = {"n_views": 3, "width": 48, "height": 36, "supersample": 1}
    a = generate_scene("tiny", tmp_path / "a", seed=5, **small)
    b = generate_scene("tiny", tmp_path / "b", seed=5, workers=2, **small)
    c = generate_scene("tiny", tmp_path / "c", seed=6, **small)
    assert _digest(a) == _digest(b)
    assert _digest(a) != _digest(c)


def test_scene_folder_contract(tiny_scene):
    spec = load_scene_spec(tiny_scene)
    config = SCENES["tiny"]
    assert spec.name == "tiny" and (spec.width, spec.height) == (config.width, config.height)
    assert {e.id for e in spec.edits} == {"snow", "blue_tent"}
    assert spec.edit("blue_tent").instruction == "Turn the tent blue"
    with pytest.raises(SceneSpecError, match="snow, blue_tent"):
        spec.edit("nope")
    images = sorted(p.name for p in (tiny_scene / "images").iterdir())
    assert len(images) == config.n_views and images[0] == "view_000.png"
    doc = json.loads((tiny_scene / "gt" / "transforms.json").read_text())
    assert (doc["w"], doc["h"]) == (config.width, config.height)
    assert all((tiny_scene / "gt" / f["file_path"]).resolve().is_file() for f in doc["frames"])
    assert load_gt_edit(tiny_scene, "autumn", images[0]) is None    # not in tiny's vocabulary


def test_ground_truth_transforms_use_nerfstudio_axes(tiny_scene):
    """The look-at target must project to the principal point through the written OpenGL c2w."""
    doc = json.loads((tiny_scene / "gt" / "transforms.json").read_text())
    target = np.array([0.0, 0.0, SCENES["tiny"].target_height, 1.0])
    for frame in doc["frames"]:
        c2w_gl = np.asarray(frame["transform_matrix"])
        w2c = np.linalg.inv(c2w_gl @ np.linalg.inv(OPENCV_TO_OPENGL))     # back to OpenCV axes
        x, y, z = (w2c @ target)[:3]
        assert z > 0
        assert doc["fl_x"] * x / z + doc["cx"] == pytest.approx(doc["cx"], abs=1e-6)
        assert doc["fl_y"] * y / z + doc["cy"] == pytest.approx(doc["cy"], abs=1e-6)


def test_edits_change_pixels_only_inside_their_masks(tiny_scene):
    import cv2

    names = sorted(p.name for p in (tiny_scene / "images").iterdir())
    for edit in ("snow", "blue_tent"):
        coverage = []
        for name in names:
            original = cv2.imread(str(tiny_scene / "images" / name))[..., ::-1]
            edited, mask = load_gt_edit(tiny_scene, edit, name)
            assert np.array_equal(edited[~mask], original[~mask])
            diff = np.abs(edited.astype(int) - original).max(axis=-1)
            assert np.all(diff[mask] > SCENES["tiny"].mask_threshold)
            coverage.append(mask.mean())
        assert min(coverage) > 0.0, f"{edit}: some view has an empty mask"
    # Snow covers the ground in every view: a global edit; the tent is a small part of the image.
    assert np.mean([load_gt_edit(tiny_scene, "snow", n)[1].mean() for n in names]) > 0.4


def test_blue_tent_mask_covers_only_the_tent():
    """Trace the tent's pixel coverage independently: the mask must lie inside it and cover most of it."""
    from dualnerf.scenes.generate import edit_ground_truth, render_view
    from dualnerf.scenes.library import BUILDERS

    config = scene_config("tiny", width=80, height=60)
    builder, edits = BUILDERS["tiny"]
    world = builder(config, 0)
    tent = [o.name for o in world.objects].index("tent")
    c2w_all, _ = scene_cameras(config)
    for i in (0, 9, 20):
        images, geometry = render_view(config, world, c2w_all[i], [None, edits[1].variant])
        s = config.supersample
        tent_fraction = (geometry.object_index == tent).reshape(config.height, s, config.width, s).mean(axis=(1, 3))
        _, mask = edit_ground_truth(images[None], images["blue_tent"], config.mask_threshold)
        assert mask.any()
        assert np.all(tent_fraction[mask] > 0)               # nothing outside the tent changes
        assert mask.sum() >= 0.8 * (tent_fraction == 1).sum()  # and the tent's interior does change


def test_trace_hits_every_ray_thanks_to_the_dome():
    config = scene_config("tiny", width=40, height=30, supersample=1)
    from dualnerf.scenes.library import BUILDERS

    world = BUILDERS["tiny"][0](config, 0)
    c2w = scene_cameras(config)[0][0]
    o, d = camera_rays(c2w, config.focal, config.focal, 20.0, 15.0, 40, 30)
    geometry = trace(world, o, d, 1.0 / config.focal)
    assert np.all(geometry.object_index >= 0)
    assert set(np.unique(geometry.lit)) <= {0.0, 1.0} and 0 < geometry.lit.mean() < 1   # some shadow


def test_malformed_scene_toml_names_file_and_field(tmp_path):
    (tmp_path / "scene.toml").write_text('[scene]\nname = "x"\n[[edits]]\nid = "a"\ninstruction = "b"\n'
                                         'source_caption = "c"\n')
    with pytest.raises(SceneSpecError, match=r"scene.toml.*target_caption"):
        load_scene_spec(tmp_path)
    (tmp_path / "scene.toml").write_text("[scene\n")
    with pytest.raises(SceneSpecError, match="not valid TOML"):
        load_scene_spec(tmp_path)
    with pytest.raises(SceneSpecError, match="is missing"):
        load_scene_spec(tmp_path / "nowhere")


def test_nerfstudio_format_writes_top_level_transforms(tmp_path):
    out = generate_scene("tiny", tmp_path / "ns", format="nerfstudio", n_views=3, width=32, height=24,
                         supersample=1)
    doc = json.loads((out / "transforms.json").read_text())
    assert [f["file_path"] for f in doc["frames"]] == [f"images/view_{i:03d}.png" for i in range(3)]
    assert (out / doc["ply_file_path"]).is_file()


def test_scene_command(tmp_path, capsys):
    from experiments.cli import main

    out = tmp_path / "s"
    assert main(["--quiet", "scene", "tiny", "--out", str(out), "--n-views", "3", "--width", "32",
                 "--height", "24", "--workers", "1"]) == 0
    assert "SYNTHETIC" in capsys.readouterr().err
    assert load_scene_spec(out).width == 32 and len(list((out / "images").iterdir())) == 3
    assert main(["scene", "tiny", "--out", str(out)]) == 2          # refuses a non-empty folder
    assert "not empty" in capsys.readouterr().err
    assert main(["scene", "castle", "--out", str(tmp_path / "c")]) == 2
    assert "available scenes: bear, campsite, portrait, tiny" in capsys.readouterr().err
    assert main(["scene", "--list"]) == 0
    assert "blue_tent" in capsys.readouterr().out
