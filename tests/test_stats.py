"""mam_lab.stats and mam_lab.scores (pure): each figure checked against a value computed by hand,
the arithmetic written beside it. tests/test_lab_stats.py has the statistical checks (coverage,
seeding, stratification) and the report built from run directories."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mam_lab.scores import (
    aligned_curves,
    best_live_score,
    bias_points,
    bucket_points,
    eval_points,
    first_reach,
    last_n_mean,
    max_average_return,
)
from mam_lab.stats import (
    BETTER,
    NOT_SEPARATED,
    WORSE,
    Interval,
    bootstrap_ci,
    curve_band,
    iqm,
    mean_ci,
    probability_of_improvement,
    probability_of_improvement_ci,
    stratified_bootstrap,
    verdict_word,
    wilson_interval,
)

# --- IQM: the mean of the middle half [n/4, 3n/4) of the sorted sample -------------------------


def test_iqm_by_hand():
    # n = 4: the middle half [1, 3) is observations 2 and 3 in full: (2 + 3) / 2 = 2.5
    assert iqm([4, 1, 3, 2]) == pytest.approx(2.5)
    # n = 5, sorted 0 1 2 3 10: the middle half [1.25, 3.75) covers 3/4 of "1", all of "2", 3/4 of "3":
    # (0.75·1 + 2 + 0.75·3) / 2.5 = 5 / 2.5 = 2.0 (the 10 does not count)
    assert iqm([10, 2, 0, 3, 1]) == pytest.approx(2.0)
    # n = 6, sorted 0 1 2 3 4 100: [1.5, 4.5) -> ½ of "1", "2", "3", ½ of "4": (0.5 + 2 + 3 + 2) / 3 = 2.5
    assert iqm([100, 4, 3, 2, 1, 0]) == pytest.approx(2.5)
    # n = 1 and n = 2: every observation counts
    assert iqm([7.0]) == 7.0
    assert iqm([1.0, 5.0]) == pytest.approx(3.0)
    # along an axis: the rows above, one per row
    np.testing.assert_allclose(iqm(np.array([[4, 1, 3, 2], [8, 2, 6, 4]]), axis=1), [2.5, 5.0])


# --- P(X > Y): pairs with X above, ties ½, averaged over envs -----------------------------------


def test_probability_of_improvement_by_hand():
    # X = {1, 4}, Y = {2, 3}: of the 4 pairs, (4, 2) and (4, 3) have X above: 2/4
    assert probability_of_improvement([[1, 4]], [[2, 3]]) == pytest.approx(0.5)
    # X = {2, 3}, Y = {1, 2, 3}: (2,1) 1, (2,2) ½, (2,3) 0, (3,1) 1, (3,2) 1, (3,3) ½ -> 4/6
    assert probability_of_improvement([[2, 3]], [[1, 2, 3]]) == pytest.approx(4 / 6)
    # two envs: 1 (X = 1 above Y = 0) and ½ (a tie), averaged: 0.75
    assert probability_of_improvement([[1.0], [0.0]], [[0.0], [0.0]]) == pytest.approx(0.75)


def test_probability_of_improvement_ci_by_hand():
    # complete separation: every resample keeps X above Y, so the CI is the point 1
    p = probability_of_improvement_ci([[5, 6]], [[1, 2]], n_boot=300, seed=0)
    assert (p.value, p.lo, p.hi) == (1.0, 1.0, 1.0)
    # one run each, a tie: ½ in every resample
    p = probability_of_improvement_ci([[3.0]], [[3.0]], n_boot=300, seed=0)
    assert (p.value, p.lo, p.hi) == (0.5, 0.5, 0.5)


# --- bootstrap CIs ---------------------------------------------------------------------------


def test_mean_ci_by_hand():
    # a constant sample: every resample has mean 2
    assert mean_ci([2.0, 2.0, 2.0], n_boot=200, seed=0) == Interval(2.0, 2.0, 2.0)
    # {0, 1}: a resample of 2 draws has mean 0, ½ or 1 with probabilities ¼, ½, ¼; the 2.5% and
    # 97.5% quantiles of 2000 such means are 0 and 1 (a quarter of them are each)
    m = mean_ci([0.0, 1.0], n_boot=2000, seed=0)
    assert (m.value, m.lo, m.hi) == (0.5, 0.0, 1.0)


def test_stratified_bootstrap_keeps_each_stratum_and_its_size():
    # strata {1, 1} and {5, 5, 5}: each replicate draws 2 from the first and 3 from the second, so the
    # pooled mean is always (2·1 + 3·5) / 5 = 3.4
    reps = stratified_bootstrap([[[1.0, 1.0], [5.0, 5.0, 5.0]]], lambda s: np.concatenate(s, axis=-1).mean(axis=-1),
                                n_boot=50, seed=0)
    np.testing.assert_allclose(reps, 3.4)
    # the point estimate of bootstrap_ci is the statistic of the sample itself: IQM of {4, 1, 3, 2} = 2.5
    ci = bootstrap_ci([[[4.0, 1.0, 3.0, 2.0]]], lambda s: iqm(np.concatenate(s, axis=-1), axis=-1), n_boot=200)
    assert ci.value == pytest.approx(2.5) and ci.lo <= 2.5 <= ci.hi
    with pytest.raises(ValueError):
        stratified_bootstrap([[[]]], lambda s: s[0].mean(axis=-1))


# --- Wilson interval: (p + z²/2n ± z·sqrt(p(1−p)/n + z²/4n²)) / (1 + z²/n) -----------------------


def test_wilson_interval_by_hand():
    z = 1.959963984540054  # 95%
    # 1 of 4: p = 0.25, z² = 3.841459; denominator 1 + 3.841459/4 = 1.960365;
    # centre (0.25 + 0.480182) / 1.960365 = 0.372473;
    # half-width 1.959964 · sqrt(0.046875 + 0.060023) / 1.960365 = 0.326886 -> [0.045587, 0.699359]
    w = wilson_interval(1, 4)
    assert w.value == 0.25
    assert w.lo == pytest.approx(0.045587, abs=1e-5) and w.hi == pytest.approx(0.699359, abs=1e-5)
    # 0 of 5: p = 0, so the upper bound is z²/(n + z²) = 3.841459 / 8.841459 = 0.434483; the lower is 0
    w = wilson_interval(0, 5)
    assert (w.value, w.lo) == (0.0, 0.0) and w.hi == pytest.approx(z * z / (5 + z * z)) == pytest.approx(0.434483,
                                                                                                        abs=1e-5)
    # 5 of 5: the mirror image
    w = wilson_interval(5, 5)
    assert (w.value, w.hi) == (1.0, 1.0) and w.lo == pytest.approx(1 - 0.434483, abs=1e-5)
    # 90%: z = 1.644854, 0 of 5: 2.705543 / 7.705543 = 0.351110
    assert wilson_interval(0, 5, confidence=0.9).hi == pytest.approx(0.351110, abs=1e-5)
    # no trials: no share
    assert all(math.isnan(v) for v in (wilson_interval(0, 0).value, wilson_interval(0, 0).lo))


# --- the verdict word ------------------------------------------------------------------------


def test_verdict_word_by_hand():
    # 5 runs a side, the Holm-adjusted exact p of the matching direction below 0.05 (tests/test_verdict.py: the rest)
    assert verdict_word(Interval(0.7, 0.51, 0.9), 5, 5, 0.01, 0.99) == BETTER  # the whole CI above ½
    assert verdict_word(Interval(0.3, 0.1, 0.49), 5, 5, 0.99, 0.01) == WORSE  # the whole CI below ½
    assert verdict_word(Interval(0.6, 0.5, 0.9), 5, 5, 0.01, 0.99) == NOT_SEPARATED  # touches ½: not separated
    assert verdict_word(Interval(0.4, 0.1, 0.5), 5, 5, 0.99, 0.01) == NOT_SEPARATED
    assert verdict_word(Interval(math.nan, math.nan, math.nan), 5, 5, 0.01, 0.01) == NOT_SEPARATED


# --- learning-curve band ---------------------------------------------------------------------


def test_curve_band_by_hand():
    # two runs over two grid points; the first run has no value at the second point
    mean, lo, hi = curve_band(np.array([[1.0, np.nan], [3.0, 5.0]]), n_boot=500, seed=0)
    assert mean.tolist() == [2.0, 5.0]  # (1 + 3) / 2; the lone 5
    assert (lo[1], hi[1]) == (5.0, 5.0)  # one value: every resample is 5
    assert (lo[0], hi[0]) == (1.0, 3.0)  # {1, 3}: a quarter of the resamples are 1 and a quarter 3


# --- per-run scores --------------------------------------------------------------------------


def test_best_live_score_by_hand():
    assert best_live_score({"mean": [1.0, None, 3.0]}) == 3.0  # the eliminated actor (None) is not live
    assert best_live_score({"returns": [[1.0, 3.0], [10.0]]}) == 10.0  # older rows: max of means 2 and 10
    assert best_live_score({"mean": [True, "x"]}) is None  # no number: no score
    assert eval_points([{"env_steps": 5, "mean": [1.0]}, {"mean": [2.0]}, {"env_steps": 9, "mean": []}]) == [(5.0, 1.0)]


def test_grid_points_last_n_and_max_average_by_hand():
    points = [(0, 1.0), (150, 2.0), (199, 3.0), (250, 4.0)]
    # floor(s / 100)·100: 0 -> 0, 150 and 199 -> 100 (199 is later: it wins), 250 -> 200
    assert bucket_points(points, 100) == {0: 1.0, 100: 3.0, 200: 4.0}
    assert last_n_mean(points, 100, n=2) == pytest.approx(3.5)  # (3 + 4) / 2
    assert math.isnan(last_n_mean([], 100))
    # run A at 0 and 200 (held at 1 in between), run B at 100 only
    grid, m = aligned_curves([[(0, 1.0), (200, 3.0)], [(100, 2.0)]], 100)
    assert grid.tolist() == [0.0, 100.0, 200.0]
    np.testing.assert_array_equal(m, [[1.0, 1.0, 3.0], [np.nan, 2.0, np.nan]])
    # only step 100 has both runs: mean (1 + 2) / 2 = 1.5, std of {1, 2} = 0.5
    best = max_average_return(grid, m)
    assert (best.value, best.std, best.step) == (1.5, 0.5, 100.0)


def test_first_reach_and_bias_points_by_hand():
    evals = [(10.0, 5.0, 1.0), (20.0, None, 50.0), (30.0, 12.0, 60.0)]
    assert first_reach(evals, 49.0) == (20.0, None)
    assert first_reach(evals, 100.0) is None
    rows = [{"point": 100, "updates": 5, "bias": {"bias_rate": 0.2}},
            {"point": 100, "updates": 5, "bias": {"bias_rate": 0.4}},  # two actors at 100: mean 0.3
            {"point": 50, "updates": 0, "bias": {"bias_rate": 9.0}},  # before the first update: left out
            {"env_steps": 200, "bias": {"bias_rate": -0.1}},  # older rows: env_steps is the point
            {"point": 300, "bias": {"bias_rate": None}}]  # no rate: left out
    assert bias_points(rows) == [(100.0, pytest.approx(0.3)), (200.0, -0.1)]


def test_eq17_rows_of_every_commit_read_as_printed_or_absolute():
    from mam_lab.scores import bias_rate_of

    # since issue #9: the printed form (÷ Q*) in bias_rate, the ÷|Q*| form beside it where Q* < 0
    new = {"q_estimate": -120.0, "q_true": -100.0, "bias_rate": 0.2, "bias_rate_abs": -0.2, "horizon": "critic"}
    assert bias_rate_of(new) == 0.2 and bias_rate_of(new, absolute=True) == -0.2
    # before: bias_rate held the ÷|Q*| form
    old = {"q_estimate": -120.0, "q_true": -100.0, "bias_rate": -0.2}
    assert bias_rate_of(old) == 0.2 and bias_rate_of(old, absolute=True) == -0.2
    positive = {"q_estimate": 110.0, "q_true": 100.0, "bias_rate": 0.1}
    assert bias_rate_of(positive) == bias_rate_of(positive, absolute=True) == 0.1
    assert bias_rate_of({"bias_rate": float("nan")}) is None
