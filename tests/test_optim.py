"""dualnerf.optim.FieldAdam: Adam's closed form, instant-NGP's zero-gradient skip on feature tables, the
kernel against its torch reference, and checkpoint round trips."""
import math
import shutil

import numpy as np
import pytest
import torch

from dualnerf import kernels
from dualnerf.dual_field import make_edit_model
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.optim import FieldAdam, adam_reference, feature_table_parameters

CONFIG = FieldConfig(grid_resolutions=(4, 8), plane_resolutions=(16,), hidden_width=16)
needs_compiler = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                    reason="no C++ compiler: the fused kernel cannot be built here")


def test_tables_and_mlps_are_separate_groups():
    model = RadianceField(CONFIG, torch.Generator().manual_seed(0))
    optimiser = FieldAdam(model, lr=0.01)
    tables, mlps = optimiser.param_groups
    assert tables["skip_zero"] and not mlps["skip_zero"]
    assert {id(p) for p in tables["params"]} == {id(p) for p in feature_table_parameters(model)}
    assert len(tables["params"]) == 2 + 3                     # 2 dense grids, 3 planes
    assert len(tables["params"]) + len(mlps["params"]) == len(list(model.parameters()))
    dual = make_edit_model(model, "dual")                    # f_S frozen: only f_D's parameters
    groups = FieldAdam(dual, lr=0.01).param_groups
    assert {id(p) for g in groups for p in g["params"]} == {id(p) for p in dual.dynamic_field.parameters()}


def test_steps_follow_adams_closed_form():
    # A constant gradient g: m_t = (1 - b1^t) g, v_t = (1 - b2^t) g^2, so each step moves p by
    # lr * g / (|g| + eps * sqrt(1 - b2^t)) ~ lr * sign(g): after 3 steps p = p0 - 3 lr sign(g).
    p = torch.nn.Parameter(torch.tensor([1.0, -2.0, 0.5]))
    module = torch.nn.Module()
    module.p = p
    optimiser = FieldAdam(module, lr=0.1, betas=(0.9, 0.99), eps=1e-15)
    for _ in range(3):
        p.grad = torch.tensor([0.3, -4.0, 1e-3])
        optimiser.step()
    torch.testing.assert_close(p.detach(), torch.tensor([1.0 - 0.3, -2.0 + 0.3, 0.5 - 0.3]), rtol=0, atol=1e-6)
    state = optimiser.state[p]
    assert state["step"] == 3
    torch.testing.assert_close(state["exp_avg"], (1 - 0.9 ** 3) * torch.tensor([0.3, -4.0, 1e-3]))


def test_table_entries_without_gradient_keep_value_and_moments():
    model = RadianceField(CONFIG, torch.Generator().manual_seed(1))
    optimiser = FieldAdam(model, lr=0.05)
    plane, weight = model.plane_encoding.planes[0], model.density_mlp[0].weight
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    optimiser.step()                                          # every entry has momentum now
    plane_before, weight_before = plane.detach().clone(), weight.detach().clone()
    moments = optimiser.state[plane]["exp_avg"].clone()
    for p in model.parameters():
        p.grad = torch.zeros_like(p)
    touched = torch.zeros(plane.shape, dtype=torch.bool)
    touched[0, :, :2, :5] = True                              # a few touched entries
    plane.grad[touched] = 0.5
    optimiser.step()
    assert torch.equal(plane.detach()[~touched], plane_before[~touched])
    assert torch.equal(optimiser.state[plane]["exp_avg"][~touched], moments[~touched])
    assert (plane.detach()[touched] != plane_before[touched]).all()
    assert (weight.detach() < weight_before).all()            # MLPs: dense Adam, momentum keeps moving them


def ieee_adam(param, grad, exp_avg, exp_avg_sq, beta1, beta2, step_size, bc2_sqrt, eps, skip_zero):
    """The update in numpy float32: every operation (mul, add, sqrt, div) correctly rounded, in the order
    adam_reference states, on any CPU: an independent, CPU-independent expectation."""
    f = np.float32
    p, g, m, v = (t.numpy().copy() for t in (param, grad, exp_avg, exp_avg_sq))
    m_new = f(beta1) * m + f(1 - beta1) * g
    v_new = f(beta2) * v + (f(1 - beta2) * g) * g
    p_new = p - f(step_size) * (m_new / (np.sqrt(v_new) / f(bc2_sqrt) + f(eps)))
    if skip_zero:
        keep = g == 0
        m_new, v_new, p_new = np.where(keep, m, m_new), np.where(keep, v, v_new), np.where(keep, p, p_new)
    return [torch.from_numpy(x) for x in (p_new, m_new, v_new)]


def adam_inputs():
    g = torch.Generator().manual_seed(2)
    param = torch.randn(1, 2, 16, 16, 16, generator=g).contiguous(memory_format=torch.channels_last_3d)
    m = torch.randn(param.shape, generator=g).abs().contiguous(memory_format=torch.channels_last_3d) * 1e-2
    v = torch.randn(param.shape, generator=g).abs().contiguous(memory_format=torch.channels_last_3d) * 1e-4
    grad = torch.randn(param.shape, generator=g).contiguous(memory_format=torch.channels_last_3d)
    grad[grad.abs() < 0.7] = 0.0                             # about half the entries untouched
    args = (0.9, 0.99, 0.01 / (1 - 0.9 ** 7), math.sqrt(1 - 0.99 ** 7), 1e-15)
    return (param, grad, m, v), args


@needs_compiler
@pytest.mark.parametrize("vector", ["1", "0"])
def test_kernel_is_bit_for_bit_ieee_float32_adam(vector, monkeypatch):
    # Both kernel paths, the touched-chunk update included, against correctly rounded float32 maths.
    monkeypatch.setenv("DUALNERF_KERNEL_VECTOR", vector)
    tensors, args = adam_inputs()
    for skip_zero in (True, False):
        expected = ieee_adam(*tensors, *args, skip_zero)
        out = [t.clone(memory_format=torch.preserve_format) for t in tensors]
        kernels.grid_kernel().adam_step(*out, *args, skip_zero)
        for got, want in zip((out[0], out[2], out[3]), expected):
            assert torch.equal(got.contiguous(), want)
        assert not torch.equal(out[0], tensors[0])
    sink = kernels.TableGradients([tensors[0]])
    buffer, touched = sink.gradient(tensors[0])
    buffer.copy_(tensors[1])
    touched.fill_(1)
    out = [t.clone(memory_format=torch.preserve_format) for t in tensors]
    kernels.grid_kernel().adam_step_touched(out[0], buffer, touched, out[2], out[3], *args)
    for got, want in zip((out[0], out[2], out[3]), ieee_adam(*tensors, *args, True)):
        assert torch.equal(got.contiguous(), want)


def test_torch_reference_agrees_with_ieee_float32_adam():
    # adam_reference runs torch's element-wise kernels, whose sqrt is not always correctly rounded (it goes
    # through the CPU's vector maths library: which entries differ by an ulp depends on the CPU), so it is
    # compared within float32 rounding, not bit for bit.
    tensors, args = adam_inputs()
    for skip_zero in (True, False):
        out = [t.clone(memory_format=torch.preserve_format) for t in tensors]
        adam_reference(*out, *args, skip_zero)
        for got, want in zip((out[0], out[2], out[3]), ieee_adam(*tensors, *args, skip_zero)):
            torch.testing.assert_close(got.contiguous(), want, rtol=1e-6, atol=1e-7)


def test_state_round_trips_through_a_weights_only_checkpoint(tmp_path):
    def trained(steps):
        model = RadianceField(CONFIG, torch.Generator().manual_seed(3))
        optimiser = FieldAdam(model, lr=0.02)
        for step in range(steps):
            g = torch.Generator().manual_seed(10 + step)
            for p in model.parameters():
                p.grad = torch.randn(p.shape, generator=g) * (torch.rand(p.shape, generator=g) < 0.3)
            optimiser.step()
        return model, optimiser

    straight, _ = trained(4)
    model, optimiser = trained(2)
    torch.save({"model": model.state_dict(), "optimizer": optimiser.state_dict()}, tmp_path / "state.pt")
    state = torch.load(tmp_path / "state.pt", weights_only=True)
    resumed = RadianceField(CONFIG, torch.Generator().manual_seed(99))
    resumed.load_state_dict(state["model"])
    resumed_optimiser = FieldAdam(resumed, lr=0.02)
    resumed_optimiser.load_state_dict(state["optimizer"])
    for step in range(2, 4):
        g = torch.Generator().manual_seed(10 + step)
        for p in resumed.parameters():
            p.grad = torch.randn(p.shape, generator=g) * (torch.rand(p.shape, generator=g) < 0.3)
        resumed_optimiser.step()
    assert all(torch.equal(a, b) for a, b in zip(straight.parameters(), resumed.parameters()))


@needs_compiler
def test_collected_table_gradients_train_the_same_bits_as_autograd():
    # The same forward, loss and FieldAdam steps, once with the tables' gradients through autograd
    # (p.grad, dense) and once collected by the kernel into TableGradients (touched chunks only).
    x = torch.rand(3000, 3, generator=torch.Generator().manual_seed(5)) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(3000, 3, generator=torch.Generator().manual_seed(6)), dim=-1)
    models = []
    for collect in (False, True):
        model = RadianceField(CONFIG, torch.Generator().manual_seed(4))
        tables = feature_table_parameters(model)
        sink = kernels.TableGradients(tables) if collect else None
        optimiser = FieldAdam(model, lr=0.05, table_gradients=sink)
        for step in range(4):
            part = slice(700 * step, 700 * step + 900)
            optimiser.zero_grad()
            with sink.collect() if collect else torch.enable_grad():
                h_sigma, h_color = model(x[part], d[part])
            (h_sigma.square().mean() + (h_color - 0.5).square().mean()).backward()
            assert all((p.grad is None) == collect for p in tables)
            optimiser.step()
        if collect:                                         # consumed: every buffer is zero again
            assert all(not buffer.any() and not flags.any() for _, buffer, flags in sink.buffers.values())
        models.append(model)
    assert all(torch.equal(a, b) for a, b in zip(models[0].parameters(), models[1].parameters()))
    plane = models[1].plane_encoding.planes[1]
    assert 0 < int((plane != RadianceField(CONFIG, torch.Generator().manual_seed(4)).plane_encoding.planes[1]).sum()) < plane.numel()


@needs_compiler
def test_a_dual_fields_trainer_collects_only_the_dynamic_fields_tables():
    from dualnerf.cameras import Cameras
    from dualnerf.training import RayTrainer, TrainConfig

    model = make_edit_model(RadianceField(CONFIG, torch.Generator().manual_seed(7)), "dual")
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[:, 2, 3] = -2.5
    cams = Cameras(c2w=c2w, intrinsics=torch.tensor([[8.0, 8.0, 4.0, 3.0]] * 2), width=8, height=6,
                   near=torch.full((2,), 0.1), far=torch.full((2,), 5.0))
    trainer = RayTrainer(model, torch.rand(2, 6, 8, 3, generator=torch.Generator().manual_seed(8)), cams,
                         TrainConfig(rays_per_batch=32), torch.Generator().manual_seed(9))
    assert set(trainer.table_gradients.buffers) == {id(p) for p in feature_table_parameters(model.dynamic_field)}
    before = [p.detach().clone() for p in model.dynamic_field.plane_encoding.planes]
    trainer.step(0, blend=(0.1, 0.1))
    assert any(not torch.equal(a, b) for a, b in zip(before, model.dynamic_field.plane_encoding.planes))
