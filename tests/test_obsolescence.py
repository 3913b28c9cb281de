"""Obsolescence technology: Eq. 8, slot allocation, and the A/C schedule."""

import json

import numpy as np
import pytest

from mam_core.obsolescence import (
    Obsolescence,
    allocate,
    allocation_probabilities,
    choose_survivor,
    counts,
)
from mam_core.schedule import Schedule

# --- Eq. 8 ---------------------------------------------------------------------------------


def test_all_positive_is_eq8():
    np.testing.assert_allclose(allocation_probabilities([1.0, 3.0]), [0.25, 0.75])
    np.testing.assert_allclose(allocation_probabilities([2.0, 3.0, 5.0]), [0.2, 0.3, 0.5])


def test_all_negative_gives_reversed_rank():
    # Eq. 8 on [-1, -3] gives [0.25, 0.75]; reversed rank: actor 0 (better) gets 0.75.
    np.testing.assert_allclose(allocation_probabilities([-1.0, -3.0]), [0.75, 0.25])
    # [-2, -5, -3]: Eq. 8 = [0.2, 0.5, 0.3]; ranks best->worst: 0, 2, 1 get 0.5, 0.3, 0.2.
    np.testing.assert_allclose(allocation_probabilities([-2.0, -5.0, -3.0]), [0.5, 0.2, 0.3])


def test_tied_returns_get_equal_probabilities_in_every_branch():
    # Negative: Eq. 8 on [-2, -2, -4] = [0.25, 0.25, 0.5]; reversed [0.5, 0.25, 0.25]; the tied
    # pair shares its ranks' 0.5 + 0.25: 0.375 each.
    np.testing.assert_allclose(allocation_probabilities([-2.0, -2.0, -4.0]), [0.375, 0.375, 0.25])
    np.testing.assert_allclose(allocation_probabilities([-4.0, -2.0, -2.0]), [0.25, 0.375, 0.375])
    np.testing.assert_allclose(allocation_probabilities([-3.0, -3.0]), [0.5, 0.5])
    # Positive (Eq. 8 as printed) and mixed (shifted) give ties equal P already.
    np.testing.assert_allclose(allocation_probabilities([2.0, 2.0, 4.0]), [0.25, 0.25, 0.5])
    p = allocation_probabilities([-1.0, 3.0, 3.0])
    assert p[1] == p[2] and p[0] < p[1]


def test_mixed_signs_shift_then_eq8():
    # R=[-1, 1]: spread 2, R' = R + 1 + 0.2 = [0.2, 2.2] -> [1/12, 11/12].
    np.testing.assert_allclose(allocation_probabilities([-1.0, 1.0]), [1 / 12, 11 / 12], rtol=1e-9)
    p = allocation_probabilities([-10.0, 5.0, 20.0])  # R' = [3, 18, 33] / 54
    np.testing.assert_allclose(p, [3 / 54, 18 / 54, 33 / 54], rtol=1e-9)


def test_zero_return_shifts():
    # R=[0, 3]: scaled [0, 1], R' = [0.1, 1.1] -> [1/12, 11/12]; the worst keeps a chance.
    np.testing.assert_allclose(allocation_probabilities([0.0, 3.0]), [1 / 12, 11 / 12], rtol=1e-9)
    np.testing.assert_allclose(allocation_probabilities([0.0, 0.0, 0.0]), [1 / 3] * 3)
    np.testing.assert_allclose(allocation_probabilities([-1.0, 0.0]), [0.1 / 1.2, 1.1 / 1.2], rtol=1e-9)


@pytest.mark.parametrize("value", [-7.0, 0.0, 4.0, 1e300, -1e-300])
def test_equal_returns_are_uniform(value):
    np.testing.assert_allclose(allocation_probabilities([value] * 4), [0.25] * 4)


def test_one_actor_and_scale_invariance():
    assert allocation_probabilities([-5.0]).tolist() == [1.0]
    r = np.array([-3.0, 2.0, 7.0])
    np.testing.assert_allclose(allocation_probabilities(r), allocation_probabilities(1000 * r))
    # huge returns do not overflow
    np.testing.assert_allclose(allocation_probabilities([1e308, 1e308]), [0.5, 0.5])


@pytest.mark.parametrize("bad", [[1.0, np.nan], [np.inf, 1.0], [], [[1.0, 2.0]]])
def test_bad_returns_raise(bad):
    with pytest.raises(ValueError):
        allocation_probabilities(bad)


def test_probabilities_are_a_distribution_and_respect_order():
    rng = np.random.default_rng(0)
    for _ in range(200):
        r = rng.normal(scale=rng.uniform(0.01, 1000), size=rng.integers(2, 7)) + rng.normal() * 100
        p = allocation_probabilities(r)
        assert np.isclose(p.sum(), 1.0) and np.all(p > 0)
        # better return never gets a smaller probability
        order = np.argsort(r)
        assert np.all(np.diff(p[order]) >= -1e-12)


# --- allocation ------------------------------------------------------------------------------


def test_allocation_counts_sum_to_slots_and_skip_eliminated():
    rng = np.random.default_rng(1)
    for _ in range(300):
        k = int(rng.integers(1, 6))
        m = int(rng.integers(0, 9))
        p = rng.dirichlet(np.ones(k))
        live = rng.random(k) < 0.6
        live[rng.integers(k)] = True
        slots = [f"w{i}" for i in range(m)]
        alloc = allocate(p, slots, rng, live=live)
        assert sorted(alloc) == sorted(slots)
        i_k = counts(alloc, k)
        assert i_k.sum() == m
        assert np.all(i_k[~live] == 0)
        assert len(allocate(p, m, rng, live=live)) == m


def test_zero_probability_actor_never_allocated_and_renormalised():
    rng = np.random.default_rng(2)
    alloc = allocate([0.0, 0.3, 0.0], 500, rng)  # unnormalised: renormalised to [0, 1, 0]
    assert set(alloc) == {1}
    # live actors all with P=0: share evenly among them rather than fail
    alloc = allocate([1.0, 0.0, 0.0], 300, rng, live=[False, True, True])
    assert set(alloc) == {1, 2}
    with pytest.raises(ValueError):
        allocate([0.5, 0.5], 3, rng, live=[False, False])
    with pytest.raises(ValueError):
        allocate([0.5, -0.5], 3, rng)


def test_slot_draws_match_probabilities_statistically():
    p = np.array([0.2, 0.5, 0.3])
    n = 20_000
    alloc = allocate(p, [f"slot-{i:05d}" for i in range(n)], np.random.default_rng(1234))
    i_k = counts(alloc, 3)
    sigma = np.sqrt(n * p * (1 - p))
    assert np.all(np.abs(i_k - n * p) < 5 * sigma), (i_k, n * p)


def test_named_slots_do_not_depend_on_listing_order():
    p = [0.3, 0.7]
    a = allocate(p, ["b", "a", "c"], np.random.default_rng(5))
    b = allocate(p, ["c", "a", "b"], np.random.default_rng(5))
    assert a == b


def test_counts_validates_range():
    assert counts({"a": 1, "b": 1, "c": 0}, 3).tolist() == [1, 2, 0]
    assert counts([], 2).tolist() == [0, 0]
    with pytest.raises(ValueError):
        counts([0, 3], 3)


def test_choose_survivor_best_with_ties_to_lowest():
    assert choose_survivor([1.0, 5.0, 3.0]) == 1
    assert choose_survivor([-4.0, -2.0, -2.0]) == 1
    assert choose_survivor([7.0, 7.0]) == 0
    assert choose_survivor([1.0, 9.0, 3.0], live=[True, False, True]) == 2
    with pytest.raises(ValueError):
        choose_survivor([1.0, np.nan])


# --- schedule ---------------------------------------------------------------------------------


def _state(enabled: bool = True) -> Obsolescence:
    return Obsolescence(3, Schedule("equal-data", slots=1, steps=10_000, start=0, compete_every=1000,
                                    eliminate_at=3500 if enabled else None))


def test_initial_state_is_uniform():
    s = _state()
    np.testing.assert_allclose(s.probabilities, [1 / 3] * 3)
    assert s.round == 0 and s.survivor is None and not s.eliminated.any()


def test_rounds_due_at_multiples_of_a_before_c():
    s = _state()
    assert not s.due_round(0) and not s.due_round(999)
    assert s.due_round(1000)
    s.record_evaluation(1000, [1.0, 3.0, 4.0])
    np.testing.assert_allclose(s.probabilities, [0.125, 0.375, 0.5])
    assert s.round == 1
    assert not s.due_round(1000) and not s.due_round(1999)  # same multiple never re-triggers
    assert s.due_round(2000)
    # the step counter jumps past 2000 and 3000: one round, at the latest multiple
    assert s.due_round(3100)
    s.record_evaluation(3100, [4.0, 3.0, 1.0])
    assert s.round == 2 and s.last_round_at == 3000
    assert not s.due_round(3400)
    assert not s.due_round(3500) and not s.due_round(4000)  # not at or after C
    assert not s.due_elimination(3499)


def test_off_schedule_evaluation_only_remembers_returns():
    s = _state()
    p = s.record_evaluation(500, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(p, [1 / 3] * 3)
    assert s.round == 0 and s.last_returns.tolist() == [1.0, 2.0, 3.0] and s.last_evaluation_step == 500
    with pytest.raises(ValueError):
        s.record_evaluation(1000, [1.0, 2.0])
    with pytest.raises(ValueError):
        s.record_evaluation(1000, [1.0, 2.0, np.nan])


def test_elimination_once_at_c_keeps_the_best():
    s = _state()
    s.record_evaluation(1000, [1.0, 2.0, 3.0])
    assert s.due_elimination(3500) and s.due_elimination(3700)
    s.record_evaluation(3600, [5.0, 9.0, 2.0])
    assert s.survivor == 1
    assert s.eliminated.tolist() == [True, False, True]
    assert s.probabilities.tolist() == [0.0, 1.0, 0.0]
    assert not s.due_elimination(3600) and not s.due_elimination(10_000)
    assert not s.due_round(5000)
    # later evaluations never revive an eliminated actor
    s.record_evaluation(10_000, [100.0, 0.0, 0.0])
    assert s.survivor == 1 and s.probabilities.tolist() == [0.0, 1.0, 0.0]
    rng = np.random.default_rng(0)
    assert s.allocation(["w0", "w1", "w2", "w3", "w4"], rng) == {f"w{i}": 1 for i in range(5)}
    assert s.allocation(4, rng) == [1, 1, 1, 1]


def test_allocation_before_elimination_follows_p():
    s = _state()
    s.record_evaluation(1000, [0.0, 0.0, 10.0])  # shift rule: R' = [1, 1, 11] / 13
    np.testing.assert_allclose(s.probabilities, [1 / 13, 1 / 13, 11 / 13], rtol=1e-9)
    i_k = counts(s.allocation(13_000, np.random.default_rng(3)), 3)
    assert i_k.sum() == 13_000 and i_k[2] > 10_000


def test_no_ot_is_uniform_round_robin_without_elimination():
    s = _state(enabled=False)
    assert not s.due_round(1000) and not s.due_elimination(10**9)
    s.record_evaluation(1000, [1.0, 2.0, 100.0])
    s.record_evaluation(5000, [1.0, 2.0, 100.0])
    np.testing.assert_allclose(s.probabilities, [1 / 3] * 3)
    assert s.survivor is None and not s.eliminated.any() and s.round == 0
    rng = np.random.default_rng(0)
    assert s.allocation(["w3", "w0", "w1", "w4", "w2"], rng) == {"w0": 0, "w1": 1, "w2": 2, "w3": 0, "w4": 1}
    assert s.allocation(5, rng) == [0, 1, 2, 0, 1]


def test_state_round_trips_through_json():
    s = _state()
    s.record_evaluation(1000, [-1.0, -3.0, -2.0])
    restored = Obsolescence.from_dict(json.loads(json.dumps(s.to_dict())))
    assert restored.to_dict() == s.to_dict()
    assert not restored.due_round(1500) and restored.due_round(2000)
    s.record_evaluation(3500, [-1.0, -3.0, -2.0])
    restored = Obsolescence.from_dict(json.loads(json.dumps(s.to_dict())))
    assert restored.survivor == 0 and restored.eliminated.tolist() == [False, True, True]
    assert not restored.due_elimination(4000)
    with pytest.raises(ValueError):
        Obsolescence.from_dict({**s.to_dict(), "schema": 99})
    with pytest.raises(ValueError):
        Obsolescence.from_dict({**s.to_dict(), "probabilities": [0.5, 0.5]})


def test_config_validation():
    with pytest.raises(ValueError):
        Obsolescence(0, Schedule("paper", slots=1, steps=1, start=0, compete_every=1, eliminate_at=1))
    with pytest.raises(ValueError):
        Obsolescence(2, Schedule("paper", slots=1, steps=1, start=0, compete_every=0, eliminate_at=1))
