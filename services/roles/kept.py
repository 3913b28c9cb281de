"""What a worker keeps of the batches it sent, and sends again (docs/RELIABILITY.md).

A worker keeps each batch until the learner has checkpointed its rows (`save_replay`; at most
`resend_rows` rows are kept). The kept batches go again, flagged as resends, in order:

- all of them to a new learner incarnation (it has only its checkpoint);
- from a lost one on, when the same learner still waits, well after this worker sent it, for an
  iteration of this slot that a kept batch holds. A put into a link that Zenoh has just closed
  is dropped without an error: a worker frozen past its lease (SIGSTOP, a swapped-out VM) comes
  back to a closed link, and its first batch after it is gone.

The learner keeps only the rows it lacks (SlotStage.add and the intake's exactly-once tracker).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from typing import Any

from services.messaging.codec import TransitionBatch

log = logging.getLogger("mam.worker")


class KeptBatches:
    def __init__(self, keep: bool, max_rows: int) -> None:
        self.keep, self.max_rows = keep, max_rows
        self.batches: deque[TransitionBatch] = deque()
        self.rows = self.resent_rows = self.resends = 0
        self.dropped_rows = 0  # over the bound: not kept (if then lost, a counted gap)

    def add(self, batch: TransitionBatch) -> None:
        if not self.keep:
            return
        self.batches.append(batch)
        self.rows += batch.rows
        while self.rows > self.max_rows and len(self.batches) > 1:
            dropped = self.batches.popleft()
            self.rows -= dropped.rows
            self.dropped_rows += dropped.rows

    def acked(self, seq: int) -> None:
        """The learner has checkpointed the rows of batches up to `seq`."""
        while self.batches and self.batches[0].batch_seq <= seq:
            self.rows -= self.batches.popleft().rows

    def forget_from(self, iteration: int) -> None:
        """The slot is rebuilt at `iteration`: the kept rows from there on will not be used."""
        self.batches = deque(b for b in self.batches if b.iteration < iteration)
        self.rows = sum(b.rows for b in self.batches)

    def holds(self, iteration: int) -> bool:
        """A kept batch has the row of `iteration`."""
        return any(b.iteration <= iteration < b.iteration + b.rows for b in self.batches)

    def resend(self, pub: Any, to: str, from_iteration: int | None = None) -> None:
        """The kept batches (those with rows of `from_iteration` and later), in order."""
        batches = [b for b in self.batches if from_iteration is None or b.iteration + b.rows > from_iteration]
        if not batches:
            return
        for batch in batches:
            pub.put(dataclasses.replace(batch, resend=True).to_bytes())
        n = sum(b.rows for b in batches)
        self.resent_rows += n
        self.resends += 1
        log.info("resent %d rows in %d batches (seq %d..%d) to %s", n, len(batches), batches[0].batch_seq,
                 batches[-1].batch_seq, to)

    def counters(self) -> dict[str, int]:
        return {"resent_rows": self.resent_rows, "resends": self.resends, "unacked_rows": self.rows,
                "unacked_dropped_rows": self.dropped_rows}
