"""The edit stage through the engine's StepContext: outputs, records, input folders untouched, clear
errors, and SIGKILL + rerun giving the same result as an uninterrupted run."""
import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.test_edit_idu import SNOW, build_small_edit_inputs

FAST = {"edit_id": SNOW, "iterations": 20, "edit_rate": 5, "edit_count": 2, "rays_per_batch": 256, "seed": 3,
            "checkpoint_every_rounds": 1, "num_threads": 1, "lpips_weight": 1.0, "lpips_net": "vgg", "patch_size": 16}
# (the 40x30 test images take VGG16's 16x16 LPIPS patches; AlexNet's need 31 px)


def run_stage(data_dir, fit_dir, root, **params):
    from pipeline.context import StepContext
    from stages.edit import EditParams, EditStage

    ctx = StepContext(key="test", params=EditParams(**params), inputs={"dataset": data_dir, "fit": fit_dir},
                      out_dir=Path(root) / "out", scratch_dir=Path(root) / "scratch",
                      log=logging.getLogger("edit-test"))
    EditStage().run(ctx)
    return ctx


def tree_digest(folder):
    digest = hashlib.sha256()
    for path in sorted(Path(folder).rglob("*")):
        if path.is_file():
            digest.update(str(path.relative_to(folder)).encode() + path.read_bytes())
    return digest.hexdigest()


@pytest.fixture(scope="module")
def small(tmp_path_factory, tiny_scene):
    return build_small_edit_inputs(tmp_path_factory, tiny_scene)


def test_stage_outputs_records_and_untouched_inputs(small, tmp_path):
    from dualnerf.model import load_model

    data_dir, fit_dir, dataset, _ = small
    before = tree_digest(data_dir), tree_digest(fit_dir)
    ctx = run_stage(data_dir, fit_dir, tmp_path, **FAST)
    assert (tree_digest(data_dir), tree_digest(fit_dir)) == before
    out = ctx.out_dir
    assert ctx.records["editor_is_simulator"] is True
    assert ctx.records["editor"]["name"] == "InstructPix2PixEmulator"
    assert ctx.records["encoder"]["kind"] == "proxy"
    updates = [json.loads(line) for line in (out / "updates.jsonl").read_text().splitlines()]
    assert len(updates) == 20 // 5 * 2
    assert {"iteration", "view", "gamma", "accepted", "temperature", "score", "editor_seed"} <= set(updates[0])
    assert [u["iteration"] for u in updates] == [0, 0, 5, 5, 10, 10, 15, 15]
    curves = json.loads((out / "curves.json").read_text())
    assert len(curves["loss"]) == 20 and len(curves["cci"]) == 4
    # the convergence probe (default every 100 iterations): at the start and at the end of the run
    assert curves["convergence"]["iteration"] == [0, 20] and all(curves["convergence"]["psnr_in"])
    assert (out / "curves.png").stat().st_size > 0
    train = dataset.indices("train")
    assert len(list((out / "edited").glob("*.png"))) == len(train)
    model = load_model(out / "model")
    assert model.render_blend == pytest.approx((0.1 * np.tanh(0.005 * 19),) * 2)
    summary = json.loads((out / "edit.json").read_text())
    assert summary["editor_is_simulator"] and summary["encoder"]["kind"] == "proxy"
    # The LPIPS loss is on by default; edit.json and the manifest say with which setting.
    assert summary["lpips"]["weight"] == 1.0 and summary["lpips"]["tag"] == "lpips-v0.1:vgg"
    assert summary["lpips"]["patches_per_batch"] == 1 and ctx.records["lpips"] == summary["lpips"]
    # an updated view's stored image is the editor's output, not the original
    import cv2

    first = updates[0]["name"]
    stored = cv2.imread(str(out / "edited" / f"{Path(first).stem}.png"))[..., ::-1]
    assert np.abs(stored.astype(int) - dataset.images[dataset.names.index(first)].astype(int)).mean() > 5
    # Failure modes and the no-oracle record: the emulator's knobs come from the emulator_* parameters,
    # each update records whether the call failed and which mode it drew, and the proxy's captions came
    # from the edit's specification.
    from dualnerf.encoders.vocabulary import SPEC

    config = ctx.records["editor"]["config"]
    assert config["lock_in"] is True and config["background_cast"] == 0.05 and config["failure_rate"] == 0.15
    assert ctx.records["editor"]["modes"] == ["snow", "grey_snow"]
    assert all(isinstance(u["editor"]["failed"], bool) and u["editor"]["mode"] in (0, 1) for u in updates)
    assert all(u["score_ratio"] is not None for u in updates)
    assert summary["encoder"]["vocabulary_source"] == SPEC and summary["params"]["dual_lr_scale"] is False


def test_emulator_parameters_reach_the_emulator(small, tmp_path):
    data_dir, fit_dir, _, _ = small
    ctx = run_stage(data_dir, fit_dir, tmp_path, **{**FAST, "iterations": 5, "lpips_weight": 0.0,
                                                    "emulator_lock_in": False, "emulator_background_cast": 0.0,
                                                    "emulator_failure_rate": 1.0})
    config = ctx.records["editor"]["config"]
    assert (config["lock_in"], config["background_cast"], config["failure_rate"]) == (False, 0.0, 1.0)
    assert ctx.records["editor"]["modes"] == ["snow"]
    updates = [json.loads(line) for line in (ctx.out_dir / "updates.jsonl").read_text().splitlines()]
    assert all(u["editor"]["failed"] and u["editor"]["mode"] == 0 for u in updates)


@pytest.mark.parametrize("params, message", [
    ({"editor": "dalle"}, "unknown editor 'dalle'"),
    ({"convergence_scale": 0.0}, "convergence_views >= 1 and convergence_scale"),
    ({"cci_text": "caption"}, "cci_text must be one of"),
    ({"edit_id": ""}, "no instruction; set"),
    ({"edit_id": "", "instruction": "Make it look like it just snowed"}, "needs edit_id"),
    ({"encoder": "clip", "encoder_model": ""}, "needs a model folder"),
    ({"instruction": "make it pink"}, "can only emulate edit 'snow'"),
    ({"lpips_net": "squeeze"}, "lpips_net must be 'alex' or 'vgg'"),
    ({"update_precision": "fp16"}, "'update_precision' must be 'fp32' or 'bf16'"),
    ({"emulator_mode_prior": 1.5}, "mode_prior must be in"),
    ({"patch_size": 32}, "more than rays_per_batch"),
    ({"device": "cuda:0"}, "no CUDA device") if not torch.cuda.is_available() else ({}, None),
])
def test_bad_parameters_are_clear_errors(small, tmp_path, params, message):
    if message is None:
        pytest.skip("CUDA is available here")
    data_dir, fit_dir, _, _ = small
    with pytest.raises(ValueError, match=message) as info:
        run_stage(data_dir, fit_dir, tmp_path, **{**FAST, **params})
    assert getattr(type(info.value), "user_error", False)


def _driver(spec_path):
    spec = json.loads(Path(spec_path).read_text())
    run_stage(Path(spec["data"]), Path(spec["fit"]), Path(spec["root"]), **spec["params"])


@pytest.mark.slow
def test_sigkill_and_rerun_gives_the_uninterrupted_result(small, tmp_path):
    data_dir, fit_dir, _, _ = small
    params = {**FAST, "iterations": 60}
    reference = run_stage(data_dir, fit_dir, tmp_path / "reference", **params)

    root = tmp_path / "killed"
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"data": str(data_dir), "fit": str(fit_dir), "root": str(root), "params": params}))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-c", f"from tests.test_edit_stage import _driver; _driver({str(spec)!r})"],
                            cwd=Path(__file__).resolve().parents[1], env=env)
    checkpoints = root / "scratch" / "checkpoints"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if checkpoints.is_dir() and any(p.name.isdigit() and int(p.name) >= 10 for p in checkpoints.iterdir()):
            break
        time.sleep(0.02)
    assert proc.poll() is None, "the stage finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (root / "out" / "model").exists()
    killed_at = max(int(p.name) for p in checkpoints.iterdir() if p.name.isdigit())
    assert 0 < killed_at < 60

    import shutil

    shutil.rmtree(root / "out")           # the engine gives every attempt a fresh out_dir
    resumed = run_stage(data_dir, fit_dir, root, **params)
    a = torch.load(reference.out_dir / "model" / "weights.pt", weights_only=True)
    b = torch.load(resumed.out_dir / "model" / "weights.pt", weights_only=True)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    for name in ("updates.jsonl", "curves.json", "edit.json"):
        assert (reference.out_dir / name).read_bytes() == (resumed.out_dir / name).read_bytes(), name
    assert tree_digest(reference.out_dir / "edited") == tree_digest(resumed.out_dir / "edited")
