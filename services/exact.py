"""Exact mode: the pieces the roles share to run Algorithm 1 in lock-step across processes.

The control flow is `mam_core.algorithm1.Algorithm1`; every role builds it from the run's
config and follows it (docs/DESIGN-DECISIONS.md, "Exact Algorithm 1"):

- A worker steps iteration i of its slot once it holds the allocation that applies to i (the
  latest decision of an iteration < i) and, unless i is random, its actor at
  `version_for(i)`. Weights change only every d iterations, so most iterations need no wait.
  Its batch carries the iteration of its first row and the slot.
- The learner stages what arrives per slot (`SlotStage`), inserts iteration i's rows in slot
  order, makes iteration i's updates (the elimination between the critic and actor phases,
  from the referee's decision), and publishes weights only when they changed. The versions an
  evaluation needs also go, once, to the referee on `weights/<k>/eval` (`snapshot_versions`).
- The referee evaluates each competition and curve point on exactly those versions
  (`WeightsHistory`), draws the allocation with the run's `allocation` stream over the slots
  `w0 .. w{M-1}`, and tags each decision with its iteration.

Any restart (learner, referee or worker) ends exactness for the rest of the run: the learner
notices (`Learner.break_exact`), says why in its stats, and every role carries on with the
asynchronous, rate-limited collection; summary.json records `exact: false` and the reason.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mam_core.algorithm1 import Algorithm1
from services.codec import TransitionBatch


class ExactnessLost(Exception):
    """Something a lock-step run cannot absorb (a restart, a foreign batch): go asynchronous."""


@dataclass
class _Staged:
    batch: TransitionBatch
    first: int  # the iteration of batch row `used`
    used: int = 0  # rows of the batch already inserted


class SlotStage:
    """The learner's staging of transition batches per slot, until their iteration comes."""

    def __init__(self, slots: int) -> None:
        self.queues: list[deque[_Staged]] = [deque() for _ in range(slots)]
        self.expected = [1] * slots  # the iteration the next batch of each slot must start at
        self.owner: list[tuple[str, str] | None] = [None] * slots  # (worker, incarnation) of each slot

    def add(self, batch: TransitionBatch) -> None:
        """Stage a batch; ExactnessLost if it does not continue its slot's iterations."""
        s = batch.slot
        if batch.iteration < 0:
            raise ExactnessLost(f"worker {batch.worker} collects asynchronously")
        if not 0 <= s < len(self.queues):
            raise ExactnessLost(f"worker {batch.worker} claims slot {s} of {len(self.queues)}")
        owner = (batch.worker, batch.incarnation)
        if self.owner[s] is None:
            self.owner[s] = owner
        elif self.owner[s] != owner:
            raise ExactnessLost(f"slot {s} changed hands ({self.owner[s][0]} -> {batch.worker}): a worker restarted")
        if batch.iteration != self.expected[s]:
            raise ExactnessLost(f"slot {s} sent iteration {batch.iteration}, expected {self.expected[s]}")
        self.queues[s].append(_Staged(batch, batch.iteration))
        self.expected[s] = batch.iteration + batch.rows

    def ready(self, index: int, slots: Sequence[int]) -> bool:
        return all(self.queues[s] and self.queues[s][0].first == index for s in slots)

    def take(self, index: int, slots: Sequence[int]) -> tuple[dict[str, np.ndarray], list[TransitionBatch]]:
        """Iteration `index`'s rows in slot order, and the batches this used up."""
        parts, done = [], []
        for s in slots:
            st = self.queues[s][0]
            b, r = st.batch, st.used
            parts.append((b.obs[r], b.action[r], b.reward[r], b.next_obs[r], b.terminated[r], b.actor, b.version))
            st.used += 1
            st.first += 1
            if st.used == b.rows:
                done.append(self.queues[s].popleft().batch)
        obs, action, reward, next_obs, term, actor, version = zip(*parts)
        rows = {"obs": np.stack(obs), "action": np.stack(action), "reward": np.asarray(reward, np.float32),
                "next_obs": np.stack(next_obs), "terminated": np.asarray(term, np.bool_),
                "actor": np.asarray(actor, np.int64), "version": np.asarray(version, np.int64)}
        return rows, done

    def leftovers(self) -> list[tuple[TransitionBatch, int]]:
        """What is staged but not inserted, (batch, first unused row), slot by slot."""
        out = [(st.batch, st.used) for q in self.queues for st in q]
        for q in self.queues:
            q.clear()
        return out


def snapshot_versions(plan: Algorithm1, index: int) -> set[int]:
    """Versions the referee needs once iteration `index`'s updates are done (index 0: before
    the first iteration): the competition of the next iteration (its acting version) and
    this iteration's curve point."""
    out = set()
    if index < plan.iterations and plan.iteration(index + 1).competes:
        out.add(plan.version_for(index + 1))
    if index >= 1:
        it = plan.iteration(index)
        if it.curve is not None or it.last:
            out.add(plan.version_after(index))
    return out


class WeightsHistory:
    """The referee's copies of each actor at the versions its evaluations need."""

    def __init__(self, n_actors: int) -> None:
        self.by_actor: list[dict[int, dict[str, np.ndarray]]] = [{} for _ in range(n_actors)]

    def add(self, actor: int, version: int, params: Mapping[str, np.ndarray]) -> None:
        self.by_actor[actor][version] = {name: np.array(a, np.float32, copy=True) for name, a in params.items()}

    def has(self, actor: int, version: int) -> bool:
        return version in self.by_actor[actor]

    def get(self, actor: int, version: int) -> dict[str, np.ndarray]:
        return self.by_actor[actor][version]

    def forget_below(self, version: int) -> None:
        for versions in self.by_actor:
            for v in [v for v in versions if v < version]:
                del versions[v]
