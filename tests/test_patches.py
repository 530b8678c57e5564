"""Square-patch ray batches and the LPIPS patch loss in the trainer: patch geometry, the loss
decomposition, exact resume and seeded determinism with LPIPS on, and the unchanged RGB-only batches."""
import numpy as np
import pytest
import torch

from dualnerf.cameras import Cameras
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.lpips import load_lpips
from dualnerf.patches import PatchConfigError, patch_count, patch_lpips_loss, sample_patches
from dualnerf.training import RayTrainer, TrainConfig

SMALL = FieldConfig(grid_resolutions=(8, 16), hidden_width=16, samples_per_ray=32, occupancy_resolution=8)
# 48x36 images with 32x32 patches (AlexNet's smallest is 31): 1 patch of 1024 rays plus 1024 uniform rays.
PATCHED = TrainConfig(rays_per_batch=2048, occupancy_warmup=2, occupancy_every=2, lpips_weight=0.5,
                      patch_size=32, patch_share=0.5)


def views(n=3, h=36, w=48):
    """Random images seen by cameras on the -z side looking at the unit cube (+z forward)."""
    images = torch.rand(n, h, w, 3, generator=torch.Generator().manual_seed(0))
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.linspace(-0.3, 0.3, n)
    c2w[:, 2, 3] = -2.5
    return images, Cameras(c2w, torch.tensor([[40.0, 40.0, w / 2, h / 2]] * n), torch.full((n,), 0.1),
                           torch.full((n,), 5.0), w, h)


def make_trainer(config=PATCHED, seed=0):
    g = torch.Generator().manual_seed(seed)
    images, cams = views()
    return RayTrainer(RadianceField(SMALL, g), images, cams, config, g)


def test_patch_count():
    assert patch_count(1024, 32, 0.5) == 1          # at least one patch: the CPU preset's whole batch
    assert patch_count(4096, 32, 0.5) == 2
    assert patch_count(4096, 32, 1.0) == 4
    with pytest.raises(PatchConfigError, match="rays_per_batch"):
        patch_count(512, 32, 0.5)
    with pytest.raises(PatchConfigError, match="patch_share"):
        patch_count(4096, 32, 0.0)


def test_patch_too_small_for_the_backbone_is_a_clear_error():
    with pytest.raises(PatchConfigError, match="too small for the LPIPS backbone 'alex'"):
        make_trainer(TrainConfig(rays_per_batch=256, lpips_weight=1.0, patch_size=16))


def test_patches_are_squares_of_one_view_in_raster_order():
    g = torch.Generator().manual_seed(3)
    train = torch.tensor([2, 5, 7])
    views, u, v = sample_patches(6, 5, train, width=9, height=7, generator=g)
    assert views.shape == u.shape == v.shape == (6 * 25,)
    for p in range(6):
        pv, pu, pp = (t[p * 25:(p + 1) * 25].reshape(5, 5) for t in (views, u, v))
        assert int(pv[0, 0]) in (2, 5, 7) and bool((pv == pv[0, 0]).all())
        assert 0 <= int(pu.min()) and int(pu.max()) < 9 and 0 <= int(pp.min()) and int(pp.max()) < 7
        assert torch.equal(pu - pu[0, 0], torch.arange(5)[None, :].expand(5, 5))     # columns left to right
        assert torch.equal(pp - pp[0, 0], torch.arange(5)[:, None].expand(5, 5))     # rows top to bottom
    with pytest.raises(PatchConfigError, match="does not fit"):
        sample_patches(1, 8, train, width=9, height=7, generator=g)


def test_patch_loss_is_the_weighted_mean_of_patch_lpips():
    model = load_lpips("alex")
    rng = np.random.default_rng(0)
    pred = torch.from_numpy(rng.uniform(0, 1, (2 * 32 * 32, 3)).astype(np.float32))
    target = torch.from_numpy(rng.uniform(0, 1, (2 * 32 * 32, 3)).astype(np.float32))
    assert float(patch_lpips_loss(model, target, target, 32)) == 0.0
    with torch.no_grad():
        first = model(pred[:1024].reshape(1, 32, 32, 3).permute(0, 3, 1, 2) * 2 - 1,
                      target[:1024].reshape(1, 32, 32, 3).permute(0, 3, 1, 2) * 2 - 1)
        weighted = patch_lpips_loss(model, pred, target, 32, torch.tensor([2.0, 0.0]))
    assert float(weighted) == pytest.approx(float(first[0]), rel=1e-5)       # (2 d0 + 0 d1) / 2


def test_trainer_loss_is_rgb_plus_weighted_lpips_and_batch_holds_patches():
    trainer = make_trainer()
    assert trainer.patches == 1
    views, u, _ = trainer.sample_batch()
    assert len(views) == 2048
    assert torch.equal(u[:1024].reshape(32, 32) - u[0], torch.arange(32)[None, :].expand(32, 32))
    stats = trainer.step(0)
    assert stats["lpips"] > 0
    # rgb_loss without view weights is the batch MSE, so the loss splits exactly into its two terms.
    assert stats["loss"] == pytest.approx(stats["mse"] + 0.5 * stats["lpips"], rel=1e-5)


def test_lpips_off_draws_the_rgb_only_batches():
    off = make_trainer(TrainConfig(rays_per_batch=64, lpips_weight=0.0, patch_size=4))   # settings unused
    plain = make_trainer(TrainConfig(rays_per_batch=64))
    assert off.lpips is None
    for a, b in zip(off.sample_batch(), plain.sample_batch()):
        assert torch.equal(a, b)
    assert off.step(0)["lpips"] is None


def test_resume_with_lpips_is_exact_and_seeded(tmp_path):
    straight = make_trainer()
    for step in range(6):
        straight.step(step)
    first = make_trainer()
    for step in range(3):
        first.step(step)
    torch.save(first.state_dict(), tmp_path / "state.pt")
    resumed = make_trainer()
    resumed.load_state_dict(torch.load(tmp_path / "state.pt", weights_only=True))
    for step in range(3, 6):
        resumed.step(step)
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    other = make_trainer(seed=1)
    for step in range(6):
        other.step(step)
    assert not torch.equal(other.model.state_dict()["encoding.grids.0"], a["encoding.grids.0"])


def test_lpips_gradient_reaches_the_field():
    # Same seed, so the same batches: only the LPIPS weight differs, and it changes the field's grids.
    runs = []
    for weight in (1.0, 1e-3):
        trainer = make_trainer(TrainConfig(rays_per_batch=256, lpips_weight=weight, lpips_net="vgg",
                                           patch_size=16, patch_share=1.0))
        for step in range(3):
            stats = trainer.step(step)
        assert stats["samples"] > 0
        runs.append(trainer.model.state_dict()["encoding.grids.0"])
    assert not torch.equal(runs[0], runs[1])
