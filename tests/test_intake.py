"""The learner's intake (services/roles/intake.py) on its own, fed real encoded transition
batches as the bus hands them over (`bus.Received`): what it admits goes into the replay once,
what it refuses is counted by reason and never reaches the replay."""

from __future__ import annotations

import numpy as np

from mam_core.replay import ReplayBuffer
from services.messaging import bus, keys
from services.messaging.codec import TransitionBatch, TransitionSpec
from services.roles.intake import Intake
from services.roles.lockstep import SlotStage

RUN = "r"
SPEC = TransitionSpec(obs_dim=3, act_dim=2, n_actors=2, max_rows=64, max_action=1.0)
VERSIONS = [5, 5]  # the learner's current version of each actor
DIGEST = "ab" * 16  # the weights digest a worker reports for a learned version


def batch(seq: int = 0, *, version: int = 3, digest: str = DIGEST, obs_dim: int = 3, resend: bool = False,
          policy_from: str = "") -> TransitionBatch:
    """Three rows of worker w0 (incarnation "a"), slot 0, from iteration 1, acted by actor 1; the
    third row ends an episode of return 1 + 2 + 3."""
    obs = np.arange(3 * obs_dim, dtype=np.float32).reshape(3, obs_dim)
    action = np.array([[0.1, -0.1], [0.2, -0.2], [0.3, -0.3]], np.float32)
    return TransitionBatch("w0", "a", seq, 1, version, obs, action, np.array([1.0, 2.0, 3.0], np.float32), obs + 1,
                           np.array([False, False, True]), (6.0,), resend=resend, iteration=1, slot=0,
                           policy_from=policy_from, policy_digest=digest)


def received(b: TransitionBatch, key_worker: str = "w0", payload: bytes | None = None) -> bus.Received:
    """`b` as the learner's inbox holds it: on the sending worker's transitions key."""
    return bus.Received(keys.transitions(RUN, key_worker), b.to_bytes() if payload is None else payload, None, 0.0)


def new_intake() -> Intake:
    out = Intake(ReplayBuffer(16, 3, 2), SPEC, 1 << 20)
    out.incarnation = "e1-learner"
    return out


def insert_all(i: Intake, b: TransitionBatch) -> None:
    """The learner's way: staged for slot 0, one row per iteration into the replay, then admitted and counted."""
    stage = SlotStage(1)
    assert stage.add(b) == (True, "", 0)
    for index in range(1, b.rows + 1):
        i.insert(*stage.take(index, (0,))[:2])
    assert i.admit(b)
    i.count(b, VERSIONS)


def test_a_valid_batch_is_admitted_and_its_rows_go_into_the_replay_in_order() -> None:
    i, b = new_intake(), batch()
    got = i.validate(received(b), VERSIONS)
    assert got is not None and (got.worker, got.incarnation, got.batch_seq, got.rows) == ("w0", "a", 0, 3)
    stage = SlotStage(1)
    assert stage.add(got) == (True, "", 0)
    i.insert(*stage.take(1, (0,))[:2])
    assert i.stream_partial == {"w0/a": (0, 1)} and i.own_rows(got) == 1  # a resend would repeat row 0
    i.insert(*stage.take(2, (0,))[:2])
    rows, sources, used = stage.take(3, (0,))
    i.insert(rows, sources)
    assert len(used) == 1 and used[0] is got and i.stream_partial == {} and i.stream_rows == {"w0/a": 3}
    assert i.admit(got)
    i.count(got, VERSIONS)
    buffer = i.buffer
    assert buffer.inserted == len(buffer) == 3
    assert buffer.obs[:3].tolist() == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    assert buffer.next_obs[:3].tolist() == [[1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert np.array_equal(buffer.action[:3], b.action)
    assert buffer.reward[:3].tolist() == [1, 2, 3] and buffer.not_done[:3].tolist() == [1, 1, 0]
    assert buffer.actor[:3].tolist() == [1, 1, 1] and buffer.version[:3].tolist() == [3, 3, 3]
    w = i.workers["w0"]
    assert (w.received, w.incarnation_rows, w.last_seq, w.rejected_rows, w.actor, w.lag) == (3, 3, 0, 0, 1, 2)
    assert i.episode_returns == [6.0] and i.rejects.total == 0
    assert i.checkpointed_prefixes() == {"w0": ("a", 0)}


def test_refused_batches_are_counted_by_reason_and_never_reach_the_replay() -> None:
    i = new_intake()
    assert i.validate(received(batch(), key_worker="w9"), VERSIONS) is None  # the key names another worker
    assert i.rejects.counts() == {"sender_mismatch": 1} and i.workers == {}  # counted for neither
    assert i.validate(received(batch(), payload=b"\xc1"), VERSIONS) is None  # not msgpack
    assert i.validate(received(batch(), payload=batch().to_bytes()[:-4]), VERSIONS) is None  # cut short
    assert i.validate(received(batch(1, obs_dim=4)), VERSIONS) is None  # 4 numbers per observation, not 3
    assert i.workers == {}  # (none of these decoded: no worker to tell)
    assert i.validate(received(batch(2, digest="")), VERSIONS) is None  # a learned version, no weights digest
    assert i.validate(received(batch(3, version=6)), VERSIONS) is None  # a version this learner has not reached
    assert i.rejects.counts() == {"sender_mismatch": 1, "not_msgpack": 2, "shape:obs": 1, "no_digest": 1,
                                  "future_version": 1}
    assert i.workers["w0"].rejected_rows == 6  # the decoded ones' rows are told back: w0 does not wait for them
    assert i.tracker.received == 0 and i.buffer.inserted == 0 and i.stream_rows == {}
    # Accepted: the random phase's rows carry no digest; a dead learner's version 6 is not this one's
    assert i.validate(received(batch(4, version=-1, digest="")), VERSIONS) is not None
    assert i.validate(received(batch(5, version=6, policy_from="e0-dead")), VERSIONS) is not None
    assert i.rejects.total == 6


def test_a_batch_delivered_twice_is_admitted_and_counted_once() -> None:
    """Its rows are in the replay after the first; the second copy, and a resend, are refused."""
    i, b = new_intake(), batch()
    insert_all(i, i.validate(received(b), VERSIONS))
    again = i.validate(received(b), VERSIONS)  # the same batch delivered twice: decodes, but is not admitted
    assert again is not None and not i.admit(again)
    assert i.rejects.counts() == {"duplicate": 1} and i.tracker.duplicates == 1
    resent = i.validate(received(batch(resend=True)), VERSIONS)  # resent to a learner that has it: redundant
    assert resent is not None and not i.admit(resent)
    assert i.tracker.redundant == 1 and i.rejects.total == 1
    w = i.workers["w0"]
    assert (w.received, w.rejected_rows, w.redundant_rows) == (3, 3, 3)
    assert i.buffer.inserted == 3 and i.stream_rows == {"w0/a": 3} and i.episode_returns == [6.0]


def test_a_gap_is_admitted_and_a_resend_fills_it() -> None:
    """Batch 1 was lost in flight: batch 2 comes in (the gap counted as lost), then batch 1's resend."""
    i = new_intake()
    assert i.admit(i.validate(received(batch(0)), VERSIONS))
    assert i.admit(i.validate(received(batch(2)), VERSIONS))
    assert i.tracker.lost == 1 and i.checkpointed_prefixes() == {"w0": ("a", 0)}
    assert i.admit(i.validate(received(batch(1, resend=True)), VERSIONS))
    assert (i.tracker.lost, i.tracker.recovered) == (0, 1) and i.checkpointed_prefixes() == {"w0": ("a", 2)}
    assert i.rejects.total == 0
