"""The lab's statistics (mam_lab/stats.py) on hand-made scores: IQM, bootstrap CIs, P(X > Y), the
Wilson interval, the verdict word."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mam_lab.stats import (
    Interval,
    iqm,
    iqm_ci,
    mean_ci,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap,
    verdict_word,
    wilson_interval,
)


def test_iqm_hand_computed():
    # n = 8: drop the 2 lowest and 2 highest, mean of 3, 4, 5, 6
    assert iqm([200, 3, 1, 6, 100, 4, 2, 5]) == pytest.approx(4.5)
    # n = 10: the middle half is 5 observations: 4..7 in full, 3 and 8 with weight 1/2
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8, 9, 1000]) == pytest.approx((0.5 * 3 + 4 + 5 + 6 + 7 + 0.5 * 8) / 5)
    # n = 3: weights 1/4, 1, 1/4 over 1.5
    assert iqm([600, 0, 6]) == pytest.approx((0.25 * 0 + 6 + 0.25 * 600) / 1.5)
    assert iqm([7.0]) == 7.0
    assert iqm([2.0, 4.0]) == pytest.approx(3.0)
    # insensitive to outliers, equal to the mean for symmetric data
    assert iqm([-1e9, 1, 2, 3, 4, 5, 6, 1e9]) == pytest.approx(3.5)
    # vectorised along an axis
    np.testing.assert_allclose(iqm(np.array([[200, 3, 1, 6, 100, 4, 2, 5], [1, 1, 1, 1, 2, 2, 2, 2]]), axis=1),
                               [4.5, 1.5])
    with pytest.raises(ValueError):
        iqm([])



def test_iqm_is_the_25_percent_trimmed_mean_for_multiples_of_four():
    rng = np.random.default_rng(3)
    x = rng.normal(size=40)
    s = np.sort(x)
    assert iqm(x) == pytest.approx(s[10:30].mean())



def test_bootstrap_is_seeded_and_contains_the_true_value():
    rng = np.random.default_rng(0)
    strata = [rng.normal(5.0, 2.0, size=30) for _ in range(3)]  # symmetric: the true IQM is 5
    a = iqm_ci(strata, n_boot=2000, seed=1)
    b = iqm_ci(strata, n_boot=2000, seed=1)
    c = iqm_ci(strata, n_boot=2000, seed=2)
    assert a == b and a != c
    assert a.lo < a.value < a.hi and a.contains(5.0)
    assert a.value == pytest.approx(iqm(np.concatenate(strata)))
    m = mean_ci(strata[0], seed=0)
    assert m.value == pytest.approx(strata[0].mean()) and m.contains(5.0)



def test_bootstrap_ci_coverage_near_95_percent():
    rng = np.random.default_rng(7)
    hits = 0
    trials = 200
    for t in range(trials):
        strata = [rng.normal(mu, 1.0, size=20) for mu in (0.0, 0.0, 0.0)]
        hits += iqm_ci(strata, n_boot=400, seed=t).contains(0.0)
    assert 0.85 <= hits / trials <= 1.0



def test_stratified_bootstrap_resamples_within_each_stratum():
    # Every replicate keeps 5 draws from each env: the pooled mean is always 5 when one env is all
    # 0 and the other all 10 (a pooled, unstratified bootstrap would vary).
    strata = [np.zeros(5), np.full(5, 10.0)]
    reps = stratified_bootstrap([strata], lambda s: np.concatenate(s, axis=-1).mean(axis=-1), n_boot=500, seed=0)
    assert reps.shape == (500,)
    np.testing.assert_allclose(reps, 5.0)
    # and resampling does vary within a stratum
    reps = stratified_bootstrap([[np.arange(10.0)]], lambda s: s[0].mean(axis=-1), n_boot=500, seed=0)
    assert reps.std() > 0.3



def test_probability_of_improvement_hand_made_scores():
    assert probability_of_improvement([[5, 6, 7]], [[1, 2, 3, 4]]) == 1.0
    assert probability_of_improvement([[1, 2, 3, 4]], [[5, 6, 7]]) == 0.0
    assert probability_of_improvement([[1, 2, 3]], [[1, 2, 3]]) == 0.5
    assert probability_of_improvement([[3.0, 4.0]], [[1.0, 3.5]]) == pytest.approx(0.75)
    assert probability_of_improvement([[1, 2, 3]], [[2, 2]]) == pytest.approx(0.5)  # ties count 1/2
    # averaged over envs: 1.0 on one, 0.0 on the other
    assert probability_of_improvement([[5.0, 6.0], [0.0]], [[1.0], [9.0, 8.0]]) == pytest.approx(0.5)



def test_probability_of_improvement_ci():
    p = probability_of_improvement_ci([[5, 6, 7]], [[1, 2, 3, 4]], n_boot=500, seed=0)
    assert (p.value, p.lo, p.hi) == (1.0, 1.0, 1.0)
    p = probability_of_improvement_ci([[1.0, 2.0, 3.0]], [[1.0, 2.0, 3.0]], n_boot=1000, seed=0)
    assert p.value == 0.5 and p.lo < 0.5 < p.hi
    rng = np.random.default_rng(1)
    p = probability_of_improvement_ci([rng.normal(1, 1, 50), rng.normal(1, 1, 50)],
                                      [rng.normal(0, 1, 50), rng.normal(0, 1, 50)], n_boot=1000, seed=0)
    true = 0.7602  # P(N(1,1) > N(0,1)) = Phi(1/sqrt(2))
    assert p.contains(true)



def test_wilson_interval():
    w = wilson_interval(0, 10)
    assert w.value == 0.0 and w.lo == 0.0 and w.hi == pytest.approx(0.2775, abs=1e-3)
    w = wilson_interval(10, 10)
    assert w.value == 1.0 and w.hi == 1.0 and w.lo == pytest.approx(0.7225, abs=1e-3)
    w = wilson_interval(5, 10)
    assert w.lo == pytest.approx(0.2366, abs=1e-3) and w.hi == pytest.approx(0.7634, abs=1e-3)



def test_verdict_words():
    # the CI of P(MA > baseline) and the Holm-adjusted exact p (tests/test_verdict.py has the rest)
    assert verdict_word(Interval(0.8, 0.55, 0.95), 5, 5, 0.01, 0.99) == "better"
    assert verdict_word(Interval(0.2, 0.05, 0.45), 5, 5, 0.99, 0.01) == "worse"
    assert verdict_word(Interval(0.6, 0.5, 0.9), 5, 5, 0.01, 0.99) == "not separated"  # the bound must be above 0.5
    assert verdict_word(Interval(0.4, 0.1, 0.5), 5, 5, 0.99, 0.01) == "not separated"
    assert verdict_word(Interval(0.5, 0.2, 0.8), 5, 5, 0.5, 0.5) == "not separated"
    assert verdict_word(Interval(1.0, 1.0, 1.0), 1, 2, 0.0, 1.0) == "too few runs"  # one run: a degenerate CI
    assert verdict_word(Interval(1.0, 1.0, 1.0), 3, 3, 0.05, 1.0) == "too few runs"  # 3 vs 3: least p is 1/20
    assert verdict_word(Interval(math.nan, math.nan, math.nan), 5, 5, math.nan, math.nan) == "not separated"



def test_wilson_interval_more_hand_computed_values():
    # p̂ = 2/3, z = 1.96: centre (p̂ + z²/2n)/(1 + z²/n) = 0.5731, half-width 0.3654
    w = wilson_interval(2, 3)
    assert (w.lo, w.hi) == (pytest.approx(0.2077, abs=1e-3), pytest.approx(0.9385, abs=1e-3))
    w = wilson_interval(1, 20)  # published: (0.0089, 0.2361)
    assert (w.lo, w.hi) == (pytest.approx(0.0089, abs=1e-3), pytest.approx(0.2361, abs=1e-3))

