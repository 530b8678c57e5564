"""Every fused kernel gives the same bits on 1, 2, 3 and 4 threads and on its AVX-512 and portable paths
(dualnerf/kernels/kernels.h, "Threads"): an output element never depends on which chunk or code path
computed it. Sizes are odd so that chunks split the vector blocks and leave tails."""
import shutil

import pytest
import torch

from dualnerf import kernels
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.rendering import ray_cube_bounds

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the fused kernel cannot be built here")

CONFIG = FieldConfig(grid_resolutions=(8, 16, 32), plane_resolutions=(32, 64), hidden_width=64)
THREADS = (1, 2, 3, 4)


def field(seed, config=CONFIG):
    model = RadianceField(config, torch.Generator().manual_seed(seed))
    with torch.no_grad():                      # non-trivial tables (they start near zero)
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed + 1)) * 0.3)
    return model


def points(m, seed=0):
    return torch.rand(m, 3, generator=torch.Generator().manual_seed(seed)) * 2.2 - 1.1


def flat(value):
    if isinstance(value, torch.Tensor):
        return [value]
    return [t for v in value for t in flat(v)]


def same_everywhere(compute, monkeypatch):
    """compute() on every thread count and both code paths; all results bit-identical (and returned)."""
    results = []
    for vector in ("1", "0"):
        monkeypatch.setenv("DUALNERF_KERNEL_VECTOR", vector)
        for n in THREADS:
            kernels.set_threads(n)
            results.append(flat(compute()))
    kernels.set_threads(1)
    for result in results[1:]:
        assert len(result) == len(results[0])
        for got, want in zip(result, results[0]):
            assert torch.equal(got, want), "a kernel's result depends on the thread count or the code path"
    return results[0]


def test_look_ups_forward_and_backward(monkeypatch):
    a, b = field(0), field(5)
    x = points(2053)
    grad = torch.randn(2053, sum(e.output_dim for e in a._encodings()), generator=torch.Generator().manual_seed(3))
    module = kernels.grid_kernel()
    same_everywhere(lambda: module.encode_forward(x, *a.grid_tables(), kernels.vector_path()), monkeypatch)
    same_everywhere(lambda: module.encode_forward_pair(x, *a.grid_tables(), *b.grid_tables(), kernels.vector_path()),
                    monkeypatch)
    same_everywhere(lambda: module.encode_backward(x, grad, *a.grid_tables(), kernels.vector_path()), monkeypatch)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_field_inference_single_and_dual(precision, monkeypatch):
    a, b = field(0), field(5)
    x = points(1999)
    sh = a.direction_features(torch.nn.functional.normalize(torch.randn(1999, 3, generator=torch.Generator().manual_seed(11)), dim=-1))
    monkeypatch.setenv("DUALNERF_KERNEL_AMX", "0")    # AMX tiles and the emulation differ (keyed: bf16_mlp)
    with torch.no_grad(), kernels.mlp_precision(precision):
        same_everywhere(lambda: kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers()), monkeypatch)
        same_everywhere(lambda: kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers(),
                                                        second=(b.grid_tables(), b.mlp_layers()), blend=(0.3, 0.1)),
                        monkeypatch)


# Tables over the look-ups' prefetch threshold (lookups.cpp kPrefetchTableBytes, 512 KB): a 48^3 grid and
# 320^2 planes of 2 floats (864 KB, 800 KB), so the AVX2 path sweeps them before it gathers.
SWEPT = FieldConfig(grid_resolutions=(8, 48), plane_resolutions=(320,), hidden_width=64)


def test_look_ups_of_swept_tables_single_pair_and_interleaved(monkeypatch):
    a, b = field(0, SWEPT), field(5, SWEPT)
    sizes = [t.numel() * 4 for t in (*a.grid_tables()[0], *a.grid_tables()[1])]
    assert max(sizes) > 512 * 1024 and min(sizes) < 512 * 1024, sizes     # swept and unswept tables
    x = points(2053, seed=4)
    sh = a.direction_features(torch.nn.functional.normalize(points(2053, seed=8), dim=-1))
    module = kernels.grid_kernel()
    pair = same_everywhere(lambda: module.encode_forward_pair(x, *a.grid_tables(), *b.grid_tables(),
                                                              kernels.vector_path()), monkeypatch)
    single = same_everywhere(lambda: module.encode_forward(x, *a.grid_tables(), kernels.vector_path()), monkeypatch)
    assert torch.equal(pair[0], single[0])
    interleaved = kernels.interleave_pair(a.grid_tables(), b.grid_tables())
    with torch.no_grad():
        dual = same_everywhere(lambda: kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers(),
                                                               second=(b.grid_tables(), b.mlp_layers()),
                                                               blend=(0.3, 0.1), interleaved=interleaved), monkeypatch)
        apart = kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers(),
                                        second=(b.grid_tables(), b.mlp_layers()), blend=(0.3, 0.1))
    assert all(torch.equal(got, want) for got, want in zip(dual, apart))


# The training kernel's weight-gradient tiles: 64 wide with 15 geometry features (the fields' layout: the
# density output's 16 and the colour output's 3 summed by inputs, unmasked), and 24 wide with 6 (inputs
# padded to 32, so masked loads, and 7 outputs: the tiles' remainders).
ODD_WIDTHS = FieldConfig(grid_resolutions=(8, 16, 32), plane_resolutions=(32, 64), hidden_width=24, geo_features=6)


@pytest.mark.parametrize("config", [CONFIG, ODD_WIDTHS], ids=["64-wide", "24-wide"])
def test_mlp_training_forward_and_backward(config, monkeypatch):
    model = RadianceField(config, torch.Generator().manual_seed(2))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(3)) * 0.3)
    m = 3 * 1024 + 77                                  # several gradient groups and a short last block
    n_features = model.mlp_layers()[0].in_features
    features = torch.randn(m, n_features, generator=torch.Generator().manual_seed(4), requires_grad=True)
    sh = model.direction_features(torch.nn.functional.normalize(torch.randn(50, 3, generator=torch.Generator().manual_seed(12)), dim=-1))
    index = torch.randint(50, (m,), generator=torch.Generator().manual_seed(6))
    weights = torch.randn(m, 4, generator=torch.Generator().manual_seed(7))

    def step():
        model.zero_grad()
        features.grad = None
        h_sigma, h_color = kernels.train_heads(features, sh, model.mlp_layers(), sh_index=index)
        ((h_sigma * weights[:, 0]).sum() + (h_color * weights[:, 1:]).square().sum()).backward()
        return h_sigma.detach(), h_color.detach(), features.grad, [p.grad for p in model.parameters() if p.grad is not None]

    h_sigma, h_color, grad_features, *grads = same_everywhere(step, monkeypatch)
    # ... and they are the layers' gradients (torch's nn.Linear, to float32 rounding).
    model.zero_grad()
    features.grad = None
    ref_sigma, ref_color = model._heads_block(features, sh[index])
    ((ref_sigma * weights[:, 0]).sum() + (ref_color * weights[:, 1:]).square().sum()).backward()
    torch.testing.assert_close(h_sigma, ref_sigma.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(h_color, ref_color.detach(), rtol=1e-5, atol=1e-5)
    # Gradients as a whole (a hidden unit within rounding of 0 may take the other side of its ReLU).
    for got, want in zip([grad_features, *grads], [features.grad, *[p.grad for p in model.parameters()
                                                                     if p.grad is not None]]):
        assert float((got - want).norm() / want.norm()) < 1e-4


def test_sampler_packing_and_compositing(monkeypatch):
    model = field(0)
    grid = model.occupancy
    g = torch.Generator().manual_seed(1)
    grid.density.copy_(torch.rand(grid.density.shape, generator=g) ** 6 * 80)
    grid.mask.copy_(grid.density > 2)
    n = 333
    origins = torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, -2.5])
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    t_start, t_end = ray_cube_bounds(origins, dirs, torch.full((n,), 0.1), torch.full((n,), 6.0))
    jitter = torch.rand(n, 47, generator=g)
    module = kernels.grid_kernel()

    def sample():
        return module.ray_samples(origins, dirs, t_start, t_end, grid.density, grid.mask, 0.005, 256, 48, 0.15,
                                  jitter, kernels.vector_path())

    t, delta, mask = same_everywhere(sample, monkeypatch)
    x, flat_index, _, starts = same_everywhere(lambda: module.occupied_samples(origins, dirs, t, mask), monkeypatch)
    h_sigma = torch.randn(x.shape[0], generator=g) * 3
    h_color = torch.randn(x.shape[0], 3, generator=g)
    background = torch.rand(n, 3, generator=g)
    same_everywhere(lambda: module.composite_rays(h_sigma, h_color, flat_index, starts, delta, background, 15.0,
                                                  kernels.vector_path()), monkeypatch)


@pytest.mark.parametrize("n_samples, n_proposal, jittered", [(1, 3, True), (2, 1, False), (7, 5, True), (48, 256, False)])
def test_sampler_walk_at_edge_shapes(n_samples, n_proposal, jittered, monkeypatch):
    """The 16-ray sampler places every edge in the bin the scalar walk does: one sample, one proposal bin,
    no jitter, rays whose interval is empty (stop <= start) and rays that miss the occupied cells."""
    g = torch.Generator().manual_seed(9)
    density = torch.rand(16, 16, 16, generator=g) ** 8 * 50
    density[density < 1] = 0
    n = 77
    origins = torch.rand(n, 3, generator=g) * 2.4 - 1.2
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    t_start = torch.rand(n, generator=g) * 0.5
    t_end = t_start + torch.rand(n, generator=g) * 3 - 0.3
    jitter = torch.rand(n, n_samples - 1, generator=g) if jittered else torch.zeros(0, 0)
    module = kernels.grid_kernel()
    t, delta, occupied = same_everywhere(lambda: module.ray_samples(
        origins, dirs, t_start, t_end, density, density > 0, 0.5, n_proposal, n_samples, 0.1, jitter,
        kernels.vector_path()), monkeypatch)
    # Intervals tile [start, max(start, stop)] in order: lengths >= 0 summing to the interval, midpoints
    # inside it and increasing.
    assert (delta >= 0).all()
    assert (t >= t_start[:, None]).all() and (t <= torch.maximum(t_start, t_end)[:, None]).all()
    assert (t[:, 1:] >= t[:, :-1]).all()
    torch.testing.assert_close(delta.sum(-1), (t_end - t_start).clamp(min=0), rtol=1e-5, atol=1e-5)
    assert not occupied[t_end <= t_start].any()


def test_adam_steps(monkeypatch):
    g = torch.Generator().manual_seed(8)
    param = torch.randn(70001, generator=g)
    grad = torch.randn(70001, generator=g) * (torch.rand(70001, generator=g) < 0.4)

    def step():
        state = [param.clone(), grad.clone(), torch.zeros_like(param), torch.zeros_like(param)]
        for _ in range(2):
            kernels.grid_kernel().adam_step(*state, 0.9, 0.99, 0.01, 0.1, 1e-15, True)
        return state[0], state[2], state[3]

    same_everywhere(step, monkeypatch)


def subnormal_count(tensors) -> int:
    tiny = torch.finfo(torch.float32).tiny
    return sum(int(((t != 0) & (t.abs() < tiny)).sum()) for t in tensors)


def test_kernels_flush_subnormals_on_every_thread_and_leave_the_caller_alone(monkeypatch):
    # kernels.h, "Denormals": outputs are never subnormal (FTZ), subnormal inputs read as zero (DAZ), on
    # every thread count and path; the calling thread's own mode is untouched.
    model = field(2)
    m = 2 * 1024 + 77
    features = torch.randn(m, model.mlp_layers()[0].in_features, generator=torch.Generator().manual_seed(4),
                           requires_grad=True)
    sh = model.direction_features(torch.nn.functional.normalize(torch.randn(m, 3, generator=torch.Generator().manual_seed(5)), dim=-1))
    # Output gradients of 1e-37 (a training step's, far behind a surface): the layers' products of them
    # fall below float32's smallest normal number.
    weights = torch.randn(m, 4, generator=torch.Generator().manual_seed(7)) * 1e-37

    def step():
        model.zero_grad()
        features.grad = None
        h_sigma, h_color = kernels.train_heads(features, sh, model.mlp_layers())
        ((h_sigma * weights[:, 0]).sum() + (h_color * weights[:, 1:]).sum()).backward()
        return features.grad, [p.grad for p in model.parameters() if p.grad is not None]

    grads = flat(same_everywhere(step, monkeypatch))
    assert subnormal_count(grads) == 0
    # The torch reference (not flushed) has them: the test exercises the flush.
    model.zero_grad()
    features.grad = None
    ref_sigma, ref_color = model._heads_block(features, sh)
    ((ref_sigma * weights[:, 0]).sum() + (ref_color * weights[:, 1:]).sum()).backward()
    reference = [features.grad, *[p.grad for p in model.parameters() if p.grad is not None]]
    assert subnormal_count(reference) > 100
    # Nonzero reference entries far above the subnormal range agree (the flush only drops what is tiny).
    for got, want in zip(grads, reference):
        big = want.abs() > 1e-30
        torch.testing.assert_close(got[big], want[big], rtol=1e-3, atol=0.0)

    # DAZ: a table entry holding a subnormal value looks up as a zero.
    dense, planes = model.grid_tables()
    x = points(1031)
    tiny = [t.clone() for t in planes]
    every_seventh = torch.arange(tiny[0].numel()).reshape(tiny[0].shape) % 7 == 0
    tiny[0].masked_fill_(every_seventh, 1e-39)
    zeroed = [t.clone() for t in tiny]
    zeroed[0].masked_fill_(every_seventh, 0.0)
    module = kernels.grid_kernel()
    looked_up = same_everywhere(lambda: module.encode_forward(x, list(dense), tiny, kernels.vector_path()), monkeypatch)
    assert torch.equal(looked_up[0], module.encode_forward(x, list(dense), zeroed, kernels.vector_path()))
    # The caller's thread still computes with subnormals.
    assert float(torch.tensor(1e-38) / 10.0) != 0.0
