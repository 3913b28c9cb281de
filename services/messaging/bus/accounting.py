"""Accounting: per-sender sequence numbers (lost, duplicate, recovered), rejected messages,
and the end-of-run notice. No zenoh here."""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from services.messaging import keys
from services.messaging.codec import Done, MessageError

if TYPE_CHECKING:
    from services.messaging.bus.receive import Latest

log = logging.getLogger("services.messaging.bus")


# --------------------------------------------------------------------------- accounting


IN_ORDER = "in_order"
GAP = "gap"
DUPLICATE = "duplicate"
RECOVERED = "recovered"  # a resent batch that fills an earlier gap (after a learner restart)
REDUNDANT = "redundant"  # a resent batch that was already received (dropped, harmless)

MAX_HOLES = 4096  # gap intervals remembered per stream; older ones stay lost for good


class SequenceTracker:
    """Per-sender sequence numbers: proves nothing was lost or delivered twice.

    Each (sender, incarnation) counts from 0. A seq above the expected one is a gap (the
    missing ones count as ``lost`` and are remembered as holes); one below it is a
    ``duplicate``. Batches a worker *resends* (after a learner restart, flagged as such) are
    different: one that fills a hole is ``RECOVERED`` (``lost`` goes down again), one that was
    already received is ``REDUNDANT`` (dropped, counted apart). A new incarnation (a restarted
    worker) starts its own count. Holes are kept as at most ``MAX_HOLES`` intervals per
    stream, so a forged huge seq costs one interval, not memory per missing number.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._next: dict[tuple[str, str], int] = {}
        self._holes: dict[tuple[str, str], list[list[int]]] = {}  # [start, stop) intervals, sorted
        self._senders: dict[str, dict] = {}
        self.received = 0
        self.lost = 0
        self.duplicates = 0
        self.recovered = 0
        self.redundant = 0

    def observe(self, sender: str, incarnation: str, seq: int, resend: bool = False) -> str:
        with self._lock:
            stream = (sender, incarnation)
            expected = self._next.get(stream, 0)
            s = self._senders.setdefault(
                sender,
                {"received": 0, "lost": 0, "duplicates": 0, "last_seq": -1, "incarnation": incarnation},
            )
            if seq < expected:
                if resend and self._fill(stream, seq):
                    self.lost -= 1
                    s["lost"] -= 1
                    self.recovered += 1
                    s["recovered"] = s.get("recovered", 0) + 1
                    self.received += 1
                    s["received"] += 1
                    return RECOVERED
                if resend:
                    self.redundant += 1
                    s["redundant"] = s.get("redundant", 0) + 1
                    return REDUNDANT
                self.duplicates += 1
                s["duplicates"] += 1
                return DUPLICATE
            self._next[stream] = seq + 1
            self.received += 1
            s["received"] += 1
            s["last_seq"] = seq
            if s["incarnation"] != incarnation:  # a new incarnation: the old stream's holes are its own
                s["incarnation"] = incarnation
                s.pop("holes", None)
            if seq > expected:
                self.lost += seq - expected
                s["lost"] += seq - expected
                holes = self._holes.setdefault(stream, [])
                holes.append([expected, seq])
                if len(holes) > MAX_HOLES:
                    del holes[0]  # the oldest gap can no longer be filled; it stays counted as lost
                s["holes"] = [list(h) for h in holes]
                return GAP
            return IN_ORDER

    def _fill(self, stream: tuple[str, str], seq: int) -> bool:
        holes = self._holes.get(stream)
        if not holes:
            return False
        for i, (a, b) in enumerate(holes):
            if a <= seq < b:
                parts = [[a, seq]] if seq > a else []
                if seq + 1 < b:
                    parts.append([seq + 1, b])
                holes[i:i + 1] = parts
                sender = self._senders.get(stream[0])
                if sender is not None and sender.get("incarnation") == stream[1]:
                    sender["holes"] = [list(h) for h in holes]
                return True
        return False

    def restore(self, per_sender: dict[str, dict]) -> None:
        """Continue from a checkpoint's ``per_sender()``: each sender's last incarnation."""
        with self._lock:
            for sender, s in per_sender.items():
                stream = (sender, s["incarnation"])
                self._next[stream] = int(s["last_seq"]) + 1
                self._holes[stream] = [[int(a), int(b)] for a, b in s.get("holes", [])][-MAX_HOLES:]
                self._senders[sender] = dict(s)
                self.lost += int(s.get("lost", 0))
                self.duplicates += int(s.get("duplicates", 0))
                self.recovered += int(s.get("recovered", 0))
                self.redundant += int(s.get("redundant", 0))

    def expected(self, sender: str, incarnation: str) -> int:
        """The next seq expected from this stream (= how many were seen, when none is lost)."""
        with self._lock:
            return self._next.get((sender, incarnation), 0)

    def contiguous(self, sender: str) -> tuple[str, int] | None:
        """(incarnation, seq) of the sender's last stream: every seq up to `seq` was received."""
        with self._lock:
            s = self._senders.get(sender)
            if s is None:
                return None
            stream = (sender, s["incarnation"])
            holes = self._holes.get(stream)
            upto = holes[0][0] - 1 if holes else self._next.get(stream, 0) - 1
            return s["incarnation"], upto

    def per_sender(self) -> dict[str, dict]:
        """``{sender: {received, lost, duplicates, last_seq, incarnation[, holes, recovered]}}`` (a copy)."""
        with self._lock:
            return {k: {**v, **({"holes": [list(h) for h in v["holes"]]} if "holes" in v else {})}
                    for k, v in self._senders.items()}


def run_is_done(done: "Latest", run: str, rejects: "RejectLog") -> bool:
    """True once a valid end-of-run notice arrived; anything else on the key is rejected."""
    item = done.get(keys.done(run))
    if item is None:
        return False
    try:
        Done.from_bytes(item.payload)
        return True
    except MessageError as e:
        rejects.reject(keys.parse_last(item.key) if "/" in item.key else "?", e)
        done.forget(item.key)
        return False


class RejectLog:
    """Counts rejected messages by reason; logs the first of each (sender, reason) pair.

    A bad message never crashes a process: it is dropped, counted here, and the operator
    sees one warning per sender and reason rather than a flood.
    """

    MAX_LOGGED_PAIRS = 10_000  # bounded: senders of hostile messages may be arbitrary

    def __init__(self, logger: logging.Logger | None = None, what: str = "message") -> None:
        self._log = logger or log
        self._what = what
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._logged: set[tuple[str, str]] = set()

    def reject(self, sender: str | None, error: MessageError | str, detail: str = "") -> None:
        reason = error.reason if isinstance(error, MessageError) else str(error)
        if isinstance(error, MessageError) and not detail:
            detail = error.detail
        sender = sender or "?"
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1
            pair = (sender[:256], reason)
            first = pair not in self._logged and len(self._logged) < self.MAX_LOGGED_PAIRS
            if first:
                self._logged.add(pair)
        if first:
            self._log.warning("rejected %s from %s: %s %s (further ones only counted)",
                              self._what, sender[:256], reason, detail[:300])

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())
