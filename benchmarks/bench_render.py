"""Full-image render speed of the static and the dual field against the machine's stated limit.

    python -m benchmarks.bench_render [--scene campsite] [--fit-iterations 600] [--fit-dir DIR]
                                      [--render-samples 48] [--repeats 5] [--threads 2]

Renders one training view at the dataset size (campsite: 256x192, the IDU view update) from f_S
(fitted once by the fit stage and cached, as in benchmarks.profile_edit) and from the dual field at its
saturated blend (f_D = f_S perturbed, so both fields really run), in float32 (evaluation renders) and
with bf16 MLPs (the edit stage's view updates), and prints per model: median seconds
per render, renders/s, evaluated field samples per image, field samples/s, and the ratio of the measured
time to the limit

    limit = FLOPs per field sample x field samples per image / measured FLOP/s

FLOPs per field sample are counted from the FieldConfig (dualnerf.flops: MLP multiply-adds x 2 plus the
interpolation arithmetic); the dual field counts two field evaluations per sample. The machine's FLOP/s
is a timed float32 matmul (1024^3, torch's BLAS on the same threads), i.e. a peak the tiny 64-wide MLPs
and the memory-bound grid look-ups cannot reach: a ratio of ~3-6 is near what this design can do.
Timings include whatever else runs on the machine (check `uptime`).
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from benchmarks.profile_edit import add_fitted_field_arguments, load_fitted_field


def matmul_flops(threads: int, size: int = 1024, repeats: int = 5) -> float:
    """Measured float32 FLOP/s of a size^3 matmul (median of `repeats`)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)      # the BLAS on the threads the kernels get (the stages keep torch on one)
    a = torch.randn(size, size)
    b = torch.randn(size, size)
    a @ b
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - start)
    torch.set_num_threads(previous)
    return 2.0 * size ** 3 / statistics.median(times)


def _render(model, dataset, view, blend, termination_eps, precision):
    from dualnerf.rendering import render_view

    return render_view(model, dataset.c2w[view], dataset.intrinsics[view], dataset.width, dataset.height,
                       float(dataset.near[view]), float(dataset.far[view]), blend=blend,
                       termination_eps=termination_eps, mlp_precision=precision)


def _evaluated_samples(model, dataset, view, blend, termination_eps) -> int:
    """Field samples one render evaluates (occupied interval midpoints), counted with the same sampler."""
    import torch

    from dualnerf import rendering
    from dualnerf.cameras import view_rays

    origins, dirs = view_rays(dataset.c2w[view], dataset.intrinsics[view], dataset.width, dataset.height)
    total = 0
    with torch.no_grad():
        for s in range(0, origins.shape[0], 8192):
            total += rendering.render_rays(model, origins[s:s + 8192], dirs[s:s + 8192], float(dataset.near[view]),
                                           float(dataset.far[view]), blend=blend,
                                           samples_per_ray=model.config.render_samples_per_ray,
                                           termination_eps=termination_eps)["evaluated"]
    return total


def main(argv: list[str] | None = None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_render")
    add_fitted_field_arguments(parser, threads=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--termination", action="store_true",
                        help="also time renders with early ray termination (ERT, termination_eps=1e-4)")
    args = parser.parse_args([] if argv is None else argv)

    import torch

    from dualnerf import kernels
    from dualnerf.dual_field import make_edit_model
    from dualnerf.flops import field_flops_per_sample

    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        _, dataset, static = load_fitted_field(args, Path(tmp))
    dual = make_edit_model(static, "dual")
    with torch.no_grad():
        g = torch.Generator().manual_seed(0)
        for p in dual.dynamic_field.parameters():
            p.add_(1e-3 * torch.randn(p.shape, generator=g))
    flops = matmul_flops(args.threads)
    per_sample = field_flops_per_sample(static.config)
    view = int(dataset.indices("train")[0])
    print(f"{args.scene} {dataset.width}x{dataset.height}, {static.config.render_samples_per_ray} samples/ray, "
          f"occupancy {static.occupancy.fraction():.2f}; matmul {flops / 1e9:.1f} GFLOP/s; "
          f"{per_sample:.0f} FLOPs per field sample")
    header = ("model", "s/render", "renders/s", "samples", "samples/s", "limit s", "ratio")
    print("  ".join(f"{h:>12s}" for h in header))
    from dualnerf.rendering import RENDER_TERMINATION_EPS

    # fp32: evaluation renders; bf16: the edit stage's view updates (update_precision, bf16 MLPs).
    cases = [("f_S", static, None, 1, 0.0, "fp32"), ("dual field", dual, (0.1, 0.1), 2, 0.0, "fp32"),
             ("f_S bf16", static, None, 1, 0.0, "bf16"), ("dual bf16", dual, (0.1, 0.1), 2, 0.0, "bf16")]
    if args.termination:
        cases += [("f_S ERT", static, None, 1, RENDER_TERMINATION_EPS, "fp32"),
                  ("dual ERT", dual, (0.1, 0.1), 2, RENDER_TERMINATION_EPS, "fp32")]
    for label, model, blend, n_fields, eps, precision in cases:
        _render(model, dataset, view, blend, eps, precision)                    # warm-up
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            _render(model, dataset, view, blend, eps, precision)
            times.append(time.perf_counter() - start)
        seconds = statistics.median(times)
        samples = _evaluated_samples(model, dataset, view, blend, eps)
        limit = n_fields * per_sample * samples / flops
        row = (label, f"{seconds:.3f}", f"{1 / seconds:.2f}", f"{samples / 1e6:.2f}M",
               f"{n_fields * samples / seconds / 1e6:.2f}M", f"{limit:.3f}", f"{seconds / limit:.1f}")
        print("  ".join(f"{c:>12s}" for c in row), flush=True)
    print("samples/s counts field evaluations (two per sample for the dual field); 'bf16': bfloat16 MLPs "
          f"({kernels.bf16_path_name()}), as the edit stage's view updates render (the limit stays the float32 "
          "one); 'ERT': early ray termination (termination_eps=1e-4); target: dual-field render <= 1 s")


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
