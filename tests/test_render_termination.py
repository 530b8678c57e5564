"""Optional early ray termination in full-image renders (dualnerf.rendering.RENDER_TERMINATION_EPS) against
the default path that evaluates every occupied sample: colours within eps, fewer field evaluations; and the
exact render speed-ups (SH once per ray, float cell index)."""
import numpy as np
import pytest
import torch

from dualnerf.dual_field import make_edit_model
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.rendering import RENDER_TERMINATION_EPS, render_rays, render_view


def dense_field(seed=0, density_bias=2.0):
    """A field that is opaque after a short distance (so termination matters), with varied colours."""
    config = FieldConfig(grid_resolutions=(4, 8), hidden_width=16, samples_per_ray=32, render_samples_per_ray=32,
                         occupancy_resolution=8, density_bias=density_bias)
    field = RadianceField(config, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        for grid in field.encoding.grids:
            grid.normal_(0, 1, generator=torch.Generator().manual_seed(seed + 1))
    return field


def rays(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, 0.0, -3.0]).expand(n, 3) + 0.3 * torch.randn(n, 3, generator=g)
    target = torch.rand(n, 3, generator=g) * 1.6 - 0.8
    dirs = target - origins
    return origins.contiguous(), dirs / dirs.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("eps", [RENDER_TERMINATION_EPS, 1e-2])
def test_terminated_colours_stay_within_eps_of_the_reference(eps):
    field = dense_field()
    o, d = rays()
    with torch.no_grad():
        reference = render_rays(field, o, d, 0.1, 6.0, samples_per_ray=32)
        fast = render_rays(field, o, d, 0.1, 6.0, samples_per_ray=32, termination_eps=eps)
    # The bound: skipped samples carry at most the transmittance in front of them (< eps) of weight.
    assert float((fast["color"] - reference["color"]).abs().max()) <= eps + 1e-6
    assert fast["evaluated"] < 0.8 * reference["evaluated"]          # it really skips samples


def test_transparent_rays_are_evaluated_exactly_as_the_reference():
    field = dense_field(density_bias=-12.0)             # sigma ~ 6e-6: no ray ever becomes opaque
    o, d = rays()
    with torch.no_grad():
        reference = render_rays(field, o, d, 0.1, 6.0, samples_per_ray=32)
        fast = render_rays(field, o, d, 0.1, 6.0, samples_per_ray=32, termination_eps=1e-4)
    assert fast["evaluated"] == reference["evaluated"]
    torch.testing.assert_close(fast["color"], reference["color"], atol=1e-6, rtol=0)


def test_dual_field_render_terminates_on_the_fused_density_and_keeps_w0_exact():
    static = dense_field()
    dual = make_edit_model(static, "dual")
    with torch.no_grad():
        for p in dual.dynamic_field.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(5)))
    c2w = np.eye(4)
    c2w[2, 3] = -3.0
    k = np.array([10.0, 10.0, 5.0, 4.0])
    eps = RENDER_TERMINATION_EPS
    assert torch.equal(render_view(dual, c2w, k, 10, 8, 0.1, 6.0, blend=(0.0, 0.0), termination_eps=eps),
                       render_view(static, c2w, k, 10, 8, 0.1, 6.0, termination_eps=eps))
    fused = render_view(dual, c2w, k, 10, 8, 0.1, 6.0, blend=(0.5, 0.5), termination_eps=eps)
    exact = render_view(dual, c2w, k, 10, 8, 0.1, 6.0, blend=(0.5, 0.5), termination_eps=0.0)
    assert float((fused - exact).abs().max()) <= RENDER_TERMINATION_EPS + 1e-6


def test_per_ray_direction_features_give_the_per_sample_result_bit_for_bit():
    """The renderer computes SH once per ray and gathers them per sample: equal to SH per sample."""
    field = dense_field()
    dual = make_edit_model(field, "dual")
    with torch.no_grad():
        for p in dual.dynamic_field.parameters():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(2)))
    g = torch.Generator().manual_seed(1)
    _, d = rays(50)
    ray_id = torch.randint(50, (300,), generator=g)
    x = torch.rand(300, 3, generator=g) * 2 - 1
    gathered = field.direction_features(d)[ray_id]
    for model, blend in ((field, None), (dual, (0.3, 0.7))):
        a = model.query(x, d[ray_id], blend=blend)
        b = model.query(x, None, blend=blend, dir_features=gathered)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
        assert torch.equal(model.query_background(d, blend=blend),
                           model.query_background(d, blend=blend, dir_features=field.direction_features(d)))


@pytest.mark.parametrize("resolution", [8, 64, 300])
def test_cell_index_equals_the_integer_formula(resolution):
    from dualnerf.occupancy import OccupancyGrid

    g = torch.Generator().manual_seed(resolution)
    x = torch.rand(20000, 3, generator=g) * 2.4 - 1.2            # inside and outside the cube
    x[:8] = torch.tensor([-1.0, 1.0, 0.0])                       # exact borders
    ijk = ((x + 1.0) * (0.5 * resolution)).floor().long().clamp(0, resolution - 1)
    expected = (ijk[:, 0] * resolution + ijk[:, 1]) * resolution + ijk[:, 2]
    index = OccupancyGrid(resolution).cell_index(x)
    assert index.dtype == torch.long and torch.equal(index, expected)
