"""Where an edit stage's time goes: a dual-field and a single-field IDU run, broken down by phase.

    python -m benchmarks.profile_edit [--scene campsite] [--iterations 100] [--fit-iterations 600]
                                      [--fit-dir DIR] [--threads 2] [--compare REV|none]

Fits f_S once with the fit stage (cached in --fit-dir, default $TMPDIR/dualnerf-profile-edit/<scene>-<N>;
reuse it with the same arguments), then runs `--iterations` editing iterations of the full DualNeRF
variant (DF+SA+CCI) and of the single-field baseline with the edit stage's update rate, timing:

    training step   sampling (ray batch, rays, the sampler: proposal intervals + occupancy), occupancy-grid
                    refresh, field forward per field (f_S, f_D / the single field), rest of the render
                    (compositing), LPIPS patch loss forward, loss + backward (LPIPS's included), optimiser step
    view update     sampler, the fused inference kernel (both fields' look-ups and MLPs, no autograd),
                    compositing, editor, encoder
    (field forward = the feature look-ups; "field MLPs" / "density MLP" are timed separately; the dual
    field's look-ups of both fields run in one kernel pass, timed as "look-ups f_S + f_D")
    checkpoint I/O  save_state + load_state of one checkpoint

--compare REV (default: the commit before issue 30's changes; 'none' skips it) then runs the same
profile as commit REV has it (a temporary git worktree, its own stage defaults, the same f_S) and prints
both side by side: the before/after table of `make bench` (benchmarks.revision).

The timers wrap the library's functions from outside (nothing in dualnerf/ knows about them), so the
numbers include only a few microseconds of overhead per call. Everything runs on this process's
threads; timings include whatever else runs on the machine (check `uptime`).
"""
from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

# The last commit before issue 30's speed changes (same bits, fewer samples, fused occupancy refresh).
BEFORE_ISSUE_30 = "25ad900"


class PhaseTimer:
    """Exclusive wall-clock time per phase: a nested phase's time is not counted in its parent's."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.calls = defaultdict(int)
        self._stack: list[list] = []

    @contextmanager
    def phase(self, name: str):
        start = time.perf_counter()
        self._stack.append([name, 0.0])
        try:
            yield
        finally:
            _, inner = self._stack.pop()
            total = time.perf_counter() - start
            self.seconds[name] += total - inner
            self.calls[name] += 1
            if self._stack:
                self._stack[-1][1] += total

    def wrap(self, owner, attribute: str, name):
        """Replace owner.attribute by a timed version; `name` is a string or a function of the context."""
        original = getattr(owner, attribute)

        def timed(*args, **kwargs):
            label = name() if callable(name) else name
            with self.phase(label):
                return original(*args, **kwargs)

        setattr(owner, attribute, timed)
        return original


def _fitted_field(args, tmp: Path):
    """The scene's dataset folder and a fitted f_S (from --fit-dir when it holds one)."""
    from dualnerf.io import PreprocessConfig, preprocess
    from dualnerf.scenes import generate_scene
    from pipeline.context import StepContext
    from stages.fit import FitParams, FitStage

    cache = Path(args.fit_dir or Path(tempfile.gettempdir()) / "dualnerf-profile-edit"
                 / f"{args.scene}-{args.fit_iterations}")
    data, fit = cache / "data", cache / "fit"
    if not (fit / "model" / "model.json").is_file():
        cache.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        generate_scene(args.scene, tmp / "scene", seed=0)
        preprocess(tmp / "scene", tmp / "data", PreprocessConfig(method="nerfstudio", max_size=args.max_size))
        params = FitParams(iterations=args.fit_iterations, num_threads=args.threads, eval_every=10**9)
        ctx = StepContext(key="profile-fit", params=params, inputs={"dataset": tmp / "data"}, out_dir=tmp / "fit",
                          scratch_dir=tmp / "fit-scratch", log=logging.getLogger("fit"))
        FitStage().run(ctx)
        (tmp / "data").rename(data)
        (tmp / "fit").rename(fit)
        print(f"fitted f_S ({args.fit_iterations} iterations) in {time.perf_counter() - start:.0f} s -> {cache}")
    else:
        print(f"f_S from {cache}")
    return data, fit / "model"


def add_fitted_field_arguments(parser, threads: int) -> None:
    """The options of the benchmarks that time a fitted f_S (profile_edit, bench_render, profile_render_cache)."""
    parser.add_argument("--scene", default="campsite")
    parser.add_argument("--fit-iterations", type=int, default=600)
    parser.add_argument("--fit-dir", default=None, help="cache folder of the fitted f_S (created if empty)")
    parser.add_argument("--max-size", type=int, default=256)
    parser.add_argument("--render-samples", type=int, default=48,
                        help="render_samples_per_ray of f_S (the ablation workflow's value)")
    parser.add_argument("--threads", type=int, default=threads)


def load_fitted_field(args, tmp: Path):
    """(dataset folder, dataset, f_S rendering --render-samples per ray) on --threads torch threads, after
    printing the machine's line."""
    import dataclasses

    import torch

    from dualnerf.dataset import load_dataset
    from dualnerf.model import load_model
    from dualnerf.numerics import use_threads

    use_threads(args.threads)          # as the stages run: the kernels on --threads, torch on one
    print(f"cores: {os.cpu_count()}, kernel threads: {args.threads} (torch: {torch.get_num_threads()}), "
          f"load {os.getloadavg()[0]:.2f}; timings include other load")
    data_dir, model_dir = _fitted_field(args, tmp)
    static = load_model(model_dir)
    static.config = dataclasses.replace(static.config, render_samples_per_ray=args.render_samples)
    return data_dir, load_dataset(data_dir), static


def _profile_variant(label, dual_field, args, data_dir, static, dataset, tmp: Path) -> dict:
    from dualnerf import patches, rendering, training
    from dualnerf.idu import IterativeDatasetUpdate
    from dualnerf.scenes import load_scene_spec
    from stages.edit import EditParams, build_editor, build_encoder, idu_config

    params = EditParams(dual_field=dual_field, annealing=dual_field, consistency=dual_field, edit_id="snow",
                        iterations=args.iterations)
    spec = load_scene_spec(data_dir).edit("snow")
    train = dataset.indices("train")
    editor = build_editor(params, data_dir, dataset, train, spec.instruction)
    timer = PhaseTimer()
    with timer.phase("set-up: encoder (caption images, vocabulary)"):   # once per edit and evaluate stage
        encoder = build_encoder(params, data_dir, dataset, spec)
    config = idu_config(params)           # the stage's own settings (RGB + LPIPS patch loss, blend schedule)
    idu = IterativeDatasetUpdate(config, static, dataset, editor, spec.instruction, encoder=encoder)

    where = ["step"]                                   # "step" or "update": which loop part is running
    saved = {}

    def field_label(role):
        return lambda: f"{where[0]}: field forward {role}"

    fields = ([(idu.model.static_field, "f_S"), (idu.model.dynamic_field, "f_D")] if dual_field
              else [(idu.model, "single field")])
    if idu.static_field is not idu.model and dual_field is False:
        fields.append((idu.static_field, "f_S (retreat)"))
    for module, role in fields:
        for method in ("forward", "density_hidden", "background_hidden"):
            timer.wrap(module, method, field_label(role) if method == "forward"
                       else (lambda r=role, m=method: f"{where[0]}: {m} {r}"))
        # The MLPs alone (nested in forward, or called on the dual field's one-pass look-ups).
        timer.wrap(module, "heads", lambda r=role: f"{where[0]}: field MLPs {r}")
        timer.wrap(module, "density_head", lambda r=role: f"{where[0]}: density MLP {r}")
    from dualnerf import kernels
    saved["pair"] = timer.wrap(kernels, "fused_pair_features",
                               lambda: f"{where[0]}: look-ups f_S + f_D (one kernel pass)")
    # In a training step the inference kernel runs only in the occupancy refresh (density only).
    saved["inference"] = timer.wrap(kernels, "field_inference",
                                    lambda: "step: occupancy refresh (fused density kernel)" if where[0] == "step"
                                    else "update: field inference kernel (look-ups + MLPs, fused)")
    saved["sampler"] = timer.wrap(rendering, "ray_samples", lambda: f"{where[0]}: sampler (proposal + occupancy)")
    saved["render_rays"] = timer.wrap(rendering, "render_rays",
                                      lambda: f"{where[0]}: render rest (compositing, packing)")
    saved["training_render_rays"] = training.render_rays
    training.render_rays = rendering.render_rays
    saved["pixel_rays"] = timer.wrap(training, "pixel_rays", "step: sampling (rays)")
    saved["patch_lpips_loss"] = timer.wrap(patches, "patch_lpips_loss", "step: LPIPS loss forward")
    timer.wrap(idu.trainer, "sample_batch", "step: sampling (batch)")
    timer.wrap(idu.trainer, "update_occupancy", "step: occupancy refresh (rest)")
    timer.wrap(idu.trainer.optimizer, "step", "step: optimiser")
    timer.wrap(idu.editor, "edit", "update: editor")
    if encoder is not None:
        timer.wrap(encoder, "encode_images", "update: encoder")
    timer.wrap(idu, "train_step", "step: loop rest (loss, logging)")
    original_update = idu.dataset_update

    def update(t):
        where[0] = "update"
        try:
            with timer.phase("update: loop rest"):
                original_update(t)
        finally:
            where[0] = "step"

    idu.dataset_update = update
    import torch
    original_backward = torch.Tensor.backward

    def backward(self, *a, **k):
        with timer.phase("step: backward"):
            return original_backward(self, *a, **k)

    torch.Tensor.backward = backward
    try:
        start = time.perf_counter()
        idu.run()
        total = time.perf_counter() - start
        with timer.phase("checkpoint: save"):
            folder = tmp / f"ckpt-{label}"
            folder.mkdir()
            idu.save_state(folder)
        with timer.phase("checkpoint: load"):
            idu.load_state(folder)
    finally:
        torch.Tensor.backward = original_backward
        rendering.ray_samples = saved["sampler"]
        kernels.field_inference = saved["inference"]
        rendering.render_rays = saved["render_rays"]
        training.render_rays = saved["training_render_rays"]
        training.pixel_rays = saved["pixel_rays"]
        patches.patch_lpips_loss = saved["patch_lpips_loss"]
        kernels.fused_pair_features = saved["pair"]
    return {"label": label, "total": total, "timer": timer, "updates": len(idu.updates),
            "iterations": args.iterations}


def _print(result) -> None:
    timer, n_it, n_up = result["timer"], result["iterations"], max(result["updates"], 1)
    print(f"\n{result['label']}: {n_it} iterations, {result['updates']} view updates, {result['total']:.1f} s "
          f"loop (per iteration {1000 * result['total'] / n_it:.0f} ms)")
    print(f"  {'phase':48s} {'total s':>8s} {'share':>6s} {'per unit':>12s}")
    for name in sorted(timer.seconds, key=lambda n: (n.split(':')[0], -timer.seconds[n])):
        seconds = timer.seconds[name]
        if name.startswith("step"):
            unit = f"{1000 * seconds / n_it:.1f} ms/it"
        elif name.startswith("update"):
            unit = f"{1000 * seconds / n_up:.0f} ms/upd"
        else:
            unit = f"{1000 * seconds:.0f} ms"
        # One-off phases (checkpoint I/O, set-up) are outside the loop: no share of it.
        share = seconds / result["total"] if name.startswith(("step", "update")) else None
        print(f"  {name:48s} {seconds:8.2f} {_cell(share, '6.1%')} {unit:>12s}")
    per = {}
    for part in ("step", "update"):
        part_total = sum(s for n, s in timer.seconds.items() if n.startswith(part))
        per[part] = part_total / (n_it if part == "step" else n_up)
        print(f"  {part + ' total':48s} {part_total:8.2f} {part_total / result['total']:6.1%} "
              f"{1000 * per[part]:9.0f} ms/{'it' if part == 'step' else 'upd'}")
    from stages.edit import EditParams

    preset = EditParams()
    n_updates = preset.iterations // preset.edit_rate * preset.edit_count
    estimate = preset.iterations * per["step"] + n_updates * per["update"]
    print(f"  estimated edit stage at the CPU preset ({preset.iterations} iterations, {n_updates} updates): "
          f"{estimate / 60:.1f} min (+ probes and checkpoints)")
    result["estimate"] = estimate
    result["summary"] = {"iteration_ms": 1000 * result["total"] / n_it, "step_ms": 1000 * per["step"],
                         "update_ms": 1000 * per["update"]}


def main(argv: list[str] | None = None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.profile_edit")
    add_fitted_field_arguments(parser, threads=2)
    parser.add_argument("--iterations", type=int, default=100,
                        help="editing iterations per variant: the first N of an edit (the edit stage runs 2000; "
                             "early iterations differ from the average, e.g. in how many gradients are "
                             "subnormal, so quote a whole edit's figure with 2000)")
    parser.add_argument("--compare", default=BEFORE_ISSUE_30,
                        help="after this profile, run the same one as this commit has it (its own defaults, the "
                             "same f_S) and print both side by side; 'none': skip (default: the commit before "
                             "issue 30's changes)")
    args = parser.parse_args([] if argv is None else argv)
    if args.fit_dir is None:                 # one f_S for both runs of a comparison
        args.fit_dir = str(Path(tempfile.gettempdir()) / "dualnerf-profile-edit" / f"{args.scene}-{args.fit_iterations}")

    from stages.edit import EditParams

    with tempfile.TemporaryDirectory(prefix="profile-edit-") as tmp:
        tmp = Path(tmp)
        data_dir, dataset, static = load_fitted_field(args, tmp)
        print(f"{args.scene} {dataset.width}x{dataset.height}, {len(dataset.indices('train'))} training views, "
              f"occupancy {static.occupancy.fraction():.2f}, f_S fitted at {static.config.samples_per_ray} samples/ray, "
              f"edited at {EditParams().samples_per_ray or static.config.samples_per_ray}")
        results = [_profile_variant("DF+SA+CCI (dual field)", True, args, data_dir, static, dataset, tmp),
                   _profile_variant("baseline (single field)", False, args, data_dir, static, dataset, tmp)]
        for result in results:
            _print(result)
            print(flush=True)
        print(f"\ndual / single loop time: {results[0]['total'] / results[1]['total']:.2f}")
    from benchmarks.revision import NESTED_RUN

    if args.compare != "none" and not os.environ.get(NESTED_RUN):
        _compare(args, results)


def _compare(args, results) -> None:
    """The same profile at commit args.compare, then both side by side (one run each, same host)."""
    from benchmarks.revision import RevisionUnavailable, parse_edit_profile, profile_revision

    argv = [f"--{name.replace('_', '-')}={getattr(args, name)}" for name in
            ("scene", "fit_iterations", "fit_dir", "max_size", "render_samples", "threads", "iterations")]
    print(f"\n--- the same profile at {args.compare} (its own stage defaults, the same f_S) ---", flush=True)
    try:
        before = parse_edit_profile(profile_revision(args.compare, "benchmarks.profile_edit", argv))
    except RevisionUnavailable as error:
        print(f"no comparison: {error}")
        return
    print(f"\nbefore ({args.compare}) / after (this checkout), ms, one run each, load {os.getloadavg()[0]:.2f}:")
    print(f"  {'':46s} {'before':>9s} {'after':>9s} {'after/before':>13s}")
    for result in results:
        old = before.get(result["label"], {})
        for key, name in (("iteration_ms", "per iteration"), ("step_ms", "training step"),
                          ("update_ms", "view update")):
            new = result["summary"][key]
            was = old.get(key)
            ratio = f"{new / was:13.2f}" if was else f"{'-':>13s}"
            print(f"  {result['label'] + ': ' + name if key == 'iteration_ms' else '    ' + name:46s} "
                  f"{_cell(was, '9.0f')} {new:9.0f} {ratio}")
    now = results[0]["total"] / results[1]["total"]
    print(f"  {'dual / single':46s} {_cell(before.get('dual_over_single'), '9.2f')} {now:9.2f}")


def _cell(value: float | None, spec: str) -> str:
    """A table cell: the value, or '-' where there is none (a one-off phase's share of the loop, a figure
    the earlier commit did not print)."""
    return format(value, spec) if value is not None else "-".rjust(int(spec.split(".")[0]))


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
