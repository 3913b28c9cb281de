"""The data plane: transition batches (worker -> learner) and actor weights (learner -> all)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from services.messaging.codec.wire import (
    MAX_MESSAGE_BYTES,
    MessageError,
    array_field,
    as_f32,
    bool_field,
    check_kind,
    decode,
    encode,
    float_field,
    floats_field,
    get_field,
    id_field,
    int_field,
    ints_field,
    text_field,
)

# --------------------------------------------------------------------------- typed messages


@dataclass(frozen=True)
class TransitionSpec:
    """What a learner accepts: the env's dimensions, K, and the batch size cap."""

    obs_dim: int
    act_dim: int
    n_actors: int
    max_rows: int = 4096
    max_action: float | None = None  # when set, |action| <= max_action * (1 + 1e-5)


@dataclass(frozen=True)
class TransitionBatch:
    """N transitions from one worker, all collected with one actor's policy ``version``.

    ``terminated`` is true only for real terminal states (truncation is not terminal).
    ``batch_seq`` counts this worker incarnation's batches from 0 (gap/duplicate detection).
    ``version`` is -1 for the uniform random actions of the start phase.
    """

    KIND: ClassVar[str] = "transitions"

    worker: str
    incarnation: str
    batch_seq: int
    actor: int
    version: int
    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    episode_return: tuple[float, ...] | None = None
    resend: bool = False  # sent again to a restarted learner (the tracker de-duplicates it)
    iteration: int = -1  # exact mode: Algorithm 1's iteration of the first row (one row per iteration)
    slot: int = -1  # exact mode: the environment slot that collected the rows
    policy_from: str = ""  # the learner incarnation whose weights `version` counts (empty: unknown)
    env_faults: int = 0  # simulator faults this worker incarnation has met so far (its run is then not the seed's)
    episode_starts: tuple[int, ...] = ()  # rows that are the first step of an episode (after a reset)
    inexact: str = ""  # why this worker's slot is no longer the seed's (its recovery failed), or ""
    policy_digest: str = ""  # mam_core.policy.params_digest of the weights the rows acted with ("" random)

    @property
    def rows(self) -> int:
        return int(self.reward.shape[0])

    def inexact_reasons(self, env_id: str) -> tuple[str, ...]:
        """Why its rows end the run's exactness, as the learner logs it (none: ())."""
        out = (f"worker {self.worker} (slot {self.slot}): {self.inexact}",) if self.inexact else ()
        if self.env_faults:
            out += (f"worker {self.worker} (slot {self.slot}) met {self.env_faults} simulator faults in {env_id} "
                    f"by iteration {self.iteration + self.rows - 1}",)
        return out

    def to_bytes(self, sender: str | None = None, seq: int | None = None) -> bytes:
        body = {
            "worker": self.worker,
            "incarnation": self.incarnation,
            "batch_seq": self.batch_seq,
            "actor": self.actor,
            "version": self.version,
            "obs": as_f32(self.obs),
            "action": as_f32(self.action),
            "reward": as_f32(self.reward),
            "next_obs": as_f32(self.next_obs),
            "terminated": np.ascontiguousarray(self.terminated, dtype=np.bool_),
            "episode_return": None
            if self.episode_return is None
            else [float(x) for x in self.episode_return],
        }
        if self.resend:
            body["resend"] = True
        if self.iteration >= 0:
            body["iteration"] = self.iteration
            body["slot"] = self.slot
        if self.policy_from:
            body["policy_from"] = self.policy_from
        if self.env_faults:
            body["env_faults"] = self.env_faults
        if self.episode_starts:
            body["episode_starts"] = [int(r) for r in self.episode_starts]
        if self.inexact:
            body["inexact"] = self.inexact
        if self.policy_digest:
            body["policy_digest"] = self.policy_digest
        return encode(
            self.KIND,
            body,
            sender=self.worker if sender is None else sender,
            seq=self.batch_seq if seq is None else seq,
        )

    @classmethod
    def from_message(cls, msg: Mapping[str, Any], spec: TransitionSpec) -> "TransitionBatch":
        check_kind(msg, cls.KIND)
        worker = id_field(msg, "worker")
        if msg.get("sender") != worker:
            raise MessageError("sender_mismatch", f"sender {msg.get('sender')!r} != worker {worker!r}")
        incarnation = id_field(msg, "incarnation")
        batch_seq = int_field(msg, "batch_seq", lo=0)
        actor = int_field(msg, "actor", lo=0)
        if actor >= spec.n_actors:
            raise MessageError("range:actor", f"actor {actor} >= K={spec.n_actors}")
        version = int_field(msg, "version", lo=-1)
        reward = get_field(msg, "reward")
        if not isinstance(reward, np.ndarray) or reward.ndim != 1:
            raise MessageError("shape:reward", "reward must be a 1-d array")
        n = reward.shape[0]
        if not 1 <= n <= spec.max_rows:
            raise MessageError("range:rows", f"{n} rows not in [1, {spec.max_rows}]")
        obs = array_field(msg, "obs", (n, spec.obs_dim))
        action = array_field(msg, "action", (n, spec.act_dim))
        reward = array_field(msg, "reward", (n,))
        next_obs = array_field(msg, "next_obs", (n, spec.obs_dim))
        term = array_field(msg, "terminated", (n,), dtypes=("bool", "uint8"))
        if term.dtype.name == "uint8":
            if n and term.max() > 1:
                raise MessageError("range:terminated", "uint8 terminated must be 0/1")
            term = term.view(np.bool_)
        if spec.max_action is not None:
            bound = spec.max_action * (1 + 1e-5)
            if np.abs(action).max() > bound:
                raise MessageError("range:action", f"|action| > {spec.max_action}")
        ret = get_field(msg, "episode_return") if "episode_return" in msg else None
        episode_return = None
        if ret is not None:
            episode_return = floats_field(msg, "episode_return")
            if len(episode_return) > spec.max_rows:
                raise MessageError("range:episode_return", "more episodes than rows")
        resend = bool_field(msg, "resend") if "resend" in msg else False
        iteration = int_field(msg, "iteration", lo=1) if "iteration" in msg else -1
        slot = int_field(msg, "slot", lo=0, hi=1 << 20) if iteration >= 0 else -1
        policy_from = id_field(msg, "policy_from") if "policy_from" in msg else ""
        env_faults = int_field(msg, "env_faults", lo=0) if "env_faults" in msg else 0
        starts = ints_field(msg, "episode_starts", lo=0) if "episode_starts" in msg else ()
        if any(r >= n for r in starts) or list(starts) != sorted(set(starts)):
            raise MessageError("range:episode_starts", f"episode starts must be distinct rows in order, < {n}")
        inexact = text_field(msg, "inexact") if "inexact" in msg else ""
        digest = id_field(msg, "policy_digest") if "policy_digest" in msg else ""
        return cls(worker, incarnation, batch_seq, actor, version, obs, action, reward,
                   next_obs, term, episode_return, resend, iteration, slot, policy_from,
                   env_faults, starts, inexact, digest)

    @classmethod
    def from_bytes(cls, payload: bytes, spec: TransitionSpec, *,
                   max_bytes: int = MAX_MESSAGE_BYTES) -> "TransitionBatch":
        return cls.from_message(decode(payload, max_bytes=max_bytes), spec)


@dataclass(frozen=True)
class SlotEpisode:
    """The learner's answer to a worker taking slot `slot` over: the rows of the slot's current
    episode (from iteration `start`, its first step, to `next` - 1) as the replay and the stage
    hold them, so the worker can rebuild the slot's env at iteration `next` (mam_core.slot.
    replay_episode). `why` says why there are no rows to give (the episode left the replay)."""

    KIND: ClassVar[str] = "slot-episode"
    MAX_ROWS: ClassVar[int] = 100_000

    slot: int
    start: int
    next: int
    obs: np.ndarray
    action: np.ndarray
    next_obs: np.ndarray
    why: str = ""

    def to_bytes(self, sender: str, seq: int) -> bytes:
        return encode(self.KIND, {"slot": self.slot, "start": self.start, "next": self.next, "obs": as_f32(self.obs),
                                  "action": as_f32(self.action), "next_obs": as_f32(self.next_obs), "why": self.why},
                      sender=sender, seq=seq)

    @classmethod
    def from_bytes(cls, payload: bytes, obs_dim: int, act_dim: int) -> "SlotEpisode":
        msg = decode(payload)
        check_kind(msg, cls.KIND)
        slot = int_field(msg, "slot", lo=0, hi=1 << 20)
        start = int_field(msg, "start", lo=1)
        nxt = int_field(msg, "next", lo=start)
        n = nxt - start
        if n > cls.MAX_ROWS:
            raise MessageError("range:rows", f"{n} rows > {cls.MAX_ROWS}")
        why = text_field(msg, "why")
        rows = 0 if why else n
        return cls(slot, start, nxt, array_field(msg, "obs", (rows, obs_dim)),
                   array_field(msg, "action", (rows, act_dim)), array_field(msg, "next_obs", (rows, obs_dim)), why)


@dataclass(frozen=True)
class Weights:
    """Actor k's policy parameters by name (float32), with a version that only grows."""

    KIND: ClassVar[str] = "weights"

    actor: int
    version: int
    params: Mapping[str, np.ndarray]
    obs_dim: int
    act_dim: int
    max_action: float
    hidden: tuple[int, ...]
    incarnation: str = ""  # the learner incarnation that made them: its versions count from its own start

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {
            "incarnation": self.incarnation,
            "actor": self.actor,
            "version": self.version,
            "params": {str(k): as_f32(v) for k, v in self.params.items()},
            "obs_dim": self.obs_dim,
            "act_dim": self.act_dim,
            "max_action": float(self.max_action),
            "hidden": [int(h) for h in self.hidden],
        }
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(
        cls,
        msg: Mapping[str, Any],
        expected: Mapping[str, tuple[int, ...]] | None = None,
        n_actors: int | None = None,
    ) -> "Weights":
        check_kind(msg, cls.KIND)
        actor = int_field(msg, "actor", lo=0, hi=None if n_actors is None else n_actors - 1)
        version = int_field(msg, "version", lo=0)
        params = get_field(msg, "params")
        if not isinstance(params, dict) or not params:
            raise MessageError("type:params", "want a non-empty map of arrays")
        for name, a in params.items():
            if not isinstance(name, str) or not name or len(name) > 256:
                raise MessageError("type:params", f"bad parameter name {name!r}"[:200])
            if not isinstance(a, np.ndarray):
                raise MessageError("type:params", f"{name}: want array, got {type(a).__name__}")
            if a.dtype.name != "float32":
                raise MessageError("dtype:params", f"{name}: {a.dtype.name} is not float32")
            if not np.isfinite(a).all():
                raise MessageError("not_finite:params", f"{name}: NaN or inf")
        if expected is not None:
            if set(params) != set(expected):
                missing = sorted(set(expected) - set(params))
                extra = sorted(set(params) - set(expected))
                raise MessageError("params:names", f"missing {missing} extra {extra}"[:300])
            for name, shape in expected.items():
                if params[name].shape != tuple(shape):
                    raise MessageError("shape:params", f"{name}: {params[name].shape} != {tuple(shape)}")
        obs_dim = int_field(msg, "obs_dim", lo=1)
        act_dim = int_field(msg, "act_dim", lo=1)
        max_action = float_field(msg, "max_action")
        if max_action <= 0:
            raise MessageError("range:max_action", f"{max_action} <= 0")
        hidden = ints_field(msg, "hidden", lo=1)
        if len(hidden) > 16:
            raise MessageError("range:hidden", "more than 16 hidden layers")
        incarnation = text_field(msg, "incarnation") if "incarnation" in msg else ""
        return cls(actor, version, params, obs_dim, act_dim, max_action, hidden, incarnation)

    @classmethod
    def from_bytes(cls, payload: bytes, expected: Mapping[str, tuple[int, ...]] | None = None,
                   n_actors: int | None = None, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Weights":
        return cls.from_message(decode(payload, max_bytes=max_bytes), expected, n_actors)
