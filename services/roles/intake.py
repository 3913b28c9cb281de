"""The learner's intake: validate transition batches, de-duplicate them, add them to the replay
buffer, and count per worker (`WorkerTally`, sent as `codec.WorkerCounters` in the stats)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mam_core.replay import ReplayBuffer
from services.messaging import bus, keys
from services.messaging.codec import MessageError, TransitionBatch, TransitionSpec, WorkerCounters
from services.run.binding import SlotBinding

log = logging.getLogger("mam.learner")

RECENT_S = 5.0  # a worker that sent within this long counts as active (if its token is not seen)


@dataclass
class WorkerTally:
    """What the learner counts for one worker (mutable; `counters()` is the wire form)."""

    actor: int
    incarnation: str = ""
    received: int = 0  # rows, all incarnations
    incarnation_rows: int = 0  # rows from the current incarnation
    redundant_rows: int = 0  # resent rows of the current incarnation that were already held
    rejected_rows: int = 0  # rows of the current incarnation refused after decoding (not in flight any more)
    last_seq: int = -1  # of the current incarnation
    lag: int = 0  # policy versions behind at its last batch
    rate: float = 0.0  # rows per second, updated about once a second
    rows_since: int = 0
    t_since: float = field(default_factory=time.monotonic)
    last_seen: float = field(default_factory=time.monotonic)

    def counters(self, now: float) -> WorkerCounters:
        dt = now - self.t_since
        if dt >= 1.0:
            self.rate, self.rows_since, self.t_since = self.rows_since / dt, 0, now
        return WorkerCounters(received=self.received, last_seq=self.last_seq, incarnation=self.incarnation,
                              incarnation_rows=self.incarnation_rows, redundant_rows=self.redundant_rows,
                              rejected_rows=self.rejected_rows,
                              actor=self.actor, lag=self.lag, rate=round(self.rate, 2))


class Intake:
    """Transition batches into the replay buffer, each exactly once (per worker incarnation and
    batch seq; resends after a learner restart fill gaps or are dropped as redundant)."""

    def __init__(self, buffer: ReplayBuffer, spec: TransitionSpec, max_message: int,
                 binding: SlotBinding | None = None) -> None:
        self.buffer = buffer
        self.binding = binding or SlotBinding(None)  # the run's slot_binding (services/run/binding.py)
        self.spec = spec
        self.max_message = max_message
        self.tracker = bus.SequenceTracker()
        self.rejects = bus.RejectLog(log, "transitions")
        self.workers: dict[str, WorkerTally] = {}
        self.stream_rows: dict[str, int] = {}  # rows per worker/incarnation (proof of exactly-once)
        # Rows per worker/incarnation received but not inserted: iterations their slot already had
        # (a replacement worker starting behind, a predecessor's late batch). Sent = rows + skipped + lost.
        self.stream_skipped: dict[str, int] = {}
        # per worker/incarnation: its batch the learner has used only in part, (seq, rows used): a resend
        # of it to a restarted learner repeats those rows, which are in the replay already
        self.stream_partial: dict[str, tuple[int, int]] = {}
        self.episode_returns: list[float] = []
        self.incarnation = ""  # the learner's (rows acted with another incarnation's weights are accepted)

    def validate(self, item: bus.Received, versions: Sequence[int]) -> TransitionBatch | None:
        """The decoded batch, or None (rejected and counted; a decoded batch's rows are told back
        to its worker as `rejected_rows`, so it does not wait for them).

        Rows acted with the weights of another learner incarnation (a learner that died, whose
        versions count from its own start) are real transitions: they are accepted, and only
        rows tagged with this learner's incarnation (or untagged) must not carry a version it
        has not reached. Rows acted with a learned version must say which weights they were
        acted with (`policy_digest`, checked against the published ones): without it they are
        refused, not trusted. With a slot binding, a worker (the id its key names, which the router's
        access control ties to a certificate) that claims a slot its binding does not allow is
        refused (`unbound_slot`): it cannot take another worker's slot over."""
        sender = keys.parse_last(item.key)
        try:
            batch = TransitionBatch.from_bytes(item.payload, self.spec, max_bytes=self.max_message)
        except MessageError as e:
            self.rejects.reject(sender, e)
            return None
        try:
            if batch.worker != sender:
                raise MessageError("sender_mismatch", f"key says {sender}, message says {batch.worker}")
            if not self.binding.allows(batch.worker, batch.slot):
                raise MessageError("unbound_slot", f"{batch.worker} claims slot {batch.slot}; the run's slot binding "
                                   f"allows it {self.binding.describe(batch.worker)}")
            if batch.version >= 0 and not batch.policy_digest:  # a worker of this run always says which weights
                raise MessageError("no_digest", f"rows acted with actor {batch.actor}'s version {batch.version} "
                                   "carry no weights digest")
            ours = batch.policy_from in ("", self.incarnation)
            if ours and batch.version > versions[batch.actor]:
                raise MessageError("future_version", f"version {batch.version} > {versions[batch.actor]}")
        except MessageError as e:
            self.rejects.reject(sender, e)
            if e.reason not in ("sender_mismatch", "unbound_slot"):  # (those are no worker's own rows: a worker
                self._tally(batch).rejected_rows += batch.rows  # refuses to start on a slot it may not claim)
            return None
        return batch

    def admit(self, batch: TransitionBatch) -> bool:
        """Exactly once: True if the batch's rows belong in the buffer (new, or a resend that
        fills a gap); duplicates and redundant resends are counted and refused."""
        status = self.tracker.observe(batch.worker, batch.incarnation, batch.batch_seq, resend=batch.resend)
        if status == bus.DUPLICATE:
            self.rejects.reject(batch.worker, "duplicate")
            self._tally(batch).rejected_rows += batch.rows
            return False
        w = self._tally(batch)
        if status == bus.REDUNDANT:  # a resend of what this learner already has: dropped
            w.redundant_rows += batch.rows
            return False
        return True

    def insert(self, rows: dict[str, np.ndarray], sources: list[tuple[TransitionBatch, int]]) -> None:
        """An iteration's rows into the replay buffer, in slot order (`SlotStage.take`: the rows, and
        for each its batch and how many rows of it are used so far), each counted for its stream."""
        self.buffer.add_batch(rows["obs"], rows["action"], rows["reward"], rows["next_obs"], rows["terminated"],
                              actor=rows["actor"], version=rows["version"])
        for batch, used in sources:
            self.insert_row(batch, used)

    def insert_row(self, batch: TransitionBatch, used: int) -> None:
        """A row of `batch` went into the replay, the `used`-th of it (the per-stream count the
        audit holds against what the worker sent; kept in checkpoints row by row)."""
        stream = f"{batch.worker}/{batch.incarnation}"
        self.stream_rows[stream] = self.stream_rows.get(stream, 0) + 1
        if used < batch.rows:
            self.stream_partial[stream] = (batch.batch_seq, used)
        else:
            self.stream_partial.pop(stream, None)

    def own_rows(self, batch: TransitionBatch) -> int:
        """Rows of `batch` (from its first) that are in the replay already: a resend of the batch
        this learner had used in part."""
        seq, used = self.stream_partial.get(f"{batch.worker}/{batch.incarnation}", (-1, 0))
        return used if seq == batch.batch_seq else 0

    def count(self, batch: TransitionBatch, versions: Sequence[int]) -> None:
        """The per-worker counters of an admitted batch whose rows are in the buffer (or skipped)."""
        w = self._tally(batch)
        w.received += batch.rows
        w.incarnation_rows += batch.rows
        w.last_seq = max(w.last_seq, batch.batch_seq)
        w.actor = batch.actor
        w.lag = versions[batch.actor] - batch.version if batch.version >= 0 else 0
        w.last_seen = time.monotonic()
        w.rows_since += batch.rows
        if batch.episode_return:
            self.episode_returns.extend(batch.episode_return)

    def skip(self, batch: TransitionBatch, rows: int) -> None:
        """`rows` of `batch` that its slot had from elsewhere: received, not inserted."""
        stream = f"{batch.worker}/{batch.incarnation}"
        self.stream_skipped[stream] = self.stream_skipped.get(stream, 0) + rows
        self._tally(batch).redundant_rows += rows

    def _tally(self, batch: TransitionBatch) -> WorkerTally:
        w = self.workers.setdefault(batch.worker, WorkerTally(actor=batch.actor))
        if w.incarnation != batch.incarnation:
            w.incarnation, w.incarnation_rows, w.redundant_rows, w.last_seq = batch.incarnation, 0, 0, -1
            w.rejected_rows = 0
        return w

    def counters(self, now: float, acked: dict[str, tuple[str, int]]) -> dict[str, WorkerCounters]:
        """Per worker, for the stats; with `acked` (worker -> (incarnation, seq) in the last
        checkpoint): what each worker may stop keeping for a resend."""
        out = {wid: w.counters(now) for wid, w in self.workers.items()}
        for wid, (incarnation, seq) in acked.items():
            base = out.get(wid) or WorkerCounters(received=0, last_seq=-1)
            out[wid] = WorkerCounters(**{**base.to_dict(), "acked_incarnation": incarnation, "acked_seq": seq})
        return out

    def active(self, now: float) -> int:
        """Workers that sent within RECENT_S."""
        return sum(1 for w in self.workers.values() if now - w.last_seen < RECENT_S)

    def checkpointed_prefixes(self) -> dict[str, tuple[str, int]]:
        """Per worker: the (incarnation, seq) up to which every batch is in the buffer."""
        out = {}
        for sender in self.tracker.per_sender():
            prefix = self.tracker.contiguous(sender)
            if prefix is not None:
                out[sender] = prefix
        return out

    def transport(self) -> dict[str, Any]:
        """Per worker and per stream, for transport.json."""
        return {"per_worker": {wid: {"received": w.received, "incarnation": w.incarnation, "last_seq": w.last_seq}
                               for wid, w in self.workers.items()},
                "rows_per_stream": dict(self.stream_rows), "skipped_per_stream": dict(self.stream_skipped),
                "streams": self.tracker.per_sender()}
