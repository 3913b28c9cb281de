"""The run's accounting: Algorithm 1's iterations, or transitions with an update-to-data ratio.

Every option that counts steps — `--steps` (T), `--start-steps`, `--compete-every` (A),
`--eliminate-at` (C), `--eval-every`, `--bias-every` — counts *schedule units*:

- `paper` (Algorithm 1, the default). A unit is an *iteration*: every live environment slot
  steps once (M transitions before the elimination), then every live actor's critics are
  updated once (`utd` updates per iteration, 1 in the paper) and, every d iterations, the
  actors and targets. After the elimination at C the survivor runs one environment slot
  (I_e = 1), so an iteration is one transition. T iterations are therefore
  C·M + (T − C) transitions when C < T (K > 1 with obsolescence), and T·M otherwise.
- `equal-data`. A unit is a transition: every run of a grid gets the same data, and the
  learner makes `utd` updates per transition after the start phase.

For K = 1 (TD3, DDPG) with M = 1 both schedules are the same run.

The distributed system counts transitions (what reaches the replay buffer); this class maps
between the two. `mam_core/algorithm1.py` builds Algorithm 1's iterations on it, so every role
follows the paper's clock exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mam_core.config import SCHEDULES, AlgoConfig


def round_multiple(units: int, compete_every: int, eliminate_at: int | None, first_round: int,
                   last_round_at: int) -> int | None:
    """The multiple of A of an allocation round due at `units`, or None: rounds are at A, 2A, ...
    strictly before C (Algorithm 1, line 15), from `first_round` on, at most one per multiple
    (after the round at `last_round_at`) even when the counter jumps past several. The one rule
    behind `Schedule.round_due` and `Obsolescence.due_round` (mam_core/obsolescence.py)."""
    if eliminate_at is None or units >= eliminate_at:
        return None
    multiple = (units // compete_every) * compete_every
    if multiple < first_round or multiple <= last_round_at:
        return None
    return multiple


def first_round_at(compete_every: int, start: int, skip_random_rounds: bool) -> int:
    """The first multiple of A at which an allocation round may happen: A, or with
    `--skip-random-rounds` the first multiple strictly after the start phase."""
    if skip_random_rounds:
        return (start // compete_every + 1) * compete_every
    return compete_every


@dataclass(frozen=True)
class Schedule:
    kind: str  # paper | equal-data
    slots: int  # M: environment slots before the elimination
    steps: int  # T, in units
    start: int  # start steps (uniform random actions, no updates), in units
    compete_every: int  # A, in units
    eliminate_at: int | None  # C, in units; None: no elimination (K = 1 or --no-ot)
    utd: float = 1.0  # updates per unit after the start phase
    skip_random_rounds: bool = False  # no allocation round while still in the start phase

    def __post_init__(self) -> None:
        if self.kind not in SCHEDULES:
            raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)}, not {self.kind!r}")
        if self.slots < 1 or self.steps < 1 or self.start < 0 or self.compete_every < 1 or self.utd <= 0:
            raise ValueError(f"invalid schedule {self}")

    @classmethod
    def for_run(cls, algo: AlgoConfig, steps: int) -> Schedule:
        """The schedule of an algorithm configuration (mam_core.config.AlgoConfig) and budget T."""
        eliminates = algo.actors > 1 and not algo.no_ot
        return cls(kind=algo.schedule, slots=algo.workers, steps=steps, start=algo.start_steps,
                   compete_every=algo.compete_every, eliminate_at=max(algo.eliminate_at, 1) if eliminates else None,
                   utd=algo.utd, skip_random_rounds=algo.skip_random_rounds)

    @property
    def paper(self) -> bool:
        return self.kind == "paper"

    # -- units <-> transitions ------------------------------------------------------------------
    def transitions_at(self, units: int) -> int:
        """Transitions collected once `units` iterations (or transitions) are complete."""
        units = max(int(units), 0)
        if not self.paper:
            return units
        c = self.eliminate_at
        if c is None or units <= c:
            return units * self.slots
        return c * self.slots + (units - c)

    def units_at(self, transitions: int) -> int:
        """Complete iterations (or transitions) after `transitions` transitions; inverse of
        `transitions_at` on its image, rounding down in between."""
        transitions = max(int(transitions), 0)
        if not self.paper:
            return transitions
        c = self.eliminate_at
        if c is None or transitions <= c * self.slots:
            return transitions // self.slots
        return c + (transitions - c * self.slots)

    @property
    def budget(self) -> int:
        """T in transitions: what the learner collects before the run is done."""
        return self.transitions_at(self.steps)

    @property
    def random_until(self) -> int:
        """Transitions collected with uniform random actions."""
        return self.transitions_at(self.start)

    def slots_at(self, units: int) -> int:
        """Environment slots of an iteration: M before C, 1 after (paper); M always otherwise."""
        if self.paper and self.eliminate_at is not None and units >= self.eliminate_at:
            return 1
        return self.slots

    # -- updates --------------------------------------------------------------------------------
    def updates_allowed(self, transitions: int) -> int:
        """Updates the learner may have made after `transitions`: utd per unit past the start."""
        units = self.units_at(transitions)
        if units < self.start:
            return 0
        return int(self.utd * (units - self.start))

    def transitions_consumed(self, updates: int) -> int:
        """The fewest transitions after which `updates` updates are allowed (inverse of
        `updates_allowed`): the point collection has been consumed up to."""
        return self.transitions_at(self.start + math.ceil(updates / self.utd))

    @property
    def total_updates(self) -> int:
        return self.updates_allowed(self.budget)

    # -- rounds ---------------------------------------------------------------------------------
    def first_round(self) -> int:
        """The first multiple of A at which an allocation round may happen (units)."""
        return first_round_at(self.compete_every, self.start, self.skip_random_rounds)

    def round_due(self, units: int, last_round_at: int) -> int | None:
        """The multiple of A of a round due at `units` after the round at `last_round_at`, or
        None (`round_multiple`)."""
        return round_multiple(units, self.compete_every, self.eliminate_at, self.first_round(), last_round_at)

    def decided_round(self, units: int) -> int:
        """The round an allocation decided at `units` closes: C at or after the elimination, else
        the multiple of A at or below `units` (what `next_barrier` takes)."""
        c = self.eliminate_at
        if c is not None and units >= c:
            return c
        return (units // self.compete_every) * self.compete_every

    def next_barrier(self, done_at: int) -> int | None:
        """Units of the next round or of the elimination after the one decided at `done_at`
        (None once the elimination is done, or without one): collection waits there for the
        referee (Algorithm 1 decides I_k before the next iteration's steps)."""
        c = self.eliminate_at
        if c is None or done_at >= c:
            return None
        nxt = max((done_at // self.compete_every + 1) * self.compete_every, self.first_round())
        return min(nxt, c)

