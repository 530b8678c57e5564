"""Metric functions against hand-computed values on tiny constructed embeddings and images."""
import math

import numpy as np
import pytest

from dualnerf import metrics


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_cosine_rows_closed_form_and_zero_vector():
    a = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 0.0]])
    b = np.array([[0.0, 2.0], [2.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(metrics.cosine_rows(a, b), [0.0, 1 / math.sqrt(2), 0.0])


def test_t2i_edit_along_caption_direction_is_one_and_orthogonal_is_zero():
    rng = np.random.default_rng(0)
    original = rng.normal(size=(5, 8))
    source, target = rng.normal(size=8), rng.normal(size=8)
    caption_dir = target - source
    scales = np.array([0.1, 0.5, 1.0, 2.0, 3.0])[:, None]
    assert metrics.clip_text_image_direction(original + scales * caption_dir, original, target, source) \
        == pytest.approx(1.0)
    assert metrics.clip_text_image_direction(original - caption_dir, original, target, source) \
        == pytest.approx(-1.0)
    # A direction orthogonal to the caption direction (Gram-Schmidt against it).
    other = rng.normal(size=8)
    ortho = other - (other @ caption_dir) / (caption_dir @ caption_dir) * caption_dir
    assert metrics.clip_text_image_direction(original + ortho, original, target, source) \
        == pytest.approx(0.0, abs=1e-12)


def test_t2i_mixture_matches_hand_computed_angle():
    original = np.zeros((2, 2))
    edited = np.array([[1.0, 0.0], [1.0, 1.0]])   # 0 deg and 45 deg from the caption direction
    value = metrics.clip_text_image_direction(edited, original, [1.0, 0.0], [0.0, 0.0])
    assert value == pytest.approx((1.0 + 1 / math.sqrt(2)) / 2)


def test_t2i_unedited_scene_scores_zero():
    original = np.random.default_rng(1).normal(size=(4, 6))
    assert metrics.clip_text_image_direction(original, original, np.ones(6), np.zeros(6)) == 0.0


def test_direction_consistency_constant_offset_is_one():
    rng = np.random.default_rng(2)
    original = rng.normal(size=(6, 5))
    edited = original + rng.normal(size=5)             # the same edit on every frame
    assert metrics.clip_direction_consistency(edited, original) == pytest.approx(1.0)
    assert metrics.clip_edit_direction_consistency(edited, original) == pytest.approx(1.0)


def test_direction_consistency_reversed_motion_is_minus_one():
    original = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    edited = original[::-1].copy()
    assert metrics.clip_direction_consistency(edited, original) == pytest.approx(-1.0)


def test_edit_direction_consistency_alternating_edit_is_minus_one():
    original = np.zeros((4, 3))
    edited = np.array([[1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0]])
    assert metrics.clip_edit_direction_consistency(edited, original) == pytest.approx(-1.0)
    # The IN2N C_dir is 0 here: the original frames do not move, a zero direction aligns with nothing.
    assert metrics.clip_direction_consistency(edited, original) == pytest.approx(0.0)


def test_frame_consistency_hand_computed():
    edited = np.array([_unit([1, 0]), _unit([1, 1]), _unit([0, 1])])
    assert metrics.clip_frame_consistency(edited) == pytest.approx(1 / math.sqrt(2))


def test_clip_metric_input_errors():
    with pytest.raises(metrics.MetricInputError, match="match in shape"):
        metrics.clip_direction_consistency(np.zeros((3, 4)), np.zeros((2, 4)))
    with pytest.raises(metrics.MetricInputError, match="at least 2 frames"):
        metrics.clip_frame_consistency(np.ones((1, 4)))
    with pytest.raises(metrics.MetricInputError, match="dimension 4"):
        metrics.clip_text_image_direction(np.ones((2, 4)), np.zeros((2, 4)), np.ones(3), np.zeros(3))
    with pytest.raises(metrics.MetricInputError, match="non-finite"):
        metrics.clip_frame_consistency(np.array([[np.nan, 1.0], [1.0, 1.0]]))
    assert issubclass(metrics.MetricInputError, ValueError)


def test_ssim_identical_is_one_and_noise_lowers_it():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(24, 32, 3), dtype=np.uint8)
    assert metrics.ssim(image, image) == pytest.approx(1.0)
    noise = rng.integers(-40, 41, size=image.shape)
    noisy = np.clip(image.astype(int) + noise, 0, 255).astype(np.uint8)
    noisier = np.clip(image.astype(int) + 3 * noise, 0, 255).astype(np.uint8)
    assert metrics.ssim(image, noisier) < metrics.ssim(image, noisy) < 0.99
    # Symmetric, and uint8 and float inputs agree.
    assert metrics.ssim(image, noisy) == pytest.approx(metrics.ssim(noisy, image))
    assert metrics.ssim(image, noisy) == pytest.approx(metrics.ssim(image / 255.0, noisy / 255.0))


def test_ssim_constant_images_closed_form():
    # For constant images only the luminance term remains: (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1).
    a = np.full((16, 16, 3), 0.25)
    b = np.full((16, 16, 3), 0.75)
    c1 = (0.01 * 1.0) ** 2
    expected = (2 * 0.25 * 0.75 + c1) / (0.25 ** 2 + 0.75 ** 2 + c1)
    assert metrics.ssim(a, b) == pytest.approx(expected, rel=1e-6)


def test_psnr_closed_form():
    a = np.zeros((12, 12, 3))
    b = np.full((12, 12, 3), 0.1)                     # MSE 0.01 -> 20 dB
    assert metrics.psnr(a, b) == pytest.approx(20.0)
    assert metrics.psnr(a, a) == math.inf


def test_masked_psnr_and_ssim_closed_form():
    original = np.full((16, 16, 3), 0.5)
    edited = original.copy()
    mask = np.zeros((16, 16), dtype=bool)
    mask[4:8, 4:12] = True                            # 32 edit pixels
    edited[mask] = 0.5 + 0.2                          # inside: error 0.2 -> MSE 0.04 -> 13.979 dB
    edited[~mask] = 0.5 + 0.01                        # outside: error 0.01 -> MSE 1e-4 -> 40 dB
    assert metrics.psnr(edited, original, ~mask) == pytest.approx(40.0)
    assert metrics.psnr(edited, original, mask) == pytest.approx(10 * math.log10(1 / 0.04))
    # Whole image: MSE = (32 * 0.04 + 224 * 1e-4) / 256.
    mse = (32 * 0.04 + 224 * 1e-4) / 256
    assert metrics.psnr(edited, original) == pytest.approx(10 * math.log10(1 / mse))
    assert np.isnan(metrics.psnr(edited, original, np.zeros((16, 16), dtype=bool)))
    # Masked SSIM only sees differences inside its mask: whatever the edited image holds outside the
    # mask does not change the value.
    far = np.zeros((16, 16), dtype=bool)
    far[12:, :] = True
    scrambled = edited.copy()
    scrambled[~far] = np.random.default_rng(4).uniform(size=scrambled[~far].shape)
    assert metrics.ssim(scrambled, original, far) == pytest.approx(metrics.ssim(edited, original, far))
    assert metrics.ssim(scrambled, original, far) < 1.0
    assert metrics.ssim(edited, original, mask) < metrics.ssim(edited, original, far)


def test_image_metric_input_errors():
    with pytest.raises(metrics.MetricInputError, match="differ in size"):
        metrics.psnr(np.zeros((12, 12, 3)), np.zeros((12, 13, 3)))
    with pytest.raises(metrics.MetricInputError, match="outside \\[0, 1\\]"):
        metrics.psnr(np.full((12, 12, 3), 2.0), np.zeros((12, 12, 3)))
    with pytest.raises(metrics.MetricInputError, match="at least 11x11"):
        metrics.ssim(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))
    with pytest.raises(metrics.MetricInputError, match="mask shape"):
        metrics.psnr(np.zeros((12, 12, 3)), np.zeros((12, 12, 3)), np.ones((3, 3), bool))


def test_mean_over_views_skips_empty_masks():
    a = np.zeros((12, 12, 3))
    b = np.full((12, 12, 3), 0.1)
    full = np.ones((12, 12), bool)
    empty = np.zeros((12, 12), bool)
    assert metrics.mean_over_views([(a, b), (a, b)], metrics.psnr, [full, empty]) == pytest.approx(20.0)
    assert np.isnan(metrics.mean_over_views([(a, b)], metrics.psnr, [empty]))



def test_ground_truth_metrics_closed_form():
    # Two views of a known scene: the GT edit turns the masked square white; the "render" gets the
    # background off by 0.01 (40 dB) and the edit off by 0.1 (20 dB).
    original = [np.full((16, 16, 3), 0.3), np.full((16, 16, 3), 0.6)]
    masks = []
    gt, render = [], []
    for view, (r0, c0) in zip(original, [(2, 2), (8, 6)]):
        mask = np.zeros((16, 16), bool)
        mask[r0:r0 + 6, c0:c0 + 6] = True
        masks.append(mask)
        edit = view.copy()
        edit[mask] = 1.0
        gt.append(edit)
        out = view + 0.01
        out[mask] = 0.9
        render.append(out)
    values = metrics.ground_truth_metrics(render, gt, masks, original)
    assert values["gt_psnr_background"] == pytest.approx(40.0)
    assert values["gt_psnr_inside"] == pytest.approx(20.0)
    # Whole image vs GT: 36 pixels at error 0.1, 220 at 0.01.
    mse = (36 * 0.01 + 220 * 1e-4) / 256
    assert values["gt_psnr_edit"] == pytest.approx(10 * math.log10(1 / mse))
    assert 0 < values["gt_ssim_inside"] < values["gt_ssim_background"] <= 1.0
    # A perfect edit scores SSIM 1 / PSNR inf everywhere.
    perfect = metrics.ground_truth_metrics(gt, gt, masks, original)
    assert perfect["gt_ssim_edit"] == pytest.approx(1.0) and perfect["gt_psnr_edit"] == math.inf
    assert perfect["gt_psnr_background"] == math.inf
    with pytest.raises(metrics.MetricInputError, match="one GT edit"):
        metrics.ground_truth_metrics(render, gt[:1], masks, original)
