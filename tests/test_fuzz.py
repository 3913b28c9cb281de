"""Hostile input while a run goes on: malformed messages on every topic each role subscribes to."""

from __future__ import annotations

import re
import time
from collections import Counter
from pathlib import Path

import msgpack
import numpy as np
import pytest

from services.messaging import bus, keys
from services.messaging.codec import (
    SCHEMA_VERSION,
    Allocation,
    Done,
    Eval,
    LearnerStats,
    TransitionBatch,
    Weights,
    decode,
    encode,
)
from tests.e2e import assert_exactly_once, load, processes_of, spawn, stop, unique_run

PER_TOPIC = 10_000
OBS, ACT, K = 2, 2, 3  # AppleCollect-v0, ma-ddpg


def valid_messages(run: str) -> dict[str, bytes]:
    """One well-formed message per topic: the raw material that gets broken."""
    rows = 4
    batch = TransitionBatch("w0", "fuzzinc", 0, 0, 0, np.zeros((rows, OBS), np.float32),
                            np.zeros((rows, ACT), np.float32), np.zeros(rows, np.float32),
                            np.zeros((rows, OBS), np.float32), np.zeros(rows, bool))
    params = {"w0": np.zeros((OBS, 32), np.float32), "b0": np.zeros((1, 32), np.float32),
              "w1": np.zeros((32, 32), np.float32), "b1": np.zeros((1, 32), np.float32),
              "w2": np.zeros((32, ACT), np.float32), "b2": np.zeros((1, ACT), np.float32)}
    return {
        keys.transitions(run, "w0"): batch.to_bytes(),
        keys.transitions(run, "intruder"): batch.to_bytes(),
        keys.weights(run, 0): Weights(0, 1, params, OBS, ACT, 0.2, (32, 32)).to_bytes("x", 1),
        keys.allocation(run): Allocation(1, 0, None, (1 / 3,) * 3, (1, 0, 0), {"w0": 0}, (False,) * 3, None,
                                         "round").to_bytes("x", 1),
        keys.learner_stats(run): LearnerStats(0, 0, 0, 0.0).to_bytes("x", 1),
        keys.eval(run): Eval(1, 0, ((1.0,), (1.0,), (1.0,)), (1.0, 1.0, 1.0), (0, 0, 0)).to_bytes("x", 1),
        keys.config(run): encode("config", {"config": {"run": run}}, sender="x", seq=1),
        keys.done(run): Done("budget", 0, 0).to_bytes("x", 1),
    }


def mutate(payload: bytes, rng: np.random.Generator, i: int) -> bytes:
    """The i-th malformed variant: a cycle over the ways a message can be broken."""
    msg = decode(payload)
    kind = i % 12
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 400)))
    if kind == 1:
        return payload[: int(rng.integers(1, max(len(payload) - 1, 2)))]
    if kind == 2:  # the same message with another schema version (arrays kept as raw ext types)
        raw = msgpack.unpackb(payload, strict_map_key=False)
        return msgpack.packb({**raw, "v": 99})
    if kind == 3:  # a required field missing
        drop = sorted(k for k in msg if k not in ("v", "kind", "sender", "seq", "t"))[i % max(len(msg) - 5, 1)]
        body = {k: v for k, v in msg.items() if k not in ("v", "kind", "sender", "seq", "t", drop)}
        return encode(msg["kind"], body, sender="w0", seq=i)
    if kind == 4:  # arrays of the wrong shape
        body = {k: (np.zeros((3, 7), np.float32) if isinstance(v, np.ndarray) else v) for k, v in msg.items()
                if k not in ("v", "kind", "sender", "seq", "t")}
        return encode(msg["kind"], body, sender="w0", seq=i)
    if kind == 5:  # wrong dtypes
        body = {k: (v.astype(np.float64) if isinstance(v, np.ndarray) else v) for k, v in msg.items()
                if k not in ("v", "kind", "sender", "seq", "t")}
        return encode(msg["kind"], body, sender="w0", seq=i)
    if kind == 6:  # NaN / inf in every array and float
        def poison(v):
            if isinstance(v, np.ndarray) and v.dtype.kind == "f":
                out = np.array(v)
                out.flat[0] = np.nan if i % 2 else np.inf
                return out
            return float("nan") if isinstance(v, float) else v
        body = {k: poison(v) for k, v in msg.items() if k not in ("v", "kind", "sender", "seq", "t")}
        body["probabilities"] = [float("nan")] * 3 if "probabilities" in body else None
        return encode(msg["kind"], {k: v for k, v in body.items() if v is not None}, sender="w0", seq=i)
    if kind == 7:  # an enormous array claimed by the header, with few bytes behind it
        header = b"\x07float32\x02" + (10**9).to_bytes(8, "little") + (10**3).to_bytes(8, "little")
        raw = msgpack.unpackb(payload, strict_map_key=False)
        raw["obs"] = msgpack.ExtType(1, header + b"\0" * 64)
        return msgpack.packb(raw)
    if kind == 8:  # unknown actor ids
        body = {k: v for k, v in msg.items() if k not in ("v", "kind", "sender", "seq", "t")}
        for name in ("actor", "survivor"):
            if name in body:
                body[name] = 7 + i % 1000
        if "slots" in body:
            body["slots"] = {"w0": 99}
        return encode(msg["kind"], body, sender="w0", seq=i)
    if kind == 9:  # stale or future versions
        body = {k: v for k, v in msg.items() if k not in ("v", "kind", "sender", "seq", "t")}
        body["version"] = -5 if i % 2 else 10**12
        return encode(msg["kind"], body, sender="w0", seq=i)
    if kind == 10:  # valid msgpack, not a message
        return msgpack.packb([1, 2, 3] if i % 2 else "hello")
    return msgpack.packb({"v": SCHEMA_VERSION, "kind": msg["kind"], "sender": 5, "seq": "x", "t": None})


def is_valid(key: str, payload: bytes, run: str) -> bool:
    """Would the receiving role accept it? (A mutation that leaves a message valid is no fuzz.)"""
    from services.messaging.codec import MessageError, TransitionSpec
    from services.run.config import RunConfig

    try:
        if "/transitions/" in key:
            TransitionBatch.from_bytes(payload, TransitionSpec(OBS, ACT, K, max_action=0.2))
        elif "/weights/" in key:
            Weights.from_bytes(payload, None, K)
        elif key == keys.allocation(run):
            Allocation.from_bytes(payload, K)
        elif key == keys.learner_stats(run):
            LearnerStats.from_bytes(payload)
        elif key == keys.eval(run):
            Eval.from_bytes(payload, K)
        elif key == keys.config(run):
            RunConfig.from_dict(decode(payload)["config"])
        elif key == keys.done(run):
            Done.from_bytes(payload)
        return True
    except (MessageError, KeyError, TypeError, ValueError):
        return False


def malformed(key: str, payload: bytes, rng: np.random.Generator, i: int, run: str) -> bytes:
    out = mutate(payload, rng, i)
    return out if not is_valid(key, out, run) else rng.bytes(64)


@pytest.mark.slow
def test_fuzz_every_topic_while_a_run_goes_on(tmp_path: Path) -> None:
    run, endpoint = unique_run("fuzz"), bus.loopback_endpoint(bus.free_tcp_port())
    steps = 3000
    # Every malformed message is made before the run starts: sending is then quick enough to end
    # long before the budget (making them while sending took longer than the run on a loaded CI box,
    # and what arrives after the learner has finished cannot be counted by it).
    rng = np.random.default_rng(0)
    base = valid_messages(run)
    fuzz = [(key, malformed(key, payload, rng, i, run)) for i in range(PER_TOPIC) for key, payload in base.items()]
    huge = rng.bytes(70 * 1024 * 1024)  # over every size cap
    fuzz += [(keys.transitions(run, "w0"), huge), (keys.weights(run, 0), huge)]
    learner = spawn("learner", "--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--schedule", "equal-data",
                    "--steps", str(steps),
                    "--start-steps", "300", "--compete-every", "500", "--eliminate-at", "2000", "--hidden", "32,32",
                    "--batch-size", "32", "--eval-episodes", "3", "--workers", "2", "--run", run, "--listen", endpoint,
                    "--run-dir", str(tmp_path), log=tmp_path / "learner.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "referee.log")
    workers = [spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i),
                     "--run-dir", str(tmp_path), log=tmp_path / f"w{i}.log") for i in range(2)]
    sent = Counter()
    role_stats: dict[str, dict] = {}
    try:
        conf = bus.make_config(connect=[endpoint])
        with bus.session_scope(conf, retry_for=30) as s:
            stats = bus.Latest.subscribe(s, keys.stats_all(run))
            deadline = time.monotonic() + 120
            while not stats.get(keys.learner_stats(run)) or \
                    LearnerStats.from_bytes(stats.get(keys.learner_stats(run)).payload).env_steps < 400:
                assert time.monotonic() < deadline, "the run did not start"
                time.sleep(0.1)
            pubs = {key: bus.declare_reliable_publisher(s, key) for key in base}
            for key, payload in fuzz:
                pubs[key].put(payload)
                sent[key] += 1
            # The premise of the count below: the learner was still taking transitions when the last
            # malformed one was sent (stats are published several times a second).
            time.sleep(0.5)
            at_end = LearnerStats.from_bytes(stats.get(keys.learner_stats(run)).payload)
            assert at_end.env_steps < steps, "the run reached its budget before the fuzz was sent"
            deadline = time.monotonic() + 240
            while not (tmp_path / "summary.json").is_file():
                assert time.monotonic() < deadline, "the run did not finish under fuzzing"
                assert learner.poll() is None or learner.returncode == 0, "the learner died"
                time.sleep(0.2)
            for key, item in stats.snapshot().items():
                if key != keys.learner_stats(run):
                    role_stats[key] = decode(item.payload)
            stats.close()
        for p in (*workers, referee, learner):
            p.wait(60)
            assert p.returncode == 0, f"{p.args} exited {p.returncode}"
    finally:
        stop(*workers, referee, learner)
    assert all(v >= PER_TOPIC for v in sent.values()) and len(sent) == 8

    # Nothing reached the replay buffer: exactly the workers' transitions, once each.
    run_data = load(tmp_path)
    t = run_data["transport"]
    rejected = sum(t["rejected"].values())
    # Every malformed transitions message is counted: rejected, or shed by an overflowing inbox.
    assert rejected + t["inbox_dropped"] >= 2 * PER_TOPIC
    t_clean = dict(t, rejected={})
    assert_exactly_once(dict(run_data, transport=t_clean))
    assert t["env_steps"] <= steps  # lock-step: never past the plan's transitions
    # Workers and the referee counted what they rejected in the stats topic.
    worker_rejects = [sum(d["rejected"].values()) for k, d in role_stats.items() if "/stats/worker-" in k]
    referee_rejects = [sum(d["rejected"].values()) for k, d in role_stats.items() if "/stats/referee-" in k]
    assert len(worker_rejects) == 2 and min(worker_rejects) > 0
    assert len(referee_rejects) == 1 and referee_rejects[0] > 0
    # Each rejection is logged once per (sender, reason), not once per message.
    lines = re.findall(r"rejected transitions from (\S+): (\S+)", (tmp_path / "learner.log").read_text())
    assert lines and max(Counter(lines).values()) == 1
    assert run_data["summary"]["env_steps"] >= steps
    assert processes_of(run) == []
