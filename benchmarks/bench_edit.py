"""The editing stage: cost and measured effect of each DF / SA / CCI variant on a procedural scene.

    python -m benchmarks.bench_edit [--scene tiny|campsite] [--fit-iterations N] [--iterations N]
                                    [--max-size PX] [--samples-per-ray N] [--lpips-weight W]

Fits f_S with the fit stage (its defaults unless overridden), then runs the six ablation variants of the
edit stage's loop (the InstructPix2Pix EMULATOR and the PROXY encoder: simulator and proxy numbers) and
prints per variant: seconds per training iteration, seconds per view update (render + emulator +
encoder), total seconds, PSNR of the edited model's training-view renders to the ground-truth edit
(f_S's for reference), background PSNR to the original outside the edit mask, SA acceptance rate, and
the CCI weights given to emulator failures. Timings include whatever else runs on the machine.
"""
from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

VARIANTS = [(False, False, False), (True, False, False), (True, True, False), (False, False, True),
            (True, False, True), (True, True, True)]


def _label(variant) -> str:
    on = [n for n, f in zip(("DF", "SA", "CCI"), variant) if f]
    return "+".join(on) if on else "baseline"


def main(argv: list[str] | None = None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(prog="python -m benchmarks.bench_edit")
    parser.add_argument("--scene", default="tiny")
    parser.add_argument("--fit-iterations", type=int, default=500)
    parser.add_argument("--iterations", type=int, default=None, help="edit iterations (default: stage default)")
    parser.add_argument("--max-size", type=int, default=512, help="preprocess max_size (long side, px)")
    parser.add_argument("--samples-per-ray", type=int, default=None, help="fit samples_per_ray override")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--lpips-weight", type=float, default=None, help="edit lpips_weight (default: stage's)")
    args = parser.parse_args([] if argv is None else argv)

    import numpy as np

    from dualnerf.dataset import load_dataset
    from dualnerf.idu import IDUConfig, IterativeDatasetUpdate
    from dualnerf.io import PreprocessConfig, preprocess
    from dualnerf.model import load_model
    from dualnerf.numerics import use_threads
    from dualnerf.rendering import render_view
    from dualnerf.scenes import generate_scene, load_gt_edit, load_scene_spec
    from pipeline.context import StepContext
    from stages.edit import EditParams, build_editor, build_encoder
    from stages.fit import FitParams, FitStage

    use_threads(args.threads)           # as the stages: the kernels on --threads, torch on one
    print(f"cores: {os.cpu_count()}, kernel threads: {args.threads}; timings include other load (check `uptime`)")
    with tempfile.TemporaryDirectory(prefix="bench-edit-") as tmp:
        tmp = Path(tmp)
        start = time.perf_counter()
        generate_scene(args.scene, tmp / "scene", seed=0)
        preprocess(tmp / "scene", tmp / "data", PreprocessConfig(method="nerfstudio", max_size=args.max_size))
        fit_overrides = {"iterations": args.fit_iterations, "num_threads": args.threads}
        if args.samples_per_ray:
            fit_overrides["samples_per_ray"] = args.samples_per_ray
        fit_ctx = StepContext(key="bench-fit", params=FitParams(**fit_overrides), inputs={"dataset": tmp / "data"},
                              out_dir=tmp / "fit", scratch_dir=tmp / "fit-scratch", log=logging.getLogger("fit"))
        fit_start = time.perf_counter()
        FitStage().run(fit_ctx)
        data_dir = tmp / "data"
        dataset = load_dataset(data_dir)
        static = load_model(tmp / "fit" / "model")
        print(f"scene {args.scene} {dataset.width}x{dataset.height}, {len(dataset.indices('train'))} training "
              f"views; fit {args.fit_iterations} it in {time.perf_counter() - fit_start:.0f} s "
              f"(setup total {time.perf_counter() - start:.0f} s); samples/ray {static.config.samples_per_ray}, "
              f"occupancy {static.occupancy.fraction():.2f}")

        train = dataset.indices("train")
        spec = load_scene_spec(data_dir).edit("snow")
        gt = [load_gt_edit(data_dir, "snow", dataset.names[i]) for i in train]
        gt_images = np.stack([g[0] for g in gt]) / 255.0
        masks = np.stack([g[1] for g in gt])
        originals = dataset.images[train] / 255.0

        def scores(model, blend):
            renders = np.stack([render_view(model, dataset.c2w[i], dataset.intrinsics[i], dataset.width,
                                            dataset.height, float(dataset.near[i]), float(dataset.far[i]),
                                            blend=blend).numpy() for i in train])
            edit_psnr = -10 * np.log10(np.mean((renders - gt_images) ** 2))
            background = ~masks
            bg_psnr = -10 * np.log10(np.mean(((renders - originals) ** 2)[background]))
            return edit_psnr, bg_psnr

        base_psnr, base_bg = scores(static, None)
        print(f"f_S: PSNR to GT edit {base_psnr:.2f} dB, background PSNR to original {base_bg:.2f} dB")
        defaults = EditParams()
        iterations = args.iterations or defaults.iterations
        print(f"edit: {iterations} iterations, edit_rate {defaults.edit_rate}, edit_count {defaults.edit_count}, "
              f"{defaults.rays_per_batch} rays/batch (editor: InstructPix2Pix EMULATOR; encoder: PROXY); LPIPS "
              f"weight {defaults.lpips_weight if args.lpips_weight is None else args.lpips_weight}")
        header = ("variant", "s/iter", "s/update", "total s", "PSNR->GT", "bg PSNR", "SA acc", "w(fail)", "w(ok)")
        print("  ".join(f"{h:>9s}" for h in header))
        for variant in VARIANTS:
            params = EditParams(dual_field=variant[0], annealing=variant[1], consistency=variant[2],
                                edit_id="snow", iterations=iterations,
                                **({} if args.lpips_weight is None else {"lpips_weight": args.lpips_weight}))
            editor = build_editor(params, data_dir, dataset, train, spec.instruction)
            encoder = build_encoder(params, data_dir, dataset, spec)
            config = IDUConfig(dual_field=variant[0], annealing=variant[1], consistency=variant[2],
                               iterations=iterations, edit_rate=params.edit_rate, edit_count=params.edit_count,
                               rays_per_batch=params.rays_per_batch, learning_rate=params.lr,
                               lpips_weight=params.lpips_weight, lpips_net=params.lpips_net,
                               patch_size=params.patch_size, patch_share=params.patch_share)
            idu = IterativeDatasetUpdate(config, static, dataset, editor, spec.instruction, encoder=encoder)
            update_time = [0.0]

            def timed_update(t, _orig=idu.dataset_update, _acc=update_time):
                s = time.perf_counter()
                _orig(t)
                _acc[0] += time.perf_counter() - s

            idu.dataset_update = timed_update
            s = time.perf_counter()
            idu.run()
            total = time.perf_counter() - s
            n_updates = len(idu.updates)
            per_iter = (total - update_time[0]) / iterations
            model = idu.final_model()
            edit_psnr, bg_psnr = scores(model, getattr(model, "render_blend", None))
            acc = idu.curves_json()["acceptance_rate"]
            fail_w = [u["weight"] for u in idu.updates if u["editor"]["failed"] and u["weight"] is not None]
            ok_w = [u["weight"] for u in idu.updates if not u["editor"]["failed"] and u["weight"] is not None]
            row = (_label(variant), f"{per_iter:.3f}", f"{update_time[0] / max(n_updates, 1):.2f}", f"{total:.0f}",
                   f"{edit_psnr:.2f}", f"{bg_psnr:.2f}", "-" if acc is None else f"{acc:.2f}",
                   f"{np.mean(fail_w):.2f}" if fail_w else "-", f"{np.mean(ok_w):.2f}" if ok_w else "-")
            print("  ".join(f"{c:>9s}" for c in row), flush=True)


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
