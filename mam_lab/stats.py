"""Statistics of the lab, pure numpy (and itertools): IQM, stratified bootstrap CIs, the probability
of improvement P(X > Y), the Wilson interval of a share, a bootstrap band of learning curves, the
exact one-sided permutation (Mann-Whitney) test, Holm's correction, and the verdict word with its
stability over bootstrap seeds. Nothing here reads files or knows about runs (tests/test_stats.py
and tests/test_verdict.py check each against values computed by hand).

Written after Agarwal et al. 2021 ("Deep RL at the edge of the statistical precipice", rliable):
the IQM is the mean of the middle 50% of the scores, CIs are percentile bootstrap CIs where the
seeds are resampled within each env (stratum), and P(X > Y) counts ties as ½.

The verdict (issue #18): *better* only when the bootstrap CI of P(X > Y) (N_BOOT_VERDICT resamples)
lies above ½ and the exact one-sided p, Holm-adjusted over the rows sharing a baseline, is below
ALPHA; *worse* the mirror image; the word must be the same under STABILITY_SEEDS bootstrap seeds,
else *not separated*; *too few runs* below MIN_RUNS runs a side. The exact test enumerates every
split of the pooled scores (itertools) up to ENUMERATE_MAX splits, and beyond counts the same
splits by dynamic programming over the doubled mid-ranks: exact in both cases, ties included.
"""

from __future__ import annotations

import itertools
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



# --- the exact rank test ---------------------------------------------------------------------


ENUMERATE_MAX = 200_000  # up to this many splits are enumerated one by one (itertools); beyond, see exact_u_counts


def mid_ranks(values: Any) -> np.ndarray:
    """Ranks 1..N of `values`, tied values getting the mean of the ranks they span (mid-ranks)."""
    v = np.asarray(values, dtype=float)
    order = np.argsort(v, kind="stable")
    ranks = np.empty(v.size)
    i = 0
    while i < v.size:
        j = i
        while j + 1 < v.size and v[order[j + 1]] == v[order[i]]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2 + 1
        i = j + 1
    return ranks


def mann_whitney_u(x: Any, y: Any) -> float:
    """U of X against Y: the pairs (x, y) with x > y, ties counting ½ (= P(X > Y)·n·m)."""
    xx, yy = np.asarray(x, dtype=float)[:, None], np.asarray(y, dtype=float)[None, :]
    return float(((xx > yy) + 0.5 * (xx == yy)).sum())


def _doubled_ranks(x: Any, y: Any) -> tuple[np.ndarray, int]:
    pooled = np.concatenate([np.asarray(x, dtype=float), np.asarray(y, dtype=float)])
    if pooled.size == 0 or not np.all(np.isfinite(pooled)):
        raise ValueError("the exact test needs finite scores")
    return np.rint(2 * mid_ranks(pooled)).astype(np.int64), len(np.asarray(x))  # 2·mid-rank is an integer


def exact_u_counts(x: Any, y: Any, method: str = "auto") -> dict[int, int]:
    """The exact permutation distribution of 2U: {2U: number of splits}, over all C(N, n) ways to
    split the pooled N = n + m scores into n "X" and m "Y" (under H0 every split is equally
    likely). 2U of a split = 2·(sum of the X side's mid-ranks) − n(n+1), an integer even with ties.

    `method`: "enumerate" (itertools.combinations, every split), "dp" (the same counts by dynamic
    programming over the doubled mid-ranks: subsets of size k with doubled rank sum s), or "auto"
    (enumerate up to ENUMERATE_MAX splits)."""
    r2, n = _doubled_ranks(x, y)
    big_n = r2.size
    if method == "auto":
        method = "enumerate" if math.comb(big_n, n) <= ENUMERATE_MAX else "dp"
    shift = n * (n + 1)
    out: dict[int, int] = {}
    if method == "enumerate":
        for split in itertools.combinations(r2.tolist(), n):
            u2 = sum(split) - shift
            out[u2] = out.get(u2, 0) + 1
        return out
    if method != "dp":
        raise ValueError(f"unknown method {method!r}")
    total = int(r2.sum())
    counts = np.zeros((n + 1, total + 1), dtype=np.int64 if big_n <= 60 else object)
    counts[0, 0] = 1
    for r in r2.tolist():
        new = counts.copy()
        new[1:, r:] += counts[:-1, :total + 1 - r]
        counts = new
    for s in np.flatnonzero(counts[n]):
        out[int(s) - shift] = int(counts[n, s])
    return out


def exact_rank_test(x: Any, y: Any, alternative: str = "greater", method: str = "auto") -> float:
    """Exact one-sided permutation (Mann-Whitney) p-value: the share of the C(N, n) splits of the
    pooled scores whose U is at least the observed U ("greater": X tends to score above Y) or at
    most it ("less"). With complete separation of n against m runs it is 1/C(n+m, n): 1/20 for
    3 against 3, the smallest value 3 vs 3 allows."""
    if alternative not in ("greater", "less"):
        raise ValueError("alternative is 'greater' or 'less'")
    counts = exact_u_counts(x, y, method)
    r2, n = _doubled_ranks(x, y)
    observed = int(r2[:n].sum()) - n * (n + 1)
    total = sum(counts.values())
    if alternative == "greater":
        tail = sum(c for u2, c in counts.items() if u2 >= observed)
    else:
        tail = sum(c for u2, c in counts.items() if u2 <= observed)
    return tail / total


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of a family of p-values (same order out; NaN stays NaN and is not
    counted): sorted ascending p₍₁₎ ≤ … ≤ p₍ₘ₎, adjusted p₍ᵢ₎ = max over j ≤ i of min(1, (m − j + 1)·p₍ⱼ₎)."""
    p = [float(v) for v in pvalues]
    idx = sorted((i for i, v in enumerate(p) if math.isfinite(v)), key=lambda i: p[i])
    m = len(idx)
    out = [math.nan] * len(p)
    running = 0.0
    for j, i in enumerate(idx):
        running = max(running, min(1.0, (m - j) * p[i]))
        out[i] = running
    return out


# --- the verdict word ------------------------------------------------------------------------


BETTER, WORSE, NOT_SEPARATED, TOO_FEW = "better", "worse", "not separated", "too few runs"
MIN_RUNS = 5  # per side: 3 against 3 cannot reach p < 0.05 two-sided (its least one-sided p is 1/20)
ALPHA = 0.05  # the exact test's level, after Holm
N_BOOT_VERDICT = 10_000  # bootstrap resamples of P(X > Y) behind a verdict
STABILITY_SEEDS = 20  # the verdict must be the same word for bootstrap seeds 0..19


def verdict_word(p: Interval, n_x: int, n_y: int, p_better: float, p_worse: float, alpha: float = ALPHA) -> str:
    """*better* only where the 95% CI of P(MA > baseline) lies above ½ **and** the Holm-adjusted exact
    one-sided p that MA scores above the baseline is below `alpha`; *worse* is the mirror image (CI
    below ½ and the Holm-adjusted p of the other direction below `alpha`); else *not separated*
    (also without a finite interval or p); *too few runs* while either side has fewer than MIN_RUNS."""
    if min(n_x, n_y) < MIN_RUNS:
        return TOO_FEW
    if math.isfinite(p.lo) and p.lo > 0.5 and math.isfinite(p_better) and p_better < alpha:
        return BETTER
    if math.isfinite(p.hi) and p.hi < 0.5 and math.isfinite(p_worse) and p_worse < alpha:
        return WORSE
    return NOT_SEPARATED


@dataclass(frozen=True)
class RankTest:
    """The exact one-sided tests of X against Y, raw and (once a family is known) Holm-adjusted."""

    n_x: int
    n_y: int
    u: float  # Mann-Whitney U of X against Y
    p_greater: float  # raw exact p that X scores above Y
    p_less: float  # raw exact p that X scores below Y
    p_greater_holm: float = math.nan
    p_less_holm: float = math.nan


def rank_test(x: Any, y: Any) -> RankTest:
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if not x.size or not y.size:
        return RankTest(x.size, y.size, math.nan, math.nan, math.nan)
    return RankTest(x.size, y.size, mann_whitney_u(x, y), exact_rank_test(x, y, "greater"),
                    exact_rank_test(x, y, "less"))


def holm_family(tests: Sequence[RankTest]) -> list[RankTest]:
    """Holm over a family (the rows sharing one baseline), each direction on its own."""
    g = holm([t.p_greater for t in tests])
    s = holm([t.p_less for t in tests])
    return [RankTest(t.n_x, t.n_y, t.u, t.p_greater, t.p_less, pg, ps) for t, pg, ps in zip(tests, g, s)]


@dataclass(frozen=True)
class VerdictResult:
    """A verdict and what it rests on: P(X > Y) with its CI (bootstrap seed 0), the exact test, and
    the word under each of STABILITY_SEEDS bootstrap seeds."""

    p: Interval
    test: RankTest
    words: tuple[str, ...]  # the word per bootstrap seed
    lo_range: tuple[float, float]  # the CI's lower bound over the seeds (min, max)
    hi_range: tuple[float, float]
    n_boot: int

    @property
    def stable(self) -> bool:
        return len(set(self.words)) <= 1

    @property
    def word(self) -> str:
        """The word every seed gives; *not separated* where the seeds disagree."""
        if not self.words:
            return NOT_SEPARATED
        return self.words[0] if self.stable else NOT_SEPARATED

    def stability_text(self) -> str:
        if not self.words:
            return "–"
        if self.stable:
            return f"same for {len(self.words)}/{len(self.words)} seeds"
        counts: dict[str, int] = {}
        for w in self.words:
            counts[w] = counts.get(w, 0) + 1
        return "seeds disagree: " + ", ".join(f"{w} {c}/{len(self.words)}" for w, c in sorted(counts.items()))


def decide(x: Any, y: Any, test: RankTest, n_boot: int = N_BOOT_VERDICT, seeds: Sequence[int] | None = None,
           alpha: float = ALPHA) -> VerdictResult:
    """The verdict of X against Y: P(X > Y)'s bootstrap CI (`n_boot` resamples) under each seed of
    `seeds` (default 0..STABILITY_SEEDS−1), each combined with the Holm-adjusted exact p of `test`
    (see verdict_word)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    seeds = list(range(STABILITY_SEEDS)) if seeds is None else list(seeds)
    nan = Interval(math.nan, math.nan, math.nan)
    if not x.size or not y.size:
        return VerdictResult(nan, test, tuple(TOO_FEW for _ in seeds), (math.nan,) * 2, (math.nan,) * 2, n_boot)
    cis = [probability_of_improvement_ci([x], [y], n_boot, seed=s) for s in seeds]
    words = tuple(verdict_word(ci, x.size, y.size, test.p_greater_holm, test.p_less_holm, alpha) for ci in cis)
    los, his = [c.lo for c in cis], [c.hi for c in cis]
    return VerdictResult(cis[0] if cis else nan, test, words, (min(los), max(los)), (min(his), max(his)), n_boot)
