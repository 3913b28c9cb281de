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
