"""LPIPS evaluation metrics (definitions: docs/metrics.md), computed with dualnerf.lpips.

    lpips_metrics(net, frames_original, frames_edited, views_original, views_edited,
                  gt_edits=None, gt_masks=None) -> (values: dict name -> float, model: LPIPS)

- lpips_edited_vs_original: mean over camera-path frames of LPIPS(o_i, e_i) (how much the edit changed,
  the perceptual counterpart of SSIM_edited_vs_original).
- lpips_background (procedural scenes: needs the edit mask): at the fixed views, the edited render vs
  the original render outside the edit mask. Inside the mask the original render is pasted into the
  edited one, so the edit itself cannot leak into the background through the network's receptive fields,
  and the spatial LPIPS map is averaged over the pixels outside the mask (nan if there are none).
- gt_lpips_edit (procedural scenes): edited render vs the ground-truth edited view, whole image.
Lower is better for all three. Images are (H,W,3) uint8 or float in [0, 1]. Images whose short side is
below the backbone's minimum (31 px AlexNet, 16 px VGG16; e.g. small test renders) are enlarged by the
smallest integer factor that reaches it, by pixel repetition (masks alike).
"""
from __future__ import annotations

import numpy as np
import torch

from dualnerf.lpips import LPIPS, MIN_SIZE, load_lpips, to_lpips_input

BATCH = 8


def _factor(model: LPIPS, height: int, width: int) -> int:
    return -(-MIN_SIZE[model.net] // min(height, width))          # ceil; 1 for large enough images


def _enlarge(tensor: torch.Tensor, factor: int) -> torch.Tensor:
    """(..., H, W) -> (..., factor H, factor W) by pixel repetition."""
    if factor == 1:
        return tensor
    return tensor.repeat_interleave(factor, dim=-2).repeat_interleave(factor, dim=-1)


def _input(model: LPIPS, image) -> torch.Tensor:
    x = to_lpips_input(image)
    return _enlarge(x, _factor(model, *x.shape[2:]))


def _distances(model: LPIPS, first, second) -> np.ndarray:
    values = []
    with torch.inference_mode():
        for s in range(0, len(first), BATCH):
            a = torch.cat([_input(model, image) for image in first[s:s + BATCH]])
            b = torch.cat([_input(model, image) for image in second[s:s + BATCH]])
            values.append(model(a, b).numpy())
    return np.concatenate(values).astype(np.float64) if values else np.zeros(0)


def masked_lpips(model: LPIPS, original, edited, mask) -> float:
    """LPIPS between `original` and `edited` over the pixels where `mask` is true (see module docstring);
    nan for an empty mask."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return float("nan")
    a, b = to_lpips_input(original), to_lpips_input(edited)
    if a.shape != b.shape or tuple(a.shape[2:]) != mask.shape:
        raise ValueError(f"masked LPIPS needs equal image and mask sizes, got {tuple(a.shape[2:])}, "
                         f"{tuple(b.shape[2:])} and {mask.shape}")
    factor = _factor(model, *mask.shape)
    a, b, keep = _enlarge(a, factor), _enlarge(b, factor), _enlarge(torch.from_numpy(mask), factor)
    b = torch.where(keep, b, a)              # outside the compared region: no difference at all
    with torch.inference_mode():
        distance_map = model(a, b, spatial=True)[0]
    return float(distance_map[keep].mean())


def lpips_metrics(net: str, frames_original, frames_edited, views_original, views_edited,
                  gt_edits=None, gt_masks=None) -> tuple[dict[str, float], LPIPS]:
    model = load_lpips(net)
    values = {"lpips_edited_vs_original": float(np.mean(_distances(model, frames_original, frames_edited)))}
    if gt_edits is not None and gt_masks is not None:
        background = [masked_lpips(model, o, e, ~np.asarray(m, dtype=bool))
                      for o, e, m in zip(views_original, views_edited, gt_masks)]
        finite = [v for v in background if not np.isnan(v)]
        values["lpips_background"] = float(np.mean(finite)) if finite else float("nan")
        values["gt_lpips_edit"] = float(np.mean(_distances(model, views_edited, gt_edits)))
    return values, model
