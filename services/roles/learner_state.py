"""The learner's state (services/roles/learner.py), in the pieces its helpers take instead of the
learner itself: `Progress` (what the loop advances and the stats report), `Acks` (what the
workers may stop keeping), `Carried` (what a checkpoint hands the loop to publish again), and
`LearnerState`, which holds them with the parts a checkpoint saves (agent, replay, intake, slot
episodes, published digests) and the slots being built (`SlotStage`).

The checkpoint's counters are written by `LearnerState.counters` and read back by
`LearnerState.restore_counters` (learner_files.py saves and restores the whole generation).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mam_core.agent import MultiActorAgent
from mam_core.algorithm1 import Algorithm1
from mam_core.pacing import CheckpointRule
from mam_core.policy import params_digest
from mam_core.replay import ReplayBuffer, ReplayLog
from services.messaging import bus
from services.messaging.codec import TransitionBatch
from services.roles.episodes import SlotEpisodes
from services.roles.intake import Intake
from services.roles.lockstep import SlotStage

log = logging.getLogger("mam.learner")

# (plan version, actor, its version, params): an actor version a checkpoint keeps for a re-send
KeptParams = tuple[int, int, int, dict[str, np.ndarray]]


class PublishedDigests:
    """`params_digest` of every actor version a slot may still act with, as this learner published
    it, to check the `policy_digest` a batch reports (`foreign`). Kept in the learner's checkpoint:
    with lag B > 0 a restarted learner receives rows acted with versions its predecessor published
    before the checkpoint, and checks those too."""

    def __init__(self, known: dict[tuple[int, int], str] | None = None) -> None:
        self.known: dict[tuple[int, int], str] = dict(known or {})  # (actor, version) -> digest

    def record(self, actor: int, version: int, params: dict) -> None:
        self.known[(actor, version)] = params_digest(params)

    def foreign(self, batch: TransitionBatch) -> str:
        """Why `batch`'s rows were acted with other weights than this learner's of their version
        (a dead incarnation's that computed otherwise), or "" (the same, or not known here)."""
        mine = self.known.get((batch.actor, batch.version)) if batch.version >= 0 else None
        if mine is None or batch.policy_digest == mine:  # (a batch without a digest is refused by the intake)
            return ""
        return (f"slot {batch.slot} acted at iteration {batch.iteration} with actor {batch.actor}'s version "
                f"{batch.version} of learner {batch.policy_from or '?'}, not this learner's")

    def prune(self, needed: int, live: list[bool]) -> None:
        """Forget live actors' versions older than `needed` - 1 (no slot acts with them again; an
        eliminated actor's last versions stay, a few entries)."""
        for key in [key for key in self.known if key[1] < needed - 1 and live[key[0]]]:
            del self.known[key]

    def to_json(self) -> str:
        return json.dumps([[a, v, d] for (a, v), d in sorted(self.known.items())])

    @classmethod
    def from_json(cls, text: str) -> PublishedDigests:
        rows = json.loads(text)
        if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 3 for r in rows):
            raise ValueError("published digests: not a list of [actor, version, digest]")
        return cls({(int(a), int(v)): str(d) for a, v, d in rows})


@dataclass
class Progress:
    """Where the run stands in this learner: what its loop advances, its stats and logs report,
    and its checkpoint carries."""

    iteration: int = 0  # iterations whose updates are done
    env_steps: int = 0  # transitions in the replay buffer
    inexact: str = ""  # why the run is not exact ("" while it is)
    survivor: int | None = None  # the actor left after the elimination (applied)
    decided_survivor: int | None = None  # the referee's choice at C, applied where the plan places it
    referee_seen: bool = False  # the run had a referee (finish() names one that never came)
    wall_before: float = 0.0  # wall seconds of the run before this incarnation (from the checkpoint)
    started: float = field(default_factory=time.monotonic)  # this incarnation's start
    awaiting: tuple[int, ...] = ()  # slots whose rows the loop waits for; -1: the referee's decision
    wait_s: float = 0.0  # seconds the loop waited for an iteration's rows (learner.jsonl: where time goes)
    ahead: int = 0  # updates made ahead of the rows of the iteration they belong to (not yet in)
    metrics: dict[str, float] = field(default_factory=dict)  # of the latest updates (losses, Q means)

    def break_exact(self, why: str) -> None:
        """The run goes on in the same order, but it is no longer the seed's run (stats, summary)."""
        if why and not self.inexact:
            self.inexact = why
            log.warning("the run is no longer exact: %s; it goes on in lock-step", why)

    def wall_s(self) -> float:
        """Wall seconds of the whole run so far, all incarnations."""
        return round(self.wall_before + time.monotonic() - self.started, 3)


@dataclass
class Acks:
    """Per worker: (incarnation, seq) such that all its batches up to seq are in the checkpoint
    generation before the newest (with the replay). Workers keep the batches after it and resend
    them to a restarted learner. One generation late: when the newest fails to verify at a resume,
    the learner falls back to the previous one, and the rows after that are still with the workers."""

    acked: dict[str, tuple[str, int]] = field(default_factory=dict)
    newest: dict[str, tuple[str, int]] = field(default_factory=dict)  # the same for the newest generation

    def checkpointed(self, prefixes: dict[str, tuple[str, int]]) -> None:
        """A new generation holds `prefixes`: the one before it now holds what the newest did."""
        self.acked, self.newest = self.newest, prefixes


@dataclass
class Carried:
    """What a checkpoint hands the resumed learner's loop to publish again (Outbox.restore): the
    older versions the workers' next iterations act with (lag B > 0), and the snapshots of the
    evaluations the referee had not reported done (it may be behind)."""

    kept_weights: list[KeptParams] = field(default_factory=list)
    kept_snapshots: list[KeptParams] = field(default_factory=list)


@dataclass
class LogRates:
    """learner.jsonl's rates: transitions and updates per second since the previous row."""

    base: tuple[int, int, float] = (0, 0, 0.0)  # (env_steps, updates, when) at the previous row
    per_s: tuple[float, float] = (0.0, 0.0)

    def advance(self, env_steps: int, updates: int, now: float) -> None:
        steps, before, t = self.base
        dt = max(now - t, 1e-9)
        self.per_s = ((env_steps - steps) / dt, (updates - before) / dt)
        self.base = (env_steps, updates, now)


@dataclass(eq=False)
class LearnerState:
    """The learner's state: what its checkpoint saves, its helpers (learner_files.py, outbox.py)
    read and change, and its loop advances. The subscriptions, publishers and timers stay with
    the learner."""

    plan: Algorithm1  # every "when" of the run
    agent: MultiActorAgent
    buffer: ReplayBuffer
    replay_log: ReplayLog | None  # the replay on disk (None: --no-save-replay)
    intake: Intake
    checkpoints: CheckpointRule  # when the next checkpoint is due
    progress: Progress = field(default_factory=Progress)
    acks: Acks = field(default_factory=Acks)
    carried: Carried = field(default_factory=Carried)
    digests: PublishedDigests = field(default_factory=PublishedDigests)  # of the versions a slot may act with
    rates: LogRates = field(default_factory=LogRates)
    allocation_rejects: bus.RejectLog = field(default_factory=lambda: bus.RejectLog(log, "message"))
    # per slot, where its current episode began (a takeover's replay); the slots being built
    episodes: SlotEpisodes = field(init=False)
    stage: SlotStage = field(init=False)

    def __post_init__(self) -> None:
        self.episodes = SlotEpisodes(self.plan)
        self.stage = SlotStage(self.plan.slots, start=self.progress.iteration + 1)

    def iterations(self) -> int:
        """Schedule steps done: Algorithm 1's iterations (paper) or transitions (equal-data)."""
        return self.plan.schedule.units_at(self.progress.env_steps)

    def updates(self) -> int:
        """Updates of the iterations whose rows are in (what stats and logs count): the agent's, less any ahead."""
        return self.agent.updates - self.progress.ahead

    def utd(self) -> float:
        """Updates per schedule step past the start (per iteration or per transition)."""
        consumed = self.plan.units_past_start(self.iterations())
        return self.updates() / consumed if consumed else 0.0

    def rejected(self) -> dict[str, int]:
        """Rejection counts by reason: transitions by reason, the allocation topic as allocation:<reason>."""
        other = self.allocation_rejects.counts()
        return {**self.intake.rejects.counts(), **{f"allocation:{r}": k for r, k in other.items()}}

    def counters(self) -> dict[str, Any]:
        """The checkpoint's counters (everything but the agent, the replay and the kept versions)."""
        p, intake = self.progress, self.intake
        return {"env_steps": p.env_steps, "per_worker": json.dumps(intake.tracker.per_sender()),
                "stream_rows": json.dumps(intake.stream_rows),
                "stream_skipped": json.dumps(intake.stream_skipped),
                "stream_partial": json.dumps(intake.stream_partial), "referee_seen": int(p.referee_seen),
                "iteration": p.iteration, "inexact": p.inexact, "episodes": self.episodes.to_json(),
                "digests": self.digests.to_json(), "retired": json.dumps(sorted(self.stage.retired)),
                "wall_s": p.wall_s()}

    def restore_counters(self, c: dict[str, Any]) -> None:
        """`counters` read back (after the replay: the iteration may follow from its transitions)."""
        p, intake = self.progress, self.intake
        intake.stream_rows = {k: int(v) for k, v in json.loads(c.get("stream_rows", "{}")).items()}
        intake.stream_skipped = {k: int(v) for k, v in json.loads(c.get("stream_skipped", "{}")).items()}
        intake.stream_partial = {k: (int(v[0]), int(v[1]))
                                 for k, v in json.loads(c.get("stream_partial", "{}")).items()}
        # The run had a referee: a learner resumed at its budget waits for it (its final evaluation).
        p.referee_seen = bool(int(c.get("referee_seen", 0)))
        # Sequence numbers go on from the checkpoint: a gap then counts what died with the old
        # learner, until the workers' resends fill it.
        intake.tracker.restore(json.loads(c.get("per_worker", "{}")))
        if self.replay_log is not None:  # just verified: its rows need not be kept twice
            self.acks.acked = self.acks.newest = intake.checkpointed_prefixes()
        p.iteration = int(c["iteration"]) if "iteration" in c else self.plan.iteration_at(p.env_steps)
        p.wall_before = float(c.get("wall_s", 0.0))
        self.episodes.inserted_through = p.iteration
        if "episodes" in c:
            self.episodes.restore(str(c["episodes"]))
        if "digests" in c:  # what the dead learner published: rows acted with it are checked too (lag B > 0)
            self.digests = PublishedDigests.from_json(str(c["digests"]))
        # Every stream and the staging point are in the checkpoint; the workers resend the rows after
        # it: the resumed learner recomputes the same updates (exact unless the run was inexact already).
        p.inexact = str(c.get("inexact", ""))
        # The slots are built from the next iteration on; their owners that lost them (a stale worker
        # back from a pause) stay refused.
        self.stage = SlotStage(self.plan.slots, start=p.iteration + 1)
        self.stage.retired |= {(str(w), str(i)) for w, i in json.loads(c.get("retired", "[]"))}
