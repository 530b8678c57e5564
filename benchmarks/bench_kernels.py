"""The fused kernels with their vector code and with their scalar code, side by side, on one thread.

    python -m benchmarks.bench_kernels [--points 30000] [--repeats 5]

What a CPU without AVX-512 gains from the AVX2 build (kernels.isa_flags: -mavx2 -mfma and the MLP
layers' AVX2 tiles), or an AVX-512 CPU from its vector code: each kernel timed with
DUALNERF_KERNEL_VECTOR=1 (the vector code this CPU and build have, `vector_code()`) and =0 (the scalar
code), with the ratio, and the two results compared bit for bit (they must be equal; a difference is
printed as an error). Two randomly initialised fields of the default FieldConfig (the kernels' work does
not depend on the values), points uniform over the scene cube:

    inference f_S / dual, fp32 and bf16   field_inference: look-ups and MLPs (renders, f_S in training)
    look-ups pair, backward               a training step's feature look-ups and their backward
    training forward + backward           a field's MLPs under autograd (mlp_train kernels), 1/4 of the points
    render sampler, compositing           ray_samples (128 proposal bins, 48 samples) and composite_rays
                                          for points / 48 rays, 70% of their samples occupied

Medians of --repeats after a warm-up, whatever else runs on the machine (check `uptime`).
"""
from __future__ import annotations

import argparse
import os

import torch

from benchmarks.timing import median_seconds


def _fields():
    from dualnerf.fields import FieldConfig, RadianceField

    def field(seed):
        model = RadianceField(FieldConfig(), torch.Generator().manual_seed(seed))
        with torch.no_grad():                       # tables start near zero: give them values
            for p in model.parameters():
                p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(seed + 1)) * 0.3)
        return model

    return field(0), field(5)


def _cases(a, b, points: int):
    from dualnerf import kernels

    g = torch.Generator().manual_seed(3)
    x = torch.rand(points, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(points, 3, generator=g), dim=-1)
    sh = a.direction_features(d)
    module = kernels.grid_kernel()
    grad = torch.randn(points, sum(e.output_dim for e in a._encodings()), generator=g)
    train = points // 4

    def inference(dual, precision):
        def run():
            with torch.no_grad(), kernels.mlp_precision(precision):
                second = {"second": (b.grid_tables(), b.mlp_layers()), "blend": (0.3, 0.1)} if dual else {}
                return kernels.field_inference(x, sh, a.grid_tables(), a.mlp_layers(), **second)
        return run

    def training():
        a.zero_grad(set_to_none=True)
        sigma, color = a(x[:train], d[:train])
        (sigma.sum() + color.sum()).backward()
        return [p.grad for p in a.parameters() if p.grad is not None]

    rays, n_samples = points // 48, 48
    density = torch.rand(64, 64, 64, generator=g) ** 4 * 400          # sparse, peaked, as a fitted grid
    origins = torch.randn(rays, 3, generator=g) * 2
    dirs = torch.nn.functional.normalize(-origins + 0.3 * torch.randn(rays, 3, generator=g), dim=-1)
    t_start, t_end = torch.full((rays,), 0.5), torch.full((rays,), 4.0)
    jitter = torch.rand(rays, n_samples - 1, generator=g)
    occupied = torch.rand(rays, n_samples, generator=g) < 0.7
    flat = torch.nonzero(occupied.reshape(-1))[:, 0]
    starts = torch.cat([torch.zeros(1, dtype=torch.long), occupied.sum(-1).cumsum(0)])
    h_sigma, h_color = torch.randn(len(flat), generator=g) * 6 + 2, torch.randn(len(flat), 3, generator=g) * 3
    delta, background = torch.rand(rays, n_samples, generator=g) * 0.05, torch.rand(rays, 3, generator=g)

    return {
        "inference f_S fp32": inference(False, "fp32"),
        "inference dual fp32": inference(True, "fp32"),
        "inference f_S bf16": inference(False, "bf16"),
        "inference dual bf16": inference(True, "bf16"),
        "look-ups pair": lambda: module.encode_forward_pair(x, *a.grid_tables(), *b.grid_tables(),
                                                            kernels.vector_path()),
        "look-ups backward": lambda: module.encode_backward(x, grad, *a.grid_tables(), kernels.vector_path()),
        f"training fwd + bwd ({train} points)": training,
        f"render sampler ({rays} rays)": lambda: module.ray_samples(
            origins, dirs, t_start, t_end, density, density > 5.0, 0.5, 128, n_samples, 0.1, jitter,
            kernels.vector_path()),
        f"compositing ({rays} rays)": lambda: module.composite_rays(h_sigma, h_color, flat, starts, delta, background,
                                                                   15.0, kernels.vector_path()),
    }


def _flat(value) -> list[torch.Tensor]:
    if isinstance(value, torch.Tensor):
        return [value]
    return [t for v in value for t in _flat(v)]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=30000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)

    from dualnerf import kernels

    if kernels.grid_kernel() is None:
        print("no compiled kernels here (torch reference path): nothing to compare")
        return
    torch.set_num_threads(1)
    kernels.set_threads(1)
    cases = _cases(*_fields(), args.points)
    load = os.getloadavg()[0]
    print(f"{args.points} points, 1 thread, vector code here: {kernels.vector_code()} "
          f"(build {kernels.build_name()}), load {load:.2f}")
    print(f"{'kernel':34s} {'vector ms':>10s} {'scalar ms':>10s} {'scalar/vector':>14s}  bits")
    previous = os.environ.get("DUALNERF_KERNEL_VECTOR")
    try:
        for name, run in cases.items():
            times, results = {}, {}
            for setting in ("1", "0"):
                os.environ["DUALNERF_KERNEL_VECTOR"] = setting
                times[setting] = 1e3 * median_seconds(run, args.repeats)
                results[setting] = _flat(run())
            same = all(torch.equal(p, q) for p, q in zip(results["1"], results["0"]))
            print(f"{name:34s} {times['1']:10.1f} {times['0']:10.1f} {times['0'] / times['1']:14.2f}  "
                  f"{'same' if same else 'ERROR: the vector and scalar code differ'}")
    finally:
        if previous is None:
            os.environ.pop("DUALNERF_KERNEL_VECTOR", None)
        else:
            os.environ["DUALNERF_KERNEL_VECTOR"] = previous


if __name__ == "__main__":
    main()
