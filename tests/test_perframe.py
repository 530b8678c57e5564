"""The per-frame InstructPix2Pix baseline: ground truth re-rendered at evaluation cameras (dataset frame ->
scene frame), each view edited independently, scored by evaluate like every other row."""
import json
import logging

import numpy as np
import pytest

from pipeline.context import StepContext
from stages.evaluate import EvaluateParams, EvaluateStage
from stages.gtviews import GroundTruthViewsParams, GroundTruthViewsStage
from stages.perframe import PerFrameError, PerFrameParams, PerFrameStage
from tests.test_evaluate import models  # noqa: F401  (the small random f_S / edit fixture)


def _read(path):
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, path
    return np.ascontiguousarray(image[..., ::-1])


def _random_similarity(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.linalg.det(q))
    return 0.37, rotation, rng.normal(size=3)


def test_similarity_fit_recovers_an_arbitrary_frame_and_refuses_a_foreign_dataset():
    """SfM returns the cameras in a frame of its own: the fit maps them back onto the scene's cameras."""
    from dualnerf.scenes import scene_cameras, scene_config
    from dualnerf.scenes.spec import SceneSpecError
    from dualnerf.scenes.views import fit_similarity

    truth, _ = scene_cameras(scene_config("tiny"))
    s, r, t = _random_similarity(np.random.default_rng(3))
    other = truth.copy()                           # the cameras as another frame sees them: x' = s R x + t
    other[:, :3, :3] = r @ truth[:, :3, :3]
    other[:, :3, 3] = s * truth[:, :3, 3] @ r.T + t
    fitted = fit_similarity(other, truth, where="test")
    assert np.allclose(fitted.apply(other), truth, atol=1e-9)
    assert fitted.rotation_residual_degrees < 1e-4 and fitted.centre_residual < 1e-9
    with pytest.raises(SceneSpecError, match="do not match the scene"):
        fit_similarity(other[::-1], truth, where="test")


def test_rendered_ground_truth_at_a_dataset_camera_equals_the_stored_views(tiny_dataset):
    from dualnerf.dataset import load_dataset
    from dualnerf.scenes.spec import load_gt_edit
    from dualnerf.scenes.views import SceneViewRenderer

    dataset = load_dataset(tiny_dataset)
    renderer = SceneViewRenderer(tiny_dataset, dataset)
    i = int(dataset.indices("train")[3])
    original, edited, mask = renderer.render(dataset.c2w[i], "blue_tent", (dataset.width, dataset.height))
    stored_edit, stored_mask = load_gt_edit(tiny_dataset, "blue_tent", dataset.names[i])
    for got, want in ((original, dataset.images[i]), (edited, stored_edit)):
        diff = np.abs(got.astype(int) - want.astype(int))
        assert diff.mean() < 0.05 and (diff.max(axis=-1) == 0).mean() > 0.995
    assert (mask == stored_mask).mean() > 0.995 and mask.any()


def _run(stage, params, inputs, out, tmp_path):
    ctx = StepContext(key="test", params=params, inputs=inputs, out_dir=tmp_path / out,
                      scratch_dir=tmp_path / f"scratch-{out}", log=logging.getLogger("test-perframe"))
    stage.run(ctx)
    return ctx.out_dir


@pytest.mark.slow
def test_per_frame_baseline_edits_each_view_alone_and_is_scored_like_any_row(tmp_path, tiny_dataset, models,  # noqa: F811
                                                                            monkeypatch):
    from dualnerf.editors.emulator import EmulatedView, InstructPix2PixEmulator
    from dualnerf.scenes.spec import load_gt_edit, load_scene_spec

    evaluate = {"n_frames": 3, "edit_id": "snow", "path_scale": 0.5}
    original = _run(EvaluateStage(), EvaluateParams(**evaluate), {"dataset": tiny_dataset, "fit": models / "fit"},
                    "original", tmp_path)
    gtviews = _run(GroundTruthViewsStage(), GroundTruthViewsParams(edit_id="snow"),
                   {"dataset": tiny_dataset, "original": original}, "gtviews", tmp_path)
    names = json.loads((original / "metrics.json").read_text())["views"]["names"]
    # A killed gtviews step resumes from its scratch folder: only the unfinished view is rendered again.
    from dualnerf.scenes.views import SceneViewRenderer

    calls = []
    real_render = SceneViewRenderer.render
    monkeypatch.setattr(SceneViewRenderer, "render", lambda self, *a: calls.append(a) or real_render(self, *a))
    (tmp_path / "scratch-gtviews" / "gt" / "views" / "gt_mask" / names[0]).unlink()
    resumed = StepContext(key="test", params=GroundTruthViewsParams(edit_id="snow"),
                          inputs={"dataset": tiny_dataset, "original": original}, out_dir=tmp_path / "gtviews2",
                          scratch_dir=tmp_path / "scratch-gtviews", log=logging.getLogger("test-perframe"))
    GroundTruthViewsStage().run(resumed)
    assert len(calls) == 1
    for file in sorted(p for p in gtviews.rglob("*.png")):
        assert file.read_bytes() == (resumed.out_dir / file.relative_to(gtviews)).read_bytes()
    perframe = _run(PerFrameStage(), PerFrameParams(edit_id="snow", seed=7),
                    {"dataset": tiny_dataset, "original": original, "gtviews": gtviews}, "perframe", tmp_path)
    names = json.loads((original / "metrics.json").read_text())["views"]["names"]
    doc = json.loads((perframe / "edit.json").read_text())
    assert doc["editor"]["is_simulator"] and doc["method"] == "per-frame"
    assert [(d["group"], d["editor_step"]) for d in doc["images"]] == \
        [("frames", k) for k in range(3)] + [("views", 3 + k) for k in range(len(names))]
    instruction = load_scene_spec(tiny_dataset).edit("snow").instruction
    for k, name in enumerate(names):
        # The re-rendered ground truth at the held-out camera is the scene's stored held-out view ...
        stored_edit, stored_mask = load_gt_edit(tiny_dataset, "snow", name)
        gt_edit = _read(gtviews / "views" / "gt_edit" / name)
        assert np.abs(gt_edit.astype(int) - stored_edit.astype(int)).mean() < 0.05
        # ... and the edited view is the emulator's output for f_S's render of that view alone, seed (7, k).
        view_original = _read(gtviews / "views" / "original" / name)
        mask = _read(gtviews / "views" / "gt_mask" / name)[..., 0] > 127
        assert (mask == stored_mask).mean() > 0.995
        emulator = InstructPix2PixEmulator([EmulatedView(view_original, gt_edit, mask)], instruction, "snow")
        expected = emulator.edit(_read(original / "views" / "original" / name), view_original, instruction,
                                 7, 3 + k)
        assert np.array_equal(_read(perframe / "views" / "edited" / name), expected)
    scored = _run(EvaluateStage(), EvaluateParams(**evaluate),
                  {"dataset": tiny_dataset, "fit": models / "fit", "original": original, "perframe": perframe},
                  "scored", tmp_path)
    metrics = json.loads((scored / "metrics.json").read_text())
    assert metrics["edited"] is True and metrics["editor"]["is_simulator"]
    # The ground-truth metric is the one of the per-frame images against the stored ground truth.
    from dualnerf import metrics as M

    pairs = [(_read(perframe / "views" / "edited" / n), load_gt_edit(tiny_dataset, "snow", n)[0]) for n in names]
    expected_psnr = M.mean_over_views(pairs, M.psnr)
    assert M.parse_json_value(metrics["metrics"]["gt_psnr_edit"]["value"]) == pytest.approx(expected_psnr, rel=1e-6)
    for n in range(3):
        assert np.array_equal(_read(scored / "frames" / "edited" / f"{n:04d}.png"),
                              _read(perframe / "frames" / "edited" / f"{n:04d}.png"))
        assert np.array_equal(_read(scored / "frames" / "original" / f"{n:04d}.png"),
                              _read(original / "frames" / "original" / f"{n:04d}.png"))


def test_synthetic_per_frame_needs_a_procedural_scene(tmp_path, tiny_dataset):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    (data / "scene.toml").write_text((data / "scene.toml").read_text().replace('name = "tiny"', 'name = "mine"'))
    with pytest.raises(PerFrameError, match="not a procedural scene.*use editor 'ip2p'"):
        _run(GroundTruthViewsStage(), GroundTruthViewsParams(edit_id="snow"),
             {"dataset": data, "original": tmp_path / "unused"}, "gt", tmp_path)
    with pytest.raises(PerFrameError, match="needs the 'gtviews' input"):
        _run(PerFrameStage(), PerFrameParams(edit_id="snow"), {"dataset": data, "original": tmp_path / "unused"},
             "pf", tmp_path)
