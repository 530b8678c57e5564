"""Fused CPU kernels for the field's feature-grid look-ups, with the plain torch code as the reference.

API:
    grid_kernel() -> module | None      the compiled kernel (built on first use), or None when unavailable
    kernel_name() -> str                "fused-cpp" or "torch-reference": what features() runs (for manifests)
    fused_grid_features(x (M,3), dense_grids, planes) -> (M, F)   autograd-aware: gradients reach the tables
    fused_pair_features(x, dense_a, planes_a, dense_b, planes_b) -> (F_a detached, F_b)   a DualField's two
        fields in one pass (the index and weight maths shared; f_S, the first, is frozen)
    can_fuse(x, features) -> bool;  can_fuse_pair(x, features) -> bool

Why: a field evaluation reads 13 feature tables (4 dense grids, 9 planes). Through F.grid_sample that is
13 calls with a (C, M) intermediate, a transpose and a concatenation each; the profile
(benchmarks.profile_edit) put the look-ups at ~60% of a render. `grid_encoding.cpp` does them in one pass
over the points on channels-last tables, table by table within blocks of neighbouring samples, and its
backward accumulates each table's gradient on one thread in point order (no races, repeatable sums).

The kernel is compiled with torch.utils.cpp_extension on first use (~30 s, cached under
$TORCH_EXTENSIONS_DIR or ~/.cache/torch_extensions). Without a C++ compiler, on a non-CPU device, or with
DUALNERF_KERNELS=0 the reference path (dualnerf.encoding's modules on F.grid_sample) runs instead; the two
agree to float32 rounding (tests/test_grid_kernel.py), not bit for bit, so results record which one ran.
"""
from __future__ import annotations

import logging
import os
import subprocess
import threading
from pathlib import Path

import torch

_SOURCE = Path(__file__).with_name("grid_encoding.cpp")
_lock = threading.Lock()
_state: dict = {}
log = logging.getLogger(__name__)


def grid_kernel():
    """The compiled extension module, or None (reference path). Built once per process, then cached on disk."""
    if os.environ.get("DUALNERF_KERNELS", "1") == "0":
        return None
    with _lock:
        if "module" not in _state:
            _state["module"] = _build()
    return _state["module"]


def _build():
    try:
        from torch.utils.cpp_extension import load

        return load("dualnerf_grid_encoding", [str(_SOURCE)],
                    extra_cflags=["-O3", "-fopenmp", "-ffp-contract=off"], extra_ldflags=["-fopenmp"], verbose=False)
    # No compiler, no ninja, a failed build: the reference path still works.
    except (OSError, RuntimeError, ImportError, subprocess.CalledProcessError) as error:
        log.warning("dualnerf: the fused grid-encoding kernel could not be built (%s); using the plain torch "
                    "reference path, which is ~2x slower. Install a C++ compiler and ninja, or set "
                    "DUALNERF_KERNELS=0 to silence this.", str(error).splitlines()[0] if str(error) else error)
        return None


def kernel_name() -> str:
    return "fused-cpp" if grid_kernel() is not None else "torch-reference"


class _FusedGridFeatures(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, n_dense, *tables):
        module = grid_kernel()
        dense, planes = list(tables[:n_dense]), list(tables[n_dense:])
        ctx.save_for_backward(x, *tables)
        ctx.n_dense = n_dense
        return module.encode_forward(x, dense, planes)

    @staticmethod
    def backward(ctx, grad):
        x, *tables = ctx.saved_tensors
        n = ctx.n_dense
        grads = grid_kernel().encode_backward(x, grad, list(tables[:n]), list(tables[n:]))
        # No gradient for the sample positions: they come from rays, which are never trained.
        return (None, None, *grads)


class _FusedPairFeatures(torch.autograd.Function):
    """Two fields' features in one pass; the first field (the frozen f_S) gets no gradient."""

    @staticmethod
    def forward(ctx, x, n_dense, n_tables, *tables):
        first, second = tables[:n_tables], tables[n_tables:]
        out_first, out_second = grid_kernel().encode_forward_pair(
            x, list(first[:n_dense]), list(first[n_dense:]), list(second[:n_dense]), list(second[n_dense:]))
        ctx.mark_non_differentiable(out_first)
        ctx.save_for_backward(x, *second)
        ctx.n_dense, ctx.n_tables = n_dense, n_tables
        return out_first, out_second

    @staticmethod
    def backward(ctx, grad_first, grad_second):
        x, *second = ctx.saved_tensors
        n = ctx.n_dense
        grads = grid_kernel().encode_backward(x, grad_second, list(second[:n]), list(second[n:]))
        return (None, None, None, *([None] * ctx.n_tables), *grads)


def fused_pair_features(x: torch.Tensor, first_dense, first_planes, second_dense, second_planes):
    """fused_grid_features for two fields with equal tables at the same points, in one pass (each corner's
    index and weight computed once): (features of the first, detached; features of the second, with
    gradients to its tables). Each equals fused_grid_features of that field bit for bit."""
    if x.requires_grad:
        raise ValueError("fused_pair_features: no gradient w.r.t. the sample positions")
    first, second = [*first_dense, *first_planes], [*second_dense, *second_planes]
    if len(first) != len(second):
        raise ValueError("fused_pair_features: the two fields must have the same tables")
    return _FusedPairFeatures.apply(x, len(first_dense), len(first), *first, *second)


def fused_grid_features(x: torch.Tensor, dense_grids, planes) -> torch.Tensor:
    """Features of points x: the dense grids' (each C columns, in order), then the planes' (level-major,
    xy/xz/yz within a level), as DenseGridEncoding and PlaneGridEncoding concatenated."""
    if x.requires_grad:
        raise ValueError("fused_grid_features: no gradient w.r.t. the sample positions; use the reference "
                         "encodings (dualnerf.encoding) when x requires grad")
    return _FusedGridFeatures.apply(x, len(dense_grids), *dense_grids, *planes)


def can_fuse(x: torch.Tensor, features: int) -> bool:
    """The kernel handles float32 CPU points with 1, 2, 4 or 8 features per table and no grad w.r.t. x."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and not x.requires_grad
            and features in (1, 2, 4, 8) and grid_kernel() is not None)


def can_fuse_pair(x: torch.Tensor, features: int) -> bool:
    """fused_pair_features applies: as can_fuse, with 2 features per table (the kernel's pair path)."""
    return features == 2 and can_fuse(x, features)
