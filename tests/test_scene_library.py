"""The scene library as a benchmark: every scene's edit vocabulary (recolour, global, geometry), masks that
are exactly the changed pixels, geometry edits that change depth and occlusion exactly as a full re-trace
does, camera spacing, determinism, the `scene list` command and the emulator on every edit."""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
import pytest

from dualnerf.editors.emulator import EmulatorConfig, InstructPix2PixEmulator
from dualnerf.scenes import (
    SCENES,
    generate_scene,
    load_gt_edit,
    load_scene_spec,
    mode_edit_id,
    scene_cameras,
    scene_config,
)
from dualnerf.scenes.cameras import neighbour_angles_degrees
from dualnerf.scenes.generate import edit_ground_truth, render_view
from dualnerf.scenes.library import BUILDERS, EDIT_KINDS
from dualnerf.scenes.render import camera_rays, shade, to_image, trace

BENCHMARK_SCENES = [name for name in SCENES if name != "tiny"]     # tiny is the CI scene
SMALL = {"width": 64, "height": 48, "supersample": 1}


def _views(name: str, indices=(0, 1), **small):
    """Small renders of views of the scene's own rig: (config, world, {i: (images, geometry)})."""
    config = scene_config(name, **{**SMALL, **small})
    builder, edits = BUILDERS[name]
    world = builder(config, 0)
    c2w = scene_cameras(config)[0]
    step = max(1, config.n_views // len(indices))
    return config, world, {i * step: render_view(config, world, c2w[i * step], [None] + [e.variant for e in edits])
                           for i in indices}


def test_library_is_the_single_list_of_scenes_and_edits():
    assert set(BUILDERS) == set(SCENES)
    assert {"tiny", "campsite", "bear", "portrait"} <= set(SCENES)
    for name, (_builder, edits) in BUILDERS.items():
        ids = [e.id for e in edits]
        assert len(set(ids)) == len(ids), name
        for e in edits:
            assert e.kind in EDIT_KINDS and e.variant.id == e.id
            assert e.instruction.strip() and e.source_caption.strip() and e.target_caption.strip()
            assert e.source_caption != e.target_caption
    for name in BENCHMARK_SCENES:
        assert {e.kind for e in BUILDERS[name][1]} == set(EDIT_KINDS), name
    # The existing edit ids keep their names (cached results and workflows refer to them).
    assert [e.id for e in BUILDERS["campsite"][1]][:3] == ["snow", "blue_tent", "autumn"]
    assert [e.id for e in BUILDERS["tiny"][1]] == ["snow", "blue_tent"]


@pytest.mark.parametrize("name", BENCHMARK_SCENES)
def test_rig_sizes_and_view_spacing(name):
    config = SCENES[name]
    assert 40 <= config.n_views <= 60 and (config.width, config.height) == (256, 192)
    c2w, _ = scene_cameras(config)
    assert neighbour_angles_degrees(c2w).max() <= 10.0
    if config.arc_degrees >= 360:      # a closed orbit: the last view neighbours the first
        assert neighbour_angles_degrees(c2w[[-1, 0]]).max() <= 10.0
    else:                              # forward-facing: every camera sees the figure from the front half
        assert 60.0 <= config.arc_degrees <= 90.0
        assert np.all(c2w[:, 1, 3] < 0)


def test_campsite_views_and_earlier_edits_are_byte_identical_to_scene_version_1():
    """Digest of two 64x48 views with snow, blue_tent and autumn, computed with the scene stage at
    version 1 (before the canoe existed): adding the geometry edit must not change any of them."""
    config = scene_config("campsite", **SMALL)
    world = BUILDERS["campsite"][0](config, 0)
    c2w = scene_cameras(config)[0]
    edits = [e for e in BUILDERS["campsite"][1] if e.id in ("snow", "blue_tent", "autumn")]
    h = hashlib.sha256()
    for i in (0, 20):
        images, _ = render_view(config, world, c2w[i], [None] + [e.variant for e in edits])
        for k in (None, "snow", "blue_tent", "autumn"):
            h.update(images[k].tobytes())
    assert h.hexdigest() == "d2c0f89850378a4afa3b23168b1f48c808227f1e69f0213a5baa8514814aef3e"


@pytest.mark.parametrize("name", BENCHMARK_SCENES)
def test_masks_are_the_changed_pixels_and_local_edits_stay_local(name):
    config, world, views = _views(name, (0, 1, 2))
    edits = BUILDERS[name][1]
    coverage = {e.id: [] for e in edits}
    for images, geometry in views.values():
        original = images[None]
        for e in edits:
            edited, mask = edit_ground_truth(original, images[e.id], config.mask_threshold)
            diff = np.abs(images[e.id].astype(int) - original.astype(int)).max(axis=-1)
            assert np.array_equal(mask, diff > config.mask_threshold)
            assert np.array_equal(edited[~mask], original[~mask])
            assert np.array_equal(edited[mask], images[e.id][mask])
            coverage[e.id].append(mask.mean())
            if e.kind == "recolour":
                # Independently: the pixels whose rays hit an object of a recoloured material.
                tags = set(e.variant.recolour)
                touched = np.isin(geometry.object_index,
                                  [k for k, o in enumerate(world.objects) if o.material.tag in tags])
                assert np.all(touched.reshape(config.height, config.width)[mask])
                assert mask.sum() >= 0.8 * touched.sum()
    for e in edits:
        mean = float(np.mean(coverage[e.id]))
        assert min(coverage[e.id]) > 0.0, f"{name}/{e.id}: some view has an empty mask"
        if e.kind == "global":
            assert mean > 0.5, f"{name}/{e.id}: a global edit must change most pixels, got {mean:.2f}"
        else:
            assert mean < 0.3, f"{name}/{e.id}: a local edit must change a minority, got {mean:.2f}"
    local = max(np.mean(coverage[e.id]) for e in edits if e.kind != "global")
    assert local < min(np.mean(coverage[e.id]) for e in edits if e.kind == "global")


@pytest.mark.parametrize("name", BENCHMARK_SCENES)
def test_geometry_edit_matches_a_full_retrace_and_changes_depth(name):
    """The re-trace of affected rays only must equal tracing the edited world from scratch, and the mask
    must be where the added object shows (nearer than what was there) or where its shadow falls."""
    (edit,) = [e for e in BUILDERS[name][1] if e.kind == "geometry"]
    config, world, views = _views(name, (0, 1, 2))
    edited_world = edit.variant.apply(world)
    added = set(range(len(world.objects), len(edited_world.objects)))
    c2w = scene_cameras(config)[0]
    for i, (images, geometry) in views.items():
        o, d = camera_rays(c2w[i], config.focal, config.focal, config.width / 2, config.height / 2,
                           config.width, config.height)
        full = trace(edited_world, o, d, 1.0 / config.focal)
        reference = to_image(shade(edited_world, full, edit.variant), config.width, config.height, 1)
        assert np.abs(reference.astype(int) - images[edit.id].astype(int)).max() <= 1
        depth_before = np.linalg.norm(geometry.points - o, axis=1)
        depth_after = np.linalg.norm(full.points - o, axis=1)
        shows = np.isin(full.object_index, list(added))
        assert shows.any()
        assert np.all(depth_after[shows] < depth_before[shows])           # it occludes what was behind
        assert np.array_equal(depth_after[~shows], depth_before[~shows])  # and nothing else moves
        _, mask = edit_ground_truth(images[None], images[edit.id], config.mask_threshold)
        changed = (shows | (full.lit != geometry.lit)).reshape(config.height, config.width)
        assert np.all(changed[mask])
        assert mask.sum() >= 0.9 * shows.sum()


def test_removing_an_object_reveals_what_was_behind_it():
    from dualnerf.scenes.render import Variant

    config, world, views = _views("campsite", (0,))
    (i, (images, geometry)), = views.items()
    variant = Variant("no_tent", remove=("tent",))
    after, _ = render_view(config, world, scene_cameras(config)[0][i], [variant])
    tent = [o.name for o in world.objects].index("tent")
    hit_tent = (geometry.object_index == tent).reshape(config.height, config.width)
    _, mask = edit_ground_truth(images[None], after["no_tent"], config.mask_threshold)
    assert hit_tent.any() and mask[hit_tent].mean() > 0.9
    with pytest.raises(ValueError, match="unknown object"):
        Variant("x", remove=("castle",)).apply(world)


@pytest.mark.parametrize("name", ["bear", "portrait"])
def test_generation_is_deterministic_and_writes_every_edit(tmp_path, name):
    small = {**SMALL, "n_views": 3}
    a = generate_scene(name, tmp_path / "a", seed=2, **small)
    b = generate_scene(name, tmp_path / "b", seed=2, workers=2, **small)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    spec = load_scene_spec(a)
    assert [(e.id, e.kind) for e in spec.edits] == [(e.id, e.kind) for e in BUILDERS[name][1]]
    for e in spec.edits:
        assert load_gt_edit(a, e.id, "view_002.png")[1].any()


def test_emulator_works_on_every_edit_of_every_scene(tmp_path):
    """Quiet, the emulator returns the ground-truth edited view (geometry edits included); with its
    default noise it moves a render toward the ground truth inside the mask."""
    import cv2

    quiet = EmulatorConfig(noise_range=(1.0, 1.0), strength_jitter=0.0, tint_jitter=0.0, spatial_jitter=0.0,
                           background_drift=0.0, background_blur=0.0, failure_rate=0.0, mask_feather=0.0,
                           lock_in=False, background_cast=0.0)
    for name in SCENES:
        folder = generate_scene(name, tmp_path / name, n_views=3, width=48, height=36, supersample=1)
        names = sorted(p.name for p in (folder / "images").iterdir())
        originals = [cv2.imread(str(folder / "images" / n))[..., ::-1].copy() for n in names]
        for e in load_scene_spec(folder).edits:
            gt, mask = load_gt_edit(folder, e.id, names[1])
            emulator = InstructPix2PixEmulator.from_scene_folder(folder, e.id, e.instruction, names, originals,
                                                                 quiet)
            out = emulator.edit(originals[1], originals[1], e.instruction, seed=0, step=0)
            assert np.abs(out.astype(int) - gt.astype(int)).max() <= 1, f"{name}/{e.id}"
            noisy = InstructPix2PixEmulator.from_scene_folder(folder, e.id, e.instruction, names, originals,
                                                              EmulatorConfig(failure_rate=0.0, lock_in=False))
            errors = [np.abs(noisy.edit(originals[1], originals[1], e.instruction, seed=s, step=0).astype(float)
                             - gt)[mask].mean() for s in range(3)]
            assert np.median(errors) < np.abs(originals[1].astype(float) - gt)[mask].mean(), f"{name}/{e.id}"
            # Every edit has an alternative mode: another appearance of the same edit, in the same region.
            assert e.modes, f"{name}/{e.id} has no alternative mode"
            alt, alt_mask = load_gt_edit(folder, mode_edit_id(e.id, e.modes[0]), names[1])
            assert (alt_mask & mask).sum() >= 0.5 * mask.sum(), f"{name}/{e.id}"
            assert np.abs(alt.astype(int) - gt.astype(int))[mask].max() > 40, f"{name}/{e.id}"
            # With lock-in, a quiet call at full noise draws each mode at its prior share.
            locked = InstructPix2PixEmulator.from_scene_folder(
                folder, e.id, e.instruction, names, originals, dataclasses.replace(quiet, lock_in=True))
            drawn = []
            for seed in range(60):
                out = locked.edit(alt, originals[1], e.instruction, seed=seed, step=0)
                drawn.append(locked.last_details["mode"])
                expect = alt if drawn[-1] == 1 else gt
                assert np.abs(out.astype(int) - expect.astype(int)).max() <= 1, f"{name}/{e.id}"
            assert 0.4 < np.mean(np.array(drawn) == 0) < 0.9, f"{name}/{e.id}"


def test_scene_list_prints_every_scene_with_views_size_and_edits(capsys):
    from experiments.cli import main

    assert main(["scene", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(SCENES)
    for line, (name, config) in zip(lines, SCENES.items()):
        assert f"{config.n_views} views" in line and f"{config.width}x{config.height}" in line
        for e in BUILDERS[name][1]:
            assert f"{e.id} ({e.kind})" in line
