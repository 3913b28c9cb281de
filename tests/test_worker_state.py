"""A worker's state on its own (services/roles/worker_state.py): the batch being built, and the
helpers of takeover.py that take what the worker knows of the learner instead of the worker."""

from __future__ import annotations

import time

import numpy as np

from services.messaging.codec import LearnerStats, TransitionBatch
from services.roles.kept import KeptBatches
from services.roles.takeover import RESYNC_S, follow_owner, out_of_step
from services.roles.worker_state import LearnerWatch, PendingBatch


def add(p: PendingBatch, index: int, value: float, *, start: bool = False, version: int = 2) -> None:
    p.add(index, np.full(3, value), np.full(2, value / 10), value, np.full(3, value + 1), value == 3,
          episode_start=start, actor=1, version=version, policy_from="e1-x", digest="d")


def test_the_pending_batch_holds_rows_of_one_source_until_sent() -> None:
    p = PendingBatch.empty(4, 3, 2)
    assert p.rows == 0 and not p.acted_otherwise(0, 5, "e9")  # nothing pending: nothing to flush
    add(p, 7, 1.0, start=True)
    add(p, 8, 2.0)
    add(p, 9, 3.0, start=True)
    assert (p.rows, p.iteration, p.starts) == (3, 7, [0, 2])
    assert (p.actor, p.version, p.policy_from, p.digest) == (1, 2, "e1-x", "d")
    assert not p.acted_otherwise(1, 2, "e1-x")
    assert p.acted_otherwise(0, 2, "e1-x") and p.acted_otherwise(1, 3, "e1-x") and p.acted_otherwise(1, 2, "e2-y")
    obs, action, reward, next_obs, terminated = p.arrays(copy=False)
    assert obs.tolist() == [[1, 1, 1], [2, 2, 2], [3, 3, 3]] and next_obs[:, 0].tolist() == [2, 3, 4]
    assert np.allclose(action[:, 0], [0.1, 0.2, 0.3]) and reward.tolist() == [1, 2, 3]
    assert terminated.tolist() == [False, False, True]
    assert np.shares_memory(obs, p.obs) and not np.shares_memory(p.arrays(copy=True)[0], p.obs)  # kept: copies
    p.returns.append(6.0)
    batch = TransitionBatch("w0", "a", 0, p.actor, p.version, *p.arrays(copy=True), tuple(p.returns),
                            iteration=p.iteration, slot=0, episode_starts=tuple(p.starts))
    p.sent()
    assert (p.rows, p.starts, p.returns) == (0, [], []) and batch.episode_starts == (0, 2)
    add(p, 10, 4.0)  # the arrays are reused: the next batch starts at its first row
    assert (p.rows, p.iteration, p.starts) == (1, 10, []) and p.obs[0].tolist() == [4, 4, 4]


def stats(owner: str = "", slots_next: tuple[int, ...] = (5,), incarnation: str = "e2-new") -> LearnerStats:
    return LearnerStats(env_steps=0, updates=0, accept_until=0, utd=0.0, incarnation=incarnation,
                        slots_next=slots_next, owners=(owner,))


def test_a_worker_named_its_slot_s_owner_leaves_once_another_is_named() -> None:
    w = LearnerWatch()
    follow_owner(w, stats("w1/b"), 0, "w0", "a")  # never named the owner: another one is no news
    assert (w.owned, w.lost_to) == (False, "")
    follow_owner(w, stats("w0/a"), 0, "w0", "a")
    assert (w.owned, w.lost_to) == (True, "")
    follow_owner(w, stats(""), 0, "w0", "a")  # a learner that names no owner yet
    assert (w.owned, w.lost_to) == (True, "")
    follow_owner(w, stats("w1/b"), 0, "w0", "a")
    assert w.lost_to == "w1/b"
    follow_owner(w, stats("w2/c"), 0, "w0", "a")
    assert w.lost_to == "w1/b"  # the first that took it


def test_a_slot_is_rebuilt_only_where_a_restarted_learner_waits_for_rows_no_one_will_send() -> None:
    now = time.monotonic()
    long_ago = now - 10 * RESYNC_S
    w = LearnerWatch(stats=stats(slots_next=(5,)), stats_at=now - 1.0, seen_at=long_ago, synced_with="e1-old")
    kept = KeptBatches(True, 1000)
    assert out_of_step(w, 0, 8, long_ago, 0, long_ago, kept)  # needs iteration 5; this slot is at 8
    assert not out_of_step(w, 0, 5, long_ago, 0, long_ago, kept)  # needs the one the slot steps next
    assert not out_of_step(w, 0, 8, long_ago, 2, long_ago, kept)  # rows still pending here
    assert not out_of_step(w, 0, 8, long_ago, 0, now, kept)  # a batch just went: its stats may not show it yet
    z = np.zeros
    kept.add(TransitionBatch("w0", "a", 0, 0, -1, z((3, 3), np.float32), z((3, 2), np.float32), z(3, np.float32),
                             z((3, 3), np.float32), z(3, np.bool_), iteration=4, slot=0))  # iterations 4..6
    assert not out_of_step(w, 0, 8, long_ago, 0, long_ago, kept)  # the kept rows go again instead
    w.synced_with = "e2-new"
    assert not out_of_step(w, 0, 8, long_ago, 0, long_ago, KeptBatches(True, 1000))  # already taken from it
    assert not out_of_step(LearnerWatch(), 0, 8, long_ago, 0, long_ago, kept)  # no stats yet
