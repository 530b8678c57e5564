"""Convergence probe for the editing loop on scenes with a ground-truth edit (procedural scenes).

API:
    ConvergenceProbe(views, c2w, intrinsics, width, height, near, far, gt_images, masks, originals, *,
                     scale=0.5, every=100)
        due(iteration, last_iteration) -> bool      probe at 0, every `every` iterations and at the end
        measure(model, blend, iteration) -> dict    {"iteration", "psnr_in", "psnr_out", "views"}
    downsample(image (H,W,C) float, factor) -> (H/f, W/f, C)   box filter (area average)
    masked_psnr(a, b, mask) -> float                PSNR over the pixels where mask is true (nan if none)

What it measures: the current model's renders of a few fixed training views, at `scale` x the dataset
resolution (intrinsics scaled, so the same rays' footprint), compared with the ground-truth edit inside
the edit mask (psnr_in: has the edit arrived?) and with the original image outside it (psnr_out: is the
rest of the scene preserved?). The ground truth and the original are box-downsampled to the render size;
a pixel is inside the mask when most of its source pixels are.

Rendering is deterministic (bin-centre samples, no generator), so probing does not change the run: a
probed and an unprobed run train the same model.
"""
from __future__ import annotations

import math

import numpy as np


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Box filter by an integer factor (the image is cropped to a multiple of it)."""
    if factor == 1:
        return image
    h, w = image.shape[0] // factor * factor, image.shape[1] // factor * factor
    cropped = image[:h, :w]
    return cropped.reshape(h // factor, factor, w // factor, factor, *image.shape[2:]).mean(axis=(1, 3))


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR (peak 1) over the pixels where `mask` (H,W) is true; nan when it selects nothing."""
    if not mask.any():
        return math.nan
    mse = float(np.mean((a[mask].astype(np.float64) - b[mask].astype(np.float64)) ** 2))
    return -10.0 * math.log10(max(mse, 1e-12))


class ConvergenceProbe:
    def __init__(self, views, c2w, intrinsics, width: int, height: int, near, far, gt_images, masks, originals,
                 *, scale: float = 0.5, every: int = 100):
        if not 0.0 < scale <= 1.0:
            raise ValueError(f"convergence probe scale must be in (0, 1], got {scale}")
        if every < 1:
            raise ValueError(f"convergence probe interval must be >= 1 iteration, got {every}")
        self.factor = max(1, round(1.0 / scale))
        self.views = [int(v) for v in views]
        self.every = int(every)
        f = self.factor
        self.width, self.height = int(width) // f, int(height) // f
        self.c2w = [np.asarray(c2w[i], np.float64) for i in range(len(self.views))]
        # Pixel u of the small image covers pixels [f u, f u + f) of the full one, whose centre f (u + 0.5)
        # is where dualnerf.cameras puts the small pixel's centre when fx, fy, cx, cy are all divided by f.
        self.intrinsics = [np.asarray(k, np.float64) / f for k in intrinsics]
        self.near = [float(x) for x in near]
        self.far = [float(x) for x in far]
        self.gt = [downsample(np.asarray(g, np.float32) / 255.0, f) for g in gt_images]
        self.originals = [downsample(np.asarray(o, np.float32) / 255.0, f) for o in originals]
        self.masks = [downsample(np.asarray(m, np.float32)[..., None], f)[..., 0] > 0.5 for m in masks]

    def due(self, iteration: int, last_iteration: int) -> bool:
        return iteration % self.every == 0 or iteration == last_iteration

    def measure(self, model, blend, iteration: int) -> dict:
        from dualnerf.rendering import render_view

        inside, outside = [], []
        for i in range(len(self.views)):
            image = render_view(model, self.c2w[i], self.intrinsics[i], self.width, self.height, self.near[i],
                                self.far[i], blend=blend).numpy()
            inside.append(masked_psnr(image, self.gt[i], self.masks[i]))
            outside.append(masked_psnr(image, self.originals[i], ~self.masks[i]))
        return {"iteration": int(iteration), "psnr_in": _nanmean(inside), "psnr_out": _nanmean(outside),
                "views": self.views}


def _nanmean(values) -> float | None:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else None


def probe_for_scene_edit(data_dir, dataset, edit_id: str, *, n_views: int = 3, scale: float = 0.5,
                         every: int = 100) -> ConvergenceProbe | None:
    """A probe over `n_views` training views (evenly spaced among those whose ground-truth edit mask is not
    empty) of a dataset with ground truth for `edit_id` in gt/edits/; None when it has none."""
    from dualnerf.scenes.spec import load_gt_edit

    candidates = []
    for index in dataset.indices("train"):
        gt = load_gt_edit(data_dir, edit_id, dataset.names[index]) if edit_id else None
        if gt is not None and gt[1].any():
            candidates.append((int(index), gt))
    if not candidates or n_views < 1:
        return None
    picks = [candidates[round(k * (len(candidates) - 1) / max(n_views - 1, 1))] for k in range(min(n_views,
                                                                                               len(candidates)))]
    picks = list({index: (index, gt) for index, gt in picks}.values())
    views = [index for index, _ in picks]
    return ConvergenceProbe(views, dataset.c2w[views], dataset.intrinsics[views], dataset.width, dataset.height,
                            dataset.near[views], dataset.far[views], [gt[0] for _, gt in picks],
                            [gt[1] for _, gt in picks], dataset.images[views], scale=scale, every=every)
