"""Statistics of the report: mean ± std over seeds, and paired differences with t and bootstrap intervals.

Pure numpy, no plotting, no files. Definitions (also in docs/metrics.md):

- A *unit* is one (scene, edit, seed) cell of the grid. A table row (one method label and one set of
  parameter-axis values) has at most one run per unit.
- `summarize_over_seeds`: the mean of each seed's mean over the scenes and edits it ran, then the mean
  ± sample standard deviation (ddof = 1) of those per-seed means. With one scene and edit this is the
  plain mean ± std over seeds; over several it is the Table-1 number and its seed-to-seed spread.
- `paired_difference`: for the units both rows ran, d_u = value(row, u) − value(reference, u); the
  estimate is mean_u d_u and the interval a percentile bootstrap: B resamples of the units with
  replacement, the mean of each, and the (1−level)/2 and (1+level)/2 quantiles of those B means
  (numpy's default linear interpolation). Units whose value is nan or ±inf in either row are left out
  and counted. A row run without a seed (seed None: the unedited scene, which no seed changes) pairs
  with every seed of the reference in the same scene and edit.
- The paired t interval of the same differences, mean ± t_{(1+level)/2, n-1} · sd/√n (sd with ddof = 1),
  is the report's verdict: `excludes_zero`. At n = 3 the percentile bootstrap has at most 10 distinct
  resampled means and under-covers; the t interval (t = 4.303 at n = 3) is the honest one if the
  differences are roughly normal. Both intervals are recorded.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

BOOTSTRAP_RESAMPLES = 10_000    # B: quantiles of 10k resampled means move < 1% of the interval width
BOOTSTRAP_LEVEL = 0.95
BOOTSTRAP_SEED = 0              # each comparison draws from a fresh default_rng(BOOTSTRAP_SEED)
BOOTSTRAP_METHOD = "percentile"
MIN_PAIRS = 2                   # fewer paired units: no interval (a single difference has no spread)
T_LEVEL = 0.95                  # the paired t interval's level (the report's "excludes 0" verdict)

# Student t quantiles t_{0.975, df} for df = 1..30; beyond, the Cornish-Fisher expansion around z (error
# < 1e-4 for df > 30).
_T975 = (12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281, 2.2010, 2.1788,
         2.1604, 2.1448, 2.1314, 2.1199, 2.1098, 2.1009, 2.0930, 2.0860, 2.0796, 2.0739, 2.0687, 2.0639,
         2.0595, 2.0555, 2.0518, 2.0484, 2.0452, 2.0423)
_Z975 = 1.959963984540054

Unit = tuple[str, str, Hashable]          # (scene, edit, seed)


@dataclass(frozen=True)
class Summary:
    mean: float
    std: float          # sample std (ddof = 1) of the per-seed means; nan with fewer than two seeds
    n: int              # runs with a finite value
    n_seeds: int        # distinct seeds among them (None counts as one)


def summarize_over_seeds(values: Sequence[float], seeds: Sequence[Hashable]) -> Summary:
    """Mean ± sample std over seeds of each seed's mean over its runs; nan values are left out. An
    infinite value makes the mean ±inf and the std nan (no spread can be stated)."""
    if len(values) != len(seeds):
        raise ValueError(f"{len(values)} values but {len(seeds)} seeds")
    per_seed: dict[Hashable, list[float]] = {}
    for value, seed in zip(values, seeds):
        if not math.isnan(value):
            per_seed.setdefault(seed, []).append(float(value))
    if not per_seed:
        return Summary(math.nan, math.nan, 0, 0)
    means = np.array([np.mean(v) for v in per_seed.values()])
    n = sum(len(v) for v in per_seed.values())
    std = float(np.std(means, ddof=1)) if means.size > 1 and np.all(np.isfinite(means)) else math.nan
    return Summary(float(np.mean(means)), std, n, len(per_seed))


@dataclass(frozen=True)
class PairedDifference:
    mean: float                          # mean paired difference (row − reference); nan without pairs
    low: float                           # bootstrap interval; nan with fewer than MIN_PAIRS pairs
    high: float
    n_pairs: int
    unpaired: tuple[Unit, ...]           # the row's units the reference did not run
    unpaired_reference: tuple[Unit, ...]  # the reference's units the row did not run
    non_finite: tuple[Unit, ...]         # paired units left out: nan/inf in either row
    t_low: float = math.nan              # paired t interval (T_LEVEL); nan with fewer than MIN_PAIRS pairs
    t_high: float = math.nan

    @property
    def excludes_zero(self) -> bool | None:
        """The report's verdict: True when the paired t interval lies entirely above or below 0; None
        without an interval."""
        if math.isnan(self.t_low) or math.isnan(self.t_high):
            return None
        return not (self.t_low <= 0.0 <= self.t_high)

    @property
    def contains_zero(self) -> bool | None:
        """True when the interval contains 0 (no difference shown at this n); None without an interval."""
        if math.isnan(self.low) or math.isnan(self.high):
            return None
        return self.low <= 0.0 <= self.high


def bootstrap_mean_interval(differences: np.ndarray, *, resamples: int = BOOTSTRAP_RESAMPLES,
                            level: float = BOOTSTRAP_LEVEL, seed: int = BOOTSTRAP_SEED) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of `differences` (resampled with replacement)."""
    differences = np.asarray(differences, dtype=np.float64)
    if differences.ndim != 1 or differences.size == 0:
        raise ValueError(f"need a non-empty 1-D array of differences, got shape {differences.shape}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    means = differences[_resample_indices(differences.size, resamples, seed)].mean(axis=1)
    low, high = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    # Every resampled mean of a constant vector is that constant up to rounding: keep it exact.
    low, high = max(float(low), float(differences.min())), min(float(high), float(differences.max()))
    return low, high


def t_quantile_975(df: int) -> float:
    """Student's t quantile at 0.975 with `df` degrees of freedom."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = _Z975
    return (z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * df ** 3))


def t_mean_interval(differences: np.ndarray) -> tuple[float, float]:
    """Paired t interval (95%) of the mean of `differences`: mean ± t_{0.975, n-1} · sd / sqrt(n)."""
    differences = np.asarray(differences, dtype=np.float64)
    if differences.ndim != 1 or differences.size < 2:
        raise ValueError(f"need a 1-D array of at least 2 differences, got shape {differences.shape}")
    mean = float(differences.mean())
    if np.all(differences == differences[0]):
        return float(differences[0]), float(differences[0])
    half = t_quantile_975(differences.size - 1) * float(differences.std(ddof=1)) / math.sqrt(differences.size)
    return mean - half, mean + half


@functools.lru_cache(maxsize=8)
def _resample_indices(n: int, resamples: int, seed: int) -> np.ndarray:
    """The B x n unit indices of default_rng(seed): the same for every comparison with n units, so they
    are drawn once (read-only) instead of once per row and metric."""
    picks = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    picks.setflags(write=False)
    return picks


def _expand_seedless(values: Mapping[Unit, float], reference: Mapping[Unit, float]) -> dict[Unit, float]:
    """A seed-None unit of `values` stands for every seed the reference ran in that scene and edit."""
    out: dict[Unit, float] = {}
    for (scene, edit, seed), value in values.items():
        partners = [u for u in reference if u[:2] == (scene, edit)] if seed is None else []
        if seed is None and partners and (scene, edit, None) not in reference:
            for unit in partners:
                out[unit] = value
        else:
            out[(scene, edit, seed)] = value
    return out


def paired_difference(values: Mapping[Unit, float], reference: Mapping[Unit, float], *,
                      resamples: int = BOOTSTRAP_RESAMPLES, level: float = BOOTSTRAP_LEVEL,
                      seed: int = BOOTSTRAP_SEED) -> PairedDifference:
    """Mean difference of `values` − `reference` over their shared units, with a percentile bootstrap
    interval over those units. Both map (scene, edit, seed) -> metric value."""
    values = _expand_seedless(values, reference)
    reference = _expand_seedless(reference, values)
    shared = [u for u in values if u in reference]
    finite = [u for u in shared if math.isfinite(values[u]) and math.isfinite(reference[u])]
    differences = np.array([values[u] - reference[u] for u in finite], dtype=np.float64)
    mean = float(differences.mean()) if differences.size else math.nan
    if differences.size and np.all(differences == differences[0]):
        mean = float(differences[0])           # exact for identical rows and constant shifts
    if differences.size >= MIN_PAIRS:
        low, high = bootstrap_mean_interval(differences, resamples=resamples, level=level, seed=seed)
        t_low, t_high = t_mean_interval(differences)
    else:
        low = high = t_low = t_high = math.nan
    return PairedDifference(
        mean, low, high, len(finite),
        unpaired=tuple(sorted((u for u in values if u not in reference), key=repr)),
        unpaired_reference=tuple(sorted((u for u in reference if u not in values), key=repr)),
        non_finite=tuple(sorted((u for u in shared if u not in finite), key=repr)), t_low=t_low, t_high=t_high)
