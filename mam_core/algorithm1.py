"""Algorithm 1's control flow, pure: what iteration i does, for every role to follow.

The one-process reference (mam_core.reference) and the distributed roles (learner, referee,
workers in services/) drive this object; none of them re-derives a rule. It knows nothing of
messages, tensors or environments: only the schedule (mam_core.schedule).

An *iteration* is one sweep over the live environment slots. Under `--schedule paper` it is
Algorithm 1's iteration t (M transitions before C, one after: the survivor runs slot 0);
under `equal-data` a sweep is M transitions and the schedule's units are transitions.

The order of operations of iteration i (Algorithm 1's line numbers), with a lag B >= 0
(`--lag`, 0 by default: Algorithm 1 as printed):

1. Collect (lines 5-10): every slot of `slots` steps once, in slot order, with the actor the
   allocation in force gives it (`decision_for(i)`: the latest competition j with
   j + 1 + B <= i) and that actor's weights after iteration i-1-B's updates (`version_for`);
   uniform random actions while `random`. The transitions enter the replay buffer in slot
   order. With B >= 1 a worker may step up to B iterations ahead of the learner's updates.
2. Critic updates (lines 11-13): the agent's update counter goes from `updates[0]` to
   `updates[1]`, one mini-batch per actor each.
3. A competition (lines 15-17) if `round` is set: the live actors are evaluated as they stand
   after iteration i-1's updates (`judged_version`: at B = 0 the actors that acted in i; the
   critic update does not touch them), P_k follows Eq. 8, and the allocation it draws
   applies from iteration i+1+B on.
4. The elimination (lines 18-20) if `eliminate`: evaluated like a round; it applies right
   before the first delayed actor update of this iteration (or at its end if it has none), so
   the eliminated actors' last version is `version_after(i-1)`. From i+1 on the survivor's
   schedule holds (one slot under `paper`); slot 0 acts with the allocation in force, which
   names the survivor from i+1+B on.
5. Delayed actor and target updates (lines 21-24): whenever the update counter is a multiple
   of d (TD3's rule; with one update per iteration this is Algorithm 1's t mod d).
6. A learning-curve evaluation after the updates if `curve` is set (`version_after(i)`),
   on episodes disjoint from every competition's.

Every evaluation judges the newest actors the learner has when it is due, whatever B: the lag
delays only when decisions and weights reach the slots (docs/DESIGN-DECISIONS.md, "The lag").
Weights change only in iterations with an actor update (`weights_change`): the others need no
new weights, so a worker steps through them without waiting.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property
from typing import TYPE_CHECKING, Any

from mam_core.config import AlgoConfig
from mam_core.schedule import Schedule

if TYPE_CHECKING:
    from mam_core.agent import MultiActorAgent


class Purpose(StrEnum):
    """What an evaluation is for (`Algorithm1.events`); its value is the word in eval.jsonl and
    the purpose of its episodes' seed (mam_core.seeding.evaluation_seed)."""

    ROUND = "round"  # a competition at j·A (lines 15-17)
    ELIMINATION = "elimination"  # the competition at C (lines 18-20)
    CURVE = "curve"  # a learning-curve point at j·eval-every
    FINAL = "final"  # after the last iteration, when it is no curve point

    @property
    def competes(self) -> bool:
        """A competition: it judges the actors after the previous iteration and draws an allocation."""
        return self in (Purpose.ROUND, Purpose.ELIMINATION)


@dataclass(frozen=True)
class Iteration:
    """What iteration `index` does (see the module docstring for the order)."""

    index: int  # 1, 2, ...
    slots: tuple[int, ...]  # the environment slots that step, in slot order
    transitions: tuple[int, int]  # transitions collected before / after it
    units: tuple[int, int]  # schedule units (iterations or transitions) before / after it
    random: bool  # uniform random actions (the start phase)
    updates: tuple[int, int]  # the agent's update counter before / after its updates
    round: int | None  # the index j of the competition at j·A decided in it, or None
    eliminate: bool  # the elimination at C happens in it
    curve: int | None  # the index j of the learning-curve evaluation at j·eval-every after it
    last: bool  # the run's last iteration (the final evaluation follows it)

    @property
    def competes(self) -> bool:
        return self.round is not None or self.eliminate

    def evaluation_index(self, purpose: Purpose | str) -> int | None:
        """The j that names the episodes of this iteration's `purpose` evaluation (with the
        run's seed: mam_core.seeding.evaluation_seed): the round's for a round, else the curve's."""
        return self.round if purpose == Purpose.ROUND else self.curve


@dataclass(frozen=True)
class Ahead:
    """An iteration's updates begun before its rows are in (`Algorithm1.updates_ahead`)."""

    made: int  # updates made (at least one)
    metrics: dict[str, float]  # the last one's
    rest: list[Any]  # the positions of the remaining updates' mini-batches, drawn (gathered once the rows are in)


def _gathering(replay: Any, agent: MultiActorAgent, positions: list[Any]) -> Callable[[], Any]:
    """A `sample` for `_updates` that gathers the mini-batches at `positions` (drawn ahead), in order."""
    pending, size, groups = iter(positions), agent.cfg.batch_size, agent.batch_groups
    return lambda: replay.gather(next(pending), size, groups)


_RECENT = 256  # iterations (and update counts) an `Algorithm1` keeps once built


def _kept(recent: dict[int, Any], index: int, build: Callable[[int], Any]) -> Any:
    """`build(index)`, kept in `recent` (emptied when full) for the next ask."""
    value = recent.get(index)
    if value is None:
        if len(recent) >= _RECENT:
            recent.clear()
        value = recent[index] = build(index)
    return value


@dataclass(frozen=True)
class Algorithm1:
    schedule: Schedule
    batch_size: int  # no update before the buffer holds a mini-batch
    policy_delay: int  # d
    eval_every: int  # learning-curve evaluations every this many units
    single_env: bool = True  # after the elimination the survivor runs one slot (slot 0)
    lag: int = 0  # B: iteration t acts with the actors after iteration t-1-B; decisions apply B iterations later

    def __post_init__(self) -> None:
        if self.lag < 0:
            raise ValueError(f"lag must be >= 0, not {self.lag}")

    @classmethod
    def for_run(cls, cfg: AlgoConfig, steps: int) -> Algorithm1:
        return cls(Schedule.for_run(cfg, steps), cfg.batch_size, cfg.policy_delay, cfg.eval_every, cfg.single_env,
                   cfg.lag)

    # -- shape of the run -------------------------------------------------------------------------
    @property
    def slots(self) -> int:
        return self.schedule.slots

    @property
    def one_slot_after_elimination(self) -> bool:
        """After C the survivor runs slot 0 alone: `--single-env-after-elimination`, or `paper`."""
        return self.single_env or self.schedule.paper

    @cached_property
    def elimination(self) -> int | None:
        """The iteration of the elimination, or None (K = 1, `--no-ot`, or C past the budget)."""
        c = self.schedule.eliminate_at
        if c is None:
            return None
        m = self.slots
        i = c if self.schedule.paper else -(-c // m)  # the first sweep whose units reach C
        return i if self.transitions_before(i) < self.schedule.budget else None

    def width(self, index: int) -> int:
        """Slots stepping in iteration `index` (the last one may be cut by the budget)."""
        e = self.elimination
        if e is not None and index > e and self.one_slot_after_elimination:
            return 1
        return self.slots

    def row_of(self, index: int, slot: int) -> int:
        """The replay row (insertion index) of slot `slot`'s transition in iteration `index`: an
        iteration's rows go in in slot order, after the iterations before it."""
        return self.transitions_before(index) + slot

    def transitions_before(self, index: int) -> int:
        c = self.schedule.eliminate_at
        m = self.slots
        if c is None:
            done = (index - 1) * m
        else:  # `elimination` without the budget check (it calls this)
            e = c if self.schedule.paper else -(-c // m)
            after = 1 if self.one_slot_after_elimination else m
            done = min(index - 1, e) * m + max(index - 1 - e, 0) * after
        return min(done, self.schedule.budget)

    @cached_property
    def iterations(self) -> int:
        """How many iterations the run has."""
        budget = self.schedule.budget
        lo, hi = 1, budget  # transitions_before is non-decreasing: the last index with before < budget
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if self.transitions_before(mid) < budget:
                lo = mid
            else:
                hi = mid - 1
        return lo

    def slot_steps(self, slot: int, index: int) -> tuple[int, int]:
        """Slot `slot`'s steps in iterations 1..index-1: (start-phase steps, steps with an actor).
        A slot steps in a prefix of the iterations (every slot until C, slot 0 after it; only the
        last iteration may be cut short), and the start phase is a prefix too."""
        n = max(min(index - 1, self.last_step(slot)), 0)
        random = min(n, self._random_iterations)
        return random, n - random

    def last_step(self, slot: int) -> int:
        """The last iteration in which `slot` steps (0: none): after it the slot needs no actor."""
        if slot not in self._last_steps:
            self._last_steps[slot] = self._find_last_step(slot)
        return self._last_steps[slot]

    @cached_property
    def _last_steps(self) -> dict[int, int]:
        return {}

    def _find_last_step(self, slot: int) -> int:
        def steps(i: int) -> bool:
            after = self.transitions_before(i + 1) if i < self.iterations else self.schedule.budget
            return slot < min(self.width(i), after - self.transitions_before(i))
        return _last_true(steps, self.iterations)

    @cached_property
    def _random_iterations(self) -> int:
        """Iterations of the start phase (uniform random actions)."""
        return _last_true(lambda i: self.transitions_before(i) < self.schedule.random_until, self.iterations)

    def units_past_start(self, units: int) -> int:
        """Schedule units after the random start phase: the ones updates are made for."""
        return max(units - self.schedule.start, 0)

    def replay_capacity(self, buffer_size: int) -> int:
        """Rows the replay buffer holds: the run's transitions, at most `buffer_size`."""
        return min(buffer_size, max(self.schedule.budget, self.batch_size))

    # -- one iteration ----------------------------------------------------------------------------
    def updates_after(self, index: int) -> int:
        """The agent's update counter after iteration `index` (0 before the first)."""
        return _kept(self._recent_updates, index, self._updates_after)

    def _updates_after(self, index: int) -> int:
        if index <= 0:
            return 0
        n = self.transitions_before(index + 1) if index < self.iterations else self.schedule.budget
        return self.schedule.updates_allowed(n) if n >= self.batch_size else 0

    def iteration(self, index: int) -> Iteration:
        """Iteration `index` (1..iterations). A role asks for the same few iterations, and their
        versions, many times (a worker on each pass of its loop): the recent ones are kept."""
        return _kept(self._recent, index, self._iteration)

    @cached_property
    def _recent(self) -> dict[int, Iteration]:
        return {}

    @cached_property
    def _recent_updates(self) -> dict[int, int]:
        return {}

    def _iteration(self, index: int) -> Iteration:
        if not 1 <= index <= self.iterations:
            raise ValueError(f"iteration {index} outside 1..{self.iterations}")
        s = self.schedule
        before = self.transitions_before(index)
        after = self.transitions_before(index + 1) if index < self.iterations else s.budget
        u0, u1 = s.units_at(before), s.units_at(after)
        eliminate = index == self.elimination
        round_ = None
        if not eliminate and s.eliminate_at is not None:
            multiple = s.round_due(u1, last_round_at=u0)  # a multiple of A in (u0, u1], before C
            round_ = None if multiple is None else multiple // s.compete_every
        curve = _crossed(u0, u1, self.eval_every)
        return Iteration(index=index, slots=tuple(range(after - before)) if after - before < self.width(index)
                         else tuple(range(self.width(index))),
                         transitions=(before, after), units=(u0, u1), random=before < s.random_until,
                         updates=(self.updates_after(index - 1), self.updates_after(index)),
                         round=round_, eliminate=eliminate, curve=curve, last=index == self.iterations)

    def crossing(self, index: int, every: int) -> int | None:
        """j when iteration `index` reaches j·`every` units (the largest such j), else None (and
        always for `every` <= 0): the rule of the curve points, applied to any period (the
        learner's bias points)."""
        return _crossed(*self.iteration(index).units, every) if every > 0 else None

    def iteration_at(self, transitions: int) -> int:
        """The iterations complete once `transitions` transitions are collected."""
        lo, hi = 0, self.iterations
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if self.transitions_before(mid + 1) <= transitions:  # capped at the budget after the last
                lo = mid
            else:
                hi = mid - 1
        return lo

    # -- weights ----------------------------------------------------------------------------------
    def version_after(self, index: int) -> int:
        """A live actor's policy version after iteration `index`'s updates (one per actor update)."""
        return self.updates_after(index) // self.policy_delay

    def version_for(self, index: int) -> int:
        """The version an actor acts with in iteration `index`: after iteration index-1-B's
        updates (an actor eliminated at C acts until C+B, never past its last version)."""
        return self.version_after(index - 1 - self.lag)

    def judged_version(self, index: int, purpose: Purpose | str) -> int:
        """The version an evaluation of iteration `index` judges: a competition (`round`,
        `elimination`) the actors after iteration index-1's updates, a `curve` point or the
        `final` evaluation those after iteration index's."""
        try:
            competes = Purpose(purpose).competes
        except ValueError:
            raise ValueError(f"unknown evaluation purpose {purpose!r}") from None
        return self.version_after(index - 1 if competes else index)

    def judged_after(self, index: int) -> set[int]:
        """The versions evaluations judge once iteration `index`'s updates are done (index 0:
        before the first iteration): the next iteration's competition and this iteration's curve
        point or final evaluation (what the learner sends the referee, once each)."""
        out = set()
        if index < self.iterations and self.iteration(index + 1).competes:
            out.add(self.judged_version(index + 1, Purpose.ROUND))
        if index >= 1:
            it = self.iteration(index)
            if it.curve is not None or it.last:
                out.add(self.judged_version(index, Purpose.CURVE))
        return out

    def weights_change(self, index: int) -> bool:
        return self.version_after(index) != self.version_after(index - 1)

    def elimination_update(self) -> int | None:
        """The update (counter value after it) whose actor phase comes right after the
        elimination, or None when the elimination iteration has no actor update (the
        elimination then follows all its updates)."""
        e = self.elimination
        if e is None:
            return None
        u0, u1 = self.updates_after(e - 1), self.updates_after(e)
        d = self.policy_delay
        first = (u0 // d + 1) * d
        return first if first <= u1 else None

    def run_updates(self, it: Iteration, agent: MultiActorAgent, sample: Callable[[], Any],
                    eliminate: Callable[[], None],
                    each: Callable[[dict[str, float]], None] | None = None) -> dict[str, float]:
        """Iteration `it`'s updates (lines 11-24) on `agent` (mam_core.agent.MultiActorAgent):
        one `sample()`d mini-batch per update, critics then, when due, actors; at C
        `eliminate()` comes right before the first actor phase (or after the updates). `each`
        sees every update's metrics. The metrics of the last update."""
        return self._updates(it, it.updates[1] - it.updates[0], agent, sample, eliminate, each)

    def _updates(self, it: Iteration, n: int, agent: MultiActorAgent, sample: Callable[[], Any],
                 eliminate: Callable[[], None], each: Callable[[dict[str, float]], None] | None = None
                 ) -> dict[str, float]:
        """The next `n` of iteration `it`'s updates (`run_updates`: all of them)."""
        at = self.elimination_update() if it.eliminate else None
        metrics: dict[str, float] = {}
        for _ in range(n):
            batch = sample()
            metrics = agent.update_critics(batch)
            if agent.actor_phase_due:
                if agent.updates == at:
                    eliminate()
                metrics.update(agent.update_actors(batch))
            if each is not None:
                each(metrics)
        if it.eliminate and at is None:
            eliminate()
        return dict(metrics)  # read once per iteration (a graphed update's metrics stay on the device)

    def updates_ahead(self, it: Iteration, agent: MultiActorAgent, replay: Any,
                      eliminate: Callable[[], None]) -> Ahead | None:
        """Iteration `it`'s first updates, made before its rows are in `replay`, as many as give
        the same bits: up to the first whose mini-batch samples a position the rows will take
        (the replay's `draw_ahead`). Never for an iteration without updates or with the
        elimination, nor on a device that samples otherwise (CUDA graphs). At lag 0 the learner's
        updates then run while the workers act and step with the weights before them; `rest_of`
        makes the others once the rows are in. None: nothing done, the replay's stream untouched."""
        n = it.updates[1] - it.updates[0]
        draw = getattr(replay, "draw_ahead", None)
        if n == 0 or it.eliminate or draw is None or agent.device.type != "cpu":
            return None
        answer = draw(len(it.slots), [agent.cfg.batch_size * (agent.batch_groups or 1)] * n)
        if answer is None:
            return None
        drawn, clear = answer
        metrics = self._updates(it, clear, agent, _gathering(replay, agent, drawn[:clear]), eliminate)
        return Ahead(clear, metrics, drawn[clear:])

    def rest_of(self, it: Iteration, ahead: Ahead, agent: MultiActorAgent, replay: Any,
                eliminate: Callable[[], None]) -> dict[str, float]:
        """The updates of `it` that `ahead` left for after its rows, at the positions it drew
        (the rows are in `replay` now). The metrics of the iteration's last update."""
        if not ahead.rest:
            return ahead.metrics
        return self._updates(it, len(ahead.rest), agent, _gathering(replay, agent, ahead.rest), eliminate)

    # -- evaluations ------------------------------------------------------------------------------
    @cached_property
    def _competitions(self) -> tuple[int, ...]:
        return tuple(i for i, purpose in self.events() if purpose.competes)

    def competitions(self) -> list[int]:
        """The iterations with a competition or the elimination, in order."""
        return list(self._competitions)

    def competitions_among(self, events: int) -> int:
        """How many of the run's first `events` evaluations are competitions (allocations drawn)."""
        return sum(1 for _, purpose in self._events[:events] if purpose.competes)

    def applies_from(self, decided_at: int) -> int:
        """The first iteration an allocation decided at iteration `decided_at` applies to:
        decided_at + 1 + B (the initial allocation, decided at 0: iteration 1)."""
        return decided_at + 1 + self.lag if decided_at else 1

    def decision_for(self, index: int) -> int:
        """The iteration whose allocation applies in iteration `index`: the latest competition
        j with j + 1 + B <= index, or 0 (the initial allocation)."""
        n = bisect.bisect_right(self._competitions, index - 1 - self.lag)
        return self._competitions[n - 1] if n else 0

    def slot_width(self, decided_at: int) -> int:
        """Slots an allocation decided at iteration `decided_at` names: one (the survivor's)
        once the elimination is decided under the one-slot rule, else M."""
        e = self.elimination
        return 1 if e is not None and decided_at >= e and self.one_slot_after_elimination else self.slots

    def first_reaching(self, units: int) -> int:
        """The first iteration whose units (after it) reach `units` (the last one if none)."""
        s = self.schedule
        lo, hi = 1, self.iterations
        while lo < hi:
            mid = (lo + hi) // 2
            after = self.transitions_before(mid + 1) if mid < self.iterations else s.budget
            if s.units_at(after) >= units:
                hi = mid
            else:
                lo = mid + 1
        return lo

    def events(self) -> list[tuple[int, Purpose]]:
        return list(self._events)

    @cached_property
    def _events(self) -> tuple[tuple[int, Purpose], ...]:
        """The run's evaluations in order, (iteration, purpose): `round` and `elimination` judge
        the actors after the previous iteration's updates, `curve` and `final` the actors after
        its own (`judged_version`; a curve point at the last iteration is the final evaluation)."""
        s = self.schedule
        final_units = self.iteration(self.iterations).units[1]
        candidates = {self.iterations}
        if s.eliminate_at is not None:
            last_round = min(s.eliminate_at, final_units + 1)
            candidates.update(self.first_reaching(m) for m in range(s.compete_every, last_round, s.compete_every))
            if self.elimination is not None:
                candidates.add(self.elimination)
        candidates.update(self.first_reaching(m) for m in range(self.eval_every, final_units + 1, self.eval_every))
        out: list[tuple[int, Purpose]] = []
        for i in sorted(candidates):
            it = self.iteration(i)
            if it.eliminate:
                out.append((i, Purpose.ELIMINATION))
            elif it.round is not None:
                out.append((i, Purpose.ROUND))
            if it.curve is not None:
                out.append((i, Purpose.CURVE))
            elif it.last:
                out.append((i, Purpose.FINAL))
        return tuple(out)


def elimination_transitions(algo: Mapping[str, Any]) -> int | None:
    """C in transitions for a run's algorithm settings (config.json's "algo"): C iterations of
    M transitions under `paper`, C transitions under `equal-data`; None without an elimination
    (K = 1, `--no-ot`, no C). What figures and plots mark as the elimination when the run has not
    logged it."""
    c, k = algo.get("eliminate_at"), algo.get("actors") or 1
    if k <= 1 or algo.get("no_ot") or not isinstance(c, (int, float)) or c <= 0:
        return None
    paper = (algo.get("schedule") or AlgoConfig.schedule) == "paper"
    return int(c) * int(algo.get("workers") or 1) if paper else int(c)


def _crossed(before: int, after: int, every: int) -> int | None:
    """j if (before, after] holds a multiple of `every` (the largest), else None."""
    return after // every if after // every > before // every else None


def _last_true(predicate: Callable[[int], bool], hi: int) -> int:
    """The largest i in 1..hi with predicate(i), for a predicate true on a prefix (0: none)."""
    lo = 0
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if predicate(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo
