"""The control plane: allocation and evaluation (referee -> all) and the end-of-run notice."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

from services.messaging import keys
from services.messaging.codec.wire import (
    MAX_MESSAGE_BYTES,
    MAX_TEXT_LEN,
    MessageError,
    as_float,
    check_kind,
    decode,
    encode,
    floats_field,
    get_field,
    int_field,
    ints_field,
    list_field,
    str_map_field,
    text_field,
)


@dataclass(frozen=True)
class Allocation:
    """The referee's decision: which actor each worker slot runs (Eq. 8 probabilities, I_k).

    ``counts[k]`` (I_k) is the number of slots running actor k; no slot runs an
    eliminated actor; ``survivor`` is set once elimination happened.
    """

    KIND: ClassVar[str] = "allocation"

    round: int
    env_steps: int
    returns: tuple[float, ...] | None
    probabilities: tuple[float, ...]
    counts: tuple[int, ...]
    slots: Mapping[str, int]
    eliminated: tuple[bool, ...]
    survivor: int | None
    reason: str
    # Exact mode: the iteration whose competition drew `slots` (they apply from the next one on;
    # 0: the initial draw), and the decision before it, (its iteration, its slots), so a worker
    # that polls the latest message never misses the allocation it still needs.
    iteration: int | None = None
    previous: tuple[int, Mapping[str, int]] | None = None

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {
            "round": self.round,
            "env_steps": self.env_steps,
            "returns": None if self.returns is None else [float(r) for r in self.returns],
            "probabilities": [float(p) for p in self.probabilities],
            "counts": [int(c) for c in self.counts],
            "slots": {str(w): int(k) for w, k in self.slots.items()},
            "eliminated": [bool(e) for e in self.eliminated],
            "survivor": None if self.survivor is None else int(self.survivor),
            "reason": self.reason,
        }
        if self.iteration is not None:
            body["iteration"] = int(self.iteration)
            if self.previous is not None:
                body["previous"] = {"iteration": int(self.previous[0]),
                                    "slots": {str(w): int(k) for w, k in self.previous[1].items()}}
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any], n_actors: int | None = None) -> "Allocation":
        check_kind(msg, cls.KIND)
        rnd = int_field(msg, "round", lo=0)
        env_steps = int_field(msg, "env_steps", lo=0)
        probs = floats_field(msg, "probabilities", n_actors)
        k = len(probs)
        if k < 1:
            raise MessageError("shape:probabilities", "no actors")
        if any(not 0.0 <= p <= 1.0 for p in probs):
            raise MessageError("range:probabilities", f"{probs} outside [0, 1]"[:200])
        if abs(sum(probs) - 1.0) > 1e-4:
            raise MessageError("range:probabilities", f"sum {sum(probs)} != 1")
        returns = None if get_field(msg, "returns") is None else floats_field(msg, "returns", k)
        counts = ints_field(msg, "counts", k, lo=0)
        elim_raw = list_field(msg, "eliminated", k)
        if any(type(e) is not bool for e in elim_raw):
            raise MessageError("type:eliminated", "want bools")
        eliminated = tuple(elim_raw)
        slots_raw = get_field(msg, "slots")
        if not isinstance(slots_raw, dict):
            raise MessageError("type:slots", "want a map worker -> actor")
        slots: dict[str, int] = {}
        for worker, a in slots_raw.items():
            try:
                keys.check_name(worker, "worker")
            except ValueError as e:
                raise MessageError("type:slots", str(e)) from None
            if type(a) is not int or not 0 <= a < k:
                raise MessageError("range:slots", f"{worker} -> {a!r} not an actor in [0, {k})")
            if eliminated[a]:
                raise MessageError("range:slots", f"{worker} -> eliminated actor {a}")
            slots[worker] = a
        per_actor = tuple(sum(1 for a in slots.values() if a == j) for j in range(k))
        if per_actor != counts:
            raise MessageError("range:counts", f"counts {counts} != slots per actor {per_actor}")
        survivor = get_field(msg, "survivor")
        if survivor is not None:
            survivor = int_field(msg, "survivor", lo=0, hi=k - 1)
            if eliminated[survivor]:
                raise MessageError("range:survivor", f"survivor {survivor} is eliminated")
        reason = text_field(msg, "reason")
        iteration = int_field(msg, "iteration", lo=0) if "iteration" in msg else None
        previous = None
        if iteration is not None and "previous" in msg:
            prev = get_field(msg, "previous")
            if not isinstance(prev, dict):
                raise MessageError("type:previous", "want a map with iteration and slots")
            p_iteration = int_field(prev, "iteration", lo=0, hi=iteration)
            p_slots = str_map_field(prev, "slots")
            if any(type(a) is not int or not 0 <= a < k for a in p_slots.values()):
                raise MessageError("range:previous", "slots of the previous decision must name actors")
            previous = (p_iteration, dict(p_slots))
        return cls(rnd, env_steps, returns, probs, counts, slots, eliminated, survivor, reason, iteration, previous)

    @classmethod
    def from_bytes(cls, payload: bytes, n_actors: int | None = None, *,
                   max_bytes: int = MAX_MESSAGE_BYTES) -> "Allocation":
        return cls.from_message(decode(payload, max_bytes=max_bytes), n_actors)


def check_plain_value(v: Any, name: str, depth: int = 0) -> None:
    """Free-form diagnostics: numbers (finite), None, bools, short strings, lists of those."""
    if v is None or type(v) in (bool, int):
        return
    if type(v) is float:
        as_float(v, name)
        return
    if isinstance(v, str) and len(v) <= MAX_TEXT_LEN:
        return
    if isinstance(v, list) and depth < 2:
        for x in v:
            check_plain_value(x, name, depth + 1)
        return
    raise MessageError(f"type:{name}", f"unsupported value {type(v).__name__}")


@dataclass(frozen=True)
class Eval:
    """One evaluation round: each actor's episode returns (empty for an actor not evaluated)."""

    KIND: ClassVar[str] = "eval"

    round: int
    env_steps: int
    returns: tuple[tuple[float, ...], ...]
    mean: tuple[float | None, ...]
    versions: tuple[int, ...]
    bias: Mapping[str, Any] | None = None

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {
            "round": self.round,
            "env_steps": self.env_steps,
            "returns": [[float(r) for r in rs] for rs in self.returns],
            "mean": [None if m is None else float(m) for m in self.mean],
            "versions": [int(v) for v in self.versions],
            "bias": None if self.bias is None else dict(self.bias),
        }
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any], n_actors: int | None = None) -> "Eval":
        check_kind(msg, cls.KIND)
        rnd = int_field(msg, "round", lo=0)
        env_steps = int_field(msg, "env_steps", lo=0)
        per_actor = list_field(msg, "returns", n_actors)
        k = len(per_actor)
        returns = tuple(floats_field({"returns": rs}, "returns") for rs in per_actor)
        mean_raw = list_field(msg, "mean", k)
        mean = tuple(None if m is None else as_float(m, "mean") for m in mean_raw)
        for rs, m in zip(returns, mean):
            if (m is None) != (len(rs) == 0):
                raise MessageError("range:mean", "mean must be None exactly when returns are empty")
        versions = ints_field(msg, "versions", k, lo=-1)
        bias = get_field(msg, "bias") if "bias" in msg else None
        if bias is not None:
            for v in str_map_field(msg, "bias").values():
                check_plain_value(v, "bias")
        return cls(rnd, env_steps, returns, mean, versions, bias)

    @classmethod
    def from_bytes(cls, payload: bytes, n_actors: int | None = None, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Eval":
        return cls.from_message(decode(payload, max_bytes=max_bytes), n_actors)


@dataclass(frozen=True)
class Done:
    """The learner's end-of-run notice, repeated until the workers have left (a last put before
    a close can be lost: docs/ZENOH-NOTES.md)."""

    KIND: ClassVar[str] = "done"

    reason: str
    env_steps: int
    updates: int

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {"reason": self.reason, "env_steps": self.env_steps, "updates": self.updates}
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any]) -> "Done":
        check_kind(msg, cls.KIND)
        return cls(text_field(msg, "reason"), int_field(msg, "env_steps", lo=0), int_field(msg, "updates", lo=0))

    @classmethod
    def from_bytes(cls, payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Done":
        return cls.from_message(decode(payload, max_bytes=max_bytes))
