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
    for draw, where it answers: the clear draws before the rows go in, the others after (as the
    learner makes an iteration's updates ahead, then the rest); the clear ones never point at the
    3 positions the rows take, and the first that is not clear does."""
    ahead, after = _twins(capacity, rows)
    answered = partial = 0
    for it in range(60):
        answer = ahead.draw_ahead(3, [16, 32, 160])
        taken = {(ahead.pos + j) % capacity for j in range(3)}
        got = []
        if answer is not None:
            drawn, clear = answer
            answered += 1
            partial += clear < 3
            assert not taken & set(np.concatenate(drawn[:clear]).tolist())
            if clear < 3:
                assert taken & set(drawn[clear].tolist())
            got = [ahead.gather(idx, 16, groups=len(idx) // 16 if len(idx) > 16 else None) for idx in drawn[:clear]]
        _insert(ahead, rows + 3 * it, 3)
        _insert(after, rows + 3 * it, 3)
        want = [after.sample(16), after.sample(16, groups=2), after.sample(16, groups=10)]
        if answer is None:  # as the learner does: it waits for the rows and samples then
            got = [ahead.sample(16), ahead.sample(16, groups=2), ahead.sample(16, groups=10)]
        else:  # the rest, at the positions drawn ahead, once the rows are in
            got += [ahead.gather(idx, 16, groups=len(idx) // 16) for idx in drawn[clear:]]
        for w, g in zip(want, got):
            assert {n: t.tolist() for n, t in w.items()} == {n: t.tolist() for n, t in g.items()}
        assert ahead.rng.bit_generator.state == after.rng.bit_generator.state
    assert answered >= 50 and partial >= 3  # 208 draws over 3,000 rows, 3 taken: ~19% hit them, mostly the last 160


def test_a_draw_ahead_that_would_sample_the_incoming_rows_leaves_the_stream_untouched():
    ahead, after = _twins(16, 2)  # 2 rows held, 3 coming: 64 draws over 5 positions hit them
    assert ahead.draw_ahead(3, [64]) is None
    assert ahead.rng.bit_generator.state == after.rng.bit_generator.state
    assert ahead.sample_indices(8).tolist() == after.sample_indices(8).tolist()


def test_an_iterations_updates_made_partly_ahead_of_its_rows_equal_those_made_after():
    """The learner's order at lag 0 (`Algorithm1.updates_ahead`, the rows, `rest_of`) against the
    plain one (the rows, `run_updates`): MA-TD3 K=2 with M=3 rows and 3 updates an iteration (the
    equal-data schedule: an update per transition; the paper's makes one an iteration), in a
    small replay so that an iteration's later mini-batches often sample a coming row (the updates
    before it go ahead, the rest wait); every parameter equal bit for bit after 60 iterations."""
    import torch

    from mam_core.agent import EnvSpec, MultiActorAgent

    cfg = resolve("ma-td3", workers=3, hidden=(8, 8), batch_size=16, start_steps=0, seed=5, schedule="equal-data")
    plan = Algorithm1.for_run(cfg, 1000)
    spec = EnvSpec(2, 1, (1.0,))
    sides = []
    for _ in range(2):
        torch.manual_seed(0)
        agent, buffer = MultiActorAgent(cfg, spec), ReplayBuffer(120, 2, 1, seed=9)
        _insert(buffer, 0, 60)
        sides.append((agent, buffer))
    (a, ra), (b, rb) = sides
    made_ahead = split = 0
    for index in range(21, 81):
        it = plan.iteration(index)
        assert it.updates[1] - it.updates[0] == 3
        first = 3 * index
        ahead = plan.updates_ahead(it, a, ra, lambda: None)
        _insert(ra, first, len(it.slots))
        ma = plan.run_updates(it, a, lambda: ra.sample(cfg.batch_size, a.batch_groups), lambda: None) \
            if ahead is None else plan.rest_of(it, ahead, a, ra, lambda: None)
        _insert(rb, first, len(it.slots))
        mb = plan.run_updates(it, b, lambda: rb.sample(cfg.batch_size, b.batch_groups), lambda: None)
        made_ahead += ahead is not None
        split += ahead is not None and bool(ahead.rest)
        assert ma == mb, index
        assert ra.rng.bit_generator.state == rb.rng.bit_generator.state
    assert made_ahead >= 10 and split >= 5, (made_ahead, split)  # both paths taken
    for net in ("actor", "critic"):
        for (name, x), (_, y) in zip(a.state_dict()[net].items(), b.state_dict()[net].items()):
            assert torch.equal(x, y), (net, name)
