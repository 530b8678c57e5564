"""What the stages share about numerics: the code paths that enter their keys and the threads they run on.

    TorchNumerics      mixin for stages that compute with torch and the fused kernels: their key carries
                       dualnerf.numerics.fingerprint() (bf16 path included where `uses_bf16(params)`),
                       their manifest dualnerf.numerics.provenance()
    NumpyNumerics      mixin for numpy/OpenCV-only stages: dualnerf.numerics.cpu_fingerprint()
    use_step_threads(ctx, requested=0) -> int   the kernels on `requested` threads (0: what the engine
                       grants), torch on one; recorded in the manifest. The results do not depend on it.
    semantic_values(params, nonsemantic) -> dict   the params a published file may echo (the keyed ones:
                       a thread count in an output would make one key's bytes differ between runs)
    FILE_COMPARERS     {suffix: (cached, recomputed) -> description} for `dualnerf cache verify
                       --recompute`: how far apart two images or two checkpoints are
"""
from __future__ import annotations

from typing import Any


class TorchNumerics:
    @classmethod
    def uses_bf16(cls, params: Any) -> bool:
        return False

    @classmethod
    def runtime_environment(cls, params: Any) -> dict[str, Any]:
        from dualnerf.numerics import fingerprint

        return fingerprint(bf16=cls.uses_bf16(params))

    @classmethod
    def provenance(cls) -> dict[str, Any]:
        from dualnerf.numerics import provenance

        return provenance()


class NumpyNumerics:
    @classmethod
    def runtime_environment(cls, params: Any) -> dict[str, Any]:
        from dualnerf.numerics import cpu_fingerprint

        return cpu_fingerprint()

    @classmethod
    def provenance(cls) -> dict[str, Any]:
        from dualnerf.numerics import provenance

        return {k: v for k, v in provenance().items() if k.startswith("cpu")}


def use_step_threads(ctx, requested: int = 0) -> int:
    from dualnerf.numerics import use_threads

    threads = max(1, requested or ctx.threads)
    ctx.record(threads=use_threads(threads))
    return threads


def semantic_values(params: Any, nonsemantic: frozenset[str]) -> dict[str, Any]:
    from dataclasses import asdict

    return {k: v for k, v in asdict(params).items() if k not in nonsemantic}


def image_difference(a, b) -> str:
    import cv2
    import numpy as np

    x, y = (cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (a, b))
    if x is None or y is None or x.shape != y.shape:
        return f"images of different shapes ({None if x is None else x.shape} vs {None if y is None else y.shape})"
    delta = np.abs(x.astype(np.int32) - y.astype(np.int32))
    return f"max pixel difference {int(delta.max())}/255 in {int((delta.max(axis=-1) > 0).sum())} of " \
           f"{delta.shape[0] * delta.shape[1]} pixels"


def tensor_difference(a, b) -> str:
    import torch

    x, y = (torch.load(p, map_location="cpu", weights_only=True) for p in (a, b))
    flat_x, flat_y = dict(_tensors(x)), dict(_tensors(y))
    worst, name, count = 0.0, None, 0
    for k in flat_x.keys() & flat_y.keys():
        if flat_x[k].shape == flat_y[k].shape and not torch.equal(flat_x[k], flat_y[k]):
            count += 1
            d = float((flat_x[k].double() - flat_y[k].double()).abs().max())
            if d >= worst:
                worst, name = d, k
    extra = "" if flat_x.keys() == flat_y.keys() else "; the tensors' names differ"
    return f"{count} of {len(flat_x)} tensors differ, max abs difference {worst:.3g} (in {name}){extra}"


def _tensors(value, prefix=""):
    import torch

    if isinstance(value, torch.Tensor):
        yield prefix, value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from _tensors(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _tensors(v, f"{prefix}[{i}]")


FILE_COMPARERS = {".png": image_difference, ".pt": tensor_difference}
