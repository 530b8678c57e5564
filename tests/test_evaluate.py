"""The evaluate stage end to end on the tiny procedural dataset with small randomly initialised models
(no training: the metrics' plumbing and invariants are what is under test, not model quality)."""
import json
import logging

import numpy as np
import pytest
import torch

from dualnerf import metrics as M
from dualnerf.dual_field import make_edit_model
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.model import save_model
from pipeline.context import StepContext
from stages.evaluate import EvaluateError, EvaluateParams, EvaluateStage

SMALL = FieldConfig(grid_resolutions=(4, 8), grid_features=2, hidden_width=8, geo_features=3,
                    direction_degree=2, density_bias=0.5, samples_per_ray=8, occupancy_resolution=8)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    static = RadianceField(SMALL, generator=torch.Generator().manual_seed(0))
    save_model(root / "fit" / "model", static)
    dual = make_edit_model(static, "dual")
    with torch.no_grad():                      # an "edit": a differently initialised dynamic field
        fresh = RadianceField(SMALL, generator=torch.Generator().manual_seed(1))
        dual.dynamic_field.load_state_dict(fresh.state_dict())
    dual.render_blend = (0.6, 0.6)
    save_model(root / "edit" / "model", dual)
    (root / "edit" / "edit.json").write_text(json.dumps(
        {"editor": {"kind": "synthetic", "name": "InstructPix2PixEmulator", "is_simulator": True}}))
    return root


def run_evaluate(tmp_path, dataset, models, edited: bool, out="out", **params):
    inputs = {"dataset": dataset, "fit": models / "fit"}
    if edited:
        inputs["edit"] = models / "edit"
    ctx = StepContext(key="test", params=EvaluateParams(**params), inputs=inputs, out_dir=tmp_path / out,
                      scratch_dir=tmp_path / "scratch", log=logging.getLogger("test-evaluate"))
    EvaluateStage().run(ctx)
    return ctx


@pytest.mark.slow
def test_original_scene_invariants(tmp_path, tiny_dataset, models):
    ctx = run_evaluate(tmp_path, tiny_dataset, models, edited=False, n_frames=5, edit_id="snow",
                       path_scale=0.5)
    out = ctx.out_dir
    doc = json.loads((out / "metrics.json").read_text())
    values = {k: M.parse_json_value(v["value"]) for k, v in doc["metrics"].items()}
    # Unedited: edited renders are the original ones.
    assert values["ssim_edited_vs_original"] == pytest.approx(1.0)
    assert values["clip_text_image_direction"] == 0.0
    assert values["clip_direction_consistency"] == pytest.approx(1.0)
    assert -1.0 <= values["clip_frame_consistency"] <= 1.0
    assert doc["edited"] is False and doc["editor"] is None
    assert doc["encoder"]["kind"] == "proxy" and doc["encoder"]["tag"] == "proxy"
    for name, entry in doc["metrics"].items():
        assert ("encoder" in entry) == M.METRICS[name].uses_encoder
        if M.METRICS[name].uses_encoder:
            assert entry["encoder"] == "proxy"
        assert entry.get("lpips") == ("lpips-v0.1:alex" if M.METRICS[name].uses_lpips else None), name
    # LPIPS: the unedited scene changed nothing, anywhere; the GT edit differs from f_S.
    assert values["lpips_edited_vs_original"] == 0.0 and values["lpips_background"] == 0.0
    assert values["gt_lpips_edit"] > 0.0
    assert doc["lpips"]["net"] == "alex" and doc["lpips"]["tag"] == "lpips-v0.1:alex"
    # Files: 5 path frames per model, held-out views with ground truth, a decodable video.
    assert len(list((out / "frames" / "original").glob("*.png"))) == 5
    assert len(list((out / "frames" / "edited").glob("*.png"))) == 5
    names = doc["views"]["names"]
    assert doc["views"]["split"] == "heldout" and names
    for kind in ("original", "edited", "gt_edit", "gt_mask"):
        assert sorted(p.name for p in (out / "views" / kind).iterdir()) == sorted(names)
    assert (out / "path.mp4").stat().st_size > 0
    from dualnerf.video import probe_video

    video = probe_video(out / "path.mp4")                       # browser-playable H.264, one frame per pose
    assert (video["codec"], video["pix_fmt"], video["frames"], video["faststart"]) == ("h264", "yuv420p", 5, True)
    path = json.loads((out / "camera_path.json").read_text())
    assert len(path["c2w"]) == 5 and not path["closed"]          # the tiny scene is an arc capture
    # path_scale 0.5: frames at half the dataset size, focal lengths and centre halved with them.
    import cv2

    from dualnerf.dataset import load_dataset

    dataset = load_dataset(tiny_dataset)
    frame = cv2.imread(str(out / "frames" / "edited" / "0000.png"))
    assert frame.shape[:2] == (round(dataset.height / 2), round(dataset.width / 2))
    train0 = dataset.indices("train")[0]
    assert path["intrinsics"] == pytest.approx((dataset.intrinsics[train0] / 2).tolist())
    # Held-out views stay at full resolution (they are compared with the ground truth).
    view = cv2.imread(str(out / "views" / "edited" / names[0]))
    assert view.shape[:2] == (dataset.height, dataset.width)
    assert ctx.records["encoder_tag"] == "proxy"


@pytest.mark.slow
def test_edited_scene_metrics_match_independent_recomputation(tmp_path, tiny_dataset, models):
    import cv2

    from dualnerf.dataset import load_dataset
    from dualnerf.scenes.spec import load_gt_edit

    ctx = run_evaluate(tmp_path, tiny_dataset, models, edited=True, n_frames=4, edit_id="snow")
    out = ctx.out_dir
    doc = json.loads((out / "metrics.json").read_text())
    values = {k: M.parse_json_value(v["value"]) for k, v in doc["metrics"].items()}
    assert doc["editor"]["kind"] == "synthetic" and doc["render_blend"] == [0.6, 0.6]

    def read(path):
        return cv2.imread(str(path))[..., ::-1]

    original = [read(p) for p in sorted((out / "frames" / "original").glob("*.png"))]
    edited = [read(p) for p in sorted((out / "frames" / "edited").glob("*.png"))]
    assert any(not np.array_equal(a, b) for a, b in zip(original, edited)), "the edit changed nothing"
    expected_ssim = np.mean([M.ssim(a, b) for a, b in zip(original, edited)])
    assert values["ssim_edited_vs_original"] == pytest.approx(expected_ssim)
    assert values["ssim_edited_vs_original"] < 1.0
    # Ground-truth metrics recomputed from the saved views and the scene's own GT files.
    dataset = load_dataset(tiny_dataset)
    names = doc["views"]["names"]
    renders = [read(out / "views" / "edited" / n) for n in names]
    gt = [load_gt_edit(tiny_dataset, "snow", n) for n in names]
    originals = [dataset.images[dataset.names.index(n)] for n in names]
    expected = M.ground_truth_metrics(renders, [g[0] for g in gt], [g[1] for g in gt], originals)
    for name, value in expected.items():
        assert values[name] == pytest.approx(value), name
    # LPIPS recomputed from the saved 8-bit frames and views (AlexNet, the default backbone).
    from dualnerf.lpips import lpips_distance
    from dualnerf.lpips_metrics import masked_lpips

    assert values["lpips_edited_vs_original"] == pytest.approx(
        np.mean([lpips_distance(a, b) for a, b in zip(original, edited)]), rel=1e-5)
    assert values["lpips_edited_vs_original"] > 0.0
    assert values["gt_lpips_edit"] == pytest.approx(
        np.mean([lpips_distance(r, g[0]) for r, g in zip(renders, gt)]), rel=1e-5)
    views_original = [read(out / "views" / "original" / n) for n in names]
    from dualnerf.lpips import load_lpips

    background = [masked_lpips(load_lpips("alex"), o, r, ~g[1].astype(bool))
                  for o, r, g in zip(views_original, renders, gt)]
    assert values["lpips_background"] == pytest.approx(np.nanmean(background), rel=1e-5)
    # CLIP-space metrics from the proxy encoder on the saved frames, captions defined by the scene.
    for name in ("clip_direction_consistency", "clip_edit_direction_consistency", "clip_frame_consistency",
                 "clip_text_image_direction"):
        assert -1.0 <= values[name] <= 1.0 and np.isfinite(values[name]), name
    assert doc["target_caption"] == "a campsite with a tent covered in fresh snow"


@pytest.mark.slow
def test_killed_run_resumes_from_render_checkpoint(tmp_path, tiny_dataset, models, monkeypatch):
    """Kill rendering after 20 renders (one checkpoint at 16), rerun: only the rest is rendered and the
    result equals an uninterrupted run's."""
    import shutil

    from dualnerf import rendering

    real_render = rendering.render_view
    calls = {"n": 0, "limit": None}

    def counting_render(*args, **kwargs):
        calls["n"] += 1
        if calls["limit"] is not None and calls["n"] > calls["limit"]:
            raise KeyboardInterrupt("simulated kill")
        return real_render(*args, **kwargs)

    monkeypatch.setattr(rendering, "render_view", counting_render)
    params = {"n_frames": 8, "edit_id": "snow", "path_scale": 0.5}
    total = 2 * (8 + 4)                                   # 2 models x (8 path frames + 4 held-out views)
    full = run_evaluate(tmp_path / "full", tiny_dataset, models, edited=True, **params)
    assert calls["n"] == total
    calls.update(n=0, limit=20)
    with pytest.raises(KeyboardInterrupt):
        run_evaluate(tmp_path / "killed", tiny_dataset, models, edited=True, out="attempt1", **params)
    calls.update(n=0, limit=None)
    resumed = run_evaluate(tmp_path / "killed", tiny_dataset, models, edited=True, out="attempt2", **params)
    assert calls["n"] == total - 16
    a, b = full.out_dir, resumed.out_dir
    assert json.loads((a / "metrics.json").read_text()) == json.loads((b / "metrics.json").read_text())
    files = sorted(p.relative_to(a) for p in a.rglob("*.png"))
    assert files == sorted(p.relative_to(b) for p in b.rglob("*.png"))
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    shutil.rmtree(tmp_path / "full")


def test_dual_field_without_blend_is_refused(tmp_path, tiny_dataset, models):
    import shutil

    broken = tmp_path / "models"
    shutil.copytree(models, broken)
    meta = json.loads((broken / "edit" / "model" / "model.json").read_text())
    meta["render_blend"] = None
    (broken / "edit" / "model" / "model.json").write_text(json.dumps(meta))
    with pytest.raises(EvaluateError, match="without render_blend"):
        run_evaluate(tmp_path, tiny_dataset, broken, edited=True, n_frames=2)


def test_bad_params_are_explained(tmp_path, tiny_dataset, models):
    from dualnerf.encoders import EncoderError

    with pytest.raises(EncoderError, match="needs a model folder"):       # before any rendering
        run_evaluate(tmp_path / "a", tiny_dataset, models, edited=False, encoder="clip")
    with pytest.raises(EvaluateError, match="n_frames"):
        run_evaluate(tmp_path, tmp_path, models, edited=False, n_frames=1)
    with pytest.raises(EvaluateError, match="path_scale"):
        run_evaluate(tmp_path, tmp_path, models, edited=False, path_scale=0.0)


@pytest.mark.slow
def test_edited_row_reuses_original_renders_with_identical_results(tmp_path, tiny_dataset, models):
    params = {"n_frames": 3, "edit_id": "snow", "path_scale": 0.5}
    original = run_evaluate(tmp_path, tiny_dataset, models, edited=False, out="original", **params)
    rendered = run_evaluate(tmp_path, tiny_dataset, models, edited=True, out="rendered", **params)
    ctx = StepContext(key="test", params=EvaluateParams(**params),
                      inputs={"dataset": tiny_dataset, "fit": models / "fit", "edit": models / "edit",
                              "original": original.out_dir},
                      out_dir=tmp_path / "reused", scratch_dir=tmp_path / "scratch2",
                      log=logging.getLogger("test-evaluate"))
    EvaluateStage().run(ctx)
    a = json.loads((rendered.out_dir / "metrics.json").read_text())["metrics"]
    b = json.loads((ctx.out_dir / "metrics.json").read_text())["metrics"]
    assert a == b
    # A different camera path is refused rather than mixed in.
    ctx_other = StepContext(key="test", params=EvaluateParams(**{**params, "n_frames": 4}),
                            inputs={**ctx.inputs}, out_dir=tmp_path / "other", scratch_dir=tmp_path / "s3",
                            log=logging.getLogger("test-evaluate"))
    with pytest.raises(EvaluateError, match="not the unedited evaluation"):
        EvaluateStage().run(ctx_other)
