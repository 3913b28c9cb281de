"""The learner's counters (learner -> all), per worker as a typed `WorkerCounters`."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from services.messaging.codec.control import check_plain_value
from services.messaging.codec.wire import (
    MAX_MESSAGE_BYTES,
    MAX_TEXT_LEN,
    MessageError,
    as_float,
    bool_field,
    check_kind,
    decode,
    encode,
    float_field,
    floats_field,
    id_field,
    int_field,
    ints_field,
    list_field,
    str_map_field,
    text_field,
)


@dataclass(frozen=True, eq=False)
class WorkerCounters(Mapping):
    """What the learner counts for one worker (`LearnerStats.per_worker[worker]`).

    On the wire a msgpack map with the field names as keys; `received` and `last_seq` always,
    the others once known (None is left out). `acked_incarnation` and `acked_seq` come as a
    pair: every batch of that worker incarnation up to `acked_seq` is in the learner's last
    checkpoint, so the worker may stop keeping it for a resend. Keys this version does not know
    are kept in `extra` if they are plain scalars. It reads as a mapping of its wire keys too
    (`counters["received"]`, `counters.get("lag")`), and compares equal to that mapping.
    """

    received: int = 0  # rows received from this worker (all its incarnations)
    last_seq: int = -1  # highest batch seq of its current incarnation
    incarnation: str | None = None  # its current incarnation
    incarnation_rows: int | None = None  # rows received from that incarnation
    redundant_rows: int | None = None  # resent rows of that incarnation already held (dropped)
    rejected_rows: int | None = None  # rows of that incarnation refused (they are not in flight any more)
    actor: int | None = None  # the actor of its last batch
    lag: int | None = None  # policy versions between its last batch and the learner
    rate: float | None = None  # rows per second, over the last second or so
    acked_incarnation: str | None = None
    acked_seq: int | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "extra"}
        return {**{k: v for k, v in out.items() if v is not None}, **self.extra}

    def __getitem__(self, key: str) -> Any:
        if key in self.extra:  # (as `to_dict`, without building it: the stats read these often)
            return self.extra[key]
        value = getattr(self, key) if key in _COUNTER_FIELDS else None
        if value is None:
            raise KeyError(key)
        return value

    def __iter__(self) -> Iterator[str]:
        return iter(self.to_dict())

    def __len__(self) -> int:
        return len(self.to_dict())

    @classmethod
    def from_message(cls, d: Mapping[str, Any], worker: str = "?") -> "WorkerCounters":
        d = str_map_field({"per_worker": d}, "per_worker")
        for v in d.values():
            if isinstance(v, list):
                raise MessageError("type:per_worker", f"{worker}: values must be scalars")
            check_plain_value(v, "per_worker")
        values: dict[str, Any] = {"received": int_field(d, "received", lo=0),
                                  "last_seq": int_field(d, "last_seq", lo=-1)}
        if "acked_seq" in d or "acked_incarnation" in d:  # the checkpointed prefix of its stream
            values["acked_seq"] = int_field(d, "acked_seq", lo=-1)
            values["acked_incarnation"] = id_field(d, "acked_incarnation")
        for name in ("incarnation_rows", "redundant_rows", "rejected_rows", "actor", "lag"):
            if d.get(name) is not None:
                values[name] = int_field(d, name)
        if d.get("incarnation") is not None:
            values["incarnation"] = text_field(d, "incarnation")
        if d.get("rate") is not None:
            values["rate"] = float_field(d, "rate")
        return cls(**values, extra={k: v for k, v in d.items() if k not in _COUNTER_FIELDS and k != "extra"})


_COUNTER_FIELDS = frozenset(f.name for f in fields(WorkerCounters) if f.name != "extra")


@dataclass(frozen=True)
class LearnerStats:
    """The learner's counters. ``accept_until`` is the rate limiter's credit: workers may
    send transitions while the learner's ``env_steps`` is below it. Losses and Q means may be
    non-finite on purpose (a diverging run must stay visible).

    ``per_worker[w]`` is a `WorkerCounters` (a plain mapping with at least ``received`` and
    ``last_seq`` is accepted when building one to send). ``live[k]`` is false for an
    eliminated actor, ``workers`` the number of live workers, ``steps`` the run's budget.
    """

    KIND: ClassVar[str] = "learner_stats"

    env_steps: int
    updates: int
    accept_until: int
    utd: float
    losses: Mapping[str, float] = field(default_factory=dict)
    q_means: tuple[float, ...] = ()
    versions: tuple[int, ...] = ()
    per_worker: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    rejected: Mapping[str, int] = field(default_factory=dict)
    done: bool = False
    live: tuple[bool, ...] = ()
    workers: int = 0
    steps: int = 0
    incarnation: str = ""  # changes when a learner restarts (workers reset their in-flight count)
    exact: bool = False  # collection in lock-step with Algorithm 1 (services/roles/lockstep.py); false once broken
    iteration: int = 0  # exact mode: the last iteration whose updates are done
    inexact: str = ""  # why the run stopped being exact (empty while exact, or never asked for)
    awaiting: tuple[int, ...] = ()  # what the learner's loop waits for now: slots, and -1 for the referee
    slots_next: tuple[int, ...] = ()  # per slot, the iteration of the next row the learner needs from it
    owners: tuple[str, ...] = ()  # per slot, "worker/incarnation" whose rows it takes ("" before the first)

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {
            "incarnation": self.incarnation,
            "env_steps": self.env_steps,
            "updates": self.updates,
            "accept_until": self.accept_until,
            "utd": float(self.utd),
            "losses": {str(k): float(v) for k, v in self.losses.items()},
            "q_means": [float(q) for q in self.q_means],
            "versions": [int(v) for v in self.versions],
            "per_worker": {str(w): d.to_dict() if isinstance(d, WorkerCounters) else dict(d)
                           for w, d in self.per_worker.items()},
            "rejected": {str(r): int(n) for r, n in self.rejected.items()},
            "done": bool(self.done),
            "live": [bool(x) for x in self.live],
            "workers": int(self.workers),
            "steps": int(self.steps),
            "exact": bool(self.exact),
            "iteration": int(self.iteration),
            "inexact": self.inexact,
            "awaiting": [int(a) for a in self.awaiting],
            "slots_next": [int(a) for a in self.slots_next],
            "owners": [str(o) for o in self.owners],
        }
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any]) -> "LearnerStats":
        check_kind(msg, cls.KIND)
        env_steps = int_field(msg, "env_steps", lo=0)
        updates = int_field(msg, "updates", lo=0)
        accept_until = int_field(msg, "accept_until", lo=0)
        utd = float_field(msg, "utd", lo=0.0)
        losses = {k: as_float(v, "losses", finite=False) for k, v in str_map_field(msg, "losses").items()}
        q_means = floats_field(msg, "q_means", finite=False)
        versions = ints_field(msg, "versions", lo=-1)
        per_worker = {w: WorkerCounters.from_message(d, w) for w, d in str_map_field(msg, "per_worker").items()}
        rej_raw = str_map_field(msg, "rejected")
        rejected = {r: int_field(rej_raw, r, lo=0) for r in rej_raw}
        done = bool_field(msg, "done")
        live = tuple(list_field(msg, "live")) if "live" in msg else ()
        if any(type(x) is not bool for x in live):
            raise MessageError("type:live", "want bools")
        workers = int_field(msg, "workers", lo=0) if "workers" in msg else 0
        steps = int_field(msg, "steps", lo=0) if "steps" in msg else 0
        incarnation = text_field(msg, "incarnation") if "incarnation" in msg else ""
        exact = bool_field(msg, "exact") if "exact" in msg else False
        iteration = int_field(msg, "iteration", lo=0) if "iteration" in msg else 0
        inexact = text_field(msg, "inexact") if "inexact" in msg else ""
        awaiting = ints_field(msg, "awaiting", lo=-1) if "awaiting" in msg else ()
        slots_next = ints_field(msg, "slots_next", lo=1) if "slots_next" in msg else ()
        owners = tuple(list_field(msg, "owners")) if "owners" in msg else ()
        if any(not isinstance(o, str) or len(o) > MAX_TEXT_LEN for o in owners):
            raise MessageError("type:owners", f"want strs of at most {MAX_TEXT_LEN} chars")
        return cls(env_steps, updates, accept_until, utd, losses, q_means, versions,
                   per_worker, rejected, done, live, workers, steps, incarnation, exact, iteration, inexact,
                   tuple(awaiting), tuple(slots_next), owners)

    @classmethod
    def from_bytes(cls, payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "LearnerStats":
        return cls.from_message(decode(payload, max_bytes=max_bytes))
