"""The learner's pacing rules (mam_core/pacing.py) and the round rule shared with Obsolescence: pure, no Zenoh."""

from __future__ import annotations

import numpy as np
import pytest

from mam_core.obsolescence import Obsolescence
from mam_core.pacing import CheckpointRule, Pacer
from mam_core.schedule import Schedule

EQUAL = Schedule(kind="equal-data", slots=2, steps=1000, start=100, compete_every=200, eliminate_at=600)


def test_credit_runs_tolerance_ahead_of_the_updates_within_the_budget():
    p = Pacer(EQUAL, tolerance=50)
    assert p.accept_until(0, referee_live=False) == 150  # the random phase, then the band
    assert p.accept_until(300, referee_live=False) == 450  # 100 random + 300 consumed + 50
    assert p.accept_until(900, referee_live=False) == 1000  # never past the budget


def test_rounds_are_barriers_while_a_referee_is_live():
    p = Pacer(EQUAL, tolerance=50)
    assert p.barrier() == 200
    assert p.accept_until(300, referee_live=True) == 200
    p.on_allocation(0, 0, None)  # the initial allocation lifts nothing
    assert p.barrier() == 200
    p.on_allocation(1, 210, None)  # the round at 200 (decided a little after it)
    assert (p.round_done_at, p.barrier()) == (200, 400)
    assert p.accept_until(300, referee_live=True) == 400
    p.on_allocation(1, 190, None)  # an older decision never moves the barrier back
    assert p.barrier() == 400
    p.on_allocation(3, 650, None)  # past C: the elimination's round
    assert p.round_done_at == 600 and p.barrier() is None
    assert p.accept_until(300, referee_live=True) == 450


def test_the_elimination_removes_the_barrier_and_paper_units_are_iterations():
    paper = Schedule(kind="paper", slots=3, steps=20, start=2, compete_every=4, eliminate_at=10)
    p = Pacer(paper, tolerance=1000)
    assert p.barrier() == 12  # iteration 4 = 3 slots x 4 transitions
    p.on_allocation(1, 13, None)  # decided at 13 transitions = iteration 4
    assert p.barrier() == 24
    p.on_allocation(2, 25, survivor=1)
    assert p.barrier() is None and p.accept_until(0, referee_live=True) == paper.budget


def test_bias_points_wait_for_the_updates():
    p = Pacer(EQUAL, tolerance=50, bias_every=300)
    assert p.next_bias == 300 and not p.bias_reached(299) and p.bias_reached(300)
    assert not p.bias_due(300, updates=199) and p.bias_due(300, updates=200)  # 200 updates after 100 random
    assert p.take_bias_point(350) == 300 and p.next_bias == 600
    assert Pacer(EQUAL, 50, bias_every=300, transitions=650).next_bias == 900  # a resumed learner
    off = Pacer(EQUAL, 50)
    assert off.next_bias is None and not off.bias_due(10_000, 10_000)
    with pytest.raises(ValueError):
        off.take_bias_point(0)


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
