"""Preprocess without SfM: nerfstudio import, normalisation, resizing, GT carrying, image reading and
every bad-input case; the stage through a fake context and through the engine."""
from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from dualnerf.dataset import load_dataset
from dualnerf.io import InputError, PreprocessConfig, preprocess
from dualnerf.io.images import apply_exif_orientation, list_images, read_image
from dualnerf.io.nerfstudio import OPENGL_TO_OPENCV
from dualnerf.scenes import load_gt_edit


def tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for path in sorted(p for p in Path(folder).rglob("*") if p.is_file()):
        h.update(str(path.relative_to(folder)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def gt_cameras(scene: Path):
    doc = json.loads((scene / "gt" / "transforms.json").read_text())
    names = [Path(f["file_path"]).name for f in doc["frames"]]
    c2w = np.array([np.asarray(f["transform_matrix"]) @ OPENGL_TO_OPENCV for f in doc["frames"]])
    return doc, names, c2w


def test_nerfstudio_import_reproduces_ground_truth_poses(tiny_dataset, tiny_scene):
    ds = load_dataset(tiny_dataset)
    doc, names, c2w_gt = gt_cameras(tiny_scene)
    assert ds.names == sorted(names)
    order = [names.index(n) for n in ds.names]
    s, offset = ds.normalisation["scale"], np.asarray(ds.normalisation["offset"])
    # Undo x_norm = s (x + offset): rotations are untouched, centres scale back.
    assert np.allclose(ds.c2w[:, :3, :3], c2w_gt[order, :3, :3], atol=1e-12)
    assert np.allclose(ds.c2w[:, :3, 3] / s - offset, c2w_gt[order, :3, 3], atol=1e-9)
    assert np.allclose(ds.intrinsics, [doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"]])
    assert ds.split[::8] == ["heldout"] * len(ds.split[::8]) and ds.split.count("heldout") == 4
    original = cv2.imread(str(tiny_scene / "images" / ds.names[3]))[..., ::-1]
    assert np.array_equal(ds.images[3], original)


def test_normalisation_bounds_cameras_and_points_and_depth_ranges(tiny_dataset, tiny_scene):
    from dualnerf.io.ply import read_ply_points

    ds = load_dataset(tiny_dataset)
    s, offset = ds.normalisation["scale"], np.asarray(ds.normalisation["offset"])
    points = s * (read_ply_points(tiny_scene / "gt" / "sparse_pc.ply") + offset)
    assert np.abs(ds.c2w[:, :3, 3]).max() < 1.0
    assert np.mean(np.all(np.abs(points) <= 1.0, axis=1)) > 0.99
    assert np.abs(points).max() > 0.8           # and the cube is used, not padded away
    for i in range(len(ds.c2w)):
        w2c = np.linalg.inv(ds.c2w[i])
        z = (points @ w2c[:3, :3].T + w2c[:3, 3])[:, 2]
        fx, fy, cx, cy = ds.intrinsics[i]
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        visible = (z > 0) & (np.abs(fx * p[:, 0] / z + cx - ds.width / 2) < ds.width / 2) \
            & (np.abs(fy * p[:, 1] / z + cy - ds.height / 2) < ds.height / 2)
        depths = z[visible]
        assert ds.near[i] < np.percentile(depths, 1) and np.percentile(depths, 99.9) < ds.far[i]


def test_resizing_scales_intrinsics_and_ground_truth_consistently(tiny_scene, tmp_path):
    preprocess(tiny_scene, tmp_path / "ds", PreprocessConfig(method="nerfstudio", max_size=80, holdout_every=0))
    ds = load_dataset(tmp_path / "ds")
    doc, _, _ = gt_cameras(tiny_scene)
    assert (ds.width, ds.height) == (80, 60) and ds.split.count("heldout") == 0
    assert np.allclose(ds.intrinsics[0], np.array([doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"]]) / 2)
    for i in (0, 7):
        edited, mask = load_gt_edit(tmp_path / "ds", "blue_tent", ds.names[i])
        assert edited.shape == ds.images[i].shape and mask.any()
        assert np.array_equal(edited[~mask], ds.images[i][~mask])    # still unchanged outside the mask
    assert (tmp_path / "ds" / "scene.toml").read_text() == (tiny_scene / "scene.toml").read_text()


def test_preprocess_never_modifies_its_input(tiny_scene, tmp_path):
    before = tree_hash(tiny_scene)
    preprocess(tiny_scene, tmp_path / "ds", PreprocessConfig(method="nerfstudio", max_size=64))
    assert tree_hash(tiny_scene) == before


# ---- image reading ---------------------------------------------------------------------------------

def test_read_image_converts_gray_16bit_and_rgba(tmp_path):
    gray = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    assert np.array_equal(read_image(tmp_path / "g.png"), np.repeat(gray[..., None], 3, axis=2))
    deep = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 257 * 20)
    cv2.imwrite(str(tmp_path / "d.png"), deep)
    assert np.array_equal(read_image(tmp_path / "d.png")[..., 0], gray)
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., :3] = (10, 20, 200)                # BGR on disk
    rgba[..., 3] = [[255, 0], [128, 255]]
    cv2.imwrite(str(tmp_path / "a.png"), rgba)
    out = read_image(tmp_path / "a.png")
    assert out[0, 0].tolist() == [200, 20, 10] and out[0, 1].tolist() == [0, 0, 0]
    assert out[1, 0].tolist() == [100, 10, 5]    # composited on black: 128/255 of the colour


@pytest.mark.parametrize("code, expected", [
    (1, [[1, 2, 3], [4, 5, 6]]), (2, [[3, 2, 1], [6, 5, 4]]), (3, [[6, 5, 4], [3, 2, 1]]),
    (4, [[4, 5, 6], [1, 2, 3]]), (5, [[1, 4], [2, 5], [3, 6]]), (6, [[4, 1], [5, 2], [6, 3]]),
    (7, [[6, 3], [5, 2], [4, 1]]), (8, [[3, 6], [2, 5], [1, 4]]),
])
def test_exif_orientation_codes(code, expected):
    stored = np.array([[1, 2, 3], [4, 5, 6]])[..., None]
    assert apply_exif_orientation(stored, code)[..., 0].tolist() == expected


def test_exif_orientation_is_applied_when_reading(tmp_path):
    import OpenImageIO as oiio

    pixels = np.zeros((20, 40, 3), np.uint8)
    pixels[:, :20] = 255                                     # left half white
    spec = oiio.ImageSpec(40, 20, 3, oiio.UINT8)
    spec.attribute("Orientation", 6)                         # display = stored turned 90 degrees clockwise
    path = str(tmp_path / "rot.jpg")
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(pixels)
    out.close()
    image = read_image(tmp_path / "rot.jpg")
    assert image.shape == (40, 20, 3)
    assert image[:15].mean() > 200 and image[-15:].mean() < 50    # stored left half is now on top


def test_empty_and_truncated_images_are_named(tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty\.png.*0 bytes"):
        read_image(tmp_path / "empty.png")
    _, data = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8))
    (tmp_path / "cut.png").write_bytes(data.tobytes()[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.png"):
        read_image(tmp_path / "cut.png")
    _ok, data = cv2.imencode(".jpg", np.full((64, 64, 3), 90, np.uint8))
    (tmp_path / "cut.jpg").write_bytes(data.tobytes()[:-40])
    with pytest.raises(InputError, match=r"cut\.jpg.*truncated"):
        read_image(tmp_path / "cut.jpg")
    (tmp_path / "fake.png").write_text("not an image")
    with pytest.raises(InputError, match=r"fake\.png.*could not be decoded"):
        read_image(tmp_path / "fake.png")


def test_non_image_files_are_skipped_with_a_warning(tmp_path, caplog):
    for name in ("b.png", "a.jpg"):
        cv2.imwrite(str(tmp_path / name), np.zeros((4, 4, 3), np.uint8))
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / ".DS_Store").write_text("x")
    with caplog.at_level(logging.WARNING):
        images = list_images(tmp_path)
    assert [p.name for p in images] == ["a.jpg", "b.png"]
    assert "notes.txt" in caplog.text and "DS_Store" not in caplog.text


# ---- bad input through preprocess ------------------------------------------------------------------

def _image_folder(tiny_scene, tmp_path, n):
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in sorted(p.name for p in (tiny_scene / "images").iterdir())[:n]:
        shutil.copyfile(tiny_scene / "images" / name, folder / name)
    return folder


def test_fewer_than_three_images(tiny_scene, tmp_path):
    folder = _image_folder(tiny_scene, tmp_path, 2)
    with pytest.raises(InputError, match="at least 3"):
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="sfm"))


def test_mixed_resolutions_name_the_odd_images(tiny_scene, tmp_path):
    folder = _image_folder(tiny_scene, tmp_path, 5)
    cv2.imwrite(str(folder / "odd.png"), np.zeros((50, 70, 3), np.uint8))
    with pytest.raises(InputError, match=r"odd\.png \(70x50\)") as err:
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="sfm"))
    assert "view_000.png" not in str(err.value)


def _transforms_case(tiny_scene, tmp_path, mutate):
    folder = tmp_path / "ns"
    shutil.copytree(tiny_scene / "images", folder / "images")
    doc = json.loads((tiny_scene / "gt" / "transforms.json").read_text())
    for frame in doc["frames"]:
        frame["file_path"] = frame["file_path"].replace("../images/", "images/")
    doc.pop("ply_file_path")
    mutate(doc)
    (folder / "transforms.json").write_text(json.dumps(doc))
    return folder


def test_transforms_with_missing_files(tiny_scene, tmp_path):
    def mutate(doc):
        doc["frames"][2]["file_path"] = "images/gone.png"
    folder = _transforms_case(tiny_scene, tmp_path, mutate)
    with pytest.raises(InputError, match=r"transforms\.json.*gone\.png"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_transforms_with_non_finite_pose(tiny_scene, tmp_path):
    def mutate(doc):
        doc["frames"][4]["transform_matrix"][0][3] = float("nan")
    folder = _transforms_case(tiny_scene, tmp_path, mutate)
    with pytest.raises(InputError, match=r"non-finite.*view_004\.png"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_transforms_with_non_rigid_pose(tiny_scene, tmp_path):
    def mutate(doc):
        m = np.asarray(doc["frames"][5]["transform_matrix"])
        m[:3, :3] *= 1.5
        doc["frames"][5]["transform_matrix"] = m.tolist()
    folder = _transforms_case(tiny_scene, tmp_path, mutate)
    with pytest.raises(InputError, match=r"view_005\.png.*not a rigid"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_transforms_with_missing_intrinsics(tiny_scene, tmp_path):
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: doc.pop("fl_x"))
    with pytest.raises(InputError, match=r"intrinsic 'fl_x' is missing"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_auto_detects_nerfstudio_and_matches_the_gt_import(tiny_scene, tiny_dataset, tmp_path):
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    report = preprocess(folder, tmp_path / "out", PreprocessConfig())
    assert report["method"] == "nerfstudio" and report["registered"] == report["total"] == 26
    a, b = load_dataset(tmp_path / "out"), load_dataset(tiny_dataset)
    # Without the point cloud the normalisation differs, but poses agree up to that similarity.
    assert np.allclose(a.c2w[:, :3, :3], b.c2w[:, :3, :3])
    ratio = np.linalg.norm(np.diff(a.c2w[:, :3, 3], axis=0), axis=1) / np.linalg.norm(
        np.diff(b.c2w[:, :3, 3], axis=0), axis=1)
    assert np.allclose(ratio, ratio[0])


def test_unknown_method_and_missing_source(tmp_path):
    with pytest.raises(InputError, match="unknown preprocess method"):
        preprocess(tmp_path, tmp_path / "o", PreprocessConfig(method="magic"))
    with pytest.raises(InputError, match="does not exist"):
        preprocess(tmp_path / "nope", tmp_path / "o", PreprocessConfig())


# ---- the stage ---------------------------------------------------------------------------------------

class FakeContext:
    def __init__(self, params, inputs, root: Path):
        self.params, self.inputs = params, inputs
        self.out_dir, self.scratch_dir = root / "out", root / "scratch"
        self.out_dir.mkdir(parents=True)
        self.scratch_dir.mkdir(parents=True)
        self.log = logging.getLogger("fake")
        self.threads = 1
        self.recorded = {}

    def record(self, **entries):
        self.recorded.update(entries)

    def progress(self, total, desc, initial=0):
        from contextlib import nullcontext

        class Bar:
            def update(self, n=1, **metrics):
                pass
        return nullcontext(Bar())


def test_preprocess_stage_with_a_fake_context(tiny_scene, tmp_path):
    from stages.preprocess import PreprocessParams, PreprocessStage

    ctx = FakeContext(PreprocessParams(method="nerfstudio", seed=3), {"scene": tiny_scene}, tmp_path)
    PreprocessStage().run(ctx)
    assert load_dataset(ctx.out_dir).names[0] == "view_000.png"
    assert (ctx.out_dir / "gt" / "edits" / "snow" / "masks" / "view_000.png").is_file()
    assert ctx.recorded["seed"] == 3 and ctx.recorded["registered"] == 26
    report = json.loads((ctx.out_dir / "sfm_report.json").read_text())
    assert report["registered"] == report["total"] == 26 and report["unregistered"] == []
    with pytest.raises(ValueError, match="exactly one input"):
        PreprocessStage().run(FakeContext(PreprocessParams(), {}, tmp_path / "again"))


def test_scene_and_preprocess_through_the_engine(tmp_path):
    from pipeline.dag import Step
    from pipeline.executors import SerialExecutor
    from pipeline.runner import run_steps
    from pipeline.store import Store
    from stages import STAGES

    scene = Step("scene", {"name": "tiny", "n_views": 4, "width": 40, "height": 30}, label="scene")
    prep = Step("preprocess", {"method": "nerfstudio"}, {"scene": scene}, label="prep")
    result = run_steps([prep], registry=STAGES, store=Store(tmp_path / "cache"),
                       executor=SerialExecutor(threads=1), run_dir=tmp_path / "runs", quiet=True)
    assert result.ok, result.summary()
    ds = load_dataset(result.results[prep])
    assert (ds.width, ds.height) == (40, 30) and len(ds.names) == 4
    manifest = json.loads((result.results[prep] / "manifest.json").read_text())
    assert "seed" in json.dumps(manifest)


def test_distorted_nerfstudio_images_are_undistorted_to_pinhole(tiny_scene, tmp_path):
    """Distort pinhole views with a known OPENCV model; preprocess must give the pinhole views back."""
    doc = json.loads((tiny_scene / "gt" / "transforms.json").read_text())
    k = np.array([[doc["fl_x"], 0, doc["cx"] - 0.5], [0, doc["fl_y"], doc["cy"] - 0.5], [0, 0, 1]])
    dist = np.array([-0.25, 0.05, 0.001, -0.001, 0.0])
    w, h = doc["w"], doc["h"]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    ideal = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), k, dist, P=k).reshape(h, w, 2)
    folder = tmp_path / "distorted"
    (folder / "images").mkdir(parents=True)
    frames = doc["frames"][:6]
    pinhole = []
    for frame in frames:
        name = Path(frame["file_path"]).name
        image = cv2.imread(str(tiny_scene / "images" / name))
        pinhole.append(image[..., ::-1])
        distorted = cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR)
        cv2.imwrite(str(folder / "images" / name), distorted)
        frame["file_path"] = f"images/{name}"
    doc.update(frames=frames, camera_model="OPENCV", k1=dist[0], k2=dist[1], p1=dist[2], p2=dist[3])
    doc.pop("ply_file_path")
    (folder / "transforms.json").write_text(json.dumps(doc))
    preprocess(folder, tmp_path / "ds", PreprocessConfig())
    ds = load_dataset(tmp_path / "ds")
    centre = (slice(12, h - 12), slice(12, w - 12))
    for i in range(len(frames)):
        undistorted_error = np.abs(ds.images[i][centre].astype(int) - pinhole[i][centre]).mean()
        distorted = cv2.imread(str(folder / "images" / ds.names[i]))[..., ::-1]
        distorted_error = np.abs(distorted[centre].astype(int) - pinhole[i][centre]).mean()
        assert undistorted_error < 4.0 and distorted_error > 2 * undistorted_error


def test_jpeg_with_exif_thumbnail_or_appended_data_is_not_called_truncated(tmp_path):
    import OpenImageIO as oiio

    pixels = np.random.default_rng(1).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    path = str(tmp_path / "exif.jpg")
    spec = oiio.ImageSpec(96, 64, 3, oiio.UINT8)
    spec.attribute("Make", "TestCam")
    out = oiio.ImageOutput.create(path)
    out.open(path, spec)
    out.write_image(pixels)
    out.close()
    assert read_image(tmp_path / "exif.jpg").shape == (64, 96, 3)
    data = (tmp_path / "exif.jpg").read_bytes()
    (tmp_path / "motion.jpg").write_bytes(data + b"\x00\x00\x00\x18ftypmp42" + bytes(100))   # appended video
    assert read_image(tmp_path / "motion.jpg").shape == (64, 96, 3)
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match="truncated"):
        read_image(tmp_path / "cut.jpg")


def test_bad_sfm_options_fail_before_any_work(tiny_scene, tmp_path):
    with pytest.raises(InputError, match="unknown matcher 'fast'"):
        preprocess(tiny_scene, tmp_path / "a", PreprocessConfig(method="sfm", matcher="fast"))
    with pytest.raises(InputError, match="camera_model 'FISHEYE'"):
        preprocess(tiny_scene, tmp_path / "b", PreprocessConfig(method="sfm", camera_model="FISHEYE"))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_broken_image_in_a_folder_stops_preprocess_with_its_name(tiny_scene, tmp_path):
    folder = _image_folder(tiny_scene, tmp_path, 5)
    (folder / "view_002.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"view_002\.png is empty"):
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="sfm"))
