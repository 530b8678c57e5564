"""The training step's kernels that wait on memory: how much of their time is waiting, and what is left.

    python -m benchmarks.bench_memory [--scene campsite] [--fit-dir DIR] [--repeats 15] [--threads 1]

On the ablation's f_S (fitted once and cached, as in benchmarks.profile_edit), one thread as the ablation's
edits run, medians of --repeats:

- the dual field's look-ups (f_S and f_D tables, one kernel pass) at a training batch's sample points
  (the edit stage's CPU preset: random training pixels' rays, their occupied samples), at as many points
  spread uniformly over the scene cube, and at points squeezed into a few grid cells. The last run has
  the same instructions as the others but finds every corner in the L1 cache: the difference is time
  spent waiting for table rows (the fine tables, ~50 MB per field, do not fit the caches). Then the pair
  kernel reading f_D's tables for both fields (the second field's rows then cost nothing: the first
  row minus this one is what f_D's own rows cost) and one field's look-ups alone;
- the look-ups' backward into the persistent gradient buffers (kernels.TableGradients) at the batch's
  points, and the Adam update of the chunks it touched (what a training step runs on f_D's tables);
- the render sampler (proposal + interval placement + occupancy) for one view update's 256x192 rays.

The kernels' results do not depend on where the data sits, so none of this changes a stage's bits; it
says which phases are at a memory limit (docs/benchmarks.md, issue 30).
Timings include whatever else runs on the machine (check `uptime`).
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from benchmarks.profile_edit import add_fitted_field_arguments, load_fitted_field
from benchmarks.timing import median_seconds
from stages.edit import EditParams

BATCH_RAYS = EditParams().rays_per_batch        # a training step's rays at the edit stage's CPU preset
BATCH_SAMPLES = EditParams().samples_per_ray


def _ms(run, repeats: int, between=None) -> float:
    return 1e3 * median_seconds(run, repeats, between=between)


def batch_points(static, dataset, generator):
    """The occupied sample points of one training batch: BATCH_RAYS random training pixels' rays (drawn as
    RayTrainer.sample_batch draws them) through the render sampler at BATCH_SAMPLES jittered samples."""
    import torch

    from dualnerf.cameras import pixel_rays
    from dualnerf.rendering import ray_cube_bounds, ray_samples

    train = torch.as_tensor(dataset.indices("train"), dtype=torch.long)
    views = train[torch.randint(len(train), (BATCH_RAYS,), generator=generator)]
    u = torch.randint(dataset.width, (BATCH_RAYS,), generator=generator)
    v = torch.randint(dataset.height, (BATCH_RAYS,), generator=generator)
    c2w = torch.as_tensor(dataset.c2w, dtype=torch.float32)[views]
    origins, dirs = pixel_rays(c2w, torch.as_tensor(dataset.intrinsics, dtype=torch.float32)[views], u, v)
    near = torch.as_tensor(dataset.near, dtype=torch.float32)[views]
    far = torch.as_tensor(dataset.far, dtype=torch.float32)[views]
    t_start, t_end = ray_cube_bounds(origins, dirs, near, far)
    jitter = torch.rand(BATCH_RAYS, BATCH_SAMPLES - 1, generator=generator)
    t, _, mask = ray_samples(static.occupancy, static.config, origins, dirs, t_start, t_end, BATCH_SAMPLES, jitter)
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    return points[mask].contiguous()


def main(argv: list[str] | None = None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_memory")
    add_fitted_field_arguments(parser, threads=1)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args([] if argv is None else argv)

    import torch

    from dualnerf import kernels
    from dualnerf.cameras import view_rays
    from dualnerf.dual_field import make_edit_model
    from dualnerf.rendering import ray_cube_bounds, ray_samples

    module = kernels.grid_kernel()
    if module is None:
        print("the C++ kernels are not built here: nothing to time")
        return
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        _, dataset, static = load_fitted_field(args, Path(tmp))
    dual = make_edit_model(static, "dual")
    generator = torch.Generator().manual_seed(0)
    points = batch_points(static, dataset, generator)
    m = points.shape[0]
    uniform = torch.rand(m, 3, generator=generator) * 2 - 1
    squeezed = torch.rand(m, 3, generator=generator) * 0.002 + 0.3
    dense_s, planes_s = static.grid_tables()
    dense_d, planes_d = dual.dynamic_field.grid_tables()
    vector = kernels.vector_path()
    print(f"{args.scene}: a training batch of {BATCH_RAYS} rays x {BATCH_SAMPLES} samples = {m} occupied points; "
          f"tables {sum(t.numel() for t in (*dense_s, *planes_s)) * 4 / 2**20:.0f} MB per field")

    def pair_forward(x):
        return lambda: module.encode_forward_pair(x, dense_s, planes_s, dense_d, planes_d, vector)

    rows = []
    for label, x in (("batch points", points), ("uniform in the cube", uniform), ("in a few cells", squeezed)):
        rows.append((f"pair look-ups, {label}", _ms(pair_forward(x), args.repeats)))
    waiting = 1.0 - rows[2][1] / rows[0][1]
    # The same instructions with f_D's tables as the second field too: its corners then come from lines the
    # first field's gathers just loaded, so the difference to the first row is what f_D's own table rows
    # cost, the most that storing both fields' corners in one line (as renders do) could save in training.
    rows.append(("pair look-ups, batch points, f_D's tables for both fields",
                 _ms(lambda: module.encode_forward_pair(points, dense_d, planes_d, dense_d, planes_d, vector),
                     args.repeats)))
    rows.append(("one field's look-ups (f_D), batch points",
                 _ms(lambda: module.encode_forward(points, dense_d, planes_d, vector), args.repeats)))

    tables = [*dense_d, *planes_d]
    sink = kernels.TableGradients(tables)
    n_features = module.encode_forward(points[:1], dense_d, planes_d, vector).shape[1]
    grad = torch.randn(m, n_features, generator=generator)
    rows.append(("look-up backward into the buffers, batch points",
                 _ms(lambda: sink.add(points, grad, dense_d, planes_d), args.repeats, between=sink.clear)))
    state = {id(t): (torch.zeros_like(t), torch.zeros_like(t)) for t in tables}

    def adam():
        for t in tables:
            buffer, touched = sink.gradient(t)
            exp_avg, exp_avg_sq = state[id(t)]
            module.adam_step_touched(t, buffer, touched, exp_avg, exp_avg_sq, 0.9, 0.99, 1e-9, 1.0, 1e-15)

    rows.append(("Adam on the touched chunks",
                 _ms(adam, args.repeats, between=lambda: sink.add(points, grad, dense_d, planes_d))))

    view = int(dataset.indices("train")[0])
    origins, dirs = view_rays(dataset.c2w[view], dataset.intrinsics[view], dataset.width, dataset.height)
    n_rays = origins.shape[0]
    t_start, t_end = ray_cube_bounds(origins, dirs, torch.full((n_rays,), float(dataset.near[view])),
                                     torch.full((n_rays,), float(dataset.far[view])))
    jitter = torch.rand(n_rays, BATCH_SAMPLES - 1, generator=generator)
    rows.append((f"render sampler, {n_rays} rays x {BATCH_SAMPLES} samples",
                 _ms(lambda: ray_samples(static.occupancy, static.config, origins, dirs, t_start, t_end,
                                         BATCH_SAMPLES, jitter), args.repeats)))
    for label, ms in rows:
        print(f"  {label:<60s} {ms:8.2f} ms")
    print(f"the pair look-ups wait on memory for {100 * waiting:.0f}% of their time at a batch's points "
          "(the same look-ups with every corner in cache take the rest)")


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
