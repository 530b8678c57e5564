"""The fused grid-encoding kernel (dualnerf.kernels) against its plain torch reference (F.grid_sample)."""
import shutil

import pytest
import torch

from dualnerf import kernels
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.occupancy import OccupancyGrid
from dualnerf.rendering import ray_cube_bounds

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the fused kernel cannot be built here")

CONFIG = FieldConfig(grid_resolutions=(4, 9, 16), plane_resolutions=(8, 32), hidden_width=16,
                     samples_per_ray=16, occupancy_resolution=8)


def field(seed=0) -> RadianceField:
    model = RadianceField(CONFIG, torch.Generator().manual_seed(seed))
    with torch.no_grad():          # features of order 1 (the initial 1e-4 would hide any error)
        g = torch.Generator().manual_seed(seed + 1)
        for p in list(model.encoding.grids) + list(model.plane_encoding.planes):
            p.copy_(torch.randn(p.shape, generator=g))
    return model


def points(n=3000, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 2.4 - 1.2          # some outside the cube: border padding
    corners = torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0],
                            [0.5, -0.25, 1.0]])             # cube corners and grid nodes, exactly
    return torch.cat([corners, x])


def test_the_kernel_builds_here():
    # CI has a compiler; a silent fall back to the reference would hide a ~2x slowdown.
    assert kernels.grid_kernel() is not None and kernels.kernel_name() == "fused-cpp"


def test_fused_features_equal_the_grid_sample_reference():
    model, x = field(), points()
    with torch.no_grad():
        fused, reference = model.features(x), model.reference_features(x)
    assert fused.shape == reference.shape == (len(x), 2 * (3 + 3 * 2))
    torch.testing.assert_close(fused, reference, atol=2e-6, rtol=1e-6)


def test_fused_gradients_equal_the_reference_gradients():
    x = points(2000, seed=3)
    weights = torch.randn(len(x), 18, generator=torch.Generator().manual_seed(4))
    grads = []
    for path in ("features", "reference_features"):
        model = field()
        (getattr(model, path)(x) * weights).sum().backward()
        grads.append([p.grad.clone() for p in list(model.encoding.grids) + list(model.plane_encoding.planes)])
    for fused, reference in zip(*grads):
        assert fused.shape == reference.shape
        torch.testing.assert_close(fused, reference, atol=1e-5, rtol=1e-5)
        assert reference.abs().max() > 0


def test_whole_field_training_step_matches_the_reference():
    # One Adam step through the full field (MLPs on top of the features) lands on the same parameters.
    x, d = points(1500, seed=5), torch.nn.functional.normalize(
        torch.randn(1505, 3, generator=torch.Generator().manual_seed(15)), dim=-1)
    results = []
    for path in ("features", "reference_features"):
        model = field()
        model.features = getattr(model, path)
        optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
        h_sigma, h_color = model(x, d)
        (h_sigma.square().mean() + h_color.square().mean()).backward()
        optimiser.step()
        results.append(torch.cat([p.detach().reshape(-1) for p in model.parameters()]))
    torch.testing.assert_close(results[0], results[1], atol=1e-5, rtol=1e-5)


def test_repeated_backward_passes_are_bit_for_bit_equal():
    # Each table's gradient is summed by one thread in point order: no run-to-run rounding noise.
    x = points(20000, seed=6)
    grads = []
    for _ in range(2):
        model = field()
        model.features(x).square().sum().backward()
        grads.append([p.grad for p in model.plane_encoding.planes])
    assert all(torch.equal(a, b) for a, b in zip(*grads))


def test_nan_points_do_not_read_outside_the_tables():
    x = points(10)
    x[3] = float("nan")
    with torch.no_grad():
        out = field().features(x)
    assert out.shape == (len(x), 18) and torch.isfinite(out[torch.arange(len(x)) != 3]).all()


def test_tables_are_stored_channels_last_and_old_contiguous_states_load():
    model = field()
    assert model.encoding.grids[0].is_contiguous(memory_format=torch.channels_last_3d)
    assert model.plane_encoding.planes[0].is_contiguous(memory_format=torch.channels_last)
    state = {k: v.contiguous() for k, v in field(seed=7).state_dict().items()}   # a pre-kernel checkpoint
    model.load_state_dict(state)
    assert all(torch.equal(model.state_dict()[k], v) for k, v in state.items())
    assert model.plane_encoding.planes[1].is_contiguous(memory_format=torch.channels_last)


def _sampler_inputs(n=405, seed=8):     # not a multiple of 16: a tail of rays one at a time
    grid = OccupancyGrid(16)
    g = torch.Generator().manual_seed(seed)
    grid.density.copy_(torch.rand(16, 16, 16, generator=g) ** 4 * 400)      # sparse, peaked densities
    grid.mask.copy_(grid.density > 5.0)
    origins = torch.randn(n, 3, generator=g) * 2
    dirs = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(n, 3, generator=g), dim=-1)
    origins[:40] = torch.nn.functional.normalize(origins[:40], dim=-1) * 3.0     # outside, looking away:
    dirs[:40] = torch.nn.functional.normalize(origins[:40], dim=-1)              # these miss the cube
    t_start, t_end = ray_cube_bounds(origins, dirs, 0.1, 8.0)
    return grid, origins, dirs, t_start, t_end, g


@pytest.mark.parametrize("vector", ["1", "0"])        # 16 rays per AVX-512 vector, or one at a time
@pytest.mark.parametrize("jittered", [False, True])
def test_fused_sampler_matches_the_torch_reference(monkeypatch, jittered, vector):
    from dualnerf.rendering import ray_samples

    monkeypatch.setenv("DUALNERF_KERNEL_VECTOR", vector)
    grid, origins, dirs, t_start, t_end, g = _sampler_inputs()
    config = FieldConfig(proposal_samples=128)
    jitter = torch.rand(len(origins), 31, generator=g) if jittered else None
    t, delta, mask = ray_samples(grid, config, origins, dirs, t_start, t_end, 32, jitter)
    monkeypatch.setenv("DUALNERF_KERNELS", "0")
    ref_t, ref_delta, ref_mask = ray_samples(grid, config, origins, dirs, t_start, t_end, 32, jitter)
    valid = t_end > t_start
    assert 0 < int(valid.sum()) < len(valid)                  # rays that miss the cube, too
    # Rounding in the cdf is divided by the pdf of a bin (frac = (u - cdf) / pdf), so edges agree to ~1e-5
    # of a ray's ~4-unit segment; a wrong bin or quantile would move them by a whole interval (~0.1).
    torch.testing.assert_close(t, ref_t, atol=1e-4, rtol=0)
    torch.testing.assert_close(delta, ref_delta, atol=1e-4, rtol=0)
    # The intervals tile each ray's segment, and the mask is the occupancy of the kernel's own midpoints
    # (the cells bit for bit the reference's), so it can only differ from the reference's where a
    # midpoint moved across a cell border by rounding.
    length = (t_end - t_start).clamp(min=0)
    torch.testing.assert_close(delta.sum(-1), length, atol=1e-5, rtol=1e-5)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    assert torch.equal(mask, valid[:, None] & grid.occupied(points))
    assert float((mask != ref_mask).float().mean()) < 1e-3
    assert float(mask.float().mean()) > 0.05


def test_kernels_off_runs_the_reference_encodings(monkeypatch):
    monkeypatch.setenv("DUALNERF_KERNELS", "0")
    model, x = field(), points(100)
    with torch.no_grad():
        assert torch.equal(model.features(x), model.reference_features(x))


def test_pair_kernel_equals_each_fields_own_kernel_bit_for_bit():
    # The dual field's one-pass look-up of f_S and f_D: a w = 0 render must still be f_S's, bit for bit.
    static, dynamic, x = field(0), field(10), points(5000, seed=11)
    first, second = kernels.fused_pair_features(x, *static.grid_tables(), *dynamic.grid_tables())
    with torch.no_grad():
        assert torch.equal(first, static.features(x)) and torch.equal(second.detach(), dynamic.features(x))
    assert not first.requires_grad and second.requires_grad
    (second * 2.0).sum().backward()
    pair_grads = [p.grad.clone() for p in dynamic.plane_encoding.planes]
    dynamic.zero_grad()
    (dynamic.features(x) * 2.0).sum().backward()
    assert all(torch.equal(a, p.grad) for a, p in zip(pair_grads, dynamic.plane_encoding.planes))
    assert all(p.grad is None for p in static.parameters())


def test_dual_field_query_with_the_pair_kernel_matches_the_reference(monkeypatch):
    from dualnerf.dual_field import DualField

    x = points(3000, seed=12)
    d = torch.nn.functional.normalize(torch.randn(len(x), 3, generator=torch.Generator().manual_seed(13)), dim=-1)
    outputs = []
    for setting in ("1", "0"):
        monkeypatch.setenv("DUALNERF_KERNELS", setting)
        model = DualField(field(0), field(10))
        h_sigma, h_color = model.query(x, d, blend=(0.3, 0.6))
        (h_sigma.sum() + h_color.sum()).backward()
        outputs.append((h_sigma.detach(), h_color.detach(), model.dynamic_field.plane_encoding.planes[1].grad))
    for fused, reference in zip(*outputs):
        torch.testing.assert_close(fused, reference, atol=1e-5, rtol=1e-5)


def test_vector_and_scalar_look_ups_and_gradients_give_the_same_bits(monkeypatch):
    # The AVX-512 look-ups (16 points per gather), or the AVX2 ones (8), must reproduce the scalar code
    # exactly: a render and a resumed run may take either path. 3000 points: a 1024-point block tail and a
    # partial 16-lane group; NaN and out-of-cube points take the clamped corners.
    if kernels.vector_code() == "none":
        pytest.skip("this CPU and build have neither AVX-512 nor AVX2: only the scalar look-ups run")
    static, dynamic, x = field(0), field(10), points(3000, seed=12)
    x[[7, 40, 41]] = float("nan")
    results, grads = [], []
    weights = torch.randn(len(x), 18, generator=torch.Generator().manual_seed(13))
    for vector in ("1", "0"):
        monkeypatch.setenv("DUALNERF_KERNEL_VECTOR", vector)
        with torch.no_grad():
            pair = kernels.fused_pair_features(x, *static.grid_tables(), *dynamic.grid_tables())
            results.append([static.features(x), *pair])
        # The backward: the same corner offsets and weights, the additions in the scalar order.
        dynamic.zero_grad()
        (kernels.fused_pair_features(x, *static.grid_tables(), *dynamic.grid_tables())[1] * weights).sum().backward()
        grads.append([p.grad.clone() for p in [*dynamic.encoding.grids, *dynamic.plane_encoding.planes]])
    assert all(torch.equal(a, b) for a, b in zip(*results))
    assert torch.isfinite(results[0][0][8:40]).all() and results[0][0].abs().max() > 1.0
    assert all(torch.equal(a, b) for a, b in zip(*grads)) and all(g.abs().max() > 0 for g in grads[0])
