"""Statistics of the lab, pure numpy: IQM, stratified bootstrap CIs, the probability of
improvement P(X > Y), the Wilson interval of a share, the verdict word, and a bootstrap band of
learning curves. Nothing here reads files or knows about runs (tests/test_stats.py checks each
against values computed by hand).

Written after Agarwal et al. 2021 ("Deep RL at the edge of the statistical precipice", rliable):
the IQM is the mean of the middle 50% of the scores, CIs are percentile bootstrap CIs where the
seeds are resampled within each env (stratum), and P(X > Y) counts ties as ½.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

CONFIDENCE = 0.95
N_BOOT = 2000


def _iqm_weights(n: int) -> np.ndarray:
    """Weights of the sorted observations for the mean of the middle 50%.

    Observation i covers [i, i+1) of [0, n); the middle half is [n/4, 3n/4), so when n is not a
    multiple of 4 the two boundary observations count fractionally (for n = 4m this is the
    25%-trimmed mean, as `scipy.stats.trim_mean(x, 0.25)` and rliable compute it).
    """
    if n < 1:
        raise ValueError("IQM of an empty sample")
    i = np.arange(n, dtype=float)
    w = np.clip(np.minimum(i + 1, 0.75 * n) - np.maximum(i, 0.25 * n), 0.0, 1.0)
    return w / w.sum()


def iqm(scores: Any, axis: int = -1) -> np.ndarray | float:
    """Interquartile mean: the mean of the middle 50% of `scores` along `axis`."""
    x = np.moveaxis(np.sort(np.asarray(scores, dtype=float), axis=axis), axis, -1)
    out = (x * _iqm_weights(x.shape[-1])).sum(axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def stratified_bootstrap(
    groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray], n_boot: int = N_BOOT, seed: int = 0,
) -> np.ndarray:
    """Bootstrap replicates of `statistic`, resampling within each stratum.

    `groups` is one or more lists of strata (one 1-D sample per env, e.g. the per-seed scores of
    one algorithm on each env). Every stratum of every group is resampled with replacement,
    independently and keeping its size. `statistic(*groups)` gets, per group, a list of arrays
    of shape (B, n_stratum) and must return shape (B,). Returns the `n_boot` replicates.
    """
    rng = np.random.default_rng(seed)
    resampled = []
    for strata in groups:
        arrays = [np.asarray(s, dtype=float) for s in strata]
        if not arrays or any(a.ndim != 1 or a.size == 0 for a in arrays):
            raise ValueError("every stratum must be a non-empty 1-D sample")
        resampled.append([a[rng.integers(0, a.size, size=(n_boot, a.size))] for a in arrays])
    return np.asarray(statistic(*resampled), dtype=float)


@dataclass(frozen=True)
class Interval:
    """A point estimate with a (lo, hi) confidence interval."""

    value: float
    lo: float
    hi: float

    def contains(self, x: float) -> bool:
        return self.lo <= x <= self.hi


def _point(groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray]) -> float:
    return float(np.asarray(statistic(*[[np.asarray(s, dtype=float)[None, :] for s in strata]
                                         for strata in groups]))[0])


def bootstrap_ci(
    groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray], n_boot: int = N_BOOT,
    confidence: float = CONFIDENCE, seed: int = 0,
) -> Interval:
    """Point estimate and percentile stratified-bootstrap CI of `statistic` (see stratified_bootstrap)."""
    reps = stratified_bootstrap(groups, statistic, n_boot, seed)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(reps, [alpha, 1.0 - alpha])
    return Interval(_point(groups, statistic), float(lo), float(hi))


def _pooled_iqm(strata: list[np.ndarray]) -> np.ndarray:
    return iqm(np.concatenate(strata, axis=-1), axis=-1)


def _pooled_mean(strata: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(strata, axis=-1).mean(axis=-1)


def iqm_ci(strata: Sequence[Any], n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0) -> Interval:
    """IQM of the scores of all strata pooled, with a stratified-bootstrap CI (one stratum per env)."""
    return bootstrap_ci([strata], _pooled_iqm, n_boot, confidence, seed)


def mean_ci(scores: Any, n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0) -> Interval:
    """Mean over seeds with a bootstrap CI (seeds resampled)."""
    return bootstrap_ci([[scores]], _pooled_mean, n_boot, confidence, seed)


def _poi_per_stratum(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of one env: mean over all pairs of 1[x > y] + ½·1[x = y]; shapes (B, n), (B, m)."""
    xx, yy = x[..., :, None], y[..., None, :]
    return ((xx > yy) + 0.5 * (xx == yy)).mean(axis=(-2, -1))


def probability_of_improvement(x_strata: Sequence[Any], y_strata: Sequence[Any]) -> float:
    """P(X > Y): per env, the chance a random run of X scores above a random run of Y (ties ½),
    averaged over envs. Strata are matched by position (one per env)."""
    return _point([x_strata, y_strata], _poi_stat)


def _poi_stat(xs: list[np.ndarray], ys: list[np.ndarray]) -> np.ndarray:
    if len(xs) != len(ys):
        raise ValueError("X and Y need the same envs")
    return np.mean([_poi_per_stratum(x, y) for x, y in zip(xs, ys)], axis=0)


def probability_of_improvement_ci(
    x_strata: Sequence[Any], y_strata: Sequence[Any], n_boot: int = N_BOOT, confidence: float = CONFIDENCE,
    seed: int = 0,
) -> Interval:
    """P(X > Y) with a stratified-bootstrap CI: the runs of X and of Y are resampled independently
    within each env."""
    return bootstrap_ci([x_strata, y_strata], _poi_stat, n_boot, confidence, seed)


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> Interval:
    """A share k/n with its Wilson score interval (sound for small n and k = 0 or n)."""
    if n <= 0:
        return Interval(math.nan, math.nan, math.nan)
    z = {0.95: 1.959963984540054, 0.9: 1.6448536269514722, 0.99: 2.5758293035489004}.get(round(confidence, 4))
    if z is None:
        from statistics import NormalDist

        z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return Interval(p, lo, hi)


def curve_band(curves: np.ndarray, n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over runs at each grid point and a bootstrap CI band (runs resampled; NaN where a run
    has no value is skipped)."""
    mean = np.full(curves.shape[1], np.nan)
    lo, hi = mean.copy(), mean.copy()
    rng = np.random.default_rng(seed)
    alpha = (1 - confidence) / 2
    for j in range(curves.shape[1]):
        col = curves[:, j][np.isfinite(curves[:, j])]
        if col.size == 0:
            continue
        mean[j] = col.mean()
        reps = col[rng.integers(0, col.size, size=(n_boot, col.size))].mean(axis=1)
        lo[j], hi[j] = np.quantile(reps, [alpha, 1 - alpha])
    return mean, lo, hi


# --- the verdict word ------------------------------------------------------------------------


BETTER, WORSE, NOT_SEPARATED, TOO_FEW = "better", "worse", "not separated", "too few runs"
MIN_RUNS = 3  # per side: with fewer, a bootstrap interval of P(X > Y) can collapse onto 0 or 1


def verdict_word(p: Interval, n_x: int = MIN_RUNS, n_y: int = MIN_RUNS) -> str:
    """*better* only where the 95% CI of P(MA > baseline) lies above ½, *worse* where it lies
    below, else *not separated* (also without a finite interval); *too few runs* while either
    side has fewer than MIN_RUNS runs (one run against two gives the interval [1, 1])."""
    if min(n_x, n_y) < MIN_RUNS:
        return TOO_FEW
    if math.isfinite(p.lo) and p.lo > 0.5:
        return BETTER
    if math.isfinite(p.hi) and p.hi < 0.5:
        return WORSE
    return NOT_SEPARATED
