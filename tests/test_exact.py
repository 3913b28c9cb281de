"""Exact mode: a distributed `mam run` is the one-process Algorithm 1, bit for bit, and reruns
from its seed (services/roles/lockstep.py, mam_core/algorithm1.py)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.algorithm1 import Algorithm1
from mam_core.config import resolve
from mam_core.policy import read_policy_file
from mam_core.reference import run_reference
from mam_core.schedule import Schedule
from services.messaging import bus
from services.run.rundir import read_jsonl
from tests.e2e import (
    ROOT,
    LinkProxy,
    assert_exactly_once,
    learner_iterations,
    load,
    mam,
    signal_when,
    spawn,
    stop,
    unique_run,
)

# -- a real distributed run against the reference ------------------------------------------------

APPLE = dict(hidden=(16, 16), batch_size=16, start_steps=100, compete_every=100, eliminate_at=300, workers=5,
             actors=3, eval_episodes=2, eval_every=100)
APPLE_STEPS = 450


def apple_args(run: str, run_dir: Path, seed: int) -> list[str]:
    """`mam run`'s flags for APPLE, APPLE_STEPS iterations of AppleCollect-v1 MA-DDPG."""
    return ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(APPLE_STEPS), "--workers", "5",
            "--actors", "3", "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300",
            "--eval-episodes", "2", "--eval-every", "100", "--hidden", "16,16", "--batch-size", "16",
            "--seed", str(seed), "--run", run, "--run-dir", str(run_dir)]


def _mam_run(tmp: Path, name: str, seed: int, *extra: str) -> Path:
    run_dir = tmp / name
    mam("run", *apple_args(unique_run(name), run_dir, seed), *extra, timeout=240)
    return run_dir


def _record(run_dir: Path) -> dict:
    meta, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    return {"evals": [(e["iterations"], e["purpose"], e["returns"]) for e in read_jsonl(run_dir / "eval.jsonl")],
            "slots": [a["slots"] for a in read_jsonl(run_dir / "allocation.jsonl")],
            "summary": json.loads((run_dir / "summary.json").read_text()), "params": params}


def _same_params(a: list[dict[str, np.ndarray]], b: list[dict[str, np.ndarray]]) -> bool:
    return len(a) == len(b) and all(set(x) == set(y) and all(np.array_equal(x[n], y[n]) for n in x)
                                    for x, y in zip(a, b))


def _equals_reference(record: dict, ref) -> None:
    assert record["evals"] == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert record["slots"] == [{f"w{i}": k for i, k in enumerate(a["slots"])} for a in ref.allocations]
    assert record["slots"][-1] == {"w0": ref.survivor}  # after C the survivor runs slot 0 alone
    assert record["summary"]["survivor"] == ref.survivor
    assert _same_params(record["params"], ref.policy)  # np.array_equal, every actor, every layer


def test_mam_run_equals_the_reference_at_lag_0_and_2(tmp_path: Path) -> None:
    """Lag 0 is Algorithm 1 as printed; lag 2 another deterministic run of the same seed. Each
    distributed run equals the one-process reference with its lag, bit for bit (the reference
    is deterministic, so each reruns from its seed), and the two lags differ."""
    torch.set_num_threads(1)  # the learner's default (learner_threads = 1): the same float sums
    first_dir = _mam_run(tmp_path, "exact-a", seed=3)
    first = _record(first_dir)
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS)
    assert first["summary"]["exact"] is True and first["summary"]["lag"] == 0
    _equals_reference(first, ref)
    plan = Algorithm1.for_run(resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS)  # the referee's events are the plan's
    assert [(i, p) for i, p, _ in first["evals"]] == [(plan.iteration(i).units[1], p) for i, p in plan.events()]
    # A worker holds the versions of its next iterations only: slots 1-4, idle after C, held every
    # version published after it (150 here, over 10 GiB in a 100k-iteration HalfCheetah run).
    held = {r["worker"]: r["weights_held_max"] for r in map(json.loads, map(Path.read_text,
                                                                          (first_dir / "workers").glob("*.json")))}
    assert sorted(held) == [f"w{i}" for i in range(5)]
    assert max(held.values()) <= APPLE["actors"] * 2, held
    # ... and, once past its last step, receives none (it unsubscribes): fewer than w0, which steps to the end
    got = {r["worker"]: r["weights_received"] for r in map(json.loads, map(Path.read_text,
                                                                          (first_dir / "workers").glob("*.json")))}
    assert all(got[f"w{i}"] < got["w0"] for i in range(1, 5)), got

    # At lag 2 the slots step ahead of the learner, two by two in one loop of a worker process
    # (`--slots-per-worker 2`: slots 0-1, 2-3 and 4 in three processes): the same run as a process a slot
    lagged_dir = _mam_run(tmp_path, "exact-lag2", 3, "--lag", "2", "--slots-per-worker", "2")
    lagged = _record(lagged_dir)
    ref2 = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, lag=2, **APPLE), APPLE_STEPS)
    assert lagged["summary"]["exact"] is True and lagged["summary"]["lag"] == 2
    _equals_reference(lagged, ref2)
    assert sorted(p.name for p in (lagged_dir / "logs").glob("worker-*.log")) == \
        ["worker-0.log", "worker-2.log", "worker-4.log"]
    assert sorted(json.loads(p.read_text())["worker"] for p in (lagged_dir / "workers").glob("*.json")) == \
        [f"w{i}" for i in range(5)]  # each slot its own worker id and report
    assert not _same_params(lagged["params"], first["params"])

    other = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=4, **APPLE), APPLE_STEPS)
    assert not _same_params(other.policy, first["params"])
    assert [e["returns"] for e in other.evaluations] != [e[2] for e in first["evals"]] or \
        [a["slots"] for a in other.allocations] != [a["slots"] for a in ref.allocations]


def test_reference_driver_is_deterministic_and_k1_needs_no_referee_rounds():
    cfg = resolve("td3", hidden=(16, 16), batch_size=16, start_steps=50, eval_episodes=1, eval_every=100, seed=1)
    a = run_reference("Pendulum-v1", cfg, 200)
    b = run_reference("Pendulum-v1", dataclasses.replace(cfg), 200)
    assert _same_params(a.policy, b.policy)
    assert [row["purpose"] for row in a.evaluations] == ["curve", "curve"]  # no round without K > 1
    assert a.updates == 150 and a.survivor is None


# -- slow: MuJoCo, a killed and a paused worker ---------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_hopper_at_lag_1_through_every_fault_equals_the_reference(tmp_path: Path) -> None:
    """MuJoCo (Hopper-v5, whose episodes end early and often), MA-TD3 at lag 1, under `mam run`:
    a worker SIGKILLed, then the learner, then the referee (each restarted by the launcher), then
    another worker SIGSTOPped past its liveliness lease. The run is still the seed's: equal to
    the one-process reference in every evaluation and every policy array."""
    torch.set_num_threads(1)
    run_dir, name = tmp_path / "hopper", unique_run("hopper")
    args = ["--env", "Hopper-v5", "--algo", "ma-td3", "--lag", "1", "--steps", "3000", "--workers", "3",
            "--start-steps", "200", "--compete-every", "500", "--eliminate-at", "2000", "--eval-episodes", "1",
            "--eval-every", "1000", "--hidden", "32,32", "--batch-size", "32", "--seed", "5",
            "--checkpoint-seconds", "1", "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    faults = [(300, f"services.roles.worker --run {name} .*--id w1 ", signal.SIGKILL),
              (300, f"services.roles.learner .*{run_dir}", signal.SIGKILL),
              (300, f"services.roles.referee --run {name} ", signal.SIGKILL),
              (200, f"services.roles.worker --run {name} .*--id w2 ", signal.SIGSTOP)]
    try:
        for after, pattern, sig in faults:  # each once the run has gone `after` iterations further
            pid = signal_when(run_dir, pattern, learner_iterations(run_dir) + after, sig, proc)
            assert learner_iterations(run_dir) < 2900, f"too late for {pattern}"
            if sig == signal.SIGSTOP:
                time.sleep(12.0)
                os.kill(pid, signal.SIGCONT)
        out, _ = proc.communicate(timeout=400)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-3000:]
    got = _record(run_dir)
    assert got["summary"]["restarts_total"] == 3 and got["summary"]["exact"] is True, got["summary"]
    cfg = resolve("ma-td3", lag=1, workers=3, start_steps=200, compete_every=500, eliminate_at=2000, eval_episodes=1,
                  eval_every=1000, hidden=(32, 32), batch_size=32, seed=5)
    ref = run_reference("Hopper-v5", cfg, 3000)
    assert got["evals"] == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert got["summary"]["survivor"] == ref.survivor
    assert _same_params(got["params"], ref.policy)


@pytest.mark.slow
def test_a_killed_worker_is_rebuilt_and_the_run_stays_exact(tmp_path: Path) -> None:
    """`mam run` restarts a SIGKILLed worker process, here one stepping slots 0 and 1 in one loop
    (`--slots-per-worker 2`); the new one rebuilds both slots from their current episodes
    (services/roles/takeover.py): the run equals the reference."""
    run_dir, name = tmp_path / "killed", unique_run("killed")
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", "3000", "--workers", "3", "--actors", "2",
            "--start-steps", "200", "--compete-every", "500", "--eliminate-at", "2000", "--eval-episodes", "2",
            "--eval-every", "500", "--hidden", "16,16", "--batch-size", "16", "--seed", "2", "--run", name,
            "--run-dir", str(run_dir), "--slots-per-worker", "2"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:  # a worker whose rows are in the replay
        signal_when(run_dir, f"services.roles.worker --run {name} .*--id w0,w1 --slot 0,1 ", 300, signal.SIGKILL, proc)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    record = _record(run_dir)
    summary = record["summary"]
    assert summary["exact"] is True and summary["restarts_total"] == 1, summary
    cfg = resolve("ma-ddpg", workers=3, actors=2, start_steps=200, compete_every=500, eliminate_at=2000,
                  eval_episodes=2, eval_every=500, hidden=(16, 16), batch_size=16, seed=2)
    assert summary["env_steps"] == Schedule.for_run(cfg, 3000).budget
    _equals_reference(record, run_reference("AppleCollect-v1", cfg, 3000))


def test_the_lag_bench_counts_the_learners_wait_over_its_training_part():
    from mam_lab.bench_lag import wait_share

    rows = [{"t": 1.0, "env_steps": 300, "updates": 0, "exact_wait_s": 0.9},  # the random phase: not counted
            {"t": 2.0, "env_steps": 600, "updates": 10, "exact_wait_s": 1.0},
            {"t": 6.0, "env_steps": 1000, "updates": 210, "exact_wait_s": 2.0}]
    assert wait_share(rows) == 0.25
    assert math.isnan(wait_share(rows[:2]))


@pytest.mark.slow
def test_a_paused_worker_is_not_a_fault_the_run_stays_exact(tmp_path: Path) -> None:
    """A worker SIGSTOPped for 40 s (four times its 10 s liveliness lease: to the others it is gone), then
    resumed: it is still its slot's owner, the run waits for it and then goes on, and it equals the
    one-process reference bit for bit."""
    run_dir, name = tmp_path / "paused", unique_run("paused")
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(APPLE_STEPS), "--workers", "5",
            "--actors", "3", "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300",
            "--eval-episodes", "2", "--eval-every", "100", "--hidden", "16,16", "--batch-size", "16", "--seed", "3",
            "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        victim = signal_when(run_dir, f"services.roles.worker --run {name} .*--id w1 ", 50, signal.SIGSTOP, proc)
        time.sleep(40.0)
        os.kill(victim, signal.SIGCONT)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    record = _record(run_dir)
    assert record["summary"]["exact"] is True, record["summary"]
    assert record["summary"]["restarts_total"] == 0, record["summary"]["restarts"]
    _equals_reference(record, run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS))


@pytest.mark.slow
def test_a_batch_lost_in_flight_is_sent_again_and_the_run_stays_exact(tmp_path: Path) -> None:
    """Worker w1 reaches the learner through a proxy that drops what w1 sends for 3 s, then cuts
    the link: a batch is lost without an error on either side (a worker frozen past its lease
    loses its first batch after it so). The learner waits for that iteration of slot 1; w1
    sees it wait and sends its kept batches from there again (services/roles/kept.py). The run
    finishes without a restart, exactly once, and equals the reference bit for bit. Before
    the resend, the learner waited until `mam run`'s stall watchdog killed w1 (300 s)."""
    run_dir, name = tmp_path / "lost", unique_run("lost")
    port = bus.free_tcp_port()
    endpoint, proxy = bus.loopback_endpoint(port), LinkProxy(port)
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(APPLE_STEPS), "--workers", "5",
            "--actors", "3", "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300",
            "--eval-episodes", "2", "--eval-every", "100", "--hidden", "16,16", "--batch-size", "16", "--seed", "3"]
    rd = ["--run", name, "--run-dir", str(run_dir)]
    learner = spawn("learner", *args, *rd, "--listen", endpoint, log=tmp_path / "learner.log")
    others = [spawn("referee", *rd, "--connect", endpoint, log=tmp_path / "referee.log")]
    for i in range(5):
        via = f"tcp/127.0.0.1:{proxy.port}" if i == 1 else endpoint
        others.append(spawn("worker", *rd, "--connect", via, "--id", f"w{i}", "--slot", str(i),
                            log=tmp_path / f"w{i}.log"))
    try:
        deadline = time.monotonic() + 180
        while learner_iterations(run_dir) < 150:  # lockstep: w1 sends a row, then waits for the next version
            assert time.monotonic() < deadline and learner.poll() is None, (tmp_path / "learner.log").read_text()
            time.sleep(0.2)
        proxy.blackhole()
        time.sleep(3.0)
        proxy.cut()
        learner.wait(timeout=120)  # without the resend: still waiting for slot 1
    finally:
        stop(learner, *others)
        proxy.close()
    assert learner.returncode == 0, (tmp_path / "learner.log").read_text()
    w1 = [w for w in load(run_dir)["workers"] if w["worker"] == "w1"]
    assert len(w1) == 1 and w1[0]["resends"] >= 1, w1  # one incarnation: no restart; it resent
    assert "resent" in (tmp_path / "w1.log").read_text()
    assert_exactly_once(load(run_dir))
    record = _record(run_dir)
    assert record["summary"]["exact"] is True, record["summary"]
    _equals_reference(record, run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS))


@pytest.mark.slow
def test_weights_overwritten_on_their_keys_neither_hang_nor_change_the_run(tmp_path: Path) -> None:
    """A process of the run's own (it holds the run's secret: one without it cannot even connect,
    tests/test_intruder.py) floods every weights key (and the referee's snapshot keys) with junk. Workers and
    the referee screen it out in their subscription callbacks, so it never takes the place of the
    learner's last weights in a one-per-key subscriber nor fills the referee's snapshot queue (the
    learner's re-sends of late weights stay as the fallback for a sample lost anyway): the run
    finishes at its usual pace and is still exactly the reference run."""
    from services.messaging import bus, keys

    torch.set_num_threads(1)
    run, run_dir = unique_run("clobber"), tmp_path / "clobber"
    args = [*apple_args(run, run_dir, 3), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONWARNINGS="ignore"))
    sent = 0
    try:
        deadline = time.monotonic() + 60
        while not (run_dir / "config.json").is_file() or not json.loads((run_dir / "config.json").read_text()).get(
                "endpoint"):
            assert proc.poll() is None and time.monotonic() < deadline, "mam run did not start"
            time.sleep(0.1)
        endpoint = json.loads((run_dir / "config.json").read_text())["endpoint"]
        insider = bus.make_config(connect=[endpoint], auth_file=run_dir / "zenoh-auth")
        with bus.session_scope(insider, retry_for=30) as session:
            targets = [keys.weights(run, k) for k in range(3)] + [keys.eval_weights(run, k) for k in range(3)]
            pubs = [session.declare_publisher(key) for key in targets]
            deadline = time.monotonic() + 240
            while proc.poll() is None:
                assert time.monotonic() < deadline, "the run hung"
                for pub in pubs:
                    pub.put(b"\x93junk")
                    sent += 1
                time.sleep(0.002)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    assert proc.returncode == 0 and sent > 1000
    got = _record(run_dir)
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS)
    assert got["summary"]["exact"] is True
    assert got["evals"] == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert _same_params(got["params"], ref.policy)
