"""Each behaviour of the InstructPix2Pix emulator (a simulator) shown statistically on a synthetic view."""
import numpy as np
import pytest

from dualnerf.editors import EditorError
from dualnerf.editors.emulator import EmulatedView, EmulatorConfig, InstructPix2PixEmulator

INSTRUCTION = "make it snowy"
QUIET = {"noise_range": (1.0, 1.0), "strength_jitter": 0.0, "tint_jitter": 0.0, "spatial_jitter": 0.0,
         "background_drift": 0.0, "background_blur": 0.0, "failure_rate": 0.0, "mask_feather": 0.0,
         "background_cast": 0.0, "lock_in": False}


def _view(size=32, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    original = np.stack([0.2 + 0.3 * xx, 0.4 + 0.2 * yy, 0.3 + 0.1 * xx * yy], -1)
    original = original + 0.1 * (((np.arange(size)[:, None] + np.arange(size)[None]) % 2) - 0.5)[..., None]
    original = np.clip(original + rng.normal(0, 0.01, original.shape), 0, 1)
    mask = np.zeros((size, size), bool)
    mask[size // 2:, :] = True                                   # the lower half gets snow
    gt = original.copy()
    gt[mask] = 0.85 + 0.1 * gt[mask]
    u8 = lambda a: (a * 255 + 0.5).astype(np.uint8)
    return EmulatedView(u8(original), u8(gt), mask)


def _emulator(view, **knobs):
    return InstructPix2PixEmulator([view], INSTRUCTION, "snow", EmulatorConfig(**{**QUIET, **knobs}))


def _f(a):
    return a.astype(np.float64) / 255


def test_quiet_emulator_reproduces_ground_truth_and_is_deterministic():
    view = _view()
    emu = _emulator(view)
    out = emu.edit(view.original, view.original, INSTRUCTION, seed=3, step=10)
    assert np.abs(out.astype(int) - view.gt_edit.astype(int)).max() <= 1
    emu = _emulator(view, **EmulatorConfig().__dict__)            # all defaults: random, but seeded
    a = emu.edit(view.original, view.original, INSTRUCTION, seed=3, step=10)
    b = emu.edit(view.original, view.original, INSTRUCTION, seed=3, step=10)
    c = emu.edit(view.original, view.original, INSTRUCTION, seed=4, step=10)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).max() > 0
    assert emu.identity["is_simulator"] and emu.identity["name"] == "InstructPix2PixEmulator"


def test_render_dependence_low_noise_keeps_render_artefacts():
    view = _view()
    artefact = np.zeros_like(view.original)
    artefact[..., 0] = 255                                        # a red artefact render
    emu = _emulator(view, noise_range=(0.02, 0.98))
    red, weights = [], []
    for seed in range(200):
        out = _f(emu.edit(artefact, view.original, INSTRUCTION, seed=seed, step=0))
        red.append(out[..., 0].mean() - out[..., 1].mean())
        weights.append(emu.last_details["render_weight"])
    red, weights = np.array(red), np.array(weights)
    assert np.corrcoef(red, weights)[0, 1] > 0.99                 # artefact survives in proportion
    assert red[weights > 0.8].mean() > 0.6 and red[weights < 0.2].mean() < 0.2
    assert abs(np.mean(1 - weights) - 0.5) < 0.05                  # s ~ U[0.02, 0.98]
    ignore = _emulator(view, noise_range=(0.02, 0.98), render_dependence=0.0)
    np.testing.assert_array_equal(ignore.edit(artefact, view.original, INSTRUCTION, 1, 0),
                                  ignore.edit(view.original, view.original, INSTRUCTION, 1, 0))


def test_strength_tint_and_spatial_jitter_make_views_inconsistent():
    view = _view()
    delta = (_f(view.gt_edit) - _f(view.original))[view.mask].mean()

    def mask_change(emu, seed):
        out = emu.edit(view.original, view.original, INSTRUCTION, seed=seed, step=0)
        return (_f(out) - _f(view.original))[view.mask]              # (M, 3)

    strength = [mask_change(_emulator(view, strength_jitter=0.2), s).mean() / delta for s in range(300)]
    assert abs(np.std(strength) - 0.2) < 0.04 and abs(np.mean(strength) - 1) < 0.05
    tints = np.array([mask_change(_emulator(view, tint_jitter=0.05), s).mean(0) for s in range(300)])
    tint_only = tints - tints.mean(0)
    assert abs(tint_only.std() - 0.05) < 0.01
    # spatial jitter: the change varies across the mask within a single call; without it, it does not
    gt_change = (_f(view.gt_edit) - _f(view.original))[view.mask]
    ratio_on = mask_change(_emulator(view, spatial_jitter=0.3), 0) / gt_change   # per-pixel strength
    ratio_off = mask_change(_emulator(view), 0) / gt_change
    assert np.std(ratio_off) < 0.02 and 0.1 < np.std(ratio_on) < 0.6


def test_background_drift_and_blur_touch_only_the_background():
    view = _view()
    bg = ~view.mask
    drift = _emulator(view, background_drift=0.05)
    diffs = [(_f(drift.edit(view.original, view.original, INSTRUCTION, s, 0)) - _f(view.original))[bg].mean(0)
             for s in range(200)]
    assert 0.04 < np.std(diffs) < 0.12                          # gain and offset both ~0.05
    out = drift.edit(view.original, view.original, INSTRUCTION, 0, 0)
    assert np.abs(out[view.mask].astype(int) - view.gt_edit[view.mask].astype(int)).max() <= 1

    def high_freq(img):
        g = _f(img)[: view.mask.shape[0] // 2 - 2]                 # background rows away from the edge
        return np.abs(np.diff(g, axis=1)).mean()

    blur = _emulator(view, background_blur=2.0)
    sharp = high_freq(view.original)
    blurred = [high_freq(blur.edit(view.original, view.original, INSTRUCTION, s, 0)) for s in range(40)]
    assert np.mean(blurred) < 0.7 * sharp


def test_failures_happen_at_the_configured_rate_and_are_far_from_the_edit():
    view = _view()
    emu = _emulator(view, failure_rate=0.3)
    failed, errors = [], []
    for seed in range(400):
        out = _f(emu.edit(view.original, view.original, INSTRUCTION, seed, 0))
        failed.append(emu.last_details["failed"])
        errors.append(np.abs(out - _f(view.gt_edit)).mean())
    failed, errors = np.array(failed), np.array(errors)
    assert abs(failed.mean() - 0.3) < 0.07                       # ~3 binomial standard errors
    assert errors[~failed].max() < 0.01 < np.median(errors[failed])
    kinds = {emu.last_details["failure_kind"]} | {None}
    assert kinds <= {None, "wrong_colour", "garbage"}


def test_clear_errors():
    view = _view()
    emu = _emulator(view)
    with pytest.raises(EditorError, match="built for 'make it snowy'"):
        emu.edit(view.original, view.original, "make it pink", 0, 0)
    with pytest.raises(EditorError, match="no ground truth"):
        emu.edit(view.original, view.gt_edit, INSTRUCTION, 0, 0)
    with pytest.raises(EditorError, match="failure_rate"):
        EmulatorConfig(failure_rate=2.0)


def _two_mode_view(size=32, cast_weight=0.5):
    """_view() with an alternative mode: the lower half turns blue-grey instead of white."""
    view = _view(size)
    alt = _f(view.original).copy()
    alt[view.mask] = np.array([0.45, 0.55, 0.85]) + 0.1 * alt[view.mask]
    u8 = (alt * 255 + 0.5).astype(np.uint8)
    return EmulatedView(view.original, view.gt_edit, view.mask, modes=((u8, view.mask),),
                        cast_weight=cast_weight)


def test_lock_in_off_and_no_cast_give_emulator_version_1_outputs():
    # sha256 of 40 outputs of emulator version 1 (git 1e9c17d) on this view: the new draws come after
    # the old ones, so with both new knobs off every output is the same bit for bit.
    import hashlib

    view = _view()
    emu = InstructPix2PixEmulator([view], INSTRUCTION, "snow", EmulatorConfig(lock_in=False, background_cast=0.0))
    digest = hashlib.sha256()
    render = np.roll(view.gt_edit, 3, axis=1)
    for seed in range(40):
        digest.update(emu.edit(render, view.original, INSTRUCTION, seed, 7).tobytes())
    assert digest.hexdigest() == "473dd55b51323826f78f64500ce74a55297ce1ec1acee1de41436e9e18e59259"


def test_lock_in_follows_the_mode_the_render_shows_at_low_noise_and_the_prior_at_high_noise():
    view = _two_mode_view()
    gt, alt = view.gt_edit, view.modes[0][0]
    half_alt = ((_f(view.original) + _f(alt)) / 2 * 255 + 0.5).astype(np.uint8)

    def modes(render, noise, **knobs):
        emu = _emulator(view, **{"lock_in": True, "noise_range": (noise, noise), **knobs})
        drawn = []
        for seed in range(300):
            emu.edit(render, view.original, INSTRUCTION, seed, 0)
            drawn.append(emu.last_details["mode"])
        return np.array(drawn)

    prior = 2 / 3
    # Low noise: the render decides, even for a render only half-way to the wrong mode.
    assert modes(alt, 0.05).mean() > 0.9 and modes(half_alt, 0.05).mean() > 0.85
    assert modes(gt, 0.05).mean() < 0.03
    # The unedited render shows neither mode (q uniform): at low noise, where the render is kept, half
    # and half; at high noise the prior.
    assert abs((modes(view.original, 0.05) == 0).mean() - 0.5) < 0.1
    # High noise: the render hardly matters, the prior does.
    high = modes(alt, 0.98)
    assert abs((high == 0).mean() - prior) < 0.12
    # Off: the ground truth is the only mode, whatever the render.
    assert (modes(alt, 0.05, lock_in=False) == 0).all()
    # The drawn mode is what the output shows: at noise 1 the output is that mode's image.
    emu = _emulator(view, lock_in=True)
    for seed in range(20):
        out = emu.edit(alt, view.original, INSTRUCTION, seed, 0)
        expect = alt if emu.last_details["mode"] == 1 else gt
        assert np.abs(out.astype(int) - expect.astype(int)).max() <= 1


def test_systematic_background_cast_does_not_average_out():
    bg_of = lambda v: ~v.mask
    for weight in (0.0, 1.0):
        view = _two_mode_view(cast_weight=weight)
        emu = _emulator(view, background_cast=0.05, background_drift=0.04)
        shifts = np.array([(_f(emu.edit(view.original, view.original, INSTRUCTION, s, 0))
                            - _f(view.original))[bg_of(view)].mean(0) for s in range(300)])
        mean = shifts.mean(0)
        if weight == 0.0:
            assert np.abs(mean).max() < 0.01         # the zero-mean drift alone averages out
        else:
            # red up, blue down, by ~5% of the background's colour: a bias averaging cannot remove
            colour = _f(view.original)[bg_of(view)].mean(0)
            np.testing.assert_allclose(mean, 0.05 * np.array([1.0, 0.3, -0.8]) * colour, atol=0.01)
