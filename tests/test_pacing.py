"""The checkpoint rule (mam_core/pacing.py), the bias points and the round rule shared with Obsolescence: pure."""

from __future__ import annotations

import numpy as np
import pytest

from mam_core.algorithm1 import Algorithm1
from mam_core.obsolescence import Obsolescence
from mam_core.pacing import CheckpointRule
from mam_core.schedule import Schedule

EQUAL = Schedule(kind="equal-data", slots=2, steps=1000, start=100, compete_every=200, eliminate_at=600)


def test_bias_points_follow_the_curve_rule_of_the_plan():
    """Bias points (the learner's Eq. 17) use the curve points' rule: iteration i measures point j
    when its units reach j·every; none when every is 0."""
    # 2 slots until C = 600 transitions (iteration 300), then the survivor's one slot
    plan = Algorithm1(EQUAL, batch_size=4, policy_delay=2, eval_every=300)
    points = {i: plan.crossing(i, 300) for i in range(1, plan.iterations + 1) if plan.crossing(i, 300) is not None}
    assert points == {150: 1, 300: 2, 600: 3}  # units 300, 600, 900
    assert points == {i: plan.iteration(i).curve for i in points}
    assert all(plan.crossing(i, 0) is None for i in (1, 150, 500))
    assert plan.iteration_at(0) == 0 and plan.iteration_at(301) == 150
    assert plan.iteration_at(1000) == plan.iterations == 700


def test_checkpoint_rule_updates_rows_or_seconds():
    rule = CheckpointRule(updates=10, rows=100, seconds=5.0)
    rule.mark(0, 0, 0.0)
    assert not rule.due(9, 99, 4.9)
    assert rule.due(10, 0, 0.0) and rule.due(0, 100, 0.0)
    assert not rule.due(0, 0, 60.0)  # nothing changed: no checkpoint however long
    assert rule.due(1, 0, 5.0)
    rule.mark(1, 0, 5.0)
    assert not rule.due(1, 0, 9.0)


@pytest.mark.parametrize("first_round", [200, 400])
def test_obsolescence_rounds_follow_the_schedule_rule(first_round: int):
    schedule = Schedule(kind="equal-data", slots=2, steps=1000, start=first_round - 100, compete_every=200,
                        eliminate_at=900, skip_random_rounds=first_round > 200)
    assert schedule.first_round() == first_round
    obs = Obsolescence(2, schedule)  # the same description of the schedule
    last = 0
    rounds = []
    for units in range(0, 1000, 70):  # the counter jumps, sometimes past a multiple
        due = schedule.round_due(units, last)
        assert obs.due_round(units) == (due is not None)
        assert obs.due_elimination(units) == (units >= 900 and obs.survivor is None)
        if due is not None or obs.due_elimination(units):
            obs.record_evaluation(units, np.array([1.0, 2.0]))
            last = schedule.decided_round(units)
            assert obs.last_round_at == (units // 200) * 200 and (due is None or due == last)
            rounds.append(units)
    assert rounds[0] >= first_round and rounds[-1] >= 900
