"""Volume rendering against closed-form cases, ray geometry, occupancy skipping, chunked rendering."""
import math

import numpy as np
import pytest
import torch

from dualnerf.cameras import pixel_rays, view_rays
from dualnerf.fields import FieldConfig, RadianceField
from dualnerf.rendering import composite, distortion, ray_cube_bounds, render_rays, render_view

DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device")])]


def constant_field(sigma: float, rgb, background: str = "black", samples: int = 64) -> RadianceField:
    """A field with density `sigma` and colour `rgb` everywhere in the cube (all weights zero, biases set)."""
    cfg = FieldConfig(grid_resolutions=(2,), grid_features=1, hidden_width=4, geo_features=1, direction_degree=2,
                      background=background, samples_per_ray=samples, occupancy_resolution=4)
    field = RadianceField(cfg)
    with torch.no_grad():
        for p in field.parameters():
            p.zero_()
        field.density_mlp[-1].bias[0] = math.log(sigma)
        rgb = torch.tensor(rgb, dtype=torch.float32)
        field.color_mlp[-1].bias.copy_(torch.log(rgb / (1 - rgb)))
    return field


def axis_ray(device="cpu"):
    return torch.tensor([[0.0, 0.0, -3.0]], device=device), torch.tensor([[0.0, 0.0, 1.0]], device=device)


@pytest.mark.parametrize("device", DEVICES)
def test_constant_slab_matches_beer_lambert(device):
    sigma, rgb = 1.7, (0.2, 0.5, 0.9)
    field = constant_field(sigma, rgb, background="white").to(device)
    origins, dirs = axis_ray(device)
    # near/far cut a slab of length 1 out of the cube (z in [-0.5, 0.5]).
    out = render_rays(field, origins, dirs, torch.tensor([2.5], device=device), torch.tensor([3.5], device=device))
    transmittance = math.exp(-sigma * 1.0)
    expected = torch.tensor(rgb) * (1 - transmittance) + 1.0 * transmittance
    assert out["opacity"].item() == pytest.approx(1 - transmittance, abs=1e-5)
    torch.testing.assert_close(out["color"][0].cpu(), expected, atol=1e-5, rtol=0)


def test_slab_through_whole_cube_is_clipped_to_the_cube():
    sigma = 0.3
    field = constant_field(sigma, (0.5, 0.5, 0.5))
    origins, dirs = axis_ray()
    out = render_rays(field, origins, dirs, 0.0, 100.0)
    # Density exists only inside [-1,1]^3: path length 2.
    assert out["opacity"].item() == pytest.approx(1 - math.exp(-2 * sigma), abs=1e-5)


@pytest.mark.parametrize("background,value", [("white", 1.0), ("black", 0.0)])
def test_empty_space_shows_background(background, value):
    field = constant_field(1e-12, (0.3, 0.3, 0.3), background=background)
    origins, dirs = axis_ray()
    out = render_rays(field, origins, dirs, 0.0, 10.0)
    assert out["opacity"].item() < 1e-9
    torch.testing.assert_close(out["color"][0], torch.full((3,), value), atol=1e-6, rtol=0)


def test_learned_background_for_rays_missing_the_cube():
    field = RadianceField(FieldConfig(grid_resolutions=(4,), samples_per_ray=16), torch.Generator().manual_seed(1))
    origins = torch.tensor([[0.0, 5.0, -3.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0]])         # passes above the cube
    out = render_rays(field, origins, dirs, 0.0, 10.0)
    assert out["evaluated"] == 0 and out["opacity"].item() == 0.0
    expected = torch.sigmoid(field.background_hidden(dirs))[0]
    torch.testing.assert_close(out["color"][0], expected)


def test_composite_weights_closed_form():
    sigma = torch.tensor([[0.0, 2.0, 1.0, 0.5]])
    delta = torch.tensor([[0.5, 0.25, 1.0, 2.0]])
    tau = (sigma * delta)[0].tolist()
    expected, acc = [], 0.0
    for t in tau:
        expected.append(math.exp(-acc) * (1 - math.exp(-t)))
        acc += t
    torch.testing.assert_close(composite(sigma, delta)[0], torch.tensor(expected))


def test_ray_cube_bounds():
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t0, t1 = ray_cube_bounds(origins, dirs, torch.tensor([0.0, 0.0, 0.0]), torch.tensor([10.0, 0.5, 10.0]))
    torch.testing.assert_close(t0[:2], torch.tensor([2.0, 0.0]))
    torch.testing.assert_close(t1[:2], torch.tensor([4.0, 0.5]))
    assert t1[2] <= t0[2]          # misses the cube


def test_pixel_rays_follow_opencv_convention():
    # Camera at (1,2,3); the rotation columns are the camera x, y, z axes in world coordinates.
    rot = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    c2w = torch.eye(4)
    c2w[:3, :3] = rot
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    k = torch.tensor([100.0, 80.0, 49.5, 29.5])
    origins, dirs = pixel_rays(c2w[None].repeat(3, 1, 1), k[None].repeat(3, 1),
                               torch.tensor([49, 99, 49]), torch.tensor([29, 29, 59]))
    torch.testing.assert_close(origins, torch.tensor([[1.0, 2.0, 3.0]] * 3))
    torch.testing.assert_close(dirs[0], rot[:, 2])                       # principal ray = camera +z
    right = (torch.tensor([50.0 / 100.0, 0.0, 1.0]) @ rot.T)
    torch.testing.assert_close(dirs[1], right / right.norm())             # u to the right = camera +x
    down = (torch.tensor([0.0, 30.0 / 80.0, 1.0]) @ rot.T)
    torch.testing.assert_close(dirs[2], down / down.norm())               # v down = camera +y
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(3))


def test_view_rays_row_major():
    _, d = view_rays(np.eye(4), np.array([10.0, 10.0, 2.0, 1.5]), 4, 3)
    assert d.shape == (12, 3)
    _, d_one = pixel_rays(torch.eye(4)[None], torch.tensor([[10.0, 10.0, 2.0, 1.5]]),
                          torch.tensor([3]), torch.tensor([1]))
    torch.testing.assert_close(d[1 * 4 + 3], d_one[0])


def test_empty_occupancy_skips_all_samples_and_full_occupancy_matches_dense():
    field = constant_field(0.8, (0.1, 0.7, 0.3), background="white")
    origins, dirs = axis_ray()
    dense = render_rays(field, origins, dirs, 0.0, 10.0)
    assert dense["evaluated"] == field.config.samples_per_ray
    field.occupancy.mask.zero_()
    skipped = render_rays(field, origins, dirs, 0.0, 10.0)
    assert skipped["evaluated"] == 0
    torch.testing.assert_close(skipped["color"][0], torch.ones(3), atol=1e-6, rtol=0)


def test_occupancy_update_finds_an_analytic_sphere():
    from dualnerf.occupancy import OccupancyGrid

    grid = OccupancyGrid(16)

    def density(x):   # a dense ball of radius 0.4 at (0.3, 0, 0)
        return torch.where((x - torch.tensor([0.3, 0.0, 0.0])).norm(dim=-1) < 0.4, 50.0, 0.0)

    grid.update(density, torch.Generator().manual_seed(0), sigma_threshold=1.0, decay=0.95)
    inside = torch.tensor([[0.3, 0.0, 0.0], [0.55, 0.1, 0.0]])
    outside = torch.tensor([[-0.8, 0.0, 0.0], [0.3, 0.9, 0.9]])
    assert grid.occupied(inside).all()
    assert not grid.occupied(outside).any()
    # Ball volume (4/3 pi 0.4^3 = 0.27) is ~3% of the cube; with dilation it stays well below a third.
    assert 0.02 < grid.fraction() < 0.3


@pytest.mark.parametrize("resolution", [8, 10])
def test_occupancy_refresh_evaluates_block_by_block_and_stores_each_cells_own_density(resolution):
    """The refresh evaluates its jittered points in blocks of cells (tile_order: a permutation, blocks of
    REFRESH_TILE^3, a smaller border block when the resolution is not a multiple) and stores every
    point's density in its own cell: the grid equals the one from the same draw in cell order."""
    from dualnerf.occupancy import REFRESH_TILE, OccupancyGrid, tile_order

    order = tile_order(resolution)
    assert torch.equal(torch.sort(order).values, torch.arange(resolution ** 3))
    first_block = order[:REFRESH_TILE ** 3]
    ijk = torch.stack([first_block // resolution ** 2, first_block // resolution % resolution,
                       first_block % resolution], dim=-1)
    assert int(ijk.max()) == REFRESH_TILE - 1           # the first cells read are the corner block's

    seen = []

    def density(x):   # x-dependent, so a point in the wrong cell shows
        seen.append(x.shape[0])
        return 1.0 + 10.0 * (x[:, 0] + 1.0) + (x[:, 1] + 1.0) ** 2 + 0.1 * x[:, 2]    # > 0: decay 0 keeps it

    grid = OccupancyGrid(resolution)
    grid.update(density, torch.Generator().manual_seed(4), sigma_threshold=1.0, decay=0.0, chunk=100)
    assert seen[0] == 100 and sum(seen) == resolution ** 3
    # The reference: the same jitter draw, evaluated in cell order.
    ar = torch.arange(resolution, dtype=torch.float32)
    corner = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3)
    jitter = torch.rand(corner.shape, generator=torch.Generator().manual_seed(4))
    points = (corner + jitter) * (2.0 / resolution) - 1.0
    assert torch.equal(grid.density, density(points).reshape(resolution, resolution, resolution))


def test_occupancy_dilation_is_the_3x3x3_neighbourhood_as_max_pool3d_computes_it():
    import torch.nn.functional as F

    from dualnerf.occupancy import dilate

    # One cell: its 3x3x3 block (27 cells), cut at the grid's faces (a corner: 8 cells; an edge: 12).
    for at, expected in (((4, 4, 4), 27), ((0, 0, 0), 8), ((7, 3, 0), 12)):
        mask = torch.zeros(8, 8, 8, dtype=torch.bool)
        mask[at] = True
        grown = dilate(mask)
        assert int(grown.sum()) == expected
        cells = torch.nonzero(grown)
        assert int((cells - torch.tensor(at)).abs().max()) == 1
    # Random masks of several densities and an odd, non-cubic shape: the same cells as the float max pool.
    g = torch.Generator().manual_seed(3)
    for share in (0.01, 0.1, 0.5):
        mask = torch.rand(9, 12, 7, generator=g) < share
        reference = F.max_pool3d(mask.float()[None, None], kernel_size=3, stride=1, padding=1)[0, 0] > 0
        assert torch.equal(dilate(mask), reference)


def test_render_view_chunking_does_not_change_the_image():
    field = RadianceField(FieldConfig(grid_resolutions=(8, 16), samples_per_ray=32),
                          torch.Generator().manual_seed(3))
    c2w = np.eye(4)
    c2w[2, 3] = -2.5
    k = np.array([12.0, 12.0, 6.0, 4.0])
    a = render_view(field, c2w, k, 12, 8, 0.5, 5.0, chunk=7)
    b = render_view(field, c2w, k, 12, 8, 0.5, 5.0, chunk=10_000)
    assert a.shape == (8, 12, 3) and a.min() >= 0 and a.max() <= 1
    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)


def test_render_view_uses_the_render_sample_count():
    from dualnerf.cameras import view_rays

    config = FieldConfig(grid_resolutions=(8, 16), samples_per_ray=4, render_samples_per_ray=64, density_bias=1.0)
    field = RadianceField(config, torch.Generator().manual_seed(3))
    with torch.no_grad():           # a lumpy density, so the sample count changes the picture
        for grid in field.encoding.grids:
            grid.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(4))
    c2w = np.eye(4)
    c2w[2, 3] = -2.5
    k = np.array([12.0, 12.0, 6.0, 4.0])
    image = render_view(field, c2w, k, 12, 8, 0.5, 5.0)
    origins, dirs = view_rays(c2w, k, 12, 8)
    by_count = {n: render_rays(field, origins, dirs, 0.5, 5.0, samples_per_ray=n)["color"].reshape(8, 12, 3)
                for n in (4, 64)}
    torch.testing.assert_close(image, by_count[64].clamp(0, 1), atol=1e-6, rtol=0)
    assert (image - by_count[4].clamp(0, 1)).abs().max() > 1e-2
    assert render_rays(field, origins, dirs, 0.5, 5.0)["evaluated"] <= 4 * len(origins)


def test_proposal_intervals_tile_the_segment_and_follow_the_density():
    from dualnerf.rendering import proposal_intervals

    t_start, t_end = torch.tensor([0.5, 2.0]), torch.tensor([3.5, 2.6])

    def slab(t):   # opaque between 1.0 and 1.2 on every ray
        return torch.where((t > 1.0) & (t < 1.2), 200.0, 0.0)

    jitter = torch.rand(2, 31, generator=torch.Generator().manual_seed(0))
    for j in (None, jitter):
        t, delta = proposal_intervals(t_start, t_end, slab, 32, 300, 0.1, j)
        assert (delta >= 0).all() and (t[:, 1:] >= t[:, :-1]).all()
        torch.testing.assert_close(delta.sum(-1), t_end - t_start)
        torch.testing.assert_close(t[:, 0] - delta[:, 0] / 2, t_start)
    t, _ = proposal_intervals(t_start, t_end, slab, 32, 300, 0.1)
    # Ray 0 sees the slab: ~90% of its intervals sit on it; ray 1 (starts beyond it) stays uniform.
    assert ((t[0] > 1.0) & (t[0] < 1.2)).sum() >= 25
    _, delta = proposal_intervals(t_start, t_end, lambda t: torch.zeros_like(t), 32, 300, 0.1)
    torch.testing.assert_close(delta, ((t_end - t_start) / 32)[:, None].expand(-1, 32))


def test_non_uniform_intervals_keep_beer_lambert_exact():
    sigma = 0.9
    field = constant_field(sigma, (0.4, 0.4, 0.4))
    with torch.no_grad():   # a lumpy proposal density: intervals become very uneven
        field.occupancy.density.copy_(torch.rand(field.occupancy.density.shape,
                                                 generator=torch.Generator().manual_seed(0)) * 50)
    origins, dirs = axis_ray()
    out = render_rays(field, origins, dirs, 0.0, 100.0, generator=torch.Generator().manual_seed(1))
    assert out["opacity"].item() == pytest.approx(1 - math.exp(-2 * sigma), abs=1e-5)


def test_distortion_matches_the_double_sum_and_prefers_one_compact_peak():
    g = torch.Generator().manual_seed(3)
    edges = torch.sort(torch.rand(5, 9, generator=g) * 4.0, dim=-1).values
    t, delta = 0.5 * (edges[:, 1:] + edges[:, :-1]), edges[:, 1:] - edges[:, :-1]
    weights = torch.rand(5, 8, generator=g) / 8
    length = torch.full((5,), 4.0)
    s, ds = t / 4.0, delta / 4.0
    brute = ((weights[:, :, None] * weights[:, None, :] * (s[:, :, None] - s[:, None, :]).abs()).sum((1, 2))
             + (weights ** 2 * ds).sum(-1) / 3)
    assert torch.allclose(distortion(weights, t, delta, length), brute, atol=1e-6)
    # All weight in one interval of normalised length 0.1: only the self term, 0.1 / 3.
    one = torch.zeros(1, 10)
    one[0, 4] = 1.0
    grid_t, grid_delta = (torch.arange(10.0)[None] + 0.5) * 0.1, torch.full((1, 10), 0.1)
    assert float(distortion(one, grid_t, grid_delta, torch.ones(1))) == pytest.approx(0.1 / 3)
    # The same total weight split between the two ends of the ray (haze / a floater) costs far more.
    split = torch.zeros(1, 10)
    split[0, 0] = split[0, 9] = 0.5
    assert float(distortion(split, grid_t, grid_delta, torch.ones(1))) > 5 * (0.1 / 3)


def test_distortion_weight_enters_the_training_loss():
    from dualnerf.cameras import Cameras
    from dualnerf.training import RayTrainer, TrainConfig

    field = constant_field(5.0, (0.4, 0.5, 0.6))
    cams = Cameras(c2w=torch.eye(4)[None].clone(), intrinsics=torch.tensor([[8.0, 8.0, 4.0, 4.0]]),
                   width=8, height=8, near=torch.tensor([0.1]), far=torch.tensor([4.0]))
    cams.c2w[0, :3, 3] = torch.tensor([0.0, 0.0, -3.0])
    images = torch.full((1, 8, 8, 3), 0.5)
    losses = {}
    for weight in (0.0, 1.0):
        trainer = RayTrainer(field, images, cams, TrainConfig(distortion_weight=weight, occupancy_warmup=10**9),
                             torch.Generator().manual_seed(0))
        losses[weight] = trainer.step(0)["loss"]
        field.load_state_dict(constant_field(5.0, (0.4, 0.5, 0.6)).state_dict())
    assert losses[1.0] > losses[0.0]
