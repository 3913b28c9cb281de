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
receivers count and log; ``detail`` says more. The typed messages (services/messaging/codec/data.py, control.py,
stats.py) validate their fields; a message that fails is dropped by the receiver, never half-used.
This package must not import zenoh.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from typing import Any, Mapping

import msgpack
import numpy as np

from services.messaging import keys

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


def pack_default(obj: Any) -> Any:
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


def unpack_ext_hook(code: int, data: bytes) -> Any:
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
    out = _packer().pack(msg)
    if len(out) > _KEEP_BUFFER_BYTES:  # a takeover's episode, say: its buffer is not kept
        _packers.packer = None
    return out


_packers = threading.local()
_KEEP_BUFFER_BYTES = 4 << 20  # a thread's packer keeps a buffer this big at most (a Humanoid actor: 0.7 MB)


def _packer() -> msgpack.Packer:
    """This thread's packer (the bytes of `msgpack.packb` with the same options). It keeps its
    grown buffer: `packb` makes a packer a message, whose buffer grows by reallocation on fresh
    pages, 440 us for a 256x256 actor's 288 KB against 55 us here."""
    packer = getattr(_packers, "packer", None)
    if packer is None:
        packer = _packers.packer = msgpack.Packer(default=pack_default, use_bin_type=True, strict_types=False,
                                                  autoreset=True)
    return packer


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
            ext_hook=unpack_ext_hook,
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
    kind = get_field(msg, "kind", "")
    if not isinstance(kind, str) or not kind or len(kind) > 64:
        raise MessageError("type:kind", "kind must be a short non-empty str")
    sender = get_field(msg, "sender", "")
    if not isinstance(sender, str) or not sender or len(sender) > 256:
        raise MessageError("type:sender", "sender must be a short non-empty str")
    int_field(msg, "seq", lo=0)
    if "t" in msg and (type(msg["t"]) not in (int, float)):
        raise MessageError("type:t", "t must be a number")
    return msg


# --------------------------------------------------------------------------- field checks


def get_field(msg: Mapping[str, Any], name: str, where: str = "") -> Any:
    if name not in msg:
        raise MessageError(f"missing:{name}", where)
    return msg[name]


def int_field(msg: Mapping[str, Any], name: str, lo: int | None = None, hi: int | None = None) -> int:
    v = get_field(msg, name)
    if type(v) is not int:
        raise MessageError(f"type:{name}", f"want int, got {type(v).__name__}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise MessageError(f"range:{name}", f"{v} not in [{lo}, {hi}]")
    return v


def as_float(v: Any, name: str, finite: bool = True) -> float:
    if type(v) not in (int, float):
        raise MessageError(f"type:{name}", f"want number, got {type(v).__name__}")
    v = float(v)
    if finite and not math.isfinite(v):
        raise MessageError(f"not_finite:{name}", str(v))
    return v


def float_field(msg: Mapping[str, Any], name: str, lo: float | None = None, finite: bool = True) -> float:
    v = as_float(get_field(msg, name), name, finite)
    if lo is not None and v < lo:
        raise MessageError(f"range:{name}", f"{v} < {lo}")
    return v


def text_field(msg: Mapping[str, Any], name: str, max_len: int = MAX_TEXT_LEN) -> str:
    v = get_field(msg, name)
    if not isinstance(v, str) or len(v) > max_len:
        raise MessageError(f"type:{name}", f"want str of at most {max_len} chars")
    return v


def bool_field(msg: Mapping[str, Any], name: str) -> bool:
    v = get_field(msg, name)
    if type(v) is not bool:
        raise MessageError(f"type:{name}", f"want bool, got {type(v).__name__}")
    return v


def list_field(msg: Mapping[str, Any], name: str, length: int | None = None) -> list:
    v = get_field(msg, name)
    if not isinstance(v, list):
        raise MessageError(f"type:{name}", f"want list, got {type(v).__name__}")
    if length is not None and len(v) != length:
        raise MessageError(f"shape:{name}", f"length {len(v)} != {length}")
    return v


def floats_field(msg: Mapping[str, Any], name: str, length: int | None = None,
                 finite: bool = True) -> tuple[float, ...]:
    return tuple(as_float(x, name, finite) for x in list_field(msg, name, length))


def ints_field(msg: Mapping[str, Any], name: str, length: int | None = None, lo: int | None = None) -> tuple[int, ...]:
    out = list_field(msg, name, length)
    for x in out:
        if type(x) is not int:
            raise MessageError(f"type:{name}", f"want ints, got {type(x).__name__}")
        if lo is not None and x < lo:
            raise MessageError(f"range:{name}", f"{x} < {lo}")
    return tuple(out)


def str_map_field(msg: Mapping[str, Any], name: str) -> dict:
    v = get_field(msg, name)
    if not isinstance(v, dict):
        raise MessageError(f"type:{name}", f"want a map, got {type(v).__name__}")
    for k in v:
        if not isinstance(k, str) or len(k) > 256:
            raise MessageError(f"type:{name}", f"map keys must be short str, got {k!r}"[:200])
    return v


def id_field(msg: Mapping[str, Any], name: str) -> str:
    v = get_field(msg, name)
    try:
        return keys.check_name(v, name)
    except ValueError as e:
        raise MessageError(f"type:{name}", str(e)) from None


def array_field(
    msg: Mapping[str, Any],
    name: str,
    shape: tuple[int, ...],
    dtypes: tuple[str, ...] = ("float32",),
    finite: bool = True,
) -> np.ndarray:
    a = get_field(msg, name)
    if not isinstance(a, np.ndarray):
        raise MessageError(f"type:{name}", f"want array, got {type(a).__name__}")
    if a.dtype.name not in dtypes:
        raise MessageError(f"dtype:{name}", f"{a.dtype.name} not in {dtypes}")
    if a.shape != shape:
        raise MessageError(f"shape:{name}", f"{a.shape} != {shape}")
    if finite and a.dtype.kind == "f" and not np.isfinite(a).all():
        raise MessageError(f"not_finite:{name}", "NaN or inf")
    return a


def check_kind(msg: Mapping[str, Any], kind: str) -> None:
    if msg.get("kind") != kind:
        raise MessageError("kind", f"got {msg.get('kind')!r}, want {kind!r}")


def as_f32(a: Any) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
