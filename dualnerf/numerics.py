"""What a computation's bits depend on besides its inputs, and how to pin it.

API:
    use_threads(n) -> dict         run the fused kernels on n threads and torch (with its BLAS) on one;
                                   returns what was set, for the manifest
    fingerprint(bf16=False) -> dict   the numerical code paths this process takes (they enter cache keys)
    cpu_fingerprint() -> dict      the part of it that numpy-only code depends on (no torch, no kernels)
    provenance() -> dict           the machine facts behind them (manifests: CPU model and flags, threads)

Why torch runs on one thread: torch's element-wise kernels compute a chunk's tail with scalar code that
rounds differently from their vector code, and its reductions and matmuls split sums by thread, so a
torch result depends on how many threads shared the work. The fused kernels (dualnerf.kernels) are
written so that no output depends on the partition; the heavy work (look-ups, MLPs, sampling,
compositing, Adam) runs there, on as many threads as a step is given, and the same bits come out for any
count. What still differs between machines is the code a library picks for the CPU: torch's vector
width (its CPU capability), the BLAS/vector-math library's branch (chosen by vendor and instruction
set), numpy's SIMD dispatch, AMX tiles for the view updates' bf16 MLPs, and whether the fused kernels
built at all. fingerprint() names all of these; a pipeline stage puts it into its cache key, so two
machines that would compute different bits never share a key.
"""
from __future__ import annotations

import os

from dualnerf.cpu import cpu_info


def use_threads(n: int) -> dict:
    import torch

    from dualnerf import kernels

    n = max(1, int(n))
    torch.set_num_threads(1)
    kernels.set_threads(n)
    return {"kernel_threads": n if kernels.grid_kernel() is not None else 0, "torch_threads": torch.get_num_threads()}


# The instruction-set levels that change which code the libraries run, highest first.
ISA_LEVELS = (("amx_bf16", "amx"), ("avx512f", "avx512"), ("avx2", "avx2"), ("sse4_2", "sse4.2"))


def isa_level() -> str:
    flags = cpu_info()[2]
    return next((name for flag, name in ISA_LEVELS if flag in flags), "baseline")


def _numpy_dispatch() -> str:
    """The SIMD targets numpy's dispatched kernels use on this CPU (NPY_DISABLE_CPU_FEATURES respected)."""
    try:
        from numpy._core import _multiarray_umath as umath
    except ImportError:                 # numpy < 2
        from numpy.core import _multiarray_umath as umath
    features = getattr(umath, "__cpu_features__", {})
    targets = getattr(umath, "__cpu_dispatch__", [])
    return " ".join(t for t in targets if features.get(t)) or "baseline"


def cpu_fingerprint() -> dict:
    """The CPU's vendor and instruction-set level and numpy's SIMD dispatch: what decides the bits of
    numpy (and OpenCV) code."""
    return {"cpu": f"{cpu_info()[0]} {isa_level()}", "numpy_simd": _numpy_dispatch()}


def fingerprint(bf16: bool = False) -> dict:
    """The code paths that decide this process's bits: the fused kernels or the torch reference, the CPU's
    vendor and instruction-set level, torch's CPU capability, numpy's dispatch; with bf16, how the bf16
    MLPs run (AMX tiles or the emulation, which sum in a different order). Not the kernels' AVX-512 or
    portable path, nor the thread count: those give the same bits (tests/test_kernel_threads.py)."""
    import torch

    from dualnerf import kernels

    out = {"kernels": kernels.kernel_name(), **cpu_fingerprint(), "torch_cpu": torch.backends.cpu.get_cpu_capability()}
    if bf16:
        out["bf16_mlp"] = kernels.bf16_path_name()
    return out


def provenance() -> dict:
    """Machine facts for a manifest (not keyed): CPU model and the flags that select code paths, the
    threads in use, overrides from the environment."""
    import torch

    from dualnerf import kernels

    vendor, model, flags = cpu_info()
    selecting = sorted(f for f in flags if f in {"avx2", "fma", "avx512f", "avx512bw", "avx512vl", "avx512_bf16",
                                                 "amx_bf16", "amx_tile", "f16c"})
    overrides = {k: v for k, v in os.environ.items()
                 if k.startswith(("DUALNERF_KERNEL", "ATEN_CPU_CAPABILITY", "MKL_", "NPY_DISABLE"))}
    return {"cpu_model": model, "cpu_vendor": vendor, "cpu_flags": selecting, "torch_threads": torch.get_num_threads(),
            "kernel_threads": kernels.kernel_threads(), "kernel_build": kernels.build_name(),
            "kernel_path": kernels.vector_code() if kernels.vector_path() else "none",
            "environment_overrides": overrides}
