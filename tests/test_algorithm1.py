"""Algorithm 1's control flow (mam_core/algorithm1.py), hand-computed: the iterations, the
updates, competitions, the elimination and curve points of a plan, the versions and decisions
with a lag, and the random streams every role derives from the seed."""

from __future__ import annotations

import numpy as np
import pytest

from mam_core import algorithm1
from mam_core.algorithm1 import Algorithm1, Purpose, elimination_transitions
from mam_core.config import resolve
from mam_core.obsolescence import initial_allocation, obsolescence_for
from mam_core.schedule import Schedule
from mam_core.seeding import stream, stream_seed


def test_plan_of_the_paper_schedule_hand_computed():
    """M = 3, T = 10, start 2, A = 3, C = 6, d = 2, batch 4: iterations 1-6 step 3 slots,
    7-10 one (the survivor on slot 0); updates from iteration 3 on (one each); rounds at 3,
    the elimination at 6 (before the update-4 actor phase), curve points every 5."""
    s = Schedule("paper", slots=3, steps=10, start=2, compete_every=3, eliminate_at=6)
    plan = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=5)
    assert plan.iterations == 10 and plan.elimination == 6
    its = [plan.iteration(i) for i in range(1, 11)]
    assert [it.slots for it in its] == [(0, 1, 2)] * 6 + [(0,)] * 4
    assert [it.transitions for it in its][:2] == [(0, 3), (3, 6)] and its[6].transitions == (18, 19)
    assert [it.random for it in its] == [True, True] + [False] * 8
    assert [it.updates for it in its] == [(0, 0), (0, 0), (0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6), (6, 7),
                                          (7, 8)]
    assert [it.round for it in its] == [None, None, 1, None, None, None, None, None, None, None]
    assert [it.eliminate for it in its] == [False] * 5 + [True] + [False] * 4
    assert [it.curve for it in its] == [None] * 4 + [1] + [None] * 4 + [2]
    # versions: an actor update at every even update count
    assert [plan.version_after(i) for i in range(0, 11)] == [0, 0, 0, 0, 1, 1, 2, 2, 3, 3, 4]
    assert [plan.weights_change(i) for i in range(1, 11)] == [False, False, False, True, False, True, False,
                                                              True, False, True]
    assert plan.version_for(6) == 1 and plan.elimination_update() == 4  # iteration 6 makes update 4
    assert plan.events() == [(3, "round"), (5, "curve"), (6, "elimination"), (10, "curve")]


def test_plan_with_a_lag_hand_computed():
    """The paper schedule above with B = 2: iteration t acts with the actors after t-3
    (version_after: 0 0 0 0 1 1 2 2 3 3 4 for t-3 = 0..10), a decision of iteration j applies
    from j+3 (the round at 3 from 6, the elimination at 6 from 9), evaluations judge the same
    versions as at B = 0, and the iterations, widths and updates do not move."""
    s = Schedule("paper", slots=3, steps=10, start=2, compete_every=3, eliminate_at=6)
    lagged = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=5, lag=2)
    plain = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=5)
    assert [lagged.version_for(t) for t in range(1, 11)] == [0, 0, 0, 0, 0, 0, 1, 1, 2, 2]
    assert [plain.version_for(t) for t in range(1, 11)] == [0, 0, 0, 0, 1, 1, 2, 2, 3, 3]
    assert [lagged.decision_for(t) for t in range(1, 11)] == [0, 0, 0, 0, 0, 3, 3, 3, 6, 6]
    assert [plain.decision_for(t) for t in range(1, 11)] == [0, 0, 0, 3, 3, 3, 6, 6, 6, 6]
    for i, purpose in plain.events():
        assert lagged.judged_version(i, purpose) == plain.judged_version(i, purpose)
    assert lagged.judged_version(6, "elimination") == plain.version_for(6) == 1  # the actors that acted at B = 0
    assert lagged.judged_version(5, "curve") == plain.version_after(5) == 1
    assert [lagged.iteration(i) for i in range(1, 11)] == [plain.iteration(i) for i in range(1, 11)]
    assert lagged.events() == plain.events() and lagged.competitions() == [3, 6]
    assert lagged.slot_width(3) == 3 and lagged.slot_width(6) == 1  # the elimination's decision: slot 0 only
    # An eliminated actor acts at most until C + B, never past its last version (after C-1).
    assert all(lagged.version_for(t) <= plain.version_after(5) for t in range(7, 9))
    with pytest.raises(ValueError, match="lag"):
        resolve("ma-td3", compete_every=3, lag=3)  # a decision would apply after the next one is drawn
    with pytest.raises(ValueError, match="lag"):
        resolve("td3", lag=-1)
    assert resolve("td3", lag=50).lag == 50  # one actor: no competitions to outrun


def test_every_when_the_roles_ask_is_the_plans():
    """The paper schedule above (B = 2): what the learner sends the referee after each iteration,
    where each decision applies, the episodes' index of each evaluation, the competitions already
    logged after n evaluations, the units past the start phase."""
    s = Schedule("paper", slots=3, steps=10, start=2, compete_every=3, eliminate_at=6)
    plan = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=5, lag=2)
    # the round at 3 judges version_after(2) = 0; the curve at 5 version_after(5) = 1; the elimination
    # at 6 version_after(5) = 1; the last iteration's curve point version_after(10) = 4
    assert [plan.judged_after(i) for i in range(0, 11)] == [set(), set(), {0}, set(), set(), {1}, set(), set(),
                                                           set(), set(), {4}]
    assert [plan.applies_from(j) for j in (0, 3, 6)] == [1, 6, 9]
    assert all(plan.decision_for(plan.applies_from(j)) == j for j in plan.competitions())
    assert [purpose for _, purpose in plan.events()] == [Purpose.ROUND, Purpose.CURVE, Purpose.ELIMINATION,
                                                          Purpose.CURVE]
    assert [plan.competitions_among(n) for n in range(5)] == [0, 1, 1, 2, 2]
    assert [plan.iteration(i).evaluation_index(p) for i, p in plan.events()] == [1, 1, None, 2]
    assert [plan.units_past_start(u) for u in (0, 2, 3, 10)] == [0, 0, 1, 8]
    assert Purpose("final") is Purpose.FINAL and Purpose.ELIMINATION.competes and not Purpose.CURVE.competes
    with pytest.raises(ValueError, match="unknown evaluation purpose"):
        plan.judged_version(3, "rounds")


def test_a_plan_keeps_recent_iterations_and_gives_what_it_would_compute():
    """`iteration` keeps the last ones it built (a worker asks for the same one on every pass):
    what it returns, in any order of asking and past its bound, is what a fresh plan computes."""
    s = Schedule("paper", slots=3, steps=1200, start=300, compete_every=150, eliminate_at=600)
    plan = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=100, lag=2)
    n = plan.iterations
    assert n > 2 * algorithm1._RECENT  # (the bound is crossed: the kept ones are dropped and built again)
    order = [*range(1, n + 1), *range(n, 0, -7), *range(1, n + 1, 3)]
    for i in order:
        fresh = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=100, lag=2)
        assert plan.iteration(i) == fresh.iteration(i)
        assert plan.iteration(i) is plan.iteration(i)  # kept, not built again
        assert len(plan._recent) <= algorithm1._RECENT
    with pytest.raises(ValueError, match="outside"):
        plan.iteration(n + 1)


def test_the_elimination_in_transitions_is_one_rule_for_plots_and_figures():
    """C counts iterations of M transitions under `paper`, transitions under `equal-data`."""
    assert elimination_transitions({"eliminate_at": 6, "actors": 2, "workers": 3, "schedule": "paper"}) == 18
    assert elimination_transitions({"eliminate_at": 6, "actors": 2, "workers": 3}) == 18  # paper: the default
    assert elimination_transitions({"eliminate_at": 6, "actors": 2, "workers": 3, "schedule": "equal-data"}) == 6
    assert elimination_transitions({"eliminate_at": 6, "actors": 1, "workers": 3}) is None
    assert elimination_transitions({"eliminate_at": 6, "actors": 2, "workers": 3, "no_ot": True}) is None
    plan = Algorithm1.for_run(resolve("ma-td3", workers=3, eliminate_at=6, compete_every=3, start_steps=2), 10)
    assert plan.iteration(plan.elimination).transitions[1] == 18


def test_the_initial_allocation_is_the_allocation_streams_first_draw():
    cfg = resolve("ma-ddpg", seed=4)
    drawn = obsolescence_for(cfg, 100).allocation(cfg.workers, stream(cfg.seed, "allocation"))
    assert initial_allocation(cfg, 100) == drawn and len(drawn) == cfg.workers


def test_plan_of_equal_data_counts_transitions():
    """M = 4, 30 transitions, C = 10: sweeps of 4; the elimination in the sweep that reaches
    10 (the third); every slot keeps running the survivor (no single slot)."""
    s = Schedule("equal-data", slots=4, steps=30, start=8, compete_every=4, eliminate_at=10)
    plan = Algorithm1(s, batch_size=2, policy_delay=1, eval_every=12, single_env=False)
    assert plan.iterations == 8 and plan.elimination == 3
    last = plan.iteration(8)
    assert last.slots == (0, 1) and last.transitions == (28, 30) and last.last  # cut by the budget
    assert [plan.iteration(i).round for i in (1, 2)] == [1, 2]
    assert plan.iteration(3).eliminate and plan.iteration(3).round is None
    assert plan.iteration(3).updates == (0, 4)  # 12 transitions, 8 of them random


def test_streams_derive_from_the_seed_alone():
    a, b = stream(7, "noise", 2).normal(size=3), stream(7, "noise", 2).normal(size=3)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, stream(7, "noise", 3).normal(size=3))  # another slot
    assert not np.array_equal(a, stream(8, "noise", 2).normal(size=3))  # another seed
    assert not np.array_equal(a, stream(7, "noise", 2, generation=1).normal(size=3))  # a restarted worker
    assert stream_seed(7, "curve", 4) == stream_seed(7, "curve", 4) != stream_seed(7, "round", 4)
    with pytest.raises(ValueError, match="unknown random stream"):
        stream(7, "uuid")


