"""Dual-field fusion (eqs. 4-6): exact static reproduction at w = 0, gradient isolation, retreat scaling."""
import math

import numpy as np
import pytest
import torch

from dualnerf.cameras import Cameras
from dualnerf.dual_field import BlendError, BlendSchedule, DualField, make_edit_model
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.rendering import render_view
from dualnerf.training import RayTrainer, TrainConfig

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device")])]
CFG = FieldConfig(grid_resolutions=(4, 8), hidden_width=16, samples_per_ray=24, occupancy_resolution=8)


def static_field(seed=0):
    field = RadianceField(CFG, torch.Generator().manual_seed(seed))
    with torch.no_grad():   # make the grids carry real signal (init values are ~1e-4)
        for grid in field.encoding.grids:
            grid.normal_(0, 1, generator=torch.Generator().manual_seed(seed + 1))
    return field


def perturbed_dual(seed=0):
    model = make_edit_model(static_field(seed), "dual")
    with torch.no_grad():
        g = torch.Generator().manual_seed(seed + 7)
        for p in model.dynamic_field.parameters():
            p.add_(torch.randn(p.shape, generator=g))
    return model


def points(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 2 - 1
    d = torch.randn(n, 3, generator=g)
    return x, d / d.norm(dim=-1, keepdim=True)


def test_blend_schedule_is_eq6():
    schedule = BlendSchedule(w_max_density=0.1, w_max_color=0.3, rate=0.005)
    for t in (0, 1, 10, 137, 1000, 15000):
        w_d, w_c = schedule.weights(t)
        assert w_d == pytest.approx(0.1 * np.tanh(0.005 * t), rel=1e-12, abs=1e-15)
        assert w_c == pytest.approx(0.3 * np.tanh(0.005 * t), rel=1e-12, abs=1e-15)
    assert schedule.weights(0) == (0.0, 0.0)
    assert schedule.weights(10**6)[0] == pytest.approx(0.1)
    with pytest.raises(BlendError):
        BlendSchedule(w_max_density=1.5)


@pytest.mark.parametrize("device", DEVICES)
def test_zero_blend_reproduces_static_field_bit_for_bit(device):
    model = perturbed_dual().to(device)
    x, d = (t.to(device) for t in points())
    s_sigma, s_color = model.static_field(x, d)
    f_sigma, f_color = model.query(x, d, blend=(0.0, 0.0))
    assert torch.equal(s_sigma, f_sigma) and torch.equal(s_color, f_color)
    assert not torch.equal(model.dynamic_field(x, d)[1], s_color)   # f_D really differs


def test_zero_blend_render_equals_static_render():
    model = perturbed_dual()
    c2w = np.eye(4)
    c2w[2, 3] = -2.0
    k = np.array([8.0, 8.0, 4.0, 3.0])
    static = render_view(model.static_field, c2w, k, 8, 6, 0.1, 4.0)
    assert torch.equal(render_view(model, c2w, k, 8, 6, 0.1, 4.0, blend=(0.0, 0.0)), static)
    assert torch.equal(render_view(model, c2w, k, 8, 6, 0.1, 4.0, blend=None), static)
    assert not torch.equal(render_view(model, c2w, k, 8, 6, 0.1, 4.0, blend=(0.5, 0.5)), static)


def test_fusion_is_the_weighted_sum_of_hidden_features():
    model = perturbed_dual()
    x, d = points()
    s_sigma, s_color = model.static_field(x, d)
    d_sigma, d_color = model.dynamic_field(x, d)
    f_sigma, f_color = model.query(x, d, blend=(0.2, 0.7))
    torch.testing.assert_close(f_sigma, 0.8 * s_sigma + 0.2 * d_sigma)
    torch.testing.assert_close(f_color, 0.3 * s_color + 0.7 * d_color)
    torch.testing.assert_close(model.query_density(x, blend=(0.2, 0.7)), f_sigma)


def test_retreat_scales_the_blend_weights():
    model = perturbed_dual()
    x, d = points()
    for gamma in (0.0, 0.25, 1.0):
        a = model.query(x, d, blend=(0.4, 0.8), retreat=gamma)
        b = model.query(x, d, blend=(0.4 * gamma, 0.8 * gamma))
        torch.testing.assert_close(a[0], b[0])
        torch.testing.assert_close(a[1], b[1])
    static = model.static_field(x, d)
    assert torch.equal(model.query(x, d, blend=(0.4, 0.8), retreat=0.0)[1], static[1])
    with pytest.raises(BlendError):
        model.query(x, d, blend=(0.1, 0.1), retreat=1.5)
    with pytest.raises(BlendError):
        model.query(x, d, blend=(-0.1, 0.1))


def test_gradients_reach_only_the_dynamic_field():
    model = perturbed_dual()
    x, d = points()
    h_sigma, h_color = model.query(x, d, blend=(0.1, 0.1))
    (h_sigma.sum() + h_color.sum()).backward()
    assert all(not p.requires_grad and p.grad is None for p in model.static_field.parameters())
    used = [*model.dynamic_field.encoding.parameters(), *model.dynamic_field.density_mlp.parameters(),
            *model.dynamic_field.color_mlp.parameters()]
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in used)
    # The static branch builds no autograd graph: its outputs come from torch.no_grad.
    assert model.query(x, d, blend=None)[0].grad_fn is None


def test_dynamic_field_starts_as_a_copy_so_any_blend_shows_the_original_scene():
    static = static_field()
    model = make_edit_model(static, "dual")
    x, d = points()
    ref = static(x, d)
    out = model.query(x, d, blend=(0.1, 0.1))
    torch.testing.assert_close(out[0], ref[0])
    torch.testing.assert_close(out[1], ref[1])
    assert model.static_field is not static   # the fitted field handed in is not modified


def test_single_field_mode_is_a_trainable_copy():
    static = static_field()
    single = make_edit_model(static, "single")
    assert isinstance(single, RadianceField) and all(p.requires_grad for p in single.parameters())
    x, d = points()
    assert torch.equal(single(x, d)[1], static(x, d)[1])
    with pytest.raises(ValueError, match="single RadianceField"):
        single.query(x, d, blend=(0.1, 0.1))
    with pytest.raises(ValueError):
        make_edit_model(static, "triple")


def test_dual_training_changes_only_the_dynamic_field():
    model = make_edit_model(static_field(), "dual")
    before_static = [p.clone() for p in model.static_field.parameters()]
    before_dynamic = [p.clone() for p in model.dynamic_field.parameters()]
    n, h, w = 3, 6, 8
    images = torch.rand(n, h, w, 3, generator=torch.Generator().manual_seed(0))
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 2, 3] = -2.0
    cams = Cameras(c2w, torch.tensor([[8.0, 8.0, 4.0, 3.0]] * n), torch.full((n,), 0.1), torch.full((n,), 4.0), w, h)
    trainer = RayTrainer(model, images, cams, TrainConfig(rays_per_batch=32, occupancy_warmup=2,
                                                          occupancy_every=2), torch.Generator().manual_seed(0))
    trainable = {id(p) for group in trainer.optimizer.param_groups for p in group["params"]}
    assert trainable == {id(p) for p in model.dynamic_field.parameters()}
    schedule = BlendSchedule(rate=0.5)
    for step in range(4):
        trainer.step(step, blend=schedule.weights(step + 1), view_weights=torch.tensor([1.0, 2.0, 3.0]))
    assert all(torch.equal(a, b) for a, b in zip(before_static, model.static_field.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(before_dynamic, model.dynamic_field.parameters()))
    assert not math.isnan(trainer.step(4, blend=schedule.weights(5))["loss"])


def test_fused_occupancy_is_the_union_of_both_fields():
    static, other = static_field(0), static_field(1)
    static.occupancy.mask.zero_()
    static.occupancy.mask[0] = True
    other.occupancy.mask.zero_()
    other.occupancy.mask[-1] = True
    model = DualField(static, other)
    assert torch.equal(model.occupancy_for((0.1, 0.1)).mask, static.occupancy.mask | other.occupancy.mask)
    assert model.occupancy_for(None) is static.occupancy
