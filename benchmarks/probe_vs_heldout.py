"""Why the report's convergence probe and the held-out evaluation can rank rows differently inside the mask.

    python -m benchmarks.probe_vs_heldout --dataset DATASET_DIR --edit-id snow EDIT_DIR [EDIT_DIR ...]

For each edit result (an edit stage output folder: model/, edited/, edit.json) renders the edited model
and reports the in-mask PSNR to the ground-truth edit (mean over views, as the probe and evaluate do)
on each side of the two measurements' differences:

    probe          the convergence probe's 3 training views at half resolution (the report's curve)
    train full     every training view at full resolution
    train half     every training view at half resolution (box-downsampled ground truth)
    heldout full   the held-out views at full resolution (evaluate's PSNR_in)
    heldout half   the held-out views at half resolution
    ..., evaluate's near/far   rendered as evaluate renders (every view between the training views'
                   smallest near and largest far, instead of the view's own near/far as training and the
                   probe do)
and, on the training views, how closely the render fits the view's own final training image (the IDU's
last edit of that view, edited/<name>.png) and how far those training images are from the ground truth.
A row that fits its training views' own (inconsistent) edits scores well on the probe and less well
on held-out views; resolution alone separates the half- from the full-size columns.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def _mean_masked_psnr(renders, targets, masks):
    from dualnerf.convergence import masked_psnr

    values = [masked_psnr(r, t, m) for r, t, m in zip(renders, targets, masks) if m.any()]
    return float(np.mean(values)) if values else float("nan")


def measure(dataset_dir: Path, edit_dir: Path, edit_id: str) -> dict:
    import cv2

    from dualnerf.convergence import downsample, probe_for_scene_edit
    from dualnerf.dataset import load_dataset
    from dualnerf.model import load_model, saved_blend
    from dualnerf.rendering import render_view
    from dualnerf.scenes.spec import load_gt_edit

    dataset = load_dataset(dataset_dir)
    model = load_model(edit_dir / "model").eval()
    blend = saved_blend(model)
    probe = probe_for_scene_edit(dataset_dir, dataset, edit_id)

    train, heldout = dataset.indices("train"), dataset.indices("heldout")
    scene_range = float(dataset.near[train].min()), float(dataset.far[train].max())

    def render(i, factor, bounds=None):
        k = dataset.intrinsics[i] / factor
        near, far = bounds or (float(dataset.near[i]), float(dataset.far[i]))
        return render_view(model, dataset.c2w[i], k, dataset.width // factor, dataset.height // factor,
                           near, far, blend=blend).numpy()

    def side(indices, factor, bounds=None):
        gts = [load_gt_edit(dataset_dir, edit_id, dataset.names[i]) for i in indices]
        renders = [render(i, factor, bounds) for i in indices]
        targets = [downsample(g[0].astype(np.float32) / 255.0, factor) for g in gts]
        masks = [downsample(g[1].astype(np.float32)[..., None], factor)[..., 0] > 0.5 for g in gts]
        return renders, targets, masks

    out = {}
    out["probe"] = _mean_masked_psnr(*side(probe.views, 2))
    renders, targets, masks = side(train, 1)
    out["train full"] = _mean_masked_psnr(renders, targets, masks)
    out["train half"] = _mean_masked_psnr(*side(train, 2))
    out["heldout full"] = _mean_masked_psnr(*side(heldout, 1))
    out["heldout half"] = _mean_masked_psnr(*side(heldout, 2))
    # evaluate renders every view between the training views' smallest near and largest far
    out["heldout full, evaluate's near/far"] = _mean_masked_psnr(*side(heldout, 1, scene_range))
    out["train full, evaluate's near/far"] = _mean_masked_psnr(*side(train, 1, scene_range))
    own = [cv2.imread(str(edit_dir / "edited" / f"{Path(dataset.names[i]).stem}.png"))[..., ::-1] / 255.0
           for i in train]
    out["train: render vs own training image"] = _mean_masked_psnr(renders, own, masks)
    out["train: training image vs ground truth"] = _mean_masked_psnr(own, targets, masks)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--edit-id", required=True)
    parser.add_argument("edits", type=Path, nargs="+")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    rows = {}
    for edit_dir in args.edits:
        toggles = json.loads((edit_dir / "edit.json").read_text())["toggles"]
        label = "+".join(k for k, on in zip(("DF", "SA", "CCI"), (toggles["dual_field"], toggles["annealing"],
                                                                   toggles["consistency"])) if on) or "IN2N"
        rows[f"{label} ({edit_dir.name[:8]})"] = measure(args.dataset, edit_dir, args.edit_id)
    names = list(next(iter(rows.values())))
    print("in-mask PSNR (dB)".ljust(40) + "".join(label.rjust(22) for label in rows))
    for name in names:
        print(name.ljust(40) + "".join(f"{rows[label][name]:22.2f}" for label in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
