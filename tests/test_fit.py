"""Static fit: exact resume (in-process and after SIGKILL), outputs, and a short fit that really learns."""
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

from dualnerf.cameras import Cameras
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.training import RayTrainer, TrainConfig

SMALL = FieldConfig(grid_resolutions=(8, 16), hidden_width=16, samples_per_ray=32, occupancy_resolution=8)
TRAIN = TrainConfig(rays_per_batch=64, occupancy_warmup=2, occupancy_every=2)
# Fit settings small enough for CI: the tiny scene at full size, few samples and coarse grids.
FAST_FIT = {"rays_per_batch": 512, "grid_levels": 3, "grid_max_resolution": 64, "plane_levels": 2,
            "plane_max_resolution": 128, "hidden_width": 32, "samples_per_ray": 32, "render_samples_per_ray": 48}


def random_views(n=3, h=6, w=8):
    images = torch.rand(n, h, w, 3, generator=torch.Generator().manual_seed(0))
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.linspace(-0.3, 0.3, n)
    c2w[:, 2, 3] = -2.0
    return images, Cameras(c2w, torch.tensor([[8.0, 8.0, 4.0, 3.0]] * n), torch.full((n,), 0.1),
                           torch.full((n,), 4.0), w, h)


def make_trainer(seed=0):
    g = torch.Generator().manual_seed(seed)
    images, cams = random_views()
    return RayTrainer(RadianceField(SMALL, g), images, cams, TRAIN, g)


def test_trainer_resume_through_a_file_is_exact(tmp_path):
    straight = make_trainer()
    for step in range(8):
        straight.step(step)
    first = make_trainer()
    for step in range(4):
        first.step(step)
    torch.save(first.state_dict(), tmp_path / "state.pt")
    resumed = make_trainer()
    resumed.load_state_dict(torch.load(tmp_path / "state.pt", weights_only=True))
    for step in range(4, 8):
        resumed.step(step)
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["encoding.grids.0"], make_trainer().model.state_dict()["encoding.grids.0"])
    # A different seed gives a different run.
    other = make_trainer(seed=1)
    for step in range(8):
        other.step(step)
    assert not torch.equal(other.model.state_dict()["encoding.grids.0"], a["encoding.grids.0"])


def test_view_weights_scale_ray_losses():
    from dualnerf.training import TrainingInputError, normalised_view_weights, rgb_loss

    w = normalised_view_weights(torch.tensor([1.0, 3.0, 100.0]), [0, 1])
    torch.testing.assert_close(w, torch.tensor([0.5, 1.5, 50.0]))
    pred, target = torch.zeros(2, 3), torch.ones(2, 3)
    assert float(rgb_loss(pred, target, torch.tensor([0.5, 1.5]))) == pytest.approx(1.0)
    pred[1] = 0.5
    assert float(rgb_loss(pred, target, torch.tensor([2.0, 0.0]))) == pytest.approx(1.0)
    with pytest.raises(TrainingInputError):
        normalised_view_weights(torch.tensor([0.0, 0.0]), [0, 1])


def test_trainer_rejects_mismatched_images():
    from dualnerf.training import TrainingInputError

    images, cams = random_views()
    with pytest.raises(TrainingInputError, match="do not match"):
        RayTrainer(RadianceField(SMALL), images[:2], cams, TRAIN, torch.Generator())
    with pytest.raises(TrainingInputError, match="float"):
        RayTrainer(RadianceField(SMALL), (images * 255).to(torch.uint8), cams, TRAIN, torch.Generator())


# ---- the stage ---------------------------------------------------------------------------------------

def make_ctx(params, dataset: Path, root: Path, scratch: Path | None = None):
    from pipeline.context import StepContext

    return StepContext(key="test", params=params, inputs={"dataset": dataset}, out_dir=root / "out",
                       scratch_dir=scratch or root / "scratch", log=logging.getLogger("test_fit"), threads=1)


def _weights(folder: Path):
    return torch.load(folder / "model" / "weights.pt", weights_only=True)


@pytest.mark.slow
def test_fit_stage_learns_the_tiny_scene(tiny_dataset, tmp_path):
    from dualnerf.dataset import load_dataset
    from stages.fit import FitParams, FitStage

    params = FitParams(iterations=300, eval_every=100, checkpoint_every=100, curve_views=1, **FAST_FIT)
    ctx = make_ctx(params, tiny_dataset, tmp_path)
    FitStage().run(ctx)
    out = ctx.out_dir
    metrics = json.loads((out / "metrics.json").read_text())
    ds = load_dataset(tiny_dataset)
    heldout = [ds.names[i] for i in ds.indices("heldout")]
    assert metrics["split"] == "heldout" and sorted(metrics["views"]) == sorted(heldout)
    # Independent baseline: an untrained field of the same configuration on the same view.
    from dualnerf.rendering import render_view

    untrained = RadianceField(load_model_config(out))
    i = int(ds.indices("heldout")[0])
    img = render_view(untrained, ds.c2w[i], ds.intrinsics[i], ds.width, ds.height, ds.near[i], ds.far[i]).numpy()
    initial_psnr = -10 * np.log10(np.mean((img - ds.images[i] / 255.0) ** 2))
    assert metrics["psnr_mean"] > initial_psnr + 6.0, (metrics["psnr_mean"], initial_psnr)
    assert 0 < metrics["ssim_mean"] <= 1
    assert all((out / "heldout" / f"{Path(n).stem}.png").is_file() for n in heldout)
    curve = json.loads((out / "curve.json").read_text())
    assert [c["step"] for c in curve] == [100, 200, 300]
    assert (out / "curve.png").stat().st_size > 1000
    assert ctx.records["seed"] == 0 and "off" in ctx.records["lpips"]
    assert metrics["lpips_loss"] == "off (RGB loss only)"             # the fit default: RGB loss only
    # Empty-space skipping is active: the occupancy grid has pruned part of the cube.
    assert metrics["occupancy_fraction"] < 0.9


def load_model_config(out: Path) -> FieldConfig:
    return FieldConfig.from_dict(json.loads((out / "model" / "model.json").read_text())["field_config"])


KILL_PARAMS = {"iterations": 60, "checkpoint_every": 10, "eval_every": 1000, "rays_per_batch": 128, "grid_levels": 2,
               "grid_max_resolution": 16, "plane_levels": 1, "plane_max_resolution": 32, "hidden_width": 16,
               "samples_per_ray": 16, "proposal_samples": 64}

CHILD = """
import logging, sys
from pathlib import Path
from pipeline.context import StepContext
from stages.fit import FitParams, FitStage
root, dataset = Path(sys.argv[1]), Path(sys.argv[2])
params = FitParams(**{k: int(v) for k, v in (a.split("=") for a in sys.argv[3:])})
ctx = StepContext(key="kill", params=params, inputs={"dataset": dataset}, out_dir=root / "out",
                  scratch_dir=root / "scratch", log=logging.getLogger("child"), threads=1)
FitStage().run(ctx)
"""


@pytest.mark.slow
def test_fit_resumes_exactly_after_sigkill(tiny_dataset, tmp_path):
    from stages.fit import FitParams, FitStage

    params = FitParams(**KILL_PARAMS)
    reference = make_ctx(params, tiny_dataset, tmp_path / "reference")
    FitStage().run(reference)

    root = tmp_path / "killed"
    args = [sys.executable, "-c", CHILD, str(root), str(tiny_dataset)] + [f"{k}={v}" for k, v in KILL_PARAMS.items()]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    child = subprocess.Popen(args, cwd=Path(__file__).resolve().parents[1], env=env)
    checkpoints = root / "scratch" / "checkpoints"
    deadline = time.time() + 120
    while time.time() < deadline and child.poll() is None:
        if checkpoints.is_dir() and any(p.name.isdigit() for p in checkpoints.iterdir()):
            break
        time.sleep(0.005)
    child.send_signal(signal.SIGKILL)
    assert child.wait() == -signal.SIGKILL, "the child finished before it could be killed"
    assert not (root / "out" / "metrics.json").exists()

    from pipeline.context import StepContext
    resumed = StepContext(key="kill", params=params, inputs={"dataset": tiny_dataset}, out_dir=root / "out2",
                          scratch_dir=root / "scratch", log=logging.getLogger("resume"), threads=1)
    step, _ = resumed.latest_checkpoint()
    assert 10 <= step < 60
    FitStage().run(resumed)
    a, b = _weights(reference.out_dir), _weights(resumed.out_dir)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    curve_a = json.loads((reference.out_dir / "curve.json").read_text())
    curve_b = json.loads((resumed.out_dir / "curve.json").read_text())
    assert [c["heldout_psnr"] for c in curve_a] == [c["heldout_psnr"] for c in curve_b]


def test_fit_stage_rejects_bad_params(tiny_dataset, tmp_path):
    from stages.fit import FitInputError, FitParams, FitStage

    with pytest.raises(FitInputError, match="device"):
        FitStage().run(make_ctx(FitParams(device="tpu"), tiny_dataset, tmp_path / "a"))
    with pytest.raises(FitInputError, match="iterations"):
        FitStage().run(make_ctx(FitParams(iterations=0), tiny_dataset, tmp_path / "b"))


def test_grid_resolutions():
    from stages.fit import grid_resolutions

    assert grid_resolutions(4, 128) == (16, 32, 64, 128)
    assert grid_resolutions(3, 64) == (16, 32, 64)
    assert grid_resolutions(1, 48) == (48,)
    assert grid_resolutions(2, 8) == (8, 8)


def test_plane_resolutions():
    from stages.fit import FitInputError, plane_resolutions

    assert plane_resolutions(3, 1024) == (256, 512, 1024)
    assert plane_resolutions(1, 48) == (48,)
    assert plane_resolutions(0, 1024) == ()
    with pytest.raises(FitInputError, match="plane_levels"):
        plane_resolutions(4, 8)
    with pytest.raises(FitInputError, match="plane_levels"):
        plane_resolutions(-1, 1024)


def test_learning_rate_decay_schedule():
    g = torch.Generator().manual_seed(0)
    images, cams = random_views()
    cfg = TrainConfig(rays_per_batch=16, learning_rate=0.02, lr_decay_steps=100, lr_final_ratio=0.1)
    trainer = RayTrainer(RadianceField(SMALL, g), images, cams, cfg, g)
    assert trainer.learning_rate(0) == pytest.approx(0.02)
    assert trainer.learning_rate(50) == pytest.approx(0.02 * 0.1 ** 0.5)
    assert trainer.learning_rate(100) == pytest.approx(0.002)
    assert trainer.learning_rate(1000) == pytest.approx(0.002)
    trainer.step(50)
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(0.02 * 0.1 ** 0.5)
    assert make_trainer().learning_rate(10**6) == TRAIN.learning_rate      # no decay by default


@pytest.mark.slow
def test_fit_through_the_engine_and_cache(tmp_path):
    from pipeline.dag import Step
    from pipeline.executors import SerialExecutor
    from pipeline.runner import run_steps
    from pipeline.store import Store
    from stages import STAGES

    scene = Step("scene", {"name": "tiny", "n_views": 5, "width": 40, "height": 30}, label="scene")
    prep = Step("preprocess", {"method": "nerfstudio", "holdout_every": 4}, {"scene": scene}, label="prep")
    fit_params = {**KILL_PARAMS, "iterations": 20, "checkpoint_every": 5}
    fit = Step("fit", fit_params, {"dataset": prep}, label="fit")
    store = Store(tmp_path / "cache")

    def run():
        return run_steps([fit], registry=STAGES, store=store, executor=SerialExecutor(threads=1),
                         run_dir=tmp_path / "runs", quiet=True)

    result = run()
    assert result.ok, result.summary()
    out = result.results[fit]
    assert (out / "model" / "model.json").is_file() and (out / "metrics.json").is_file()
    again = run()                                   # same key: served from the cache, same folder
    assert again.status[fit] == "cached" and again.results[fit] == out
