"""Issue 18's verdict rules and the deployed actor (mam_lab.stats, mam_lab.scores; pure): the exact
one-sided permutation (Mann-Whitney) test against splits enumerated by hand, Holm, the verdict word
with its stability over bootstrap seeds, and the deployed actor's score on small hand-made logs."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mam_lab.scores import (
    auc_after,
    competition_winner,
    deployed_points,
    final_return,
    initial_actor,
)
from mam_lab.stats import (
    BETTER,
    MIN_RUNS,
    N_BOOT_VERDICT,
    NOT_SEPARATED,
    STABILITY_SEEDS,
    TOO_FEW,
    WORSE,
    Interval,
    RankTest,
    decide,
    exact_rank_test,
    exact_u_counts,
    holm,
    holm_family,
    mann_whitney_u,
    mid_ranks,
    rank_test,
    verdict_word,
)

# --- the exact test: every split of the pooled scores is equally likely under H0 --------------


def test_exact_test_3_vs_3_enumerated_by_hand():
    # X = {4, 5, 6}, Y = {1, 2, 3}: U = 9 (all 9 pairs). The C(6, 3) = 20 splits of the ranks
    # 1..6 into a 3-set for X have rank sums R and U = R − 6:
    #   123:0 124:1 125:2 126:3 134:2 135:3 136:4 145:4 146:5 156:6
    #   234:3 235:4 236:5 245:5 246:6 256:7 345:6 346:7 356:8 456:9
    # U ≥ 9: only 456 -> 1/20; U ≤ 9: all -> 20/20
    assert mann_whitney_u([4, 5, 6], [1, 2, 3]) == 9.0
    assert exact_rank_test([4, 5, 6], [1, 2, 3], "greater") == pytest.approx(1 / 20) == 0.05
    assert exact_rank_test([4, 5, 6], [1, 2, 3], "less") == 1.0
    # X = {1, 5, 6}, Y = {2, 3, 4}: ranks {1, 5, 6}, U = 12 − 6 = 6. From the list, U ≥ 6 is
    # 156, 246, 256, 345, 346, 356, 456 -> 7/20; U ≤ 6: all but 256, 346, 356, 456 (U = 7, 7, 8, 9) -> 16/20
    assert mann_whitney_u([1, 5, 6], [2, 3, 4]) == 6.0
    assert exact_rank_test([1, 5, 6], [2, 3, 4], "greater") == pytest.approx(7 / 20)
    assert exact_rank_test([1, 5, 6], [2, 3, 4], "less") == pytest.approx(16 / 20)
    # the U counts are the list above: U = 0..9 occur 1, 1, 2, 3, 3, 3, 3, 2, 1, 1 times (2U keys)
    counts = exact_u_counts([4, 5, 6], [1, 2, 3])
    assert {u2 // 2: c for u2, c in counts.items()} == {0: 1, 1: 1, 2: 2, 3: 3, 4: 3, 5: 3, 6: 3, 7: 2, 8: 1, 9: 1}


def test_exact_test_3_vs_3_with_ties_by_hand():
    # pooled 1, 2, 2, 3, 4, 5: mid-ranks 1, 2.5, 2.5, 4, 5, 6. X = {2, 4, 5}: R = 2.5 + 5 + 6 = 13.5,
    # U = 7.5 (= 1.5 + 3 + 3 pairs, the tie ½). Of the 20 splits, rank sum ≥ 13.5: {4, 5, 6} = 15 and
    # {2.5, 5, 6} = 13.5 twice (either 2) -> 3/20; the next, {2.5, 4, 6} = 12.5, is below.
    np.testing.assert_array_equal(mid_ranks([1, 2, 2, 3, 4, 5]), [1, 2.5, 2.5, 4, 5, 6])
    assert mann_whitney_u([2, 4, 5], [1, 2, 3]) == 7.5
    assert exact_rank_test([2, 4, 5], [1, 2, 3], "greater") == pytest.approx(3 / 20)
    # all equal: every split has U = 4.5, so both tails are 1
    assert exact_rank_test([1, 1, 1], [1, 1, 1], "greater") == exact_rank_test([1, 1, 1], [1, 1, 1], "less") == 1.0


def test_exact_test_4_vs_5_enumerated_by_hand():
    # C(9, 4) = 126 splits. Complete separation: only the top 4 ranks reach U = 20 -> 1/126.
    assert exact_rank_test([6, 7, 8, 9], [1, 2, 3, 4, 5], "greater") == pytest.approx(1 / 126)
    # X = {2, 5, 7, 9}, Y = {1, 3, 4, 6, 8}: U = 1 + 3 + 4 + 5 = 13 (x = 2 beats 1; 5 beats 1, 3, 4; ...).
    # U of a split is the number of (x, y) pairs with x above, so the count of splits with U = u is the
    # number of partitions of u into at most 4 parts, each at most 5 (the Y runs each X run is above):
    #   u = 0: 1   1: 1   2: 2 (2, 11)   3: 3 (3, 21, 111)   4: 5 (4, 31, 22, 211, 1111)
    #   5: 6 (5, 41, 32, 311, 221, 2111)   6: 8 (51, 42, 411, 33, 321, 3111, 222, 2211)
    #   7: 9 (52, 511, 43, 421, 4111, 331, 322, 3211, 2221)
    # U is symmetric about nm/2 = 10, so P(U ≥ 13) = P(U ≤ 7) = (1+1+2+3+5+6+8+9)/126 = 35/126
    assert mann_whitney_u([2, 5, 7, 9], [1, 3, 4, 6, 8]) == 13.0
    assert exact_rank_test([2, 5, 7, 9], [1, 3, 4, 6, 8], "greater") == pytest.approx(35 / 126)
    # the other tail: P(U ≤ 13) = 1 − P(U ≥ 14) = 1 − P(U ≤ 6) = 1 − 26/126 = 100/126
    assert exact_rank_test([2, 5, 7, 9], [1, 3, 4, 6, 8], "less") == pytest.approx(100 / 126)


def test_enumeration_and_dynamic_programming_give_the_same_counts():
    rng = np.random.default_rng(0)
    for n, m in ((3, 3), (4, 5), (7, 9)):
        x, y = rng.integers(0, 6, n).astype(float), rng.integers(0, 6, m).astype(float)  # many ties
        assert exact_u_counts(x, y, "enumerate") == exact_u_counts(x, y, "dp")
        assert sum(exact_u_counts(x, y, "dp").values()) == math.comb(n + m, n)
    # a brute-force check of one tail against itertools directly, U counted pair by pair
    x, y = [3.0, 1.0, 4.0, 1.0], [5.0, 9.0, 2.0, 6.0, 5.0]
    pooled = x + y
    u_obs = mann_whitney_u(x, y)
    hits = sum(mann_whitney_u([pooled[i] for i in s], [pooled[i] for i in range(9) if i not in s]) >= u_obs
               for s in itertools.combinations(range(9), 4))
    assert exact_rank_test(x, y, "greater") == pytest.approx(hits / 126)
    # 20 against 20 (C(40, 20) ≈ 1.4e11 splits) goes by dynamic programming: complete separation
    assert exact_rank_test(np.arange(20, 40), np.arange(20)) == pytest.approx(1 / math.comb(40, 20))
    with pytest.raises(ValueError):
        exact_rank_test([1.0, math.nan], [2.0])


# --- Holm ------------------------------------------------------------------------------------


def test_holm_by_hand():
    # sorted 0.01, 0.03, 0.04 (m = 3): 3·0.01 = 0.03; 2·0.03 = 0.06; 1·0.04 = 0.04 -> max(0.06, 0.04) = 0.06
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    # capped at 1; a single p is unchanged; NaN is kept and not counted in m
    assert holm([0.5, 0.6]) == pytest.approx([1.0, 1.0])
    assert holm([0.02]) == [0.02]
    out = holm([0.01, math.nan, 0.02])
    assert out[0] == pytest.approx(0.02) and math.isnan(out[1]) and out[2] == pytest.approx(0.02)
    # the family of evidence-a: 0.1, 0.05, 0.05, 0.65 -> 0.2, 0.2 (4·0.05), 0.2 (max of 3·0.05, 0.2), 0.65
    assert holm([0.1, 0.05, 0.05, 0.65]) == pytest.approx([0.2, 0.2, 0.2, 0.65])
    t = holm_family([RankTest(3, 3, 9.0, 0.05, 1.0), RankTest(3, 3, 8.0, 0.1, 0.95)])
    assert [(r.p_greater_holm, r.p_less_holm) for r in t] == [pytest.approx((0.1, 1.0)), pytest.approx((0.1, 1.0))]


# --- the verdict word -------------------------------------------------------------------------


def test_verdict_word_needs_the_ci_and_the_holm_p():
    assert MIN_RUNS == 5 and N_BOOT_VERDICT >= 10_000 and STABILITY_SEEDS == 20
    above, below, across = Interval(0.8, 0.6, 0.95), Interval(0.2, 0.05, 0.4), Interval(0.6, 0.45, 0.8)
    assert verdict_word(above, 5, 5, p_better=0.01, p_worse=0.99) == BETTER
    assert verdict_word(above, 5, 5, p_better=0.06, p_worse=0.99) == NOT_SEPARATED  # CI alone is not enough
    assert verdict_word(across, 5, 5, p_better=0.001, p_worse=0.99) == NOT_SEPARATED  # p alone is not enough
    assert verdict_word(Interval(0.7, 0.5, 0.9), 5, 5, 0.01, 0.99) == NOT_SEPARATED  # the bound must be above ½
    assert verdict_word(below, 6, 8, p_better=0.99, p_worse=0.01) == WORSE
    assert verdict_word(below, 6, 8, p_better=0.99, p_worse=0.2) == NOT_SEPARATED
    assert verdict_word(below, 6, 8, p_better=0.01, p_worse=0.2) == NOT_SEPARATED  # a p of the wrong side
    assert verdict_word(above, 4, 10, 0.001, 0.999) == TOO_FEW  # below 5 runs a side
    assert verdict_word(Interval(math.nan, math.nan, math.nan), 5, 5, math.nan, math.nan) == NOT_SEPARATED


def test_decide_five_against_five():
    # complete separation 5 vs 5: raw p = 1/C(10, 5) = 1/252; the CI is [1, 1] under every seed
    x, y = [6.0, 7.0, 8.0, 9.0, 10.0], [1.0, 2.0, 3.0, 4.0, 5.0]
    t = holm_family([rank_test(x, y)])[0]
    assert t.p_greater == pytest.approx(1 / 252) and t.p_greater_holm == pytest.approx(1 / 252)
    r = decide(x, y, t, n_boot=N_BOOT_VERDICT)
    assert r.word == BETTER and r.stable and len(r.words) == 20 and r.p.value == 1.0
    assert r.stability_text() == "same for 20/20 seeds"
    # the same data in a family of 20 rows sharing the baseline: Holm multiplies by 20 -> 20/252 ≥ 0.05
    family = holm_family([rank_test(x, y)] + [RankTest(5, 5, 12.5, 0.5, 0.5)] * 19)
    assert family[0].p_greater_holm == pytest.approx(20 / 252)
    assert decide(x, y, family[0], n_boot=N_BOOT_VERDICT).word == NOT_SEPARATED
    # the mirror image
    t = holm_family([rank_test(y, x)])[0]
    assert decide(y, x, t).word == WORSE
    # three against three can never be better: too few runs
    t = holm_family([rank_test(x[2:], y[:3])])[0]
    assert decide(x[2:], y[:3], t).word == TOO_FEW


def test_a_verdict_that_depends_on_the_bootstrap_seed_is_not_separated():
    # 6 vs 6: the exact test separates them (p = 18/924 ≈ 0.0195 < 0.05), but the CI's lower bound is
    # 0.5 under some bootstrap seeds and above it under others (10,000 resamples each)
    x, y = [0, 7, 8, 8, 9, 9], [0, 1, 1, 2, 2, 3]
    t = holm_family([rank_test(x, y)])[0]
    assert t.p_greater_holm == pytest.approx(18 / 924)
    r = decide(x, y, t)
    assert set(r.words) == {BETTER, NOT_SEPARATED} and not r.stable
    assert r.word == NOT_SEPARATED
    assert r.lo_range[0] <= 0.5 < r.lo_range[1]
    assert r.stability_text().startswith("seeds disagree: better ")
    # one seed alone would have said better for some seeds: the seeds it says so for
    assert decide(x, y, t, seeds=[s for s, w in enumerate(r.words) if w == BETTER]).word == BETTER


# --- the deployed actor ---------------------------------------------------------------------


def _eval(it, means, purpose=None):
    row = {"env_steps": 3 * it, "iterations": it, "mean": means, "returns": [[m] if m is not None else []
                                                                           for m in means]}
    if purpose is not None:
        row["purpose"] = purpose
    return row


def _alloc(reason, it, returns=None, survivor=None, probs=None, tie=None):
    return {"reason": reason, "iterations": it, "env_steps": 3 * it, "returns": returns, "survivor": survivor,
            "probabilities": probs, "tie": tie}


# An old-format run of K = 2 (no `purpose`): rounds at 100 and 200, the elimination at 300; each
# competition selected on its own evaluation row at the same iteration.
OLD_EVALS = [_eval(100, [1.0, 5.0]), _eval(200, [7.0, 3.0]), _eval(300, [2.0, 9.0]), _eval(400, [None, 11.0]),
             _eval(500, [None, 13.0])]
OLD_ALLOC = [_alloc("initial", 0, probs=[0.5, 0.5]), _alloc("workers-changed", 0, probs=[0.5, 0.5]),
             _alloc("round", 100, [1.0, 5.0], probs=[0.3, 0.7]), _alloc("round", 200, [7.0, 3.0], probs=[0.6, 0.4]),
             _alloc("elimination", 300, [2.0, 9.0], survivor=1, probs=[0.0, 1.0])]


def test_deployed_actor_on_an_old_log_is_the_one_chosen_before_the_row():
    pts = deployed_points(OLD_EVALS, OLD_ALLOC)
    # 100: no competition before it -> actor 0 (the initial allocation is uniform): 1.0, not the best 5.0
    # 200: chosen at 100 (5 > 1) -> actor 1: 3.0, not the best 7.0
    # 300: chosen at 200 (7 > 3) -> actor 0: 2.0 (the elimination's own row)
    # 400, 500: the survivor, actor 1: 11, 13
    assert [(p.x, p.actor, p.score) for p in pts] == [(100, 0, 1.0), (200, 1, 3.0), (300, 0, 2.0), (400, 1, 11.0),
                                                      (500, 1, 13.0)]
    # best-of-K would have said 5, 7, 9, 11, 13 at those rows
    # final return: the mean of the last 3 grid points (spacing 100): (2 + 11 + 13) / 3
    xy = [(p.x, p.score) for p in pts]
    assert final_return(xy, 100) == pytest.approx(26 / 3)
    # the transitions axis gives the same actors (3 transitions per iteration here)
    assert [p.actor for p in deployed_points(OLD_EVALS, OLD_ALLOC, axis="transitions")] == [0, 1, 0, 1, 1]


def test_deployed_actor_on_a_log_with_purposes_skips_the_selection_rows():
    evals = [_eval(100, [1.0, 5.0], "round"), _eval(100, [1.5, 4.0], "curve"),
             _eval(200, [7.0, 3.0], "round"), _eval(200, [6.0, 2.5], "curve"),
             _eval(300, [2.0, 9.0], "elimination"), _eval(300, [None, 8.0], "curve"),
             _eval(400, [None, 12.0], "final")]
    pts = deployed_points(evals, OLD_ALLOC)
    # selection rows are never scored; a curve row at a competition's iteration scores that
    # competition's winner on its own (disjoint) episodes: 100 -> actor 1 (4.0), 200 -> actor 0 (6.0),
    # 300 -> the survivor (8.0), the final evaluation -> the survivor (12.0)
    assert [(p.x, p.actor, p.score, p.purpose) for p in pts] == [
        (100, 1, 4.0, "curve"), (200, 0, 6.0, "curve"), (300, 1, 8.0, "curve"), (400, 1, 12.0, "final")]


def test_competition_winner_ties_and_the_initial_actor():
    assert competition_winner(_alloc("round", 1, [3.0, 3.0, 1.0], tie=[1, 0])) == 0  # a tie: the lowest index
    assert competition_winner(_alloc("round", 1, [2.0, 3.0, 3.0])) == 1  # equal returns without `tie`
    assert competition_winner(_alloc("round", 1, [None, 3.0])) == 1  # an actor without a return is not ranked
    assert competition_winner(_alloc("elimination", 1, [3.0, 3.0], survivor=1)) == 1  # the seeded tie-break
    assert competition_winner(_alloc("round", 1, None)) is None
    assert initial_actor([_alloc("initial", 0, probs=[0.2, 0.5, 0.3])]) == 1
    assert initial_actor([_alloc("initial", 0, probs=[0.5, 0.5])]) == 0
    assert initial_actor([]) == 0
    # a single-actor run: no competitions, actor 0 throughout
    assert [p.actor for p in deployed_points([_eval(100, [4.0]), _eval(200, [6.0])], [])] == [0, 0]


def test_auc_after_the_random_phase_by_hand():
    pts = [(0, 100.0), (50, 0.0), (100, 0.0), (200, 10.0), (300, 10.0), (400, 30.0)]
    # start 100: trapezoids over 100..400: (0+10)/2·100 + (10+10)/2·100 + (10+30)/2·100 = 500 + 1000 + 2000
    # = 3500, over the span 300: 11.666…; the random phase's 100 at step 0 does not count
    assert auc_after(pts, 50, 100) == pytest.approx(3500 / 300)
    assert auc_after(pts, 50, 100, end=300) == pytest.approx(1500 / 200)
    assert auc_after(pts, 50, 400) == 30.0  # one point: its score
    assert math.isnan(auc_after(pts, 50, 500))
    # points on a grid: 210 and 290 fall in the cell 200 (the later wins), 95 in 0 (before start 100)
    assert auc_after([(95, 99.0), (100, 0.0), (210, 5.0), (290, 10.0)], 100, 100) == pytest.approx(5.0)
