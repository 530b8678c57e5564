"""experiments/statistics.py against closed forms: identical rows, constant shifts, known means and spreads,
a two-point bootstrap distribution worked out by hand, and pairing by (scene, edit, seed) only."""
import math

import numpy as np
import pytest

from experiments import statistics as S


def _units(values, scene="tiny", edit="snow"):
    return {(scene, edit, seed): v for seed, v in enumerate(values)}


def test_identical_rows_give_a_zero_interval():
    row = _units([0.11, 0.37, 0.52, 0.08])
    diff = S.paired_difference(row, dict(row))
    assert (diff.mean, diff.low, diff.high, diff.n_pairs) == (0.0, 0.0, 0.0, 4)
    assert diff.contains_zero is True
    assert diff.unpaired == diff.unpaired_reference == diff.non_finite == ()


def test_a_constant_shift_gives_that_shift_exactly():
    reference = _units([0.11, 0.37, 0.52, 0.08, 0.9])
    shifted = {u: v + 0.25 for u, v in reference.items()}
    diff = S.paired_difference(shifted, reference)
    assert diff.low == pytest.approx(0.25, abs=1e-15) and diff.high == pytest.approx(0.25, abs=1e-15)
    assert diff.mean == pytest.approx(0.25, abs=1e-15)
    assert diff.contains_zero is False
    negative = S.paired_difference(reference, shifted)
    assert negative.high == pytest.approx(-0.25, abs=1e-15) and negative.contains_zero is False


def test_two_point_bootstrap_matches_its_exact_distribution():
    # Differences {0, 1}: a resampled mean is 0, 0.5 or 1 with probabilities 1/4, 1/2, 1/4, so the 2.5%
    # and 97.5% quantiles of many resamples are 0 and 1, and the estimate is 0.5.
    diff = S.paired_difference(_units([0.0, 1.0]), _units([0.0, 0.0]))
    assert (diff.mean, diff.low, diff.high) == (0.5, 0.0, 1.0)
    assert diff.contains_zero is True


def test_large_sample_interval_matches_the_normal_approximation():
    rng = np.random.default_rng(7)
    d = rng.normal(0.3, 1.0, size=400)
    low, high = S.bootstrap_mean_interval(d)
    half = 1.959964 * d.std(ddof=1) / math.sqrt(d.size)
    assert low == pytest.approx(d.mean() - half, abs=0.1 * half)
    assert high == pytest.approx(d.mean() + half, abs=0.1 * half)
    # Seeded: the same call gives the same interval; another seed a slightly different one.
    assert S.bootstrap_mean_interval(d) == (low, high)
    assert S.bootstrap_mean_interval(d, seed=1) != (low, high)


def test_pairing_uses_matching_units_only_and_says_what_was_unpaired():
    row = {("a", "snow", 0): 1.0, ("a", "snow", 1): 2.0, ("b", "snow", 0): 50.0}
    reference = {("a", "snow", 0): 0.0, ("a", "snow", 1): 0.0, ("c", "fire", 0): -50.0}
    diff = S.paired_difference(row, reference)
    assert diff.n_pairs == 2 and diff.mean == 1.5
    assert diff.unpaired == (("b", "snow", 0),)
    assert diff.unpaired_reference == (("c", "fire", 0),)
    assert (diff.low, diff.high) == (1.0, 2.0)         # resamples of {1, 2}: the exact two-point case


def test_non_finite_units_are_left_out_and_counted():
    row = {("a", "e", 0): math.inf, ("a", "e", 1): 3.0, ("a", "e", 2): 4.0, ("a", "e", 3): math.nan}
    reference = {("a", "e", s): 1.0 for s in range(4)}
    diff = S.paired_difference(row, reference)
    assert diff.n_pairs == 2 and diff.mean == 2.5
    assert diff.non_finite == (("a", "e", 0), ("a", "e", 3))


def test_a_seedless_row_pairs_with_every_seed_of_the_reference():
    original = {("a", "e", None): 1.0, ("b", "e", None): 2.0}
    reference = {("a", "e", 0): 0.5, ("a", "e", 1): 0.5, ("b", "e", 0): 1.0}
    diff = S.paired_difference(original, reference)
    assert diff.n_pairs == 3 and diff.mean == pytest.approx((0.5 + 0.5 + 1.0) / 3)
    assert diff.unpaired == diff.unpaired_reference == ()


def test_one_pair_has_an_estimate_but_no_interval():
    diff = S.paired_difference(_units([2.0]), _units([1.0]))
    assert diff.mean == 1.0 and math.isnan(diff.low) and diff.contains_zero is None


def test_summary_is_mean_and_sample_std_of_per_seed_means():
    # Seed 0 ran two scenes (1, 3 -> mean 2), seed 1 too (2, 6 -> mean 4): mean 3, std sqrt(2).
    summary = S.summarize_over_seeds([1.0, 3.0, 2.0, 6.0], [0, 0, 1, 1])
    assert (summary.mean, summary.n, summary.n_seeds) == (3.0, 4, 2)
    assert summary.std == pytest.approx(math.sqrt(2.0))
    # One scene: the plain mean ± sample std over seeds.
    plain = S.summarize_over_seeds([0.10, 0.14, 0.15], [0, 1, 2])
    assert plain.mean == pytest.approx(0.13) and plain.std == pytest.approx(np.std([0.10, 0.14, 0.15], ddof=1))
    single = S.summarize_over_seeds([0.5, math.nan], [None, 3])
    assert (single.mean, single.n, single.n_seeds) == (0.5, 1, 1) and math.isnan(single.std)
    infinite = S.summarize_over_seeds([math.inf, math.inf], [0, 1])
    assert infinite.mean == math.inf and math.isnan(infinite.std)


def test_paired_t_interval_and_its_verdict_on_known_data():
    # d = (1, 2, 3): mean 2, sd 1, t_{0.975,2} = 4.3027 -> 2 ± 4.3027/sqrt(3) = [-0.4842, 4.4842]: includes 0
    # although every unit is positive (3 units cannot show it at 95%).
    diff = S.paired_difference(_units([1.0, 2.0, 3.0]), _units([0.0, 0.0, 0.0]))
    assert diff.t_low == pytest.approx(2 - 4.3027 / math.sqrt(3), abs=1e-4)
    assert diff.t_high == pytest.approx(2 + 4.3027 / math.sqrt(3), abs=1e-4)
    assert diff.excludes_zero is False
    assert diff.contains_zero is False                  # the percentile bootstrap ([1, 3]) is narrower
    # d = (1.0, 1.1, 0.9, 1.0): mean 1, sd 0.08165, t_{0.975,3} = 3.1824 -> [0.870, 1.130]: excludes 0.
    tight = S.paired_difference(_units([1.0, 1.1, 0.9, 1.0]), _units([0.0] * 4))
    assert (tight.t_low, tight.t_high) == pytest.approx((1 - 3.1824 * 0.0816497 / 2, 1 + 3.1824 * 0.0816497 / 2),
                                                        abs=1e-4)
    assert tight.excludes_zero is True
    # Below zero, too; a constant shift has a zero-width interval; one pair has no verdict.
    assert S.paired_difference(_units([0.0] * 4), _units([1.0, 1.1, 0.9, 1.0])).excludes_zero is True
    assert S.paired_difference(_units([0.0, 0.0]), _units([0.0, 0.0])).excludes_zero is False
    assert S.paired_difference(_units([2.0]), _units([1.0])).excludes_zero is None


def test_t_quantiles_match_the_tables():
    # Student's t at 0.975 (printed tables): df 1, 2, 10, 30; the expansion beyond 30: 40, 120, and z.
    for df, value in ((1, 12.706), (2, 4.303), (10, 2.228), (30, 2.042), (40, 2.021), (120, 1.980)):
        assert S.t_quantile_975(df) == pytest.approx(value, abs=1e-3)
    assert S.t_quantile_975(10 ** 6) == pytest.approx(1.960, abs=1e-3)
    with pytest.raises(ValueError):
        S.t_quantile_975(0)
