"""LPIPS cost: one 256x192 image pair (evaluation; target <= 50 ms with AlexNet on 2 threads) and the
training loss's share of a ray-batch step (1024 rays, the fit stage's default field, one 32x32 patch).

    python -m benchmarks.bench_lpips [--threads 2] [--repeats 20]

Prints medians of `repeats` timed runs after warm-up, for AlexNet and VGG16; the training steps are
timed interleaved (RGB only, + LPIPS AlexNet, + LPIPS VGG16, repeated) so that load changes hit all
three alike, and their ratios are printed. Timings include whatever else runs on the machine; the load
average is printed next to them.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

from benchmarks.timing import median_seconds


def _median_ms(fn, repeats: int, warmup: int = 3) -> float:
    return 1000.0 * median_seconds(fn, repeats, warmup=warmup)


def pair_timings(repeats: int) -> dict[str, float]:
    import torch

    from dualnerf.lpips import load_lpips

    generator = torch.Generator().manual_seed(0)
    a = torch.rand(1, 3, 192, 256, generator=generator) * 2 - 1
    b = torch.rand(1, 3, 192, 256, generator=generator) * 2 - 1
    out = {}
    for net in ("alex", "vgg"):
        model = load_lpips(net)

        def run(model=model):
            with torch.inference_mode():
                model(a, b)
        out[net] = _median_ms(run, repeats)
    return out


def _views(n=4, h=96, w=128):
    import torch

    from dualnerf.cameras import Cameras

    images = torch.rand(n, h, w, 3, generator=torch.Generator().manual_seed(0))
    c2w = torch.eye(4).repeat(n, 1, 1)
    c2w[:, 0, 3] = torch.linspace(-0.3, 0.3, n)
    c2w[:, 2, 3] = -2.5
    return images, Cameras(c2w, torch.tensor([[100.0, 100.0, w / 2, h / 2]] * n), torch.full((n,), 0.1),
                           torch.full((n,), 5.0), w, h)


def step_timings(repeats: int) -> dict[str, float]:
    import torch

    from dualnerf.fields import RadianceField
    from dualnerf.training import RayTrainer, TrainConfig
    from stages.fit import FitParams, field_config

    images, cams = _views()
    settings = {"RGB only": {}, "+ LPIPS alex": {"lpips_weight": 1.0, "lpips_net": "alex"},
                "+ LPIPS vgg": {"lpips_weight": 1.0, "lpips_net": "vgg"}}
    trainers = {}
    for name, extra in settings.items():
        g = torch.Generator().manual_seed(0)
        trainers[name] = RayTrainer(RadianceField(field_config(FitParams()), g), images, cams,
                                    TrainConfig(rays_per_batch=1024, **extra), g)
    step = {name: 0 for name in settings}
    times = {name: [] for name in settings}
    for round_ in range(repeats + 3):
        for name, trainer in trainers.items():
            start = time.perf_counter()
            trainer.step(step[name])
            step[name] += 1
            if round_ >= 3:                 # warm-up rounds (occupancy warm-up, allocator)
                times[name].append(time.perf_counter() - start)
    return {name: 1000.0 * statistics.median(t) for name, t in times.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_lpips")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args([] if argv is None else argv)

    import torch

    torch.set_num_threads(args.threads)
    print(f"torch threads: {args.threads}; load average before: {os.getloadavg()[0]:.2f} "
          f"(timings include other load)")
    pairs = pair_timings(args.repeats)
    for net, ms in pairs.items():
        target = "  (target <= 50 ms)" if net == "alex" else ""
        print(f"LPIPS {net:4s} 256x192 pair, forward: median {ms:6.1f} ms{target}")
    steps = step_timings(max(5, args.repeats // 2))
    base = steps["RGB only"]
    for name, ms in steps.items():
        print(f"train step, 1024 rays, fit-default field, {name:13s}: median {ms:6.1f} ms  ({ms / base:.2f}x)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
