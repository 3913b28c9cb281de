"""Wire format: msgpack maps with a schema version; numpy arrays as raw bytes. No pickle.

Every message is one msgpack map::

    {"v": SCHEMA_VERSION, "kind": str, "sender": str, "seq": int, "t": float, **body}

``seq`` is the sender's own counter for that kind of message; ``t`` is the sender's
``time.time()``. Map keys are always strings.

A numpy array is a msgpack ExtType with code ``NDARRAY_EXT`` (1) whose data is::

    u8 len(dtype name) | dtype name (ascii, e.g. b"float32") | u8 ndim
    | ndim x int64 little-endian dims | raw little-endian C-order bytes

Only the dtypes in ``DTYPES`` are allowed, ``ndim <= MAX_NDIM``, and the byte count
must equal ``prod(shape) * itemsize``. Decoded arrays are read-only ``np.frombuffer``
views of the ext data: no copy after msgpack's own.

Decoding is hostile-input safe: payload size capped before parsing, container and
string lengths capped, only string map keys, and every failure is a ``MessageError``
whose ``reason`` is a short stable token (``"too_large"``, ``"shape:obs"``, ...) that
receivers count and log; ``detail`` says more. The typed messages below validate their
fields; a message that fails is dropped by the receiver, never half-used.
This module must not import zenoh.
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import msgpack
import numpy as np

from services import keys

SCHEMA_VERSION = 1
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
NDARRAY_EXT = 1
MAX_NDIM = 4
MAX_DIM = 1 << 31
DTYPES = frozenset({"float32", "float64", "int64", "int32", "int16", "uint8", "bool"})

# Limits handed to msgpack on top of the payload size cap.
MAX_STR_LEN = 1 << 20
MAX_ARRAY_LEN = 1 << 20
MAX_MAP_LEN = 1 << 16
HEADER_KEYS = frozenset({"v", "kind", "sender", "seq", "t"})
MAX_TEXT_LEN = 1024  # free-text fields such as reasons


class MessageError(ValueError):
    """A received message is invalid. ``reason`` is short and stable (used as a counter key)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


# --------------------------------------------------------------------------- arrays


def _pack_array(a: np.ndarray) -> msgpack.ExtType:
    name = a.dtype.name
    if name not in DTYPES:
        raise TypeError(f"dtype {a.dtype} is not allowed on the wire (allowed: {sorted(DTYPES)})")
    if a.ndim > MAX_NDIM:
        raise TypeError(f"array with ndim {a.ndim} > {MAX_NDIM}")
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<"))
    header = bytes([len(name)]) + name.encode("ascii") + bytes([a.ndim])
    header += struct.pack(f"<{a.ndim}q", *a.shape)
    return msgpack.ExtType(NDARRAY_EXT, header + a.tobytes())


def _unpack_array(data: bytes) -> np.ndarray:
    try:
        n = data[0]
        name = data[1 : 1 + n].decode("ascii")
        ndim = data[1 + n]
    except (IndexError, UnicodeDecodeError):
        raise MessageError("array_ext", "truncated or non-ascii array header") from None
    if name not in DTYPES:
        raise MessageError("array_dtype", f"dtype {name!r} not allowed")
    if ndim > MAX_NDIM:
        raise MessageError("array_ndim", f"ndim {ndim} > {MAX_NDIM}")
    off = 2 + n
    if len(data) < off + 8 * ndim:
        raise MessageError("array_ext", "truncated array shape")
    shape = struct.unpack_from(f"<{ndim}q", data, off)
    if any(d < 0 for d in shape):
        raise MessageError("array_shape", f"negative dimension in {shape}")
    if any(d > MAX_DIM for d in shape):
        raise MessageError("array_shape", f"dimension above {MAX_DIM} in {shape}")
    off += 8 * ndim
    dtype = np.dtype(name).newbyteorder("<")
    count = math.prod(shape)
    if len(data) - off != count * dtype.itemsize:
        raise MessageError(
            "array_bytes", f"{len(data) - off} bytes for shape {shape} of {name}"
        )
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=off).reshape(shape)
    if name == "bool" and count and arr.view(np.uint8).max() > 1:
        raise MessageError("array_bytes", "bool array holds values other than 0/1")
    return arr


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _pack_array(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, (tuple, frozenset, set)):
        return list(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != NDARRAY_EXT:
        raise MessageError("array_ext", f"unknown ext type {code}")
    return _unpack_array(data)


# --------------------------------------------------------------------------- envelope


def encode(kind: str, body: Mapping[str, Any], *, sender: str, seq: int) -> bytes:
    """Pack ``body`` with the header fields. Arrays inside may be nested in dicts/lists."""
    clash = HEADER_KEYS.intersection(body)
    if clash:
        raise ValueError(f"body uses reserved keys {sorted(clash)}")
    msg = {"v": SCHEMA_VERSION, "kind": kind, "sender": sender, "seq": int(seq), "t": time.time()}
    msg.update(body)
    return msgpack.packb(msg, default=_default, use_bin_type=True, strict_types=False)


def decode(payload: bytes | bytearray | memoryview, *, max_bytes: int = MAX_MESSAGE_BYTES) -> dict:
    """Unpack and check the envelope. Raises MessageError on anything malformed."""
    try:
        size = memoryview(payload).nbytes
    except TypeError:
        raise MessageError("type:payload", f"want bytes, got {type(payload).__name__}") from None
    if size > max_bytes:
        raise MessageError("too_large", f"{size} bytes > {max_bytes}")
    try:
        # msgpack.unpackb has no max_buffer_size: the size cap above plays that role.
        msg = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            use_list=True,
            ext_hook=_ext_hook,
            max_str_len=MAX_STR_LEN,
            max_bin_len=max_bytes,
            max_ext_len=max_bytes,
            max_array_len=MAX_ARRAY_LEN,
            max_map_len=MAX_MAP_LEN,
        )
    except MessageError:
        raise
    except Exception as e:  # msgpack raises ValueError, FormatError, StackError, ...
        raise MessageError("not_msgpack", f"{type(e).__name__}: {e}"[:200]) from None
    if not isinstance(msg, dict):
        raise MessageError("not_a_map", type(msg).__name__)
    if "v" not in msg:
        raise MessageError("version", "missing schema version")
    if type(msg["v"]) is not int or msg["v"] != SCHEMA_VERSION:
        raise MessageError("version", f"got {msg['v']!r}, want {SCHEMA_VERSION}")
    kind = _get(msg, "kind", "")
    if not isinstance(kind, str) or not kind or len(kind) > 64:
        raise MessageError("type:kind", "kind must be a short non-empty str")
    sender = _get(msg, "sender", "")
    if not isinstance(sender, str) or not sender or len(sender) > 256:
        raise MessageError("type:sender", "sender must be a short non-empty str")
    _int(msg, "seq", lo=0)
    if "t" in msg and (type(msg["t"]) not in (int, float)):
        raise MessageError("type:t", "t must be a number")
    return msg


# --------------------------------------------------------------------------- field checks


def _get(msg: Mapping[str, Any], name: str, where: str = "") -> Any:
    if name not in msg:
        raise MessageError(f"missing:{name}", where)
    return msg[name]


def _int(msg: Mapping[str, Any], name: str, lo: int | None = None, hi: int | None = None) -> int:
    v = _get(msg, name)
    if type(v) is not int:
        raise MessageError(f"type:{name}", f"want int, got {type(v).__name__}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise MessageError(f"range:{name}", f"{v} not in [{lo}, {hi}]")
    return v


def _as_float(v: Any, name: str, finite: bool = True) -> float:
    if type(v) not in (int, float):
        raise MessageError(f"type:{name}", f"want number, got {type(v).__name__}")
    v = float(v)
    if finite and not math.isfinite(v):
        raise MessageError(f"not_finite:{name}", str(v))
    return v


def _float(msg: Mapping[str, Any], name: str, lo: float | None = None, finite: bool = True) -> float:
    v = _as_float(_get(msg, name), name, finite)
    if lo is not None and v < lo:
        raise MessageError(f"range:{name}", f"{v} < {lo}")
    return v


def _text(msg: Mapping[str, Any], name: str, max_len: int = MAX_TEXT_LEN) -> str:
    v = _get(msg, name)
    if not isinstance(v, str) or len(v) > max_len:
        raise MessageError(f"type:{name}", f"want str of at most {max_len} chars")
    return v


def _bool(msg: Mapping[str, Any], name: str) -> bool:
    v = _get(msg, name)
    if type(v) is not bool:
        raise MessageError(f"type:{name}", f"want bool, got {type(v).__name__}")
    return v


def _list(msg: Mapping[str, Any], name: str, length: int | None = None) -> list:
    v = _get(msg, name)
    if not isinstance(v, list):
        raise MessageError(f"type:{name}", f"want list, got {type(v).__name__}")
    if length is not None and len(v) != length:
        raise MessageError(f"shape:{name}", f"length {len(v)} != {length}")
    return v


def _floats(msg: Mapping[str, Any], name: str, length: int | None = None, finite: bool = True) -> tuple[float, ...]:
    return tuple(_as_float(x, name, finite) for x in _list(msg, name, length))


def _ints(msg: Mapping[str, Any], name: str, length: int | None = None, lo: int | None = None) -> tuple[int, ...]:
    out = _list(msg, name, length)
    for x in out:
        if type(x) is not int:
            raise MessageError(f"type:{name}", f"want ints, got {type(x).__name__}")
        if lo is not None and x < lo:
            raise MessageError(f"range:{name}", f"{x} < {lo}")
    return tuple(out)


def _str_map(msg: Mapping[str, Any], name: str) -> dict:
    v = _get(msg, name)
    if not isinstance(v, dict):
        raise MessageError(f"type:{name}", f"want a map, got {type(v).__name__}")
    for k in v:
        if not isinstance(k, str) or len(k) > 256:
            raise MessageError(f"type:{name}", f"map keys must be short str, got {k!r}"[:200])
    return v


def _id(msg: Mapping[str, Any], name: str) -> str:
    v = _get(msg, name)
    try:
        return keys.check_name(v, name)
    except ValueError as e:
        raise MessageError(f"type:{name}", str(e)) from None


def _array(
    msg: Mapping[str, Any],
    name: str,
    shape: tuple[int, ...],
    dtypes: tuple[str, ...] = ("float32",),
    finite: bool = True,
) -> np.ndarray:
    a = _get(msg, name)
    if not isinstance(a, np.ndarray):
        raise MessageError(f"type:{name}", f"want array, got {type(a).__name__}")
    if a.dtype.name not in dtypes:
        raise MessageError(f"dtype:{name}", f"{a.dtype.name} not in {dtypes}")
    if a.shape != shape:
        raise MessageError(f"shape:{name}", f"{a.shape} != {shape}")
    if finite and a.dtype.kind == "f" and not np.isfinite(a).all():
        raise MessageError(f"not_finite:{name}", "NaN or inf")
    return a


def _check_kind(msg: Mapping[str, Any], kind: str) -> None:
    if msg.get("kind") != kind:
        raise MessageError("kind", f"got {msg.get('kind')!r}, want {kind!r}")


def _f32(a: Any) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)


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

    @property
    def rows(self) -> int:
        return int(self.reward.shape[0])

    def to_bytes(self, sender: str | None = None, seq: int | None = None) -> bytes:
        body = {
            "worker": self.worker,
            "incarnation": self.incarnation,
            "batch_seq": self.batch_seq,
            "actor": self.actor,
            "version": self.version,
            "obs": _f32(self.obs),
            "action": _f32(self.action),
            "reward": _f32(self.reward),
            "next_obs": _f32(self.next_obs),
            "terminated": np.ascontiguousarray(self.terminated, dtype=np.bool_),
            "episode_return": None
            if self.episode_return is None
            else [float(x) for x in self.episode_return],
        }
        if self.resend:
            body["resend"] = True
        return encode(
            self.KIND,
            body,
            sender=self.worker if sender is None else sender,
            seq=self.batch_seq if seq is None else seq,
        )

    @classmethod
    def from_message(cls, msg: Mapping[str, Any], spec: TransitionSpec) -> "TransitionBatch":
        _check_kind(msg, cls.KIND)
        worker = _id(msg, "worker")
        if msg.get("sender") != worker:
            raise MessageError("sender_mismatch", f"sender {msg.get('sender')!r} != worker {worker!r}")
        incarnation = _id(msg, "incarnation")
        batch_seq = _int(msg, "batch_seq", lo=0)
        actor = _int(msg, "actor", lo=0)
        if actor >= spec.n_actors:
            raise MessageError("range:actor", f"actor {actor} >= K={spec.n_actors}")
        version = _int(msg, "version", lo=-1)
        reward = _get(msg, "reward")
        if not isinstance(reward, np.ndarray) or reward.ndim != 1:
            raise MessageError("shape:reward", "reward must be a 1-d array")
        n = reward.shape[0]
        if not 1 <= n <= spec.max_rows:
            raise MessageError("range:rows", f"{n} rows not in [1, {spec.max_rows}]")
        obs = _array(msg, "obs", (n, spec.obs_dim))
        action = _array(msg, "action", (n, spec.act_dim))
        reward = _array(msg, "reward", (n,))
        next_obs = _array(msg, "next_obs", (n, spec.obs_dim))
        term = _array(msg, "terminated", (n,), dtypes=("bool", "uint8"))
        if term.dtype.name == "uint8":
            if n and term.max() > 1:
                raise MessageError("range:terminated", "uint8 terminated must be 0/1")
            term = term.view(np.bool_)
        if spec.max_action is not None:
            bound = spec.max_action * (1 + 1e-5)
            if np.abs(action).max() > bound:
                raise MessageError("range:action", f"|action| > {spec.max_action}")
        ret = _get(msg, "episode_return") if "episode_return" in msg else None
        episode_return = None
        if ret is not None:
            episode_return = _floats(msg, "episode_return")
            if len(episode_return) > spec.max_rows:
                raise MessageError("range:episode_return", "more episodes than rows")
        resend = _bool(msg, "resend") if "resend" in msg else False
        return cls(worker, incarnation, batch_seq, actor, version, obs, action, reward,
                   next_obs, term, episode_return, resend)

    @classmethod
    def from_bytes(cls, payload: bytes, spec: TransitionSpec, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "TransitionBatch":
        return cls.from_message(decode(payload, max_bytes=max_bytes), spec)


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

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {
            "actor": self.actor,
            "version": self.version,
            "params": {str(k): _f32(v) for k, v in self.params.items()},
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
        _check_kind(msg, cls.KIND)
        actor = _int(msg, "actor", lo=0, hi=None if n_actors is None else n_actors - 1)
        version = _int(msg, "version", lo=0)
        params = _get(msg, "params")
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
        obs_dim = _int(msg, "obs_dim", lo=1)
        act_dim = _int(msg, "act_dim", lo=1)
        max_action = _float(msg, "max_action")
        if max_action <= 0:
            raise MessageError("range:max_action", f"{max_action} <= 0")
        hidden = _ints(msg, "hidden", lo=1)
        if len(hidden) > 16:
            raise MessageError("range:hidden", "more than 16 hidden layers")
        return cls(actor, version, params, obs_dim, act_dim, max_action, hidden)

    @classmethod
    def from_bytes(cls, payload: bytes, expected: Mapping[str, tuple[int, ...]] | None = None,
                   n_actors: int | None = None, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Weights":
        return cls.from_message(decode(payload, max_bytes=max_bytes), expected, n_actors)


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
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any], n_actors: int | None = None) -> "Allocation":
        _check_kind(msg, cls.KIND)
        rnd = _int(msg, "round", lo=0)
        env_steps = _int(msg, "env_steps", lo=0)
        probs = _floats(msg, "probabilities", n_actors)
        k = len(probs)
        if k < 1:
            raise MessageError("shape:probabilities", "no actors")
        if any(not 0.0 <= p <= 1.0 for p in probs):
            raise MessageError("range:probabilities", f"{probs} outside [0, 1]"[:200])
        if abs(sum(probs) - 1.0) > 1e-4:
            raise MessageError("range:probabilities", f"sum {sum(probs)} != 1")
        returns = None if _get(msg, "returns") is None else _floats(msg, "returns", k)
        counts = _ints(msg, "counts", k, lo=0)
        elim_raw = _list(msg, "eliminated", k)
        if any(type(e) is not bool for e in elim_raw):
            raise MessageError("type:eliminated", "want bools")
        eliminated = tuple(elim_raw)
        slots_raw = _get(msg, "slots")
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
        survivor = _get(msg, "survivor")
        if survivor is not None:
            survivor = _int(msg, "survivor", lo=0, hi=k - 1)
            if eliminated[survivor]:
                raise MessageError("range:survivor", f"survivor {survivor} is eliminated")
        reason = _text(msg, "reason")
        return cls(rnd, env_steps, returns, probs, counts, slots, eliminated, survivor, reason)

    @classmethod
    def from_bytes(cls, payload: bytes, n_actors: int | None = None, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Allocation":
        return cls.from_message(decode(payload, max_bytes=max_bytes), n_actors)


def _plain_value(v: Any, name: str, depth: int = 0) -> None:
    """Free-form diagnostics: numbers (finite), None, bools, short strings, lists of those."""
    if v is None or type(v) in (bool, int):
        return
    if type(v) is float:
        _as_float(v, name)
        return
    if isinstance(v, str) and len(v) <= MAX_TEXT_LEN:
        return
    if isinstance(v, list) and depth < 2:
        for x in v:
            _plain_value(x, name, depth + 1)
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
        _check_kind(msg, cls.KIND)
        rnd = _int(msg, "round", lo=0)
        env_steps = _int(msg, "env_steps", lo=0)
        per_actor = _list(msg, "returns", n_actors)
        k = len(per_actor)
        returns = tuple(_floats({"returns": rs}, "returns") for rs in per_actor)
        mean_raw = _list(msg, "mean", k)
        mean = tuple(None if m is None else _as_float(m, "mean") for m in mean_raw)
        for rs, m in zip(returns, mean):
            if (m is None) != (len(rs) == 0):
                raise MessageError("range:mean", "mean must be None exactly when returns are empty")
        versions = _ints(msg, "versions", k, lo=-1)
        bias = _get(msg, "bias") if "bias" in msg else None
        if bias is not None:
            for v in _str_map(msg, "bias").values():
                _plain_value(v, "bias")
        return cls(rnd, env_steps, returns, mean, versions, bias)

    @classmethod
    def from_bytes(cls, payload: bytes, n_actors: int | None = None, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Eval":
        return cls.from_message(decode(payload, max_bytes=max_bytes), n_actors)


@dataclass(frozen=True)
class LearnerStats:
    """The learner's counters. ``accept_until`` is the rate limiter's credit: workers may
    send transitions while the learner's ``env_steps`` is below it. Losses and Q means may be
    non-finite on purpose (a diverging run must stay visible).

    ``per_worker[w]`` holds at least ``received`` and ``last_seq``; the learner may add
    more plain scalars (incarnation, rows, actor, lag, rate). With the replay persisted it also
    holds ``acked_incarnation`` and ``acked_seq`` (validated): every batch of that worker
    incarnation up to ``acked_seq`` is in the learner's last checkpoint, so the worker may stop
    keeping it for a resend. ``live[k]`` is false for an
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
    per_worker: Mapping[str, Mapping[str, int]] = field(default_factory=dict)
    rejected: Mapping[str, int] = field(default_factory=dict)
    done: bool = False
    live: tuple[bool, ...] = ()
    workers: int = 0
    steps: int = 0
    incarnation: str = ""  # changes when a learner restarts (workers reset their in-flight count)

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
            "per_worker": {str(w): dict(d) for w, d in self.per_worker.items()},
            "rejected": {str(r): int(n) for r, n in self.rejected.items()},
            "done": bool(self.done),
            "live": [bool(x) for x in self.live],
            "workers": int(self.workers),
            "steps": int(self.steps),
        }
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any]) -> "LearnerStats":
        _check_kind(msg, cls.KIND)
        env_steps = _int(msg, "env_steps", lo=0)
        updates = _int(msg, "updates", lo=0)
        accept_until = _int(msg, "accept_until", lo=0)
        utd = _float(msg, "utd", lo=0.0)
        losses = {k: _as_float(v, "losses", finite=False) for k, v in _str_map(msg, "losses").items()}
        q_means = _floats(msg, "q_means", finite=False)
        versions = _ints(msg, "versions", lo=-1)
        per_worker: dict[str, dict[str, Any]] = {}
        for w, d in _str_map(msg, "per_worker").items():
            d = _str_map({"per_worker": d}, "per_worker")
            _int(d, "received", lo=0)
            _int(d, "last_seq", lo=-1)
            if "acked_seq" in d or "acked_incarnation" in d:  # the checkpointed prefix of its stream
                _int(d, "acked_seq", lo=-1)
                _id(d, "acked_incarnation")
            for v in d.values():
                if isinstance(v, list):
                    raise MessageError("type:per_worker", f"{w}: values must be scalars")
                _plain_value(v, "per_worker")
            per_worker[w] = d
        rej_raw = _str_map(msg, "rejected")
        rejected = {r: _int(rej_raw, r, lo=0) for r in rej_raw}
        done = _bool(msg, "done")
        live = tuple(_list(msg, "live")) if "live" in msg else ()
        if any(type(x) is not bool for x in live):
            raise MessageError("type:live", "want bools")
        workers = _int(msg, "workers", lo=0) if "workers" in msg else 0
        steps = _int(msg, "steps", lo=0) if "steps" in msg else 0
        incarnation = _text(msg, "incarnation") if "incarnation" in msg else ""
        return cls(env_steps, updates, accept_until, utd, losses, q_means, versions,
                   per_worker, rejected, done, live, workers, steps, incarnation)

    @classmethod
    def from_bytes(cls, payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "LearnerStats":
        return cls.from_message(decode(payload, max_bytes=max_bytes))


@dataclass(frozen=True)
class Done:
    """The learner's end-of-run notice (acknowledged by receivers, see ZENOH.md)."""

    KIND: ClassVar[str] = "done"

    reason: str
    env_steps: int
    updates: int

    def to_bytes(self, sender: str, seq: int) -> bytes:
        body = {"reason": self.reason, "env_steps": self.env_steps, "updates": self.updates}
        return encode(self.KIND, body, sender=sender, seq=seq)

    @classmethod
    def from_message(cls, msg: Mapping[str, Any]) -> "Done":
        _check_kind(msg, cls.KIND)
        return cls(_text(msg, "reason"), _int(msg, "env_steps", lo=0), _int(msg, "updates", lo=0))

    @classmethod
    def from_bytes(cls, payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> "Done":
        return cls.from_message(decode(payload, max_bytes=max_bytes))
