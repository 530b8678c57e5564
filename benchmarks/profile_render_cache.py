"""How much of a full-image render is cache misses: the same samples with the tables shrunk to fit in cache.

    python -m benchmarks.profile_render_cache [--scene campsite] [--fit-iterations 600] [--fit-dir DIR]
                                              [--render-samples 48] [--repeats 5] [--threads 1]

Renders one training view from the fitted f_S (cached as in benchmarks.profile_edit) and records every
call of the fused inference kernel (points, per-ray SH features, each sample's ray). It then replays those
calls, f_S alone and the dual field (interleaved tables, as render_view runs it), twice: with the fitted
tables (~52 MB per field), and with the same MLPs on tables shrunk to 4-32^3 grids and 16-64^2 planes
(~0.2 MB: every look-up hits in cache). The look-ups do the same arithmetic either way, so the time
difference is what the cache misses of the real tables cost. bf16 MLPs, as the edit stage's view
updates run them. Timings include whatever else runs on the machine (check `uptime`).

--compare REV runs the same measurement as commit REV has it (its own kernel build, the same f_S and
view; benchmarks.revision), alternating with this checkout's for --rounds rounds (A B A B: a slow spell
of a shared host hits both), and prints the fitted-table times side by side with each round's ratio.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
from pathlib import Path

from benchmarks.profile_edit import add_fitted_field_arguments, load_fitted_field
from benchmarks.timing import median_seconds


def _record_inference_calls(model, dataset, view) -> list[tuple]:
    """(x, sh, sh_index) of every field_inference call of one render of `view`."""
    import torch

    from dualnerf import kernels
    from dualnerf.rendering import render_view

    calls, original = [], kernels.field_inference

    def record(x, sh, *args, **kwargs):
        index = kwargs.get("sh_index")
        calls.append((x.clone(), sh.clone(), None if index is None else index.clone()))
        return original(x, sh, *args, **kwargs)

    kernels.field_inference = record
    try:
        with torch.no_grad():
            render_view(model, dataset.c2w[view], dataset.intrinsics[view], dataset.width, dataset.height,
                        float(dataset.near[view]), float(dataset.far[view]))
    finally:
        kernels.field_inference = original
    return calls


def _replay_seconds(model, blend, calls, repeats: int) -> float:
    import torch

    from dualnerf import kernels

    def replay():
        with torch.no_grad(), kernels.mlp_precision("bf16"), model.render_session():
            for x, sh, index in calls:
                model.query(x, None, blend=blend, dir_features=sh, dir_index=index)

    return median_seconds(replay, repeats)


def main(argv: list[str] | None = None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.profile_render_cache")
    add_fitted_field_arguments(parser, threads=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--compare", default="none", help="an earlier commit to time alternately ('none': skip)")
    parser.add_argument("--rounds", type=int, default=3, help="with --compare: A B rounds")
    args = parser.parse_args([] if argv is None else argv)

    import torch

    from dualnerf.dual_field import make_edit_model
    from dualnerf.fields import RadianceField

    with tempfile.TemporaryDirectory(prefix="profile-render-cache-") as tmp:
        _, dataset, static = load_fitted_field(args, Path(tmp))
    view = int(dataset.indices("train")[0])
    calls = _record_inference_calls(static, dataset, view)
    # Same MLPs (same feature count: 13 tables x 2), tables small enough to stay in cache.
    small_config = dataclasses.replace(static.config, grid_resolutions=(4, 8, 16, 32), plane_resolutions=(16, 32, 64))
    small = RadianceField(small_config, generator=torch.Generator().manual_seed(0))
    mlps = {k: v for k, v in static.state_dict().items() if "mlp" in k}
    loaded = small.load_state_dict(mlps, strict=False)
    if not mlps or loaded.unexpected_keys or any(k in loaded.missing_keys for k in mlps):
        raise RuntimeError(f"the fitted MLPs did not load into the cache-sized field: {loaded}")
    models = {}
    for label, blend in (("f_S", None), ("dual", (0.1, 0.1))):
        for base in (static, small):
            base.requires_grad_(False)
            model = base if blend is None else make_edit_model(base, "dual")
            model.requires_grad_(False)
            models[label, base is small] = (model, blend)

    def measure() -> dict[str, tuple[float, float]]:
        return {label: tuple(_replay_seconds(*models[label, cached], calls, args.repeats) for cached in (False, True))
                for label in ("f_S", "dual")}

    print(f"{args.scene} {dataset.width}x{dataset.height}: {sum(len(c[0]) for c in calls) / 1e6:.2f}M samples "
          f"in {len(calls)} kernel calls, replayed {args.repeats}x")
    print(format_table(measure()), flush=True)
    from benchmarks.revision import NESTED_RUN

    if args.compare != "none" and not os.environ.get(NESTED_RUN):
        _compare(args, measure)


def format_table(seconds: dict[str, tuple[float, float]]) -> str:
    lines = [f"{'model':>10s}  {'fitted tables s':>15s}  {'cache-sized s':>13s}  {'misses share':>12s}"]
    for label, (fitted, cached) in seconds.items():
        lines.append(f"{label:>10s}  {fitted:15.3f}  {cached:13.3f}  {1 - cached / fitted:12.0%}")
    return "\n".join(lines)


def _compare(args, measure) -> None:
    """Alternate this checkout's measurement with commit args.compare's, then print both side by side."""
    from benchmarks.revision import RevisionUnavailable, parse_render_cache_profile, profile_revision

    argv = [f"--{name.replace('_', '-')}={getattr(args, name)}" for name in
            ("scene", "fit_iterations", "fit_dir", "max_size", "render_samples", "threads", "repeats")
            if getattr(args, name) is not None]
    rounds = []
    for round_ in range(args.rounds):
        print(f"--- round {round_ + 1}/{args.rounds}: {args.compare} (its own kernel build), then this checkout ---",
              flush=True)
        try:
            before = parse_render_cache_profile(profile_revision(args.compare, "benchmarks.profile_render_cache", argv))
        except RevisionUnavailable as error:
            print(f"no comparison: {error}")
            return
        rounds.append((before, measure()))
    print(f"\nbefore ({args.compare}) / after (this checkout), fitted tables, s, {args.rounds} rounds A B, "
          f"load {os.getloadavg()[0]:.2f}:")
    print(f"{'model':>10s}  {'before (median)':>15s}  {'after (median)':>14s}  {'before/after per round':>30s}")
    for label in ("f_S", "dual"):
        pairs = [(b[label][0], a[label][0]) for b, a in rounds if label in b]
        if not pairs:
            continue
        ratios = " ".join(f"{was / now:.2f}" for was, now in pairs)
        print(f"{label:>10s}  {statistics.median(p[0] for p in pairs):15.3f}  "
              f"{statistics.median(p[1] for p in pairs):14.3f}  {ratios:>30s}")


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
