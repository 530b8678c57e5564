"""The packed render path (dualnerf.rendering._render_packed: kernels.occupied_samples + composite_rays)
against the torch code it replaces in renders without autograd."""
import shutil

import pytest
import torch

from dualnerf import kernels, rendering
from dualnerf.cameras import view_rays
from dualnerf.dual_field import DualField
from dualnerf.fields import TRUNC_EXP_MAX, FieldConfig, RadianceField

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the kernels cannot be built here")

CONFIG = FieldConfig(grid_resolutions=(4, 9, 16), plane_resolutions=(8, 32), hidden_width=32,
                     samples_per_ray=21, occupancy_resolution=8)


def frozen_field(seed) -> RadianceField:
    model = RadianceField(CONFIG, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        g = torch.Generator().manual_seed(seed + 1)
        for p in model.parameters():
            p.add_(0.7 * torch.randn(p.shape, generator=g))
        model.occupancy.density.uniform_(0.0, 50.0, generator=g)
        model.occupancy.mask.copy_(model.occupancy.density > 12.0)     # some cells empty: masked samples
    return model.requires_grad_(False)


def rays(n=900, seed=0):
    c2w = torch.eye(4)
    c2w[2, 3] = -2.6
    origins, dirs = view_rays(c2w, torch.tensor([20.0, 20.0, 15.0, 15.0]), 30, 30)
    return origins[:n], dirs[:n]


def test_occupied_samples_pack_the_torch_points_in_flat_order():
    g = torch.Generator().manual_seed(3)
    origins, dirs = torch.randn(50, 3, generator=g), torch.randn(50, 3, generator=g)
    t = torch.rand(50, 13, generator=g) * 4.0
    mask = torch.rand(50, 13, generator=g) > 0.4
    mask[7] = False                                                     # a ray without occupied samples
    x, flat, ray, starts = kernels.grid_kernel().occupied_samples(origins, dirs, t, mask)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    expected_flat = torch.nonzero(mask.reshape(-1))[:, 0]
    assert torch.equal(flat, expected_flat)
    assert torch.equal(x, points.reshape(-1, 3)[expected_flat])         # bit for bit
    assert torch.equal(ray, expected_flat // 13)
    assert torch.equal(starts[1:] - starts[:-1], mask.sum(-1)) and starts[0] == 0


@pytest.mark.parametrize("dual", [False, True])
def test_packed_renders_equal_the_torch_compositing(dual):
    model = DualField(frozen_field(0), frozen_field(5)) if dual else frozen_field(0)
    blend = (0.3, 0.6) if dual else None
    origins, dirs = rays()
    with torch.enable_grad():               # grad mode on (nothing requires grad): the torch compositing
        reference = rendering.render_rays(model, origins, dirs, 0.5, 4.0, blend=blend)
    with torch.no_grad():
        packed = rendering.render_rays(model, origins, dirs, 0.5, 4.0, blend=blend)
    assert packed["evaluated"] == reference["evaluated"] > 0
    assert 0.1 < reference["opacity"].mean() < 0.9 and reference["color"].std() > 0.05      # non-trivial
    torch.testing.assert_close(packed["opacity"], reference["opacity"], atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(packed["color"], reference["color"], atol=2e-6, rtol=1e-5)


def test_vector_and_scalar_compositing_agree(monkeypatch):
    if kernels.vector_code() == "none":
        pytest.skip("this build has no vector code: only the scalar compositing runs")
    g = torch.Generator().manual_seed(9)
    n_rays, n_samples = 40, 37                         # not a multiple of 16 or 8: masked tails
    mask = torch.rand(n_rays, n_samples, generator=g) > 0.3
    flat = torch.nonzero(mask.reshape(-1))[:, 0]
    starts = torch.cat([torch.zeros(1, dtype=torch.long), mask.sum(-1).cumsum(0)])
    h_sigma = torch.randn(len(flat), generator=g) * 6.0 + 2.0           # some beyond the clamp at 15
    h_color = torch.randn(len(flat), 3, generator=g) * 3.0
    delta = torch.rand(n_rays, n_samples, generator=g) * 0.05
    background = torch.rand(n_rays, 3, generator=g)
    module = kernels.grid_kernel()
    vector = module.composite_rays(h_sigma, h_color, flat, starts, delta, background, TRUNC_EXP_MAX, True)
    scalar = module.composite_rays(h_sigma, h_color, flat, starts, delta, background, TRUNC_EXP_MAX, False)
    # the torch formulas (rendering.composite) on the dense samples
    sigma = torch.zeros(n_rays * n_samples).index_put((flat,), torch.exp(h_sigma.clamp(max=TRUNC_EXP_MAX)))
    weights = rendering.composite(sigma.view(n_rays, n_samples), delta)
    opacity = weights.sum(-1)
    color = torch.zeros(n_rays, 3).index_add(0, flat // n_samples,
                                             weights.reshape(-1)[flat, None] * torch.sigmoid(h_color))
    color = color + (1.0 - opacity)[:, None] * background
    for got in (vector, scalar):
        torch.testing.assert_close(got[1], opacity, atol=2e-6, rtol=1e-5)
        torch.testing.assert_close(got[0], color, atol=2e-6, rtol=1e-5)
