"""A worker's state (services/roles/worker.py), in the pieces its helpers take instead of the
worker itself: `SlotState` (where the slot stands between two steps: what a takeover rebuilds,
takeover.py), `PendingBatch` (the batch being built) and `LearnerWatch` (what the worker knows
of the learner: its stats, and whether the slot is still this worker's)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mam_core.slot import SlotStreams
from services.messaging.codec import LearnerStats


@dataclass
class SlotState:
    """Where the slot stands between two steps: what a worker taking the slot over rebuilds."""

    streams: SlotStreams  # the slot's random streams (mam_core.slot), from --seed and the slot only
    obs: np.ndarray  # the env's observation the next step acts on
    episode_return: float = 0.0  # of the episode under way
    first_row: bool = True  # the next step is an episode's first (batches flag it: episode_starts)
    inexact: str = ""  # why this slot is no longer the seed's (a failed rebuild): every batch says it


@dataclass
class PendingBatch:
    """The rows not yet sent: of one actor at one policy version of one learner incarnation
    (`Worker.flush` sends them as one `TransitionBatch`)."""

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    rows: int = 0
    actor: int = -1
    version: int = -1
    iteration: int = -1  # the iteration of the first row
    starts: list[int] = field(default_factory=list)  # rows that begin an episode
    policy_from: str = ""  # the learner incarnation of the rows' weights
    digest: str = ""  # ... and their params_digest
    started: float = field(default_factory=time.monotonic)  # when the first row was added
    returns: list[float] = field(default_factory=list)  # of the episodes finished since the last batch

    @classmethod
    def empty(cls, rows: int, obs_dim: int, act_dim: int) -> PendingBatch:
        """Room for `rows` rows (the arrays are reused from batch to batch)."""
        return cls(np.empty((rows, obs_dim), np.float32), np.empty((rows, act_dim), np.float32),
                   np.empty(rows, np.float32), np.empty((rows, obs_dim), np.float32), np.empty(rows, np.bool_))

    def acted_otherwise(self, actor: int, version: int, policy_from: str) -> bool:
        """Rows are pending that were acted with another actor, version or learner's weights."""
        return bool(self.rows) and (actor != self.actor or version != self.version or policy_from != self.policy_from)

    def add(self, index: int, obs: np.ndarray, action: np.ndarray, reward: float, next_obs: np.ndarray,
            terminated: bool, *, episode_start: bool, actor: int, version: int, policy_from: str, digest: str) -> None:
        """Iteration `index`'s transition (truncation is not terminal: the target still bootstraps)."""
        i = self.rows
        if i == 0:
            self.iteration, self.started = index, time.monotonic()
        self.obs[i] = obs
        if episode_start:
            self.starts.append(i)
        self.action[i] = action
        self.reward[i] = reward
        self.next_obs[i] = next_obs
        self.terminated[i] = terminated
        self.actor, self.version, self.policy_from, self.digest = actor, version, policy_from, digest
        self.rows += 1

    def arrays(self, copy: bool) -> tuple[np.ndarray, ...]:
        """The pending rows: obs, action, reward, next_obs, terminated (copies: kept for a resend)."""
        n = self.rows
        rows = (self.obs[:n], self.action[:n], self.reward[:n], self.next_obs[:n], self.terminated[:n])
        return tuple(a.copy() for a in rows) if copy else rows

    def sent(self) -> None:
        """The rows went out: the next batch starts empty."""
        self.rows, self.starts, self.returns = 0, [], []


@dataclass
class LearnerWatch:
    """What a worker knows of the learner: its newest stats, the incarnation its kept batches were
    resent to and the one its slot's position was taken from, and whether the slot is still its own
    (fencing: takeover.follow_owner)."""

    stats: LearnerStats | None = None  # the newest learner's latest stats
    stats_at: float = 0.0  # when they arrived
    incarnation: str | None = None  # the learner incarnation the kept batches went to (resent to each new one)
    seen_at: float = 0.0  # when that incarnation was first seen (and the kept batches resent to it)
    synced_with: str = ""  # the learner incarnation this slot's position was taken from (out_of_step)
    newest: tuple[int, str] = (0, "")  # role.learner_order of the newest learner seen: an older one is stale
    owned: bool = False  # the learner's stats have named this incarnation its slot's owner
    lost_to: str = ""  # the "worker/incarnation" that took the slot over since (this one then leaves)
