"""The learner's pacing rules, pure (no Zenoh, no torch): the rate limiter's credit, the round
barriers, the bias points and when to checkpoint. `services/learner.py` wires them to messages.

All counts are transitions received unless a name says units (iterations with the paper's
schedule, transitions with equal-data: mam_core/schedule.py).
"""

from __future__ import annotations

from dataclasses import dataclass

from mam_core.schedule import Schedule


class Pacer:
    """Where collection may go next, from the schedule and what the referee has decided.

    - Credit (`accept_until`): collection may run `tolerance` transitions ahead of what the
      updates have consumed (never before the random start phase is collected), never past the
      budget, and never past the next allocation round or the elimination until the referee has
      published it (a barrier, as in Algorithm 1: the allocation for iterations (jA, (j+1)A] is
      decided from the evaluation at jA). Without a live referee, or after the elimination,
      there is no barrier.
    - Bias points: every `bias_every` units; one is measured once the updates have caught up
      with it (the critic as trained on the point's transitions).
    """

    def __init__(self, schedule: Schedule, tolerance: int, bias_every: int = 0, transitions: int = 0) -> None:
        self.schedule = schedule
        self.tolerance = tolerance
        self.bias_every = bias_every
        self.round_done_at = 0  # units of the last round (or the elimination) the referee published
        self.eliminated = False
        self.next_bias = self._bias_point_after(schedule.units_at(transitions))

    # -- rounds -----------------------------------------------------------------------------------
    def on_allocation(self, round_: int, decided_at: int, survivor: int | None) -> None:
        """An allocation from the referee: round `round_` decided at `decided_at` transitions."""
        if round_ > 0:
            units = self.schedule.decided_round(self.schedule.units_at(decided_at))
            self.round_done_at = max(self.round_done_at, units)
        if survivor is not None:
            self.eliminated = True

    def barrier(self) -> int | None:
        """Transitions at the next round or elimination the referee has not published (None: none)."""
        if self.eliminated:
            return None
        units = self.schedule.next_barrier(self.round_done_at)
        return None if units is None else self.schedule.transitions_at(units)

    def accept_until(self, updates: int, referee_live: bool) -> int:
        """The credit: transitions the learner accepts (workers send while it has fewer)."""
        s = self.schedule
        consumed = max(s.transitions_consumed(updates), s.random_until)
        limit = min(s.budget, consumed + self.tolerance)
        barrier = self.barrier()
        if barrier is not None and referee_live:
            limit = min(limit, barrier)
        return limit

    # -- bias points ------------------------------------------------------------------------------
    def _bias_point_after(self, units: int) -> int | None:
        every = self.bias_every
        return (units // every + 1) * every if every > 0 else None

    def bias_reached(self, transitions: int) -> bool:
        """The next bias point is reached (updates aside: `finish` measures it then anyway)."""
        return self.next_bias is not None and self.schedule.units_at(transitions) >= self.next_bias

    def bias_due(self, transitions: int, updates: int) -> bool:
        """A bias point is reached and the updates have caught up with it."""
        point = self.next_bias
        return self.bias_reached(transitions) and \
            updates >= self.schedule.updates_allowed(self.schedule.transitions_at(point))

    def take_bias_point(self, transitions: int) -> int:
        """The bias point to measure now; the next one follows the current units."""
        point = self.next_bias
        if point is None:
            raise ValueError("no bias measurement in this run")
        self.next_bias = self._bias_point_after(self.schedule.units_at(transitions))
        return point


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
