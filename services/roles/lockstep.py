"""Lock-step: the pieces the roles share to run Algorithm 1 across processes.

The control flow is `mam_core.algorithm1.Algorithm1`; every role builds it from the run's
config and follows it (docs/DESIGN-DECISIONS.md, "Exact Algorithm 1" and "The lag"):

- A worker steps iteration i of its slot once it holds the allocation that applies to i
  (`decision_for(i)`) and, unless i is random, its actor at `version_for(i)` (after iteration
  i-1-B). It keeps the few versions it may still need (`WeightsHistory`). Its batch carries the
  iteration of its first row and the slot.
- The learner stages what arrives per slot (`SlotStage`), inserts iteration i's rows in slot
  order, makes iteration i's updates (the elimination between the critic and actor phases,
  from the referee's decision), and publishes weights only when they changed. The versions an
  evaluation judges also go, once, to the referee on `weights/<k>/eval` (`Algorithm1.judged_after`).
- The referee evaluates each event of `plan.events()` on exactly those versions, draws the
  allocation with the run's `allocation` stream over the slots `w0 .. w{M-1}`, and tags each
  decision with its iteration.

A fault does not change this order. A restarted referee continues from its saved state (its
allocation stream included), a restarted learner from its checkpoint with the rows the workers
resend, and a restarted or replacement worker rebuilds its slot from the slot's current episode
(services/roles/episodes.py, mam_core/slot.py): each stays exact. What cannot be rebuilt (an
env that replays differently, rows lost for good) continues in the same lock-step order, and
the run records `exact: false` with the reason.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mam_core.policy import params_digest
from services.messaging.codec import TransitionBatch
from services.roles.role import Decodes, decoded

log = logging.getLogger("mam.learner")


@dataclass
class _Staged:
    batch: TransitionBatch
    first: int  # the iteration of batch row `used`
    used: int = 0  # rows of the batch already inserted (or skipped: iterations the slot had already)


class SlotStage:
    """The learner's staging of transition batches per slot, until their iteration comes.

    Each slot has an owner, the (worker, incarnation) whose rows it takes. A batch of another
    incarnation takes the slot over (a restarted or replacement worker, which rebuilt the slot
    from its current episode); its predecessor's late batches are dropped from then on. Rows of
    iterations the slot already has are skipped (resends to a restarted learner, a replacement
    starting behind). The owner's batch that starts past the slot's next iteration waits for
    the rows before it (its resend to a restarted learner, or the owner rebuilding the slot
    there); a new owner's fills the gap (rows were lost) and says so, and so does the slot's
    owner stepping iterations again.
    """

    def __init__(self, slots: int, start: int = 1) -> None:
        self.queues: list[deque[_Staged]] = [deque() for _ in range(slots)]
        self.end = [start] * slots  # per slot: the iteration its next new row belongs to
        self.owner: list[tuple[str, str] | None] = [None] * slots
        self.retired: set[tuple[str, str]] = set()

    def add(self, batch: TransitionBatch) -> tuple[bool, str, int]:
        """Stage a batch: (staged, why exactness broke or "", its rows not staged: iterations the
        slot had already, all of a predecessor's late batch). A batch not staged holds nothing new,
        but for one of the slot's owner that starts past the slot's next iteration (0 rows not
        staged): held back, since its earlier rows come first in the owner's resend, or the owner
        rebuilds the slot at the next iteration and steps from there."""
        s, owner = batch.slot, (batch.worker, batch.incarnation)
        if batch.iteration < 1 or not 0 <= s < len(self.queues):
            return False, f"worker {batch.worker} sent iteration {batch.iteration} of slot {s} " \
                          f"(of {len(self.queues)} slots)", 0
        if owner in self.retired:
            return False, "", batch.rows  # a predecessor's late batch
        why, changed = "", False
        if self.owner[s] is None:
            self.owner[s] = owner
        elif self.owner[s] != owner:  # a replacement: it rebuilt the slot (its batches say if it could not)
            log.info("slot %d changed hands (%s -> %s) at iteration %d", s, self.owner[s][0], batch.worker,
                     batch.iteration)
            self.retired.add(self.owner[s])
            self.owner[s] = owner
            changed = True
        skip = self.end[s] - batch.iteration
        if skip > 0 and not batch.resend and not changed:
            why = f"slot {s} stepped iterations {batch.iteration}..{self.end[s] - 1} again ({batch.worker} went " \
                  f"back to where a restarted learner stood)"
        if skip >= batch.rows:
            return False, why, batch.rows
        if skip < 0 and not changed:  # the owner's earlier rows are on their way (a resend), or it rebuilds
            return False, why, 0      # the slot where this learner stands (worker out_of_step): not staged
        if skip < 0:
            why = why or f"slot {s} lost iterations {self.end[s]}..{batch.iteration - 1} (rows lost in flight)"
            skip = 0  # its rows stand in for the lost iterations
        staged = _Staged(batch, self.end[s], used=skip)
        self.queues[s].append(staged)
        self.end[s] += batch.rows - skip
        return True, why, skip

    def holds(self, batch: TransitionBatch) -> bool:
        """This very batch (worker, incarnation, seq) is staged already (a resend of it came)."""
        q = self.queues[batch.slot] if 0 <= batch.slot < len(self.queues) else ()
        return any((st.batch.worker, st.batch.incarnation, st.batch.batch_seq) ==
                   (batch.worker, batch.incarnation, batch.batch_seq) for st in q)

    def ready(self, index: int, slots: Sequence[int]) -> bool:
        return all(self.queues[s] and self.queues[s][0].first == index for s in slots)

    def missing(self, index: int, slots: Sequence[int]) -> list[int]:
        return [s for s in slots if not (self.queues[s] and self.queues[s][0].first == index)]

    def take(self, index: int, slots: Sequence[int]) -> tuple[dict[str, np.ndarray],
                                                              list[tuple[TransitionBatch, int]], list[TransitionBatch]]:
        """Iteration `index`'s rows in slot order, (batch, rows of it used so far) for each row,
        and the batches this used up."""
        parts, sources, done = [], [], []
        for s in slots:
            st = self.queues[s][0]
            b, r = st.batch, st.used
            parts.append((b.obs[r], b.action[r], b.reward[r], b.next_obs[r], b.terminated[r], b.actor, b.version))
            st.used += 1
            sources.append((b, st.used))
            st.first += 1
            if st.used == b.rows:
                done.append(self.queues[s].popleft().batch)
        obs, action, reward, next_obs, term, actor, version = zip(*parts)
        rows = {"obs": np.stack(obs), "action": np.stack(action), "reward": np.asarray(reward, np.float32),
                "next_obs": np.stack(next_obs), "terminated": np.asarray(term, np.bool_),
                "actor": np.asarray(actor, np.int64), "version": np.asarray(version, np.int64)}
        return rows, sources, done


def held_copy(params: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], str]:
    """A role's own copy of an actor's parameters (never a view of a message's buffer), and its
    `params_digest`: what rows acted with it carry. Read, never changed, once made."""
    copy = {name: np.array(a, np.float32, copy=True) for name, a in params.items()}
    return copy, params_digest(copy)


class WeightsHistory:
    """A role's copies of each actor at the versions it may still need (the referee's
    evaluations, a worker's next B+1 iterations). A version is one set of parameters of one
    learner incarnation; after a learner restart its successor's copy of a version replaces
    the dead one's (`prefer`)."""

    def __init__(self, n_actors: int, decodes: Decodes | None = None) -> None:
        self.by_actor: list[dict[int, tuple[str, dict[str, np.ndarray], str]]] = [{} for _ in range(n_actors)]
        self.decodes = decodes  # shared by the slots of one process: one copy of a version between them

    def add(self, actor: int, version: int, params: Mapping[str, np.ndarray], incarnation: str = "",
            prefer: str = "", payload: bytes | None = None) -> bool:
        """Keep `params` as `actor`'s `version` unless a copy from `prefer` (the current learner
        incarnation) is held already; True if kept. `payload`: the message they came in, under
        which `decodes` keeps the copy (`held_copy`) for the other slots of the process."""
        held = self.by_actor[actor].get(version)
        if held is not None and (held[0] == incarnation or (prefer and held[0] == prefer)):
            return False
        copy, digest = decoded(self.decodes, "held", payload, lambda: held_copy(params))
        self.by_actor[actor][version] = (incarnation, copy, digest)
        return True

    def has(self, actor: int, version: int) -> bool:
        return version in self.by_actor[actor]

    def get(self, actor: int, version: int) -> dict[str, np.ndarray]:
        return self.by_actor[actor][version][1]

    def source(self, actor: int, version: int) -> str:
        """The learner incarnation the held copy came from."""
        return self.by_actor[actor][version][0]

    def digest(self, actor: int, version: int) -> str:
        """`params_digest` of the held copy (what the rows acted with it carry)."""
        return self.by_actor[actor][version][2]

    def held(self) -> int:
        """Versions held, of all actors (a worker reports it: an idle slot holds none)."""
        return sum(len(versions) for versions in self.by_actor)

    def clear(self) -> None:
        for versions in self.by_actor:
            versions.clear()

    def forget_below(self, version: int) -> None:
        for versions in self.by_actor:
            for v in [v for v in versions if v < version]:
                del versions[v]
