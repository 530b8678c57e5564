"""The fused inference kernel (dualnerf.kernels.field_inference: look-ups + MLPs in one pass, no autograd)
against the torch path it replaces in renders (features() + heads(), DualField's eqs. 4-5)."""
import shutil

import pytest
import torch

from dualnerf import kernels
from dualnerf.dual_field import DualField
from dualnerf.fields import FieldConfig, RadianceField

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the fused kernel cannot be built here")

# Widths that are not multiples of the kernel's 16-float vectors (padding, masked stores) next to the
# default 64; 131 points leave a partial row tile and a partial block.
CONFIGS = [FieldConfig(grid_resolutions=(4, 9, 16), plane_resolutions=(8, 32), hidden_width=64),
           FieldConfig(grid_resolutions=(5, 12), plane_resolutions=(16,), hidden_width=24, geo_features=7,
                       direction_degree=3)]


def field(config, seed) -> RadianceField:
    model = RadianceField(config, torch.Generator().manual_seed(seed))
    with torch.no_grad():          # values of order 1 everywhere (the initial 1e-4 grids would hide errors)
        g = torch.Generator().manual_seed(seed + 1)
        for p in model.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=g))
    return model


def samples(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 2.4 - 1.2          # some outside the cube: border padding
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, d


def reference(model, x, d):
    with torch.no_grad():
        return model.heads(model.reference_features(x), model.direction_features(d))


@pytest.mark.parametrize("config", CONFIGS)
def test_single_field_inference_matches_features_and_heads(config):
    model, (x, d) = field(config, 0), samples(3000)
    with torch.no_grad():
        assert model.can_infer(x)
        h_sigma, h_color = model(x, d)
    ref_sigma, ref_color = reference(model, x, d)
    assert h_sigma.shape == ref_sigma.shape and h_color.shape == ref_color.shape
    assert ref_color.abs().max() > 1.0                # non-trivial values
    torch.testing.assert_close(h_sigma, ref_sigma, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(h_color, ref_color, atol=2e-5, rtol=1e-5)


@pytest.mark.parametrize("config", CONFIGS)
def test_dual_inference_matches_the_autograd_fusion(config):
    model, (x, d) = DualField(field(config, 0), field(config, 10)), samples(2000, seed=1)
    expected = model.query(x, d, blend=(0.3, 0.6), retreat=0.5)          # autograd on: torch path
    with torch.no_grad():
        fused = model.query(x, d, blend=(0.3, 0.6), retreat=0.5)
        static = model.static_field(x, d)
        assert all(torch.equal(a, b) for a, b in zip(model.query(x, d, blend=(0.0, 0.0)), static))
        full = model.query(x, d, blend=(1.0, 1.0))
        dynamic = model.dynamic_field(x, d)
    for got, want in zip(fused, expected):
        torch.testing.assert_close(got, want.detach(), atol=2e-5, rtol=1e-5)
    assert all(torch.equal(a, b) for a, b in zip(full, dynamic))      # w = 1: f_D alone, exactly


def test_a_samples_result_does_not_depend_on_its_batch_or_threads():
    model, (x, d) = field(CONFIGS[0], 3), samples(1000, seed=2)
    with torch.no_grad():
        whole = model(x, d)
        order = torch.randperm(len(x), generator=torch.Generator().manual_seed(4))
        shuffled = model(x[order], d[order])
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(1 if threads > 1 else 2)
            other_threads = model(x, d)
        finally:
            torch.set_num_threads(threads)
        part = model(x[7:70], d[7:70])
    for a, b, c, p in zip(whole, shuffled, other_threads, part):
        assert torch.equal(a[order], b) and torch.equal(a, c) and torch.equal(a[7:70], p)


def test_portable_and_vector_layer_code_give_the_same_bits(monkeypatch):
    if kernels.vector_code() == "none":
        pytest.skip("this CPU and build have neither AVX-512 nor the AVX2 layer tiles: only the scalar code runs")
    model, (x, d) = field(CONFIGS[1], 5), samples(777, seed=3)
    with torch.no_grad():
        vector = model(x, d)
        monkeypatch.setenv("DUALNERF_KERNEL_VECTOR", "0")
        portable = model(x, d)
    assert all(torch.equal(a, b) for a, b in zip(vector, portable))


def test_inference_refuses_autograd_and_is_not_used_for_training():
    model, (x, d) = field(CONFIGS[0], 6), samples(50)
    with pytest.raises(ValueError, match="no_grad"):
        kernels.field_inference(x, model.direction_features(d), model.grid_tables(), model.mlp_layers())
    assert not model.can_infer(x)
    h_sigma, _ = model(x, d)
    assert h_sigma.requires_grad                     # the autograd path ran
    model.requires_grad_(False)                      # a frozen field (f_S) needs no graph: the kernel runs
    assert model.can_infer(x) and not model(x, d)[0].requires_grad
    dual = DualField(field(CONFIGS[0], 6), field(CONFIGS[0], 7))
    h_sigma, _ = dual.query(x, d, blend=(0.1, 0.1))
    assert h_sigma.requires_grad                     # a training step: f_D through autograd


def test_heads_without_autograd_run_the_kernels_mlps():
    # The frozen f_S in a dual-field training step: its MLPs on the pair kernel's features.
    model, (x, d) = field(CONFIGS[1], 8), samples(500, seed=5)
    sh = model.direction_features(d)
    with torch.no_grad():
        features = model.features(x)
        fused = model.heads(features, sh)
        whole = model(x, d)
    with torch.enable_grad():
        reference = model.heads(features, sh)
    assert all(torch.equal(a, b) for a, b in zip(fused, whole))       # the same MLP code as field_inference
    for got, want in zip(fused, reference):
        torch.testing.assert_close(got, want.detach(), atol=2e-5, rtol=1e-5)


def test_a_render_session_reads_interleaved_tables_with_the_same_bits():
    # render_view wraps an image in DualField.render_session(): both fields' tables interleaved once.
    model, (x, d) = DualField(field(CONFIGS[0], 20), field(CONFIGS[0], 21)), samples(1500, seed=9)
    with torch.no_grad():
        separate = model.query(x, d, blend=(0.3, 0.6))
        with model.render_session():
            assert model._interleaved is not None and len(model._interleaved) == 3 + 3 * 2
            interleaved = model.query(x, d, blend=(0.3, 0.6))
        assert model._interleaved is None                     # never outlives the render
    assert all(torch.equal(a, b) for a, b in zip(separate, interleaved))
    table = kernels.interleave_pair(model.static_field.grid_tables(),
                                                               model.dynamic_field.grid_tables())[0]
    grid_s, grid_d = model.static_field.grid_tables()[0][0], model.dynamic_field.grid_tables()[0][0]
    cell = (1, 2, 3)                                            # (z, y, x) of the first dense grid
    flat = (cell[0] * grid_s.shape[3] + cell[1]) * grid_s.shape[4] + cell[2]
    expected = torch.cat([grid_s[0, :, cell[0], cell[1], cell[2]], grid_d[0, :, cell[0], cell[1], cell[2]]])
    assert torch.equal(table[4 * flat:4 * flat + 4], expected)


def test_kept_interleaved_tables_follow_changes_of_either_field():
    # Sessions keep the interleaved tables and rewrite f_D's half each time (f_S's when it changed): after
    # a training-like change of f_D, and after an in-place change of the frozen f_S (a checkpoint load),
    # a session still equals the separate tables' result, and reuses its memory.
    model, (x, d) = DualField(field(CONFIGS[0], 24), field(CONFIGS[0], 25)), samples(900, seed=12)
    with torch.no_grad():
        with model.render_session():
            first = model._interleaved
        for changed in (model.dynamic_field, model.static_field):
            for table in (*changed.grid_tables()[0], *changed.grid_tables()[1]):
                table.add_(0.25 * torch.randn(table.shape, generator=torch.Generator().manual_seed(13)))
            separate = model.query(x, d, blend=(0.4, 0.5))
            with model.render_session():
                assert model._interleaved is first                  # the same buffers, rewritten
                interleaved = model.query(x, d, blend=(0.4, 0.5))
            assert all(torch.equal(a, b) for a, b in zip(separate, interleaved))


def test_per_ray_direction_features_with_an_index_equal_the_gathered_rows():
    # A render passes one SH row per ray and each sample's ray instead of an (M, S) gathered copy.
    model, (x, d) = DualField(field(CONFIGS[0], 22), field(CONFIGS[0], 23)), samples(1200, seed=10)
    per_ray = model.static_field.direction_features(d[:40])
    ray_id = torch.randint(40, (len(x),), generator=torch.Generator().manual_seed(11))
    with torch.no_grad():
        for blend in (None, (0.2, 0.7)):
            gathered = model.query(x, None, blend=blend, dir_features=per_ray[ray_id])
            indexed = model.query(x, None, blend=blend, dir_features=per_ray, dir_index=ray_id)
            assert all(torch.equal(a, b) for a, b in zip(gathered, indexed))
        with pytest.raises(RuntimeError, match="out of range"):
            kernels.field_inference(x, per_ray, model.static_field.grid_tables(), model.static_field.mlp_layers(),
                                    sh_index=ray_id + 1)
    expected = model.query(x, None, blend=(0.2, 0.7), dir_features=per_ray[ray_id])    # autograd: torch path
    got = model.query(x, None, blend=(0.2, 0.7), dir_features=per_ray, dir_index=ray_id)
    assert all(torch.equal(a, b) for a, b in zip(expected, got))


def bf16_reference(model, x, d):
    """The bf16 MLPs computed in torch, independently of the kernel: each layer's inputs and weights
    rounded to bfloat16 by torch's conversion (round to nearest even), then float64 sums plus the bias."""
    layers = model.mlp_layers()

    def layer(index, inputs, relu_inputs=False):
        inputs = inputs.clamp(min=0.0) if relu_inputs else inputs
        weight = layers[index].weight.detach().bfloat16().double()
        return inputs.bfloat16().double() @ weight.t() + layers[index].bias.detach().double()

    with torch.no_grad():
        features, sh = model.reference_features(x), model.direction_features(d)
        density = layer(1, layer(0, features), relu_inputs=True)
        color_in = torch.cat([density[:, 1:], sh.double()], dim=-1)
        return density[:, 0], layer(3, layer(2, color_in), relu_inputs=True)


def agree_to_bf16_rounding(got, want, scale):
    """Sums in another order can round a hidden value to the neighbouring bf16 number (0.4% apart) on a
    few rows; everywhere else the results agree to float32 rounding."""
    diff = (got.double() - want.double()).abs() / scale
    assert torch.quantile(diff.flatten(), 0.95) < 1e-5
    assert diff.max() < 2e-2


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("tiles", ["1", "0"])
def test_bf16_mlps_equal_the_rounded_torch_computation(config, tiles, monkeypatch):
    if tiles == "1" and kernels.bf16_path_name() != "amx-tiles":
        pytest.skip("this CPU has no AMX tiles: only the bf16 emulation runs")
    monkeypatch.setenv("DUALNERF_KERNEL_AMX", tiles)
    model, (x, d) = field(config, 30), samples(2131, seed=12)
    want_sigma, want_color = bf16_reference(model, x, d)
    _, exact_color = reference(model, x, d)
    with torch.no_grad(), kernels.mlp_precision("bf16"):
        h_sigma, h_color = model(x, d)
    scale = exact_color.abs().max()
    agree_to_bf16_rounding(h_sigma, want_sigma, scale)
    agree_to_bf16_rounding(h_color, want_color, scale)
    # ... and the rounding is real: bf16 is far from float32 (the kernel did not run its float32 code)
    rounding = (h_color.double() - exact_color.double()).abs().mean() / scale
    assert 1e-4 < rounding < 2e-2


def test_bf16_tiles_and_emulation_agree_and_fp32_stays_exact(monkeypatch):
    if kernels.bf16_path_name() != "amx-tiles":
        pytest.skip("this CPU has no AMX tiles")
    model = DualField(field(CONFIGS[0], 31), field(CONFIGS[0], 32))
    x, d = samples(1777, seed=13)
    with torch.no_grad():
        fp32 = model.query(x, d, blend=(0.3, 0.6))
        with kernels.mlp_precision("bf16"):
            tiles = model.query(x, d, blend=(0.3, 0.6))
            monkeypatch.setenv("DUALNERF_KERNEL_AMX", "0")
            emulated = model.query(x, d, blend=(0.3, 0.6))
        assert kernels.current_mlp_precision() == "fp32"        # the context restores the precision
        after = model.query(x, d, blend=(0.3, 0.6))
    scale = fp32[1].abs().max()
    for a, b in zip(tiles, emulated):
        agree_to_bf16_rounding(a, b, scale)
    assert all(torch.equal(a, b) for a, b in zip(fp32, after))
    with pytest.raises(ValueError, match="bf16"), kernels.mlp_precision("fp16"):
        pass


def test_a_bf16_render_stays_within_a_fraction_of_an_8_bit_step():
    from dualnerf.rendering import render_view

    model = DualField(field(CONFIGS[0], 33), field(CONFIGS[0], 34))
    for f in (model.static_field, model.dynamic_field):
        f.occupancy.mask.fill_(True)
        f.occupancy.density.fill_(1.0)
    model.occupancy.mask.fill_(True)
    model.occupancy.density.fill_(1.0)
    c2w = torch.eye(4)
    c2w[2, 3] = -2.5                                  # looking down +z at the cube
    intrinsics = torch.tensor([24.0, 24.0, 16.0, 12.0])
    fp32 = render_view(model, c2w, intrinsics, 32, 24, 0.5, 4.0, blend=(0.2, 0.2))
    bf16 = render_view(model, c2w, intrinsics, 32, 24, 0.5, 4.0, blend=(0.2, 0.2), mlp_precision="bf16")
    diff = (fp32 - bf16).abs()
    assert fp32.std() > 0.05                          # the field is in view, not just background
    assert 0.0 < diff.mean() < 1.0 / 255.0


@pytest.mark.parametrize("config", CONFIGS)
def test_density_only_inference_is_the_full_passes_h_sigma(config):
    # The occupancy refresh needs h_sigma alone: the colour MLPs are skipped, h_sigma is the same bits as
    # the full pass's, and close to the torch path (features + density MLP), for f_S and the dual field.
    static, dynamic = field(config, 30), field(config, 31)
    model, (x, d) = DualField(static, dynamic), samples(700, seed=14)
    with torch.no_grad():
        sh = static.direction_features(d)
        empty = static.empty_direction_features(x)
        for second, blend in ((None, (0.0, 0.0)), ((dynamic.grid_tables(), dynamic.mlp_layers()), (0.3, 0.8))):
            full = kernels.field_inference(x, sh, static.grid_tables(), static.mlp_layers(), second=second,
                                           blend=blend)
            sigma, color = kernels.field_inference(x, empty, static.grid_tables(), static.mlp_layers(),
                                                   second=second, blend=blend, density_only=True)
            assert torch.equal(sigma, full[0]) and color.shape == (0, 3)
        torch.testing.assert_close(static.density_hidden(x), static.density_head(static.reference_features(x)),
                                   atol=2e-5, rtol=1e-5)
        expected = ((1 - 0.3) * static.density_head(static.reference_features(x))
                    + 0.3 * dynamic.density_head(dynamic.reference_features(x)))
        torch.testing.assert_close(model.query_density(x, blend=(0.6, 0.9), retreat=0.5), expected,
                                   atol=2e-5, rtol=1e-5)
