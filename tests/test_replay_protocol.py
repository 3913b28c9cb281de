"""The replay protocol (mam_core.replay.Replay): rows found by insertion index, across the ring's wrap."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from mam_core.algorithm1 import Algorithm1
from mam_core.config import resolve
from mam_core.replay import Replay, ReplayBuffer


def _insert(buffer: ReplayBuffer, first: int, n: int) -> None:
    """Rows first..first+n-1, each row's values its insertion index."""
    i = np.arange(first, first + n, dtype=np.float32)
    buffer.add_batch(np.stack([i, -i], 1), i[:, None], i, np.stack([i + 0.5, i], 1), np.zeros(n, bool),
                     actor=np.zeros(n, np.int64), version=np.arange(first, first + n))


def test_the_uniform_replay_has_every_member_of_the_protocol():
    members = {n for n, _ in inspect.getmembers(Replay) if not n.startswith("_")} | set(Replay.__annotations__)
    buffer = ReplayBuffer(8, 2, 1)
    assert members and not [n for n in members if not hasattr(buffer, n)]
    assert (buffer.obs_dim, buffer.act_dim) == (2, 1)


def test_rows_at_reads_rows_by_insertion_index_across_the_wrap():
    buffer = ReplayBuffer(8, 2, 1)
    _insert(buffer, 0, 6)
    _insert(buffer, 6, 5)  # 11 rows in a ring of 8: rows 0-2 are gone, 8-10 sit at positions 0-2
    assert [buffer.holds(r) for r in (2, 3, 10, 11)] == [False, True, True, False]
    rows = buffer.rows_at([7, 8, 9, 10])
    assert rows["reward"].tolist() == [7, 8, 9, 10] and rows["obs"][:, 1].tolist() == [-7, -8, -9, -10]
    assert rows["version"].tolist() == [7, 8, 9, 10]
    assert {n: v.tolist() for n, v in buffer.rows_at([3, 4]).items()} == \
        {n: v.tolist() for n, v in buffer.rows_between(3, 5).items()}
    assert buffer.rows_at([])["obs"].shape == (0, 2)
    for gone in ([2, 3], [10, 11]):
        with pytest.raises(ValueError, match="not all held"):
            buffer.rows_at(gone)


def test_a_slots_row_in_an_iteration_is_algorithm1s_rule():
    """Rows go in in slot order, iteration after iteration; after C under `paper` one slot steps."""
    plan = Algorithm1.for_run(resolve("ma-td3", workers=3, eliminate_at=4, compete_every=2, start_steps=0,
                                      batch_size=1), 8)
    assert [plan.row_of(i, s) for i in (1, 2) for s in range(3)] == [0, 1, 2, 3, 4, 5]
    assert plan.row_of(5, 0) == 12 and plan.row_of(6, 0) == 13  # after the elimination at iteration 4


def _twins(capacity: int, rows: int) -> tuple[ReplayBuffer, ReplayBuffer]:
    a, b = ReplayBuffer(capacity, 2, 1, seed=7), ReplayBuffer(capacity, 2, 1, seed=7)
    for buffer in (a, b):
        _insert(buffer, 0, rows)
    return a, b


@pytest.mark.parametrize("capacity, rows", [(4096, 3000), (1000, 3000)])  # not full; a wrapped, full ring
def test_samples_drawn_ahead_of_the_rows_equal_those_drawn_after(capacity: int, rows: int):
    """`draw_ahead` before 3 rows go in, then `gather`, equals inserting first and sampling, draw
    for draw, where it answers; the answers never point at the 3 positions the rows take."""
    ahead, after = _twins(capacity, rows)
    answered = 0
    for it in range(40):
        drawn = ahead.draw_ahead(3, [16, 32])
        taken = {(ahead.pos + j) % capacity for j in range(3)}
        _insert(ahead, rows + 3 * it, 3)
        _insert(after, rows + 3 * it, 3)
        want = [after.sample(16), after.sample(16, groups=2)]
        if drawn is None:  # as the learner does: it waits for the rows and samples then
            got = [ahead.sample(16), ahead.sample(16, groups=2)]
        else:
            answered += 1
            assert not taken & set(np.concatenate(drawn).tolist())
            got = [ahead.gather(drawn[0], 16), ahead.gather(drawn[1], 16, groups=2)]
        for w, g in zip(want, got):
            assert {n: t.tolist() for n, t in w.items()} == {n: t.tolist() for n, t in g.items()}
    assert answered >= 30  # 48 draws over 3,000 rows, 3 taken: ~5% hit them
    assert ahead.rng.bit_generator.state == after.rng.bit_generator.state


def test_a_draw_ahead_that_would_sample_the_incoming_rows_leaves_the_stream_untouched():
    ahead, after = _twins(16, 2)  # 2 rows held, 3 coming: 64 draws over 5 positions hit them
    assert ahead.draw_ahead(3, [64]) is None
    assert ahead.rng.bit_generator.state == after.rng.bit_generator.state
    assert ahead.sample_indices(8).tolist() == after.sample_indices(8).tolist()
