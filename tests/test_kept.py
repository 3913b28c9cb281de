"""KeptBatches on its own, with made-up batches: what a worker keeps, forgets and sends again."""

from __future__ import annotations

import numpy as np

from services.messaging.codec import TransitionBatch, TransitionSpec
from services.roles.kept import KeptBatches


def batch(seq: int, iteration: int, rows: int) -> TransitionBatch:
    obs = np.full((rows, 2), float(iteration), np.float32)
    return TransitionBatch("w0", "inc", seq, 0, -1, obs, obs[:, :1] * 0.0, np.zeros(rows, np.float32), obs + 1.0,
                           np.zeros(rows, np.bool_), iteration=iteration, slot=0)


class Publisher:
    """Takes what `resend` puts, decoded."""

    def __init__(self) -> None:
        self.sent: list[TransitionBatch] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(TransitionBatch.from_bytes(payload, TransitionSpec(obs_dim=2, act_dim=1, n_actors=1)))


def test_kept_until_acked_and_bounded_by_rows():
    kept = KeptBatches(True, max_rows=10)
    for seq, it in enumerate((1, 5, 9)):
        kept.add(batch(seq, it, 4))  # 12 rows > 10: the oldest batch is dropped, counted
    assert [b.batch_seq for b in kept.batches] == [1, 2] and kept.rows == 8 and kept.dropped_rows == 4
    kept.acked(1)  # the learner checkpointed through seq 1
    assert [b.batch_seq for b in kept.batches] == [2] and kept.rows == 4
    assert kept.counters() == {"resent_rows": 0, "resends": 0, "unacked_rows": 4, "unacked_dropped_rows": 4}
    off = KeptBatches(False, max_rows=10)  # without --save-replay nothing is kept
    off.add(batch(0, 1, 4))
    assert not off.batches and off.rows == 0


def test_holds_forget_and_resend_from_an_iteration():
    kept = KeptBatches(True, max_rows=100)
    for seq, it in enumerate((1, 5, 9)):
        kept.add(batch(seq, it, 4))  # iterations 1-4, 5-8, 9-12
    assert [kept.holds(i) for i in (0, 1, 8, 12, 13)] == [False, True, True, True, False]
    pub = Publisher()
    kept.resend(pub, "the learner", from_iteration=7)  # the batches with rows of 7 and later
    assert [(b.batch_seq, b.iteration, b.resend) for b in pub.sent] == [(1, 5, True), (2, 9, True)]
    assert np.array_equal(pub.sent[1].obs, np.full((4, 2), 9.0, np.float32))
    assert kept.counters()["resent_rows"] == 8 and kept.resends == 1
    kept.resend(pub, "a new learner")  # all of them
    assert [b.batch_seq for b in pub.sent[2:]] == [0, 1, 2] and kept.resends == 2
    kept.forget_from(5)  # the slot is rebuilt at iteration 5
    assert [b.iteration for b in kept.batches] == [1] and kept.rows == 4 and not kept.holds(5)
    kept.resend(pub, "the learner", from_iteration=5)  # nothing left from there: nothing sent
    assert len(pub.sent) == 5 and kept.resends == 2
