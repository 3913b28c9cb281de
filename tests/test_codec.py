"""The wire format: round trips, zero-copy arrays, and rejection of every kind of bad input."""

from __future__ import annotations

import dataclasses
import math
import random
import struct
import subprocess
import sys

import msgpack
import numpy as np
import pytest

from services.messaging import codec
from services.messaging.codec import (
    SCHEMA_VERSION,
    Allocation,
    Done,
    Eval,
    LearnerStats,
    MessageError,
    TransitionBatch,
    TransitionSpec,
    Weights,
    decode,
    encode,
)

OBS, ACT, K = 5, 2, 3
SPEC = TransitionSpec(obs_dim=OBS, act_dim=ACT, n_actors=K, max_rows=64, max_action=1.0)


def make_batch(n: int = 8, seed: int = 0, **kw) -> TransitionBatch:
    rng = np.random.default_rng(seed)
    fields = dict(
        worker="w0",
        incarnation="inc-1",
        batch_seq=3,
        actor=1,
        version=7,
        obs=rng.standard_normal((n, OBS)).astype(np.float32),
        action=rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
        reward=rng.standard_normal(n).astype(np.float32),
        next_obs=rng.standard_normal((n, OBS)).astype(np.float32),
        terminated=rng.random(n) < 0.2,
        episode_return=(12.5, -3.0),
    )
    fields.update(kw)
    return TransitionBatch(**fields)


def make_weights(version: int = 4) -> Weights:
    rng = np.random.default_rng(1)
    params = {
        "l1.weight": rng.standard_normal((16, OBS)).astype(np.float32),
        "l1.bias": np.zeros(16, np.float32),
        "l2.weight": rng.standard_normal((ACT, 16)).astype(np.float32),
        "l2.bias": np.zeros(ACT, np.float32),
    }
    return Weights(actor=2, version=version, params=params, obs_dim=OBS, act_dim=ACT,
                   max_action=1.0, hidden=(16,))


EXPECTED_SHAPES = {n: a.shape for n, a in make_weights().params.items()}


def make_allocation() -> Allocation:
    return Allocation(round=2, env_steps=5000, returns=(10.0, 30.0, -1.0),
                      probabilities=(0.25, 0.75, 0.0), counts=(1, 2, 0),
                      slots={"w0": 1, "w1": 0, "w2": 1}, eliminated=(False, False, True),
                      survivor=None, reason="compete")


def make_eval() -> Eval:
    return Eval(round=2, env_steps=5000, returns=((1.0, 2.0), (3.0,), ()),
                mean=(1.5, 3.0, None), versions=(10, 11, -1),
                bias={"q_estimate": 1.0, "mc_return": [0.5, None], "actor": 1})


def make_stats() -> LearnerStats:
    return LearnerStats(env_steps=1000, updates=990, accept_until=1100, utd=1.0,
                        losses={"critic": 0.5, "actor": float("nan")}, q_means=(1.0, 2.0, 3.0),
                        versions=(5, 5, 4),
                        per_worker={"w0": {"received": 10, "last_seq": 9, "incarnation": "i0",
                                           "incarnation_rows": 10, "actor": 1, "rate": 2.5}},
                        rejected={"shape:obs": 2}, done=False, live=(True, True, False),
                        workers=3, steps=10_000)


def raw(msg: dict) -> bytes:
    """Pack a hand-made message, bypassing ``encode`` (to build bad ones)."""
    return msgpack.packb(msg, default=codec.pack_default, use_bin_type=True)


def reason_of(fn) -> str:
    with pytest.raises(MessageError) as e:
        fn()
    assert e.value.reason, "a MessageError must carry a reason"
    return e.value.reason


# --------------------------------------------------------------------------- round trips


def test_envelope_round_trip():
    payload = encode("custom", {"x": 1, "arr": np.arange(6, dtype=np.int64).reshape(2, 3)},
                     sender="me", seq=42)
    msg = decode(payload)
    assert msg["v"] == SCHEMA_VERSION and msg["kind"] == "custom"
    assert msg["sender"] == "me" and msg["seq"] == 42 and isinstance(msg["t"], float)
    assert msg["arr"].dtype == np.int64 and msg["arr"].shape == (2, 3)
    np.testing.assert_array_equal(msg["arr"], np.arange(6).reshape(2, 3))


def test_encode_packs_the_bytes_of_packb_and_a_failed_message_leaves_nothing_behind():
    """`encode` reuses one msgpack packer a thread (its grown buffer): a large message, a small
    one after it and one after a refused message are the bytes `msgpack.packb` gives."""
    from services.messaging.codec.wire import pack_default

    big = {"w": np.arange(300 * 300, dtype=np.float32).reshape(300, 300), "n": 3}
    small = {"x": [1, 2.5, "a"], "b": np.array([True, False])}
    for kind, body in (("big", big), ("small", small), ("big", big)):
        sent = encode(kind, body, sender="s", seq=7)
        t = decode(sent)["t"]
        head = {"v": SCHEMA_VERSION, "kind": kind, "sender": "s", "seq": 7, "t": t}
        assert sent == msgpack.packb({**head, **body}, default=pack_default, use_bin_type=True, strict_types=False)
    with pytest.raises(TypeError):  # refused midway, after a large array went into the buffer
        encode("k", {"a": big["w"], "z": np.zeros(2, np.complex64)}, sender="s", seq=0)
    assert decode(encode("small", small, sender="s", seq=8))["x"] == [1, 2.5, "a"]
    assert len(encode("small", small, sender="s", seq=8)) < 200
    huge = {"w": np.ones((1100, 1000), np.float32)}  # 4.4 MB: packed, then its packer is not kept
    assert decode(encode("huge", huge, sender="s", seq=9))["w"].shape == (1100, 1000)
    assert decode(encode("small", small, sender="s", seq=10))["seq"] == 10


def test_encode_refuses_reserved_keys_and_bad_dtypes():
    with pytest.raises(ValueError):
        encode("k", {"seq": 1}, sender="s", seq=0)
    with pytest.raises(TypeError):
        encode("k", {"a": np.array(["x"], dtype=object)}, sender="s", seq=0)
    with pytest.raises(TypeError):
        encode("k", {"a": np.zeros((1, 1, 1, 1, 1), np.float32)}, sender="s", seq=0)


def test_transition_batch_round_trip_zero_copy():
    b = make_batch()
    payload = b.to_bytes()
    msg = decode(payload)
    assert msg["sender"] == "w0" and msg["seq"] == 3
    d = TransitionBatch.from_message(msg, SPEC)
    for name in ("obs", "action", "reward", "next_obs", "terminated"):
        got, want = getattr(d, name), getattr(b, name)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == (np.bool_ if name == "terminated" else np.float32)
        assert not got.flags.writeable and not got.flags.owndata  # a view, not a copy
    assert d.obs.shape == (8, OBS) and d.rows == 8
    assert d.obs.base is not None
    assert (d.worker, d.incarnation, d.batch_seq, d.actor, d.version) == ("w0", "inc-1", 3, 1, 7)
    assert d.episode_return == (12.5, -3.0)


def test_transition_batch_accepts_uint8_terminated_and_no_returns():
    b = make_batch(terminated=np.array([0, 1] * 4, np.uint8), episode_return=None, version=-1)
    body = decode(b.to_bytes())
    body["terminated"] = np.array([0, 1] * 4, np.uint8)
    d = TransitionBatch.from_bytes(raw(body), SPEC)
    assert d.terminated.dtype == np.bool_ and d.terminated.tolist() == [False, True] * 4
    assert d.episode_return is None and d.version == -1


def test_weights_round_trip():
    w = make_weights()
    d = Weights.from_bytes(w.to_bytes("learner", 9), EXPECTED_SHAPES, n_actors=K)
    assert d.version == 4 and d.actor == 2 and d.hidden == (16,)
    for name, a in w.params.items():
        np.testing.assert_array_equal(d.params[name], a)
        assert d.params[name].dtype == np.float32


def test_allocation_eval_stats_done_round_trip():
    a = make_allocation()
    assert Allocation.from_bytes(a.to_bytes("referee", 1), n_actors=K) == a
    e = make_eval()
    de = Eval.from_bytes(e.to_bytes("referee", 1), n_actors=K)
    assert de.returns == e.returns and de.mean == e.mean and de.versions == e.versions
    assert de.bias == {"q_estimate": 1.0, "mc_return": [0.5, None], "actor": 1}
    s = make_stats()
    ds = LearnerStats.from_bytes(s.to_bytes("learner", 1))
    assert ds.env_steps == 1000 and ds.accept_until == 1100 and math.isnan(ds.losses["actor"])
    assert ds.per_worker == s.per_worker
    assert ds.rejected == {"shape:obs": 2} and ds.q_means == (1.0, 2.0, 3.0)
    assert (ds.live, ds.workers, ds.steps) == ((True, True, False), 3, 10_000)
    minimal = decode(s.to_bytes("learner", 1))
    for name in ("live", "workers", "steps"):
        del minimal[name]
    assert LearnerStats.from_bytes(raw(minimal)).workers == 0  # optional fields
    done = Done(reason="budget", env_steps=10, updates=10)
    assert Done.from_bytes(done.to_bytes("learner", 0)) == done
    survivor = Allocation(round=3, env_steps=9, returns=None, probabilities=(0.0, 1.0, 0.0),
                          counts=(0, 2, 0), slots={"w0": 1, "w1": 1},
                          eliminated=(True, False, True), survivor=1, reason="eliminate")
    assert Allocation.from_bytes(survivor.to_bytes("referee", 2)) == survivor


# --------------------------------------------------------------------------- envelope rejections


def test_rejects_garbage_truncated_and_non_maps():
    rng = random.Random(0)
    assert reason_of(lambda: decode(bytes(rng.randrange(256) for _ in range(64)))) in (
        "not_msgpack", "not_a_map", "version", "array_ext", "array_dtype")
    good = make_batch().to_bytes()
    assert reason_of(lambda: decode(good[: len(good) // 2])) == "not_msgpack"
    assert reason_of(lambda: decode(good + b"\x00")) == "not_msgpack"  # trailing data
    assert reason_of(lambda: decode(b"")) == "not_msgpack"
    assert reason_of(lambda: decode(msgpack.packb([1, 2, 3]))) == "not_a_map"
    assert reason_of(lambda: decode("a str")) == "type:payload"
    # non-string map keys are refused by msgpack itself
    assert reason_of(lambda: decode(msgpack.packb({1: 2}))) == "not_msgpack"


def test_rejects_wrong_or_missing_version_and_header_fields():
    msg = decode(make_batch().to_bytes())
    for v in (2, 0, "1", True, None):
        assert reason_of(lambda: decode(raw({**msg, "v": v}))) == "version"
    assert reason_of(lambda: decode(raw({k: x for k, x in msg.items() if k != "v"}))) == "version"
    for field in ("kind", "sender", "seq"):
        bad = {k: x for k, x in msg.items() if k != field}
        assert reason_of(lambda: decode(raw(bad))) in (f"missing:{field}", f"type:{field}")
    assert reason_of(lambda: decode(raw({**msg, "seq": -1}))) == "range:seq"
    assert reason_of(lambda: decode(raw({**msg, "seq": 1.5}))) == "type:seq"
    assert reason_of(lambda: decode(raw({**msg, "sender": ""}))) == "type:sender"


def test_size_cap_default_and_override():
    payload = make_batch().to_bytes()
    decode(payload, max_bytes=len(payload))
    assert reason_of(lambda: decode(payload, max_bytes=len(payload) - 1)) == "too_large"
    assert reason_of(lambda: TransitionBatch.from_bytes(payload, SPEC, max_bytes=100)) == "too_large"
    big = b"\x00" * (codec.MAX_MESSAGE_BYTES + 1)
    assert reason_of(lambda: decode(big)) == "too_large"


# --------------------------------------------------------------------------- array rejections


def ext(name: bytes, shape: tuple[int, ...], data: bytes, ndim: int | None = None) -> msgpack.ExtType:
    nd = len(shape) if ndim is None else ndim
    head = bytes([len(name)]) + name + bytes([nd]) + struct.pack(f"<{len(shape)}q", *shape)
    return msgpack.ExtType(codec.NDARRAY_EXT, head + data)


@pytest.mark.parametrize(
    "arr, reason",
    [
        (ext(b"object", (1,), b"\x00" * 8), "array_dtype"),
        (ext(b"float16", (2,), b"\x00" * 4), "array_dtype"),
        (ext(b"<f4", (2,), b"\x00" * 8), "array_dtype"),
        (ext(b"\xff\xfe", (2,), b"\x00" * 8), "array_ext"),
        (ext(b"float32", (-1, 2), b""), "array_shape"),
        (ext(b"float32", (1, 1, 1, 1, 1), b"\x00" * 4), "array_ndim"),
        (ext(b"float32", (3,), b"\x00" * 8), "array_bytes"),
        (ext(b"float32", (2,), b"\x00" * 12), "array_bytes"),
        (ext(b"float32", (1 << 40, 1 << 40), b""), "array_shape"),
        (ext(b"float32", (2,), b"", ndim=2), "array_ext"),
        (ext(b"bool", (2,), b"\x00\x07"), "array_bytes"),
        (msgpack.ExtType(7, b"whatever"), "array_ext"),
        (msgpack.ExtType(codec.NDARRAY_EXT, b""), "array_ext"),
    ],
)
def test_rejects_bad_array_ext(arr, reason):
    msg = {"v": SCHEMA_VERSION, "kind": "transitions", "sender": "w0", "seq": 0, "obs": arr}
    assert reason_of(lambda: decode(raw(msg))) == reason


# --------------------------------------------------------------------------- typed rejections


def batch_body(**changes) -> bytes:
    msg = decode(make_batch().to_bytes())
    msg.update(changes)
    return raw({k: v for k, v in msg.items() if v is not _DROP})


_DROP = object()


@pytest.mark.parametrize(
    "changes, reason",
    [
        ({"obs": np.zeros((8, OBS + 1), np.float32)}, "shape:obs"),
        ({"action": np.zeros((8, ACT), np.float64)}, "dtype:action"),
        ({"next_obs": np.zeros((7, OBS), np.float32)}, "shape:next_obs"),
        ({"reward": np.zeros((8, 1), np.float32)}, "shape:reward"),
        ({"reward": np.full(8, np.nan, np.float32)}, "not_finite:reward"),
        ({"obs": np.full((8, OBS), np.inf, np.float32)}, "not_finite:obs"),
        ({"terminated": np.zeros(8, np.float32)}, "dtype:terminated"),
        ({"terminated": np.full(8, 2, np.uint8)}, "range:terminated"),
        ({"action": np.full((8, ACT), 1.5, np.float32)}, "range:action"),
        ({"actor": K}, "range:actor"),
        ({"actor": -1}, "range:actor"),
        ({"actor": "0"}, "type:actor"),
        ({"version": -2}, "range:version"),
        ({"batch_seq": True}, "type:batch_seq"),
        ({"worker": "w/0"}, "type:worker"),
        ({"worker": "w1"}, "sender_mismatch"),
        ({"incarnation": "*"}, "type:incarnation"),
        ({"obs": _DROP}, "missing:obs"),
        ({"episode_return": [1.0, float("inf")]}, "not_finite:episode_return"),
        ({"episode_return": "x"}, "type:episode_return"),
        ({"kind": "weights"}, "kind"),
        ({"reward": np.zeros(0, np.float32), "obs": np.zeros((0, OBS), np.float32)}, "range:rows"),
    ],
)
def test_transition_batch_rejections(changes, reason):
    assert reason_of(lambda: TransitionBatch.from_bytes(batch_body(**changes), SPEC)) == reason


def test_transition_batch_row_cap():
    big = make_batch(n=65)
    assert reason_of(lambda: TransitionBatch.from_bytes(big.to_bytes(), SPEC)) == "range:rows"


def test_weights_rejections():
    def body(**changes):
        msg = decode(make_weights().to_bytes("learner", 0))
        msg.update(changes)
        return raw(msg)

    params = make_weights().params
    bad_nan = {**params, "l1.bias": np.full(16, np.nan, np.float32)}
    cases = [
        (body(params={**params, "l1.bias": np.zeros(16, np.float64)}), "dtype:params"),
        (body(params=bad_nan), "not_finite:params"),
        (body(params={**params, "l1.bias": np.zeros(17, np.float32)}), "shape:params"),
        (body(params={k: v for k, v in params.items() if k != "l2.bias"}), "params:names"),
        (body(params={**params, "extra": np.zeros(1, np.float32)}), "params:names"),
        (body(params={}), "type:params"),
        (body(params={**params, "l1.bias": [0.0]}), "type:params"),
        (body(version=-1), "range:version"),
        (body(actor=K), "range:actor"),
        (body(max_action=0.0), "range:max_action"),
        (body(hidden=[0]), "range:hidden"),
    ]
    for payload, reason in cases:
        assert reason_of(lambda: Weights.from_bytes(payload, EXPECTED_SHAPES, n_actors=K)) == reason


def test_allocation_rejections():
    def body(**changes):
        msg = decode(make_allocation().to_bytes("referee", 0))
        msg.update(changes)
        return raw(msg)

    cases = [
        (body(probabilities=[0.5, 0.6, 0.0]), "range:probabilities"),
        (body(probabilities=[1.5, -0.5, 0.0]), "range:probabilities"),
        (body(probabilities=[0.5, 0.5]), "shape:probabilities"),
        (body(probabilities=[0.25, float("nan"), 0.75]), "not_finite:probabilities"),
        (body(counts=[1, 1, 0]), "range:counts"),
        (body(slots={"w0": 3}), "range:slots"),
        (body(slots={"w0": 2}), "range:slots"),  # eliminated actor
        (body(slots={"w/0": 1}), "type:slots"),
        (body(eliminated=[0, 0, 1]), "type:eliminated"),
        (body(survivor=2), "range:survivor"),
        (body(survivor=5), "range:survivor"),
        (body(returns=[1.0]), "shape:returns"),
        (body(reason=7), "type:reason"),
    ]
    for payload, reason in cases:
        assert reason_of(lambda: Allocation.from_bytes(payload, n_actors=K)) == reason


def test_eval_stats_done_rejections():
    def ev(**changes):
        msg = decode(make_eval().to_bytes("referee", 0))
        msg.update(changes)
        return raw(msg)

    assert reason_of(lambda: Eval.from_bytes(ev(mean=[1.5, None, None]))) == "range:mean"
    assert reason_of(lambda: Eval.from_bytes(ev(returns=[[1.0], [float("inf")], []]))) == "not_finite:returns"
    assert reason_of(lambda: Eval.from_bytes(ev(versions=[1, 2]))) == "shape:versions"
    assert reason_of(lambda: Eval.from_bytes(ev(bias={"x": {"nested": 1}}))) == "type:bias"
    assert reason_of(lambda: Eval.from_bytes(ev(), n_actors=2)) == "shape:returns"

    def st(**changes):
        msg = decode(make_stats().to_bytes("learner", 0))
        msg.update(changes)
        return raw(msg)

    assert reason_of(lambda: LearnerStats.from_bytes(st(env_steps=-1))) == "range:env_steps"
    assert reason_of(lambda: LearnerStats.from_bytes(st(per_worker={"w0": {"received": 1}}))) == "missing:last_seq"
    assert reason_of(lambda: LearnerStats.from_bytes(st(done=1))) == "type:done"
    assert reason_of(lambda: LearnerStats.from_bytes(st(losses=[1.0]))) == "type:losses"
    assert reason_of(lambda: LearnerStats.from_bytes(st(rejected={"x": -1}))) == "range:x"
    bad_pw = {"w0": {"received": 1, "last_seq": 0, "rate": float("nan")}}
    assert reason_of(lambda: LearnerStats.from_bytes(st(per_worker=bad_pw))) == "not_finite:per_worker"
    bad_pw = {"w0": {"received": 1, "last_seq": 0, "x": [1]}}
    assert reason_of(lambda: LearnerStats.from_bytes(st(per_worker=bad_pw))) == "type:per_worker"
    assert reason_of(lambda: LearnerStats.from_bytes(st(live=[1, 0]))) == "type:live"
    assert reason_of(lambda: LearnerStats.from_bytes(st(workers=-1))) == "range:workers"
    done = decode(Done("budget", 1, 1).to_bytes("learner", 0))
    assert reason_of(lambda: Done.from_bytes(raw({**done, "updates": None}))) == "type:updates"


# --------------------------------------------------------------------------- fuzz


def _mutations(rng: random.Random, payload: bytes) -> bytes:
    b = bytearray(payload)
    op = rng.randrange(6)
    if op == 0:  # flip bytes
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] = rng.randrange(256)
    elif op == 1:  # truncate
        b = b[: rng.randrange(len(b))]
    elif op == 2:  # insert junk
        i = rng.randrange(len(b))
        b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    elif op == 3:  # pure noise
        b = bytearray(rng.randrange(256) for _ in range(rng.randint(0, 300)))
    elif op == 4:  # noise after a map header
        b = bytearray(b[:1] + bytes(rng.randrange(256) for _ in range(rng.randint(0, 300))))
    else:  # delete a slice
        i = rng.randrange(len(b))
        del b[i : i + rng.randint(1, 32)]
    return bytes(b)


_ODD_VALUES = [None, -1, 0, 1 << 62, -(1 << 62), 1.5, float("nan"), float("inf"), "", "x" * 300, True,
               [], [1, 2], {}, {"a": 1}, b"bytes", np.zeros(3, np.float32),
               np.zeros((2, 2), np.float64), np.zeros(4, np.uint8), np.ones((8, OBS), np.float32)]


def test_fuzz_only_message_errors():
    rng = random.Random(1234)
    parsers = [
        (make_batch().to_bytes(), lambda p: TransitionBatch.from_bytes(p, SPEC)),
        (make_weights().to_bytes("l", 0), lambda p: Weights.from_bytes(p, EXPECTED_SHAPES, K)),
        (make_allocation().to_bytes("r", 0), lambda p: Allocation.from_bytes(p, K)),
        (make_eval().to_bytes("r", 0), lambda p: Eval.from_bytes(p, K)),
        (make_stats().to_bytes("l", 0), LearnerStats.from_bytes),
        (Done("x", 1, 1).to_bytes("l", 0), Done.from_bytes),
    ]
    outcomes = {"ok": 0, "rejected": 0}
    for i in range(2000):
        good, parse = parsers[i % len(parsers)]
        if i % 2:
            payload = _mutations(rng, good)
        else:  # structurally valid msgpack with one field replaced, added or removed
            msg = decode(good)
            key = rng.choice(sorted(msg))
            r = rng.random()
            if r < 0.15:
                del msg[key]
            elif r < 0.3:
                msg[f"extra{i}"] = rng.choice(_ODD_VALUES)
            else:
                msg[key] = rng.choice(_ODD_VALUES)
            payload = raw(msg)
        try:
            parse(payload)
            outcomes["ok"] += 1
        except MessageError as e:
            assert e.reason
            outcomes["rejected"] += 1
    assert outcomes["rejected"] > 1500, outcomes


def test_codec_does_not_import_zenoh():
    code = "import sys, services.messaging.codec, services.messaging.keys; assert 'zenoh' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_resend_flag_and_acknowledgements_are_validated():
    from services.messaging.codec import LearnerStats, TransitionBatch, TransitionSpec, encode

    spec = TransitionSpec(3, 2, 2, max_rows=8, max_action=1.0)
    z = np.zeros
    batch = TransitionBatch("w0", "inc0", 4, 1, 7, z((2, 3), np.float32), z((2, 2), np.float32),
                            z(2, np.float32), z((2, 3), np.float32), z(2, np.bool_))
    assert not TransitionBatch.from_bytes(batch.to_bytes(), spec).resend
    again = TransitionBatch.from_bytes(dataclasses.replace(batch, resend=True).to_bytes(), spec)
    assert again.resend and again.batch_seq == 4
    msg = msgpack.unpackb(batch.to_bytes(), raw=False)
    msg["resend"] = 1  # not a bool
    with pytest.raises(MessageError, match="resend"):
        TransitionBatch.from_bytes(msgpack.packb(msg, use_bin_type=True), spec)
    ok = {"received": 3, "last_seq": 2, "acked_seq": 1, "acked_incarnation": "inc0"}
    body = {"env_steps": 1, "updates": 0, "accept_until": 5, "utd": 0.0, "losses": {}, "q_means": [],
            "versions": [0, 0], "per_worker": {"w0": ok}, "rejected": {}, "done": False}
    st = LearnerStats.from_bytes(encode("learner_stats", body, sender="l", seq=1))
    assert st.per_worker["w0"]["acked_seq"] == 1
    for bad in ({"acked_seq": -2, "acked_incarnation": "inc0"}, {"acked_seq": 1},
                {"acked_seq": 1, "acked_incarnation": "../x"}, {"acked_seq": "1", "acked_incarnation": "i"}):
        body["per_worker"] = {"w0": {"received": 3, "last_seq": 2, **bad}}
        with pytest.raises(MessageError):
            LearnerStats.from_bytes(encode("learner_stats", body, sender="l", seq=1))
