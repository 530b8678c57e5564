"""Field components: SH orthonormality, trilinear grids, decoders, config and model-file round trips."""
import json
import math

import pytest
import torch

from dualnerf.dual_field import make_edit_model
from dualnerf.encoding import DenseGridEncoding, spherical_harmonics
from dualnerf.fields import FieldConfig, FieldConfigError, RadianceField, decode_color, decode_density
from dualnerf.model import ModelFileError, load_model, save_model, saved_blend

SMALL = FieldConfig(grid_resolutions=(4, 8), hidden_width=16, samples_per_ray=16, occupancy_resolution=8)


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    y = spherical_harmonics(d, 4)
    assert y.shape == (400_000, 16)
    gram = 4 * math.pi * (y.T @ y) / len(d)          # Monte Carlo estimate of the integral over the sphere
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)
    assert spherical_harmonics(d[:5], 2).shape == (5, 4)
    with pytest.raises(ValueError):
        spherical_harmonics(d[:5], 5)


def test_dense_grid_reproduces_linear_functions_exactly():
    # Trilinear interpolation is exact for affine functions of the position.
    enc = DenseGridEncoding((5, 9), features=2)
    a = torch.tensor([0.3, -1.2, 2.0])
    with torch.no_grad():
        for grid in enc.grids:
            r = grid.shape[-1]
            lin = torch.linspace(-1, 1, r)
            z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")   # grid dims are (D, H, W) = (z, y, x)
            grid[0, 0] = a[0] * x + a[1] * y + a[2] * z + 0.5
            grid[0, 1] = -x
    pts = torch.rand(100, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    out = enc(pts)
    assert out.shape == (100, 4)
    expected = pts @ a + 0.5
    for level in range(2):
        torch.testing.assert_close(out[:, 2 * level], expected, atol=1e-5, rtol=0)
        torch.testing.assert_close(out[:, 2 * level + 1], -pts[:, 0], atol=1e-5, rtol=0)


def test_decoders():
    h = torch.tensor([-2.0, 0.0, 3.0, 100.0], requires_grad=True)
    sigma = decode_density(h)
    torch.testing.assert_close(sigma[:3], torch.exp(h[:3]))
    assert torch.isfinite(sigma).all() and float(sigma[3].detach()) == pytest.approx(math.exp(15.0), rel=1e-5)
    sigma.sum().backward()
    assert torch.isfinite(h.grad).all() and h.grad[3] > 0        # truncated, not dead
    torch.testing.assert_close(decode_color(torch.tensor([0.0])), torch.tensor([0.5]))


def test_field_output_shapes_and_config_validation():
    field = RadianceField(SMALL, torch.Generator().manual_seed(0))
    x = torch.rand(7, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(7, 3), dim=-1)
    h_sigma, h_color = field(x, d)
    assert h_sigma.shape == (7,) and h_color.shape == (7, 3)
    assert FieldConfig.from_dict(json.loads(json.dumps(SMALL.to_dict()))) == SMALL
    with pytest.raises(FieldConfigError, match="background"):
        FieldConfig(background="pink")
    with pytest.raises(FieldConfigError, match="unknown keys"):
        FieldConfig.from_dict({**SMALL.to_dict(), "colour_mlp_depth": 3})


def test_seeded_construction_is_deterministic():
    a = RadianceField(SMALL, torch.Generator().manual_seed(5))
    b = RadianceField(SMALL, torch.Generator().manual_seed(5))
    c = RadianceField(SMALL, torch.Generator().manual_seed(6))
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))
    assert not all(torch.equal(p, q) for p, q in zip(a.parameters(), c.parameters()))


def _inputs():
    g = torch.Generator().manual_seed(1)
    return torch.rand(20, 3, generator=g) * 2 - 1, torch.nn.functional.normalize(torch.randn(20, 3, generator=g), dim=-1)


def test_static_field_save_load_round_trip(tmp_path):
    field = RadianceField(SMALL, torch.Generator().manual_seed(0))
    field.occupancy.mask[0, 0, :3] = False
    save_model(tmp_path / "m", field, extra={"psnr": 30.0})
    loaded = load_model(tmp_path / "m")
    assert isinstance(loaded, RadianceField) and loaded.config == SMALL
    x, d = _inputs()
    assert torch.equal(loaded(x, d)[1], field(x, d)[1])
    assert torch.equal(loaded.occupancy.mask, field.occupancy.mask)
    assert saved_blend(loaded) is None
    assert json.loads((tmp_path / "m" / "model.json").read_text())["extra"] == {"psnr": 30.0}


def test_dual_field_save_load_round_trip(tmp_path):
    model = make_edit_model(RadianceField(SMALL, torch.Generator().manual_seed(0)), "dual")
    with torch.no_grad():
        for p in model.dynamic_field.parameters():
            p.add_(0.1)
    model.render_blend = (0.05, 0.08)
    save_model(tmp_path / "m", model)
    loaded = load_model(tmp_path / "m")
    assert saved_blend(loaded) == (0.05, 0.08)
    assert all(not p.requires_grad for p in loaded.static_field.parameters())
    x, d = _inputs()
    for blend in (None, (0.05, 0.08)):
        assert torch.equal(loaded.query(x, d, blend=blend)[1], model.query(x, d, blend=blend)[1])


def test_bad_model_folders_raise_clear_errors(tmp_path):
    with pytest.raises(ModelFileError, match="model.json is missing"):
        load_model(tmp_path)
    save_model(tmp_path / "m", RadianceField(SMALL))
    doc = json.loads((tmp_path / "m" / "model.json").read_text())
    (tmp_path / "m" / "model.json").write_text(json.dumps({**doc, "version": 99}))
    with pytest.raises(ModelFileError, match="refit"):
        load_model(tmp_path / "m")
    other = FieldConfig(grid_resolutions=(4,), hidden_width=16)
    (tmp_path / "m" / "model.json").write_text(json.dumps({**doc, "field_config": other.to_dict()}))
    with pytest.raises(ModelFileError, match="does not match"):
        load_model(tmp_path / "m")
    (tmp_path / "m" / "weights.pt").unlink()
    with pytest.raises(ModelFileError, match="weights.pt is missing"):
        load_model(tmp_path / "m")


def test_hash_grid_without_collisions_matches_the_dense_grid():
    # A table as large as the grid is indexed densely: same trilinear result as grid_sample.
    dense = DenseGridEncoding((6,), features=3, generator=torch.Generator().manual_seed(0))
    from dualnerf.encoding import HashGridEncoding

    hashed = HashGridEncoding((6,), features=3, table_size_log2=10)
    with torch.no_grad():
        grid = dense.grids[0][0]                                   # (F, z, y, x)
        hashed.tables[0].copy_(grid.permute(3, 2, 1, 0).reshape(-1, 3))   # flat index (x * R + y) * R + z
    pts = torch.rand(200, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    torch.testing.assert_close(hashed(pts), dense(pts), atol=1e-6, rtol=0)


def test_hashed_level_is_used_and_trainable():
    cfg = FieldConfig(grid_resolutions=(4,), hash_resolutions=(64,), hash_table_size_log2=12, hidden_width=16)
    field = RadianceField(cfg, torch.Generator().manual_seed(0))
    assert field.hash_encoding.tables[0].shape == (4096, 2)
    x, d = _inputs()
    field(x, d)[1].sum().backward()
    assert field.hash_encoding.tables[0].grad.abs().sum() > 0
    assert FieldConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_plane_grid_reads_each_plane_at_the_points_projection():
    # Bilinear interpolation is exact for affine functions of the two in-plane coordinates, so a plane
    # holding a*u + b*v returns exactly that at every point: this pins which axes each plane sees.
    from dualnerf.encoding import PlaneGridEncoding

    enc = PlaneGridEncoding((5, 16), features=1)
    coefficients = {(0, 1): (0.7, -1.1), (0, 2): (2.0, 0.3), (1, 2): (-0.4, 1.5)}
    with torch.no_grad():
        for level, res in enumerate((5, 16)):
            lin = torch.linspace(-1, 1, res)
            v, u = torch.meshgrid(lin, lin, indexing="ij")          # plane dims are (H, W) = (v, u)
            for axis, axes in enumerate(PlaneGridEncoding._AXES):
                a, b = coefficients[axes]
                enc.planes[3 * level + axis][0, 0] = a * u + b * v
    pts = torch.rand(300, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    out = enc(pts)
    assert out.shape == (300, 6) and enc.output_dim == 6
    for level in range(2):
        for axis, axes in enumerate(PlaneGridEncoding._AXES):
            a, b = coefficients[axes]
            torch.testing.assert_close(out[:, 3 * level + axis], a * pts[:, axes[0]] + b * pts[:, axes[1]],
                                       atol=1e-5, rtol=0)


def test_plane_levels_are_used_trainable_and_saved_in_the_config():
    cfg = FieldConfig(grid_resolutions=(4,), plane_resolutions=(32,), hidden_width=16)
    field = RadianceField(cfg, torch.Generator().manual_seed(0))
    assert [tuple(p.shape) for p in field.plane_encoding.planes] == [(1, 2, 32, 32)] * 3
    x, d = _inputs()
    field(x, d)[1].sum().backward()
    assert all(p.grad.abs().sum() > 0 for p in field.plane_encoding.planes)
    assert FieldConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    # A point only moves the four texels around its projection on each plane.
    field.zero_grad()
    field(torch.tensor([[0.1, -0.3, 0.5]]), torch.tensor([[0.0, 0.0, 1.0]]))[0].sum().backward()
    assert all(int((p.grad.abs().sum(dim=(0, 1)) > 0).sum()) <= 4 for p in field.plane_encoding.planes)
