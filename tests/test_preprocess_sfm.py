"""Preprocess through COLMAP SfM (pycolmap) on procedural scenes: registration, pose accuracy against
ground truth after a similarity alignment, focal length, COLMAP-model import, failure reporting."""
from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from dualnerf.dataset import load_dataset
from dualnerf.io import InputError, PreprocessConfig, preprocess
from dualnerf.io.align import aligned_centre_errors, umeyama
from dualnerf.io.nerfstudio import import_nerfstudio
from tests.test_preprocess import tree_hash


def pose_errors(scene, dataset_dir):
    """(max centre error / camera-circle radius, relative focal error) against the scene's ground truth."""
    ds = load_dataset(dataset_dir)
    gt = import_nerfstudio(scene / "gt" / "transforms.json", root=scene)
    order = [gt.names.index(n) for n in ds.names]
    centres = ds.c2w[:, :3, 3] / ds.normalisation["scale"] - ds.normalisation["offset"]
    radius = float(np.median(np.linalg.norm(gt.c2w[:, :2, 3], axis=1)))
    error = aligned_centre_errors(centres, gt.c2w[order, :3, 3]).max() / radius
    scale = ds.width / gt.sizes[0][0]
    focal = ds.intrinsics[:, 0].mean() / (gt.intrinsics[0, 0] * scale) - 1.0
    return error, focal


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20, 3))
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.diag(r))
    if np.linalg.det(rotation) < 0:
        rotation[:, 0] *= -1
    y = 2.5 * x @ rotation.T + [1.0, -2.0, 0.5]
    s, r_est, t = umeyama(x, y)
    assert s == pytest.approx(2.5) and np.allclose(r_est, rotation) and np.allclose(t, [1.0, -2.0, 0.5])
    assert aligned_centre_errors(x, y).max() < 1e-9


@pytest.mark.slow
def test_sfm_registers_tiny_and_colmap_import_matches(tiny_scene, tmp_path):
    before = tree_hash(tiny_scene)
    config = PreprocessConfig(method="auto")
    report = preprocess(tiny_scene, tmp_path / "sfm", config, scratch=tmp_path / "scratch")
    assert tree_hash(tiny_scene) == before                     # the input folder is never modified
    assert report["method"] == "sfm" and report["registered"] == report["total"] == 26
    assert report["unregistered"] == [] and report["points"] > 200
    assert report["mean_reprojection_error"] < 1.0
    error, focal = pose_errors(tiny_scene, tmp_path / "sfm")
    assert error < 0.03 and abs(focal) < 0.06
    # SfM is deterministic: a second run gives the very same cameras.
    preprocess(tiny_scene, tmp_path / "sfm1", PreprocessConfig(method="auto"))
    assert np.array_equal(load_dataset(tmp_path / "sfm1").c2w, load_dataset(tmp_path / "sfm").c2w)
    # The same model imported as a COLMAP sparse folder gives the same dataset.
    colmap = tmp_path / "colmap"
    shutil.copytree(tmp_path / "scratch" / "sparse" / "0", colmap / "sparse" / "0")
    shutil.copytree(tiny_scene / "images", colmap / "images")
    report2 = preprocess(colmap, tmp_path / "imported", PreprocessConfig(method="auto"))
    assert report2["method"] == "colmap" and report2["registered"] == 26
    a, b = load_dataset(tmp_path / "sfm"), load_dataset(tmp_path / "imported")
    assert a.names == b.names
    assert np.allclose(a.c2w, b.c2w, atol=1e-9) and np.allclose(a.intrinsics, b.intrinsics)
    assert np.array_equal(a.images, b.images)
    # ... and so does the text format of the same model.
    import pycolmap

    text = tmp_path / "colmap_txt"
    (text / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(str(colmap / "sparse" / "0")).write_text(str(text / "sparse" / "0"))
    assert (text / "sparse" / "0" / "cameras.txt").is_file()
    shutil.copytree(tiny_scene / "images", text / "images")
    preprocess(text, tmp_path / "imported_txt", PreprocessConfig(method="colmap"))
    c = load_dataset(tmp_path / "imported_txt")
    assert np.allclose(a.c2w, c.c2w, atol=1e-6) and np.allclose(a.intrinsics, c.intrinsics, atol=1e-6)


@pytest.mark.slow
def test_sfm_on_campsite_meets_pose_and_focal_accuracy(tmp_path):
    from dualnerf.scenes import generate_scene
    from dualnerf.scenes.library import BUILDERS

    scene = generate_scene("campsite", tmp_path / "campsite", n_views=36, workers=2)
    report = preprocess(scene, tmp_path / "ds", PreprocessConfig(method="sfm"))
    assert report["registered"] == report["total"] == 36
    error, focal = pose_errors(scene, tmp_path / "ds")
    assert error <= 0.01, f"camera-centre error {error:.4f} of the radius"
    assert abs(focal) <= 0.01, f"focal error {focal:.4f}"
    # Preprocess carries every ground-truth edit the scene renders (the library's list for campsite) and
    # every edit's alternative modes (gt/edits/<edit>.<mode>/).
    edits = BUILDERS["campsite"][1]
    assert sorted(report["gt_edits"]) == sorted([e.id for e in edits]
                                                + [f"{e.id}.{m.id}" for e in edits for m in e.modes])
    assert {"autumn", "blue_tent", "canoe", "snow"} <= set(report["gt_edits"])


@pytest.mark.slow
def test_sfm_that_registers_under_half_lists_the_images(tiny_scene, tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in sorted(p.name for p in (tiny_scene / "images").iterdir())[:8]:
        shutil.copyfile(tiny_scene / "images" / name, folder / name)
    rng = np.random.default_rng(0)
    for i in range(10):   # unrelated pictures: smooth random blobs, nothing in common with the scene
        noise = cv2.resize(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8), (160, 120),
                           interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(folder / f"zz_other_{i}.png"), noise)
    with pytest.raises(InputError, match=r"registered only \d+ of 18") as err:
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="sfm"))
    message = str(err.value)
    assert "zz_other_0.png" in message and "overlap" in message


@pytest.mark.slow
def test_sequential_matcher_registers_tiny(tiny_scene, tmp_path):
    report = preprocess(tiny_scene, tmp_path / "seq", PreprocessConfig(method="sfm", matcher="sequential"))
    assert report["matcher"] == "sequential" and report["registered"] == report["total"] == 26
    error, _ = pose_errors(tiny_scene, tmp_path / "seq")
    assert error < 0.03
