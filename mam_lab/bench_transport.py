"""`mam bench` transport pieces: transitions/s from M publisher processes into a learner-like
consumer, the latency of a weights broadcast, and a profile of one worker step. The publisher
and subscriber processes re-enter this module through `python -c`: it imports torch and the
services lazily, so such a process starts in ~0.2 s."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import time
import uuid
from typing import Any, Callable

import numpy as np

from mam_lab.bench_sizes import ROOT, SHAPES, BenchSizes, child_env, median, percentile, python_c, stop_children

WEIGHTS_WARMUP = 3  # broadcasts not counted in the latency figures


def publisher_process(argv: list[str] | None = None) -> None:
    """Worker-like publisher (a child process): `batches` TransitionBatch messages of `rows`
    HalfCheetah-shaped rows, encoded one by one and put RELIABLE + BLOCK as fast as allowed."""
    from services.messaging import bus, keys
    from services.messaging.codec import TransitionBatch

    endpoint, run, wid, batches, rows, obs_dim, act_dim = (argv or sys.argv[1:])[:7]
    batches, rows, obs_dim, act_dim = int(batches), int(rows), int(obs_dim), int(act_dim)
    rng = np.random.default_rng(abs(hash(wid)) % 2**32)
    variants = [(rng.normal(size=(rows, obs_dim)).astype(np.float32),
                 rng.uniform(-1, 1, (rows, act_dim)).astype(np.float32),
                 rng.normal(size=rows).astype(np.float32),
                 rng.normal(size=(rows, obs_dim)).astype(np.float32),
                 rng.random(rows) < 0.01) for _ in range(8)]
    incarnation = uuid.uuid4().hex[:12]
    with bus.session_scope(bus.make_config(connect=[endpoint]), retry_for=30.0) as session:
        pub = bus.declare_reliable_publisher(session, keys.transitions(run, wid))
        deadline = time.monotonic() + 30.0
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        for seq in range(batches):
            o, a, r, o2, d = variants[seq % len(variants)]
            pub.put(TransitionBatch(wid, incarnation, seq, 0, -1, o, a, r, o2, d).to_bytes())
        time.sleep(1.0)  # the last puts before close can be lost (docs/ZENOH-NOTES.md): let them drain
        pub.undeclare()


def bench_transport(sizes: BenchSizes, log: Callable[[str], None] = print,
                    obs_dim: int = 17, act_dim: int = 6) -> dict[str, Any]:
    """Transitions/s into a learner-like consumer from M publisher processes over loopback."""
    from mam_core.replay import ReplayBuffer
    from services.messaging import bus, keys
    from services.messaging.codec import TransitionBatch, TransitionSpec

    m, per, rows = sizes.transport_publishers, sizes.transport_batches, sizes.transport_rows
    log(f"transport: {m} publisher process(es) x {per} messages of {rows} transitions -> Inbox, decode, replay")
    run = f"bench-tx-{uuid.uuid4().hex[:8]}"
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    spec = TransitionSpec(obs_dim, act_dim, 1, max_rows=4096, max_action=1.0)
    expected = m * per * rows
    buffer = ReplayBuffer(expected, obs_dim, act_dim)
    tracker = bus.SequenceTracker()
    procs: list[subprocess.Popen] = []
    code = "import sys; from mam_lab.bench_transport import publisher_process; publisher_process(sys.argv[1:])"
    received = payload_bytes = messages = 0
    t_first = t_last = 0.0
    rows_first = 0
    with bus.session_scope(bus.make_config(listen=[endpoint])) as session:
        inbox = bus.Inbox(maxsize=8192).subscribe(session, keys.transitions_all(run))
        try:
            for i in range(m):
                procs.append(subprocess.Popen(
                    python_c(code, endpoint, run, f"p{i}", str(per), str(rows), str(obs_dim), str(act_dim)),
                    cwd=ROOT, env=child_env(), stdin=subprocess.DEVNULL, start_new_session=True))
            idle_deadline = time.monotonic() + sizes.timeout_s
            while received < expected and time.monotonic() < idle_deadline:
                items = inbox.drain(256)
                if not items:
                    item = inbox.get(timeout=0.5)
                    if item is None:
                        if any(p.poll() not in (None, 0) for p in procs):
                            raise RuntimeError("a publisher process failed")
                        continue
                    items = [item]
                for item in items:
                    batch = TransitionBatch.from_bytes(item.payload, spec)
                    tracker.observe(batch.worker, batch.incarnation, batch.batch_seq)
                    buffer.add_batch(batch.obs, batch.action, batch.reward, batch.next_obs, batch.terminated,
                                     actor=batch.actor, version=batch.version)
                    if messages == 0:
                        t_first, rows_first = time.perf_counter(), batch.rows
                    received += batch.rows
                    payload_bytes += len(item.payload)
                    messages += 1
                t_last = time.perf_counter()
                idle_deadline = time.monotonic() + 10.0
        finally:
            dropped = inbox.dropped
            inbox.close()
            stop_children(procs)
    if received == 0:
        raise RuntimeError("no transition arrived")
    span = max(t_last - t_first, 1e-9)
    return {
        "transport_publishers": m, "transport_rows_per_message": rows,
        "transport_transitions_per_s": (received - rows_first) / span if messages > 1 else float("nan"),
        "transport_messages_per_s": (messages - 1) / span if messages > 1 else float("nan"),
        "transport_received": received, "transport_expected": expected,
        "transport_lost": tracker.lost + (expected - received), "transport_inbox_dropped": dropped,
        "transport_bytes_per_transition": payload_bytes / received,
    }


def weights_subscriber_process(argv: list[str] | None = None) -> None:
    """Worker-like weights subscriber (a child process): on every new weights sample, decode,
    validate against the actor's shapes and load it; print the latencies as JSON."""
    import torch

    from mam_core.ensemble import ActorEnsemble
    from services.messaging import bus, keys
    from services.messaging.codec import Weights

    endpoint, run, obs_dim, act_dim, hidden, count, warmup = (argv or sys.argv[1:])[:7]
    obs_dim, act_dim, count, warmup = int(obs_dim), int(act_dim), int(count), int(warmup)
    hidden_t = tuple(int(h) for h in hidden.split(","))
    torch.set_num_threads(1)
    actors = ActorEnsemble(1, obs_dim, act_dim, hidden_t, 1.0).requires_grad_(False)
    shapes = actors.net.member_shapes()
    latencies: list[float] = []
    with bus.session_scope(bus.make_config(connect=[endpoint]), retry_for=30.0) as session:
        latest = bus.Latest.subscribe(session, keys.weights_all(run))
        token = bus.declare_alive(session, run, "worker", "latency")
        deadline = time.monotonic() + 120.0
        last_version = 0
        while last_version < warmup + count and time.monotonic() < deadline:
            if not latest.wait_fresh(timeout=0.5):
                continue
            for item in latest.fresh().values():
                w = Weights.from_bytes(item.payload, shapes, 1)
                actors.net.load_member(0, w.params)
                done = time.perf_counter()  # CLOCK_MONOTONIC: one clock for every process on the host
                if w.version > last_version and item.attachment is not None:
                    (sent,) = struct.unpack("<d", item.attachment)
                    if w.version > warmup:  # the first broadcasts also set up routes and caches
                        latencies.append((done - sent) * 1e3)
                    last_version = w.version
        token.undeclare()
        latest.close()
    print(json.dumps({"latencies_ms": latencies}), flush=True)


def bench_weights(sizes: BenchSizes, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Latency of one weights broadcast: learner-side `actor_params` + encode + put, to decoded,
    validated and loaded in a worker-like subscriber process. Per actor size."""
    import torch

    from mam_core.ensemble import ActorEnsemble
    from services.messaging import bus, keys
    from services.messaging.codec import Weights

    out: dict[str, Any] = {}
    code = ("import sys; from mam_lab.bench_transport import weights_subscriber_process; "
            "weights_subscriber_process(sys.argv[1:])")
    for shape in ("halfcheetah", "humanoid"):
        obs_dim, act_dim, max_action = SHAPES[shape]
        hidden = sizes.weights_hidden
        log(f"weights: {shape} actor ({obs_dim}->{'x'.join(map(str, hidden))}->{act_dim}), "
            f"{sizes.weights_messages} broadcasts")
        run = f"bench-w-{uuid.uuid4().hex[:8]}"
        endpoint = bus.loopback_endpoint(bus.free_tcp_port())
        torch.set_num_threads(1)
        actor = ActorEnsemble(1, obs_dim, act_dim, hidden, max_action).requires_grad_(False)
        encode_ms: list[float] = []
        size = 0
        with bus.session_scope(bus.make_config(listen=[endpoint])) as session:
            pub = bus.declare_latest_publisher(session, keys.weights(run, 0))
            alive = bus.watch_alive(session, run, "worker")
            proc = subprocess.Popen(python_c(code, endpoint, run, str(obs_dim), str(act_dim),
                                              ",".join(map(str, hidden)), str(sizes.weights_messages),
                                              str(WEIGHTS_WARMUP)),
                                    cwd=ROOT, env=child_env(), stdout=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                    start_new_session=True)
            try:
                if not alive.wait_for(lambda ids: "latency" in ids, timeout=60.0):
                    raise RuntimeError("the weights subscriber did not come up")
                time.sleep(0.2)
                for version in range(1, WEIGHTS_WARMUP + sizes.weights_messages + 1):
                    t0 = time.perf_counter()
                    params = actor.net.member_state(0)  # the learner's actor_params(k)
                    msg = Weights(0, version, params, obs_dim, act_dim, max_action, hidden)
                    payload = msg.to_bytes("bench", version)
                    if version > WEIGHTS_WARMUP:
                        encode_ms.append((time.perf_counter() - t0) * 1e3)
                    size = len(payload)
                    pub.put(payload, attachment=struct.pack("<d", t0))
                    time.sleep(sizes.weights_interval_s)
                stdout, _ = proc.communicate(timeout=60.0)
            finally:
                alive.close()
                stop_children([proc])
        lat = json.loads(stdout.decode().strip().splitlines()[-1])["latencies_ms"]
        if not lat:
            raise RuntimeError(f"no weights latency measured for {shape}")
        out[f"weights_{shape}_p50_ms"] = percentile(lat, 50)
        out[f"weights_{shape}_p99_ms"] = percentile(lat, 99)
        out[f"weights_{shape}_encode_ms"] = median(encode_ms)
        out[f"weights_{shape}_bytes"] = size
        out[f"weights_{shape}_samples"] = len(lat)
    out["weights_latency_p50_ms"] = max(out["weights_halfcheetah_p50_ms"], out["weights_humanoid_p50_ms"])
    out["weights_latency_p99_ms"] = max(out["weights_halfcheetah_p99_ms"], out["weights_humanoid_p99_ms"])
    return out


# --------------------------------------------------------------------------- profile


def profile_worker_step(env_id: str = "HalfCheetah-v5", steps: int = 2000, hidden: tuple[int, ...] = (256, 256),
                        send_batch: int = 32) -> dict[str, float]:
    """Where one worker step goes: env.step, the 1-row policy forward (as the worker runs it,
    numpy `NumpyActors`, and as it ran before, a torch forward), encoding and publishing (µs per
    transition).
    Publishing goes to a subscriber of the same session (no network). The two policy paths
    alternate by episode chunk so both see the same cache state after MuJoCo's step."""
    import gymnasium as gym
    import torch

    import mam_core.envs  # noqa: F401
    from mam_core.ensemble import ActorEnsemble
    from mam_core.policy import EnvSpec, NumpyActors
    from services.messaging import bus
    from services.messaging.codec import TransitionBatch

    torch.set_num_threads(1)
    env = gym.make(env_id)
    spec = EnvSpec.from_env(env)
    max_a = np.asarray(spec.max_action, np.float32)
    actors = ActorEnsemble(1, spec.obs_dim, spec.act_dim, hidden, max_a).requires_grad_(False)
    members = torch.tensor([0])
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    numpy_actors = NumpyActors(1, spec, hidden)
    numpy_actors.load_member(0, actors.net.member_state(0))
    numpy_policy = numpy_actors.policy(0)
    t_env = t_pol = t_np = t_enc = t_pub = 0.0
    n_torch = n_np = 0
    buf_o = np.empty((send_batch, spec.obs_dim), np.float32)
    buf_a = np.empty((send_batch, spec.act_dim), np.float32)
    buf_r = np.empty(send_batch, np.float32)
    buf_o2 = np.empty((send_batch, spec.obs_dim), np.float32)
    buf_d = np.empty(send_batch, np.bool_)
    with bus.session_scope(bus.make_config()) as session:
        inbox = bus.Inbox(maxsize=1 << 16).subscribe(session, "mam/bench-profile/transitions/*")
        pub = bus.declare_reliable_publisher(session, "mam/bench-profile/transitions/w0")
        n = 0
        for t in range(steps):
            use_torch = (t // 100) % 2 == 0
            t0 = time.perf_counter()
            if use_torch:  # services.roles.worker's forward before it dropped torch
                with torch.inference_mode():
                    a = actors(torch.from_numpy(np.asarray(obs, np.float32)).view(1, -1), members=members)[0, 0].numpy()
            else:
                a = numpy_policy(obs)
            t1 = time.perf_counter()
            a = np.clip(a + rng.normal(0, 0.1, spec.act_dim).astype(np.float32) * max_a, -max_a, max_a)
            next_obs, r, term, trunc, _ = env.step(a)
            t2 = time.perf_counter()
            buf_o[n], buf_a[n], buf_r[n], buf_o2[n], buf_d[n] = obs, a, r, next_obs, term
            n += 1
            obs = env.reset()[0] if term or trunc else next_obs
            if use_torch:
                t_pol, n_torch = t_pol + t1 - t0, n_torch + 1
            else:
                t_np, n_np = t_np + t1 - t0, n_np + 1
            t_env += t2 - t1
            if n == send_batch:
                t3 = time.perf_counter()
                payload = TransitionBatch("w0", "profile", t // send_batch, 0, 0, buf_o, buf_a, buf_r, buf_o2,
                                          buf_d).to_bytes()
                t4 = time.perf_counter()
                pub.put(payload)
                t5 = time.perf_counter()
                t_enc += t4 - t3
                t_pub += t5 - t4
                n = 0
                inbox.drain()
        inbox.close()
    env.close()
    us = 1e6 / steps
    torch_us, numpy_us = t_pol * 1e6 / max(n_torch, 1), t_np * 1e6 / max(n_np, 1)
    rest = (t_env + t_enc + t_pub) * us
    return {"env.step (+ noise, clip)": t_env * us, "policy forward, torch (the worker before numpy)": torch_us,
            "policy forward, numpy (NumpyActors)": numpy_us, "encode (per transition)": t_enc * us,
            "publish (per transition)": t_pub * us, "total with the torch forward": rest + torch_us,
            "total with the numpy forward": rest + numpy_us}
