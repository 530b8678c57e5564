"""Evaluation metrics for text-driven scene editing (definitions and sources: docs/metrics.md).

CLIP-space metrics take embeddings, not images, so they are independent of which encoder produced them;
the caller stores the encoder identity next to every number (a proxy encoder's numbers are not CLIP's).
Image metrics take (H, W, 3) images, uint8 in [0, 255] or float in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# metrics.json, written by the evaluate stage and read by the report.
METRICS_FORMAT = "dualnerf-metrics"
METRICS_VERSION = 1

# Wang et al. 2004 SSIM settings: 11x11 Gaussian window (sigma 1.5), population covariance, K1/K2 defaults.
SSIM_SIGMA = 1.5
SSIM_WINDOW = 11
# Zero-length directions (an unedited frame) have no alignment with anything: their cosine counts as 0.
_ZERO_NORM = 1e-12


class MetricInputError(ValueError):
    """Inputs a metric cannot be computed on; the message says which input and what to do."""

    user_error = True        # the CLI prints the message and exits 2 (pipeline.errors)


@dataclass(frozen=True)
class MetricInfo:
    symbol: str
    higher_is_better: bool
    uses_encoder: bool
    summary: str
    uses_lpips: bool = False        # entries name the LPIPS backbone ("lpips" key), as CLIP ones the encoder


# Which direction is better for each metric name written to metrics.json (the report marks the best).
METRICS: dict[str, MetricInfo] = {
    "clip_text_image_direction": MetricInfo(
        "C_t2i", True, True, "cos(E_I(edit)-E_I(orig), E_T(target)-E_T(source)), mean over frames"),
    "clip_direction_consistency": MetricInfo(
        "C_dir", True, True, "cos(E_I(e_i+1)-E_I(e_i), E_I(o_i+1)-E_I(o_i)), mean over adjacent frames"),
    "clip_edit_direction_consistency": MetricInfo(
        "C_dir(edit)", True, True, "cos(E_I(e_i)-E_I(o_i), E_I(e_i+1)-E_I(o_i+1)), mean over adjacent frames"),
    "clip_frame_consistency": MetricInfo(
        "C_frame", True, True, "cos(E_I(e_i), E_I(e_i+1)), mean over adjacent edited frames"),
    "ssim_edited_vs_original": MetricInfo(
        "SSIM", True, False, "SSIM between original and edited path renders (background maintenance)"),
    "gt_psnr_edit": MetricInfo("PSNR_gt", True, False, "PSNR of edited renders vs ground-truth edited views"),
    "gt_ssim_edit": MetricInfo("SSIM_gt", True, False, "SSIM of edited renders vs ground-truth edited views"),
    "gt_psnr_background": MetricInfo(
        "PSNR_bg", True, False, "PSNR outside the edit mask vs the original views"),
    "gt_ssim_background": MetricInfo(
        "SSIM_bg", True, False, "SSIM outside the edit mask vs the original views"),
    "gt_psnr_inside": MetricInfo("PSNR_in", True, False, "PSNR inside the edit mask vs the GT edit"),
    "gt_ssim_inside": MetricInfo("SSIM_in", True, False, "SSIM inside the edit mask vs the GT edit"),
    "gt_mode_share": MetricInfo(
        "Mode_gt", True, False, "share of the in-region change that went to the ground-truth mode rather than "
        "the edit's alternative modes (1: ground truth, 0: an alternative, ~0.5: mixed)"),
    "lpips_edited_vs_original": MetricInfo(
        "LPIPS", False, False, "LPIPS between original and edited path renders", uses_lpips=True),
    "lpips_background": MetricInfo(
        "LPIPS_bg", False, False, "LPIPS outside the edit mask, edited vs original renders", uses_lpips=True),
    "gt_lpips_edit": MetricInfo(
        "LPIPS_gt", False, False, "LPIPS of edited renders vs ground-truth edited views", uses_lpips=True),
}


def json_value(value: float) -> float | str | None:
    """A metric value for plain JSON: nan (undefined) -> null, inf (identical images) -> "inf"."""
    value = float(value)
    if np.isnan(value):
        return None
    if np.isinf(value):
        return "inf" if value > 0 else "-inf"
    return value


def parse_json_value(value) -> float:
    """Inverse of json_value."""
    if value is None:
        return float("nan")
    if isinstance(value, str):
        return float(value)            # "inf" / "-inf"
    return float(value)


# ---------------------------------------------------------------------------------------------- CLIP space

def _as_matrix(name: str, values) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 2 or array.shape[0] == 0:
        raise MetricInputError(f"{name} must be a non-empty (frames, dim) array of embeddings, "
                               f"got shape {array.shape}; pass one embedding per rendered frame.")
    if not np.all(np.isfinite(array)):
        raise MetricInputError(f"{name} contains non-finite values; the encoder output is broken.")
    return array


def cosine_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cosine similarity; a row with a zero-length vector scores 0 (no direction, no alignment)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    norm = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.where(norm > _ZERO_NORM, dot / np.maximum(norm, _ZERO_NORM), 0.0)


def _paired(edited, original) -> tuple[np.ndarray, np.ndarray]:
    e = _as_matrix("edited image embeddings", edited)
    o = _as_matrix("original image embeddings", original)
    if e.shape != o.shape:
        raise MetricInputError(f"edited and original image embeddings must match in shape, got {e.shape} "
                               f"and {o.shape}; render both models along the same camera path.")
    return e, o


def _need_adjacent(e: np.ndarray) -> None:
    if len(e) < 2:
        raise MetricInputError("adjacent-frame consistency needs at least 2 frames; raise n_frames.")


def clip_text_image_direction(edited, original, target_text, source_text) -> float:
    """C_t2i (IN2N / StyleGAN-NADA directional similarity): mean_i cos(dI_i, dT), with
    dI_i = E_I(e_i) - E_I(o_i) and dT = E_T(target caption) - E_T(source caption)."""
    e, o = _paired(edited, original)
    target = np.asarray(target_text, dtype=np.float64).reshape(-1)
    source = np.asarray(source_text, dtype=np.float64).reshape(-1)
    if target.shape != source.shape or target.shape[0] != e.shape[1]:
        raise MetricInputError(f"caption embeddings must both have dimension {e.shape[1]} like the image "
                               f"embeddings, got {target.shape} and {source.shape}; use one encoder.")
    return float(np.mean(cosine_rows(e - o, target - source)))


def clip_direction_consistency(edited, original) -> float:
    """C_dir as IN2N defines it: mean_i cos(E_I(e_{i+1}) - E_I(e_i), E_I(o_{i+1}) - E_I(o_i))."""
    e, o = _paired(edited, original)
    _need_adjacent(e)
    return float(np.mean(cosine_rows(np.diff(e, axis=0), np.diff(o, axis=0))))


def clip_edit_direction_consistency(edited, original) -> float:
    """Alternative reading of "directional consistency": adjacent frames' edit directions agree,
    mean_i cos(E_I(e_i) - E_I(o_i), E_I(e_{i+1}) - E_I(o_{i+1}))."""
    e, o = _paired(edited, original)
    _need_adjacent(e)
    d = e - o
    return float(np.mean(cosine_rows(d[:-1], d[1:])))


def clip_frame_consistency(edited) -> float:
    """Adjacent edited frames' similarity, mean_i cos(E_I(e_i), E_I(e_{i+1})); defined for an unedited
    scene too, which is the reading under which the paper's "Original Scene" row has C_dir < 1."""
    e = _as_matrix("edited image embeddings", edited)
    _need_adjacent(e)
    return float(np.mean(cosine_rows(e[:-1], e[1:])))


# ---------------------------------------------------------------------------------------------- images

def to_unit_float(image, name: str = "image") -> np.ndarray:
    """(H, W, 3) uint8 or float image -> float64 in [0, 1]."""
    array = np.asarray(image)
    if array.ndim != 3 or array.shape[-1] != 3:
        raise MetricInputError(f"{name} must be an (H, W, 3) RGB image, got shape {array.shape}.")
    if array.dtype == np.uint8:
        return array.astype(np.float64) / 255.0
    array = array.astype(np.float64)
    if not np.all(np.isfinite(array)) or array.min() < -1e-6 or array.max() > 1 + 1e-6:
        raise MetricInputError(f"{name} is a float image outside [0, 1]; clip or rescale renders first.")
    return array


def _pair_images(a, b, mask, names: tuple[str, str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    x = to_unit_float(a, names[0])
    y = to_unit_float(b, names[1])
    if x.shape != y.shape:
        raise MetricInputError(f"{names[0]} {x.shape} and {names[1]} {y.shape} differ in size; render at "
                               f"the dataset resolution.")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != x.shape[:2]:
            raise MetricInputError(f"mask shape {mask.shape} does not match image size {x.shape[:2]}.")
    return x, y, mask


def psnr(a, b, mask=None) -> float:
    """Peak signal-to-noise ratio, 10 log10(1 / MSE) with intensities in [0, 1]; MSE over all channels of
    the pixels where `mask` is true (all pixels without a mask). inf for identical images, nan for an
    empty mask (undefined, reported as null)."""
    x, y, mask = _pair_images(a, b, mask, ("first image", "second image"))
    squared = (x - y) ** 2
    if mask is not None:
        if not mask.any():
            return float("nan")
        squared = squared[mask]
    mse = float(np.mean(squared))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def ssim(a, b, mask=None) -> float:
    """Structural similarity (Wang et al. 2004: Gaussian window sigma 1.5, K1 0.01, K2 0.03, data range
    1), averaged over colour channels. With a mask, the second image's pixels are pasted into the first
    outside the mask, so only differences inside the mask count (a window straddling the mask edge does
    not see differences from the other side), and the SSIM map is averaged over the masked pixels
    (image borders included, unlike the unmasked mean, which skimage takes over the interior). nan for
    an empty mask."""
    from skimage.metrics import structural_similarity

    x, y, mask = _pair_images(a, b, mask, ("first image", "second image"))
    if min(x.shape[:2]) < SSIM_WINDOW:
        raise MetricInputError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got "
                               f"{x.shape[1]}x{x.shape[0]}; render at a higher resolution.")
    if mask is not None:
        x = np.where(mask[..., None], x, y)
    mean, full = structural_similarity(x, y, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)
    if mask is None:
        return float(mean)
    if not mask.any():
        return float("nan")
    return float(np.mean(full.mean(axis=-1)[mask]))


def mean_over_views(pairs, metric, masks=None) -> float:
    """Mean of `metric(a, b[, mask])` over views, skipping views whose value is nan (empty mask) and
    returning nan if all are. inf values (identical images) make the mean inf."""
    values = []
    for i, (a, b) in enumerate(pairs):
        values.append(metric(a, b) if masks is None else metric(a, b, masks[i]))
    values = np.asarray(values, dtype=np.float64)
    finite_or_inf = values[~np.isnan(values)]
    return float(np.mean(finite_or_inf)) if finite_or_inf.size else float("nan")


def ground_truth_metrics(edited_renders, gt_edits, masks, original_views) -> dict[str, float]:
    """Ground-truth metrics over views (procedural scenes, where the edited scene is known):
    edit fidelity (edited render vs GT edited view, whole image), background preservation (outside the
    edit mask vs the original view) and the edit itself (inside the mask vs the GT edited view).
    Each is the mean over views; masked values skip views whose mask region is empty."""
    n = len(edited_renders)
    if not (n and len(gt_edits) == n and len(masks) == n and len(original_views) == n):
        raise MetricInputError(f"ground-truth metrics need one GT edit, mask and original view per render, "
                               f"got {n} renders, {len(gt_edits)} GT edits, {len(masks)} masks and "
                               f"{len(original_views)} original views.")
    outside = [~np.asarray(m, dtype=bool) for m in masks]
    vs_gt = list(zip(edited_renders, gt_edits))
    vs_original = list(zip(edited_renders, original_views))
    return {
        "gt_psnr_edit": mean_over_views(vs_gt, psnr),
        "gt_ssim_edit": mean_over_views(vs_gt, ssim),
        "gt_psnr_background": mean_over_views(vs_original, psnr, outside),
        "gt_ssim_background": mean_over_views(vs_original, ssim, outside),
        "gt_psnr_inside": mean_over_views(vs_gt, psnr, masks),
        "gt_ssim_inside": mean_over_views(vs_gt, ssim, masks),
    }


MODE_SHARE_MIN_CHANGE = 0.1       # below this much of an edit (in coefficient units) the mode is undefined


def mode_share(edited_renders, gt_edits, mode_edits, original_views, masks) -> float:
    """Which mode the edited renders are in: the change render - original inside `masks` (the union of the
    modes' regions), fitted by least squares over all views as a (gt - original) + sum_k b_k (mode_k -
    original), and a+ / (a+ + sum_k b_k+) with x+ = max(x, 0). 1: the ground-truth mode, 0: an alternative,
    in between: mixed. nan when a+ + sum b_k+ < MODE_SHARE_MIN_CHANGE (too little edit to tell, e.g. the
    unedited scene). `mode_edits[k]` holds mode k's image per view; images in [0, 255] or [0, 1] alike."""
    n = len(edited_renders)
    if not (n and len(gt_edits) == n and len(original_views) == n and len(masks) == n
            and all(len(m) == n for m in mode_edits) and mode_edits):
        raise MetricInputError("mode_share needs per view a render, a GT edit, an original, a mask and every "
                               "alternative mode's image.")
    f = lambda images: [np.asarray(x, np.float64) / (255.0 if np.asarray(x).dtype == np.uint8 else 1.0)
                        for x in images]
    renders, gts, originals = f(edited_renders), f(gt_edits), f(original_views)
    modes = [f(m) for m in mode_edits]
    sel = [np.asarray(m, bool) for m in masks]
    if not any(m.any() for m in sel):
        return float("nan")
    column = lambda images: np.concatenate([(x - o)[m].ravel() for x, o, m in zip(images, originals, sel)])
    basis = np.stack([column(gts)] + [column(m) for m in modes], axis=1)
    coefficients = np.maximum(np.linalg.lstsq(basis, column(renders), rcond=None)[0], 0.0)
    total = float(coefficients.sum())
    return float(coefficients[0] / total) if total >= MODE_SHARE_MIN_CHANGE else float("nan")


def clip_metrics(edited, original, target_text=None, source_text=None) -> dict[str, float]:
    """Every CLIP-space metric for one camera path (embeddings per frame, in path order). Without caption
    embeddings C_t2i is nan (undefined, reported as null)."""
    values = {"clip_text_image_direction": float("nan")}
    if target_text is not None and source_text is not None:
        values["clip_text_image_direction"] = clip_text_image_direction(edited, original, target_text,
                                                                        source_text)
    values["clip_direction_consistency"] = clip_direction_consistency(edited, original)
    values["clip_edit_direction_consistency"] = clip_edit_direction_consistency(edited, original)
    values["clip_frame_consistency"] = clip_frame_consistency(edited)
    return values
