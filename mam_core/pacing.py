"""When the learner checkpoints, pure (no Zenoh, no torch). Every other "when" of a run is
Algorithm 1's (mam_core/algorithm1.py); this one depends on the wall clock as well, and changes
nothing the run computes.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class CheckpointRule:
    """A checkpoint is due every `updates` updates, `rows` transitions or `seconds` (whichever
    comes first; the time only when something changed since the last one). The rows bound also
    bounds what workers keep for a resend (docs/DESIGN-DECISIONS.md, "Supervision")."""

    updates: int
    rows: int
    seconds: float
    last: tuple[int, int, float] = (0, 0, 0.0)  # (updates, transitions, time) of the last checkpoint

    def mark(self, updates: int, transitions: int, now: float) -> None:
        self.last = (updates, transitions, now)

    def due(self, updates: int, transitions: int, now: float) -> bool:
        u, n, t = self.last
        if updates - u >= self.updates or transitions - n >= self.rows:
            return True
        return (updates != u or transitions != n) and now - t >= self.seconds
