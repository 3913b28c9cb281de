"""The distributed system end to end: real processes, real Zenoh on loopback, real envs."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from mam_core.config import resolve
from mam_core.obsolescence import allocation_probabilities
from mam_core.schedule import Schedule
from services.messaging import bus, keys
from services.messaging.codec import Allocation, Weights
from services.roles.monitor import watch
from tests.e2e import assert_exactly_once, load, mam, processes_of, spawn, stop, unique_run

SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "3"]


def check_obsolescence(run: dict, a: int, c: int, workers: int, overrun: int) -> None:
    """`overrun`: how far past its multiple of A a competition's transitions can be (an
    iteration's M transitions under equal-data, where A counts transitions)."""
    rounds = [r for r in run["allocation"] if r["reason"] in ("round", "elimination")]
    # Rounds decide at the iteration that reaches their multiple of A (or C).
    boundaries = [min(b, c) for b in range(a, c + a, a)]
    assert [r["env_steps"] // a * a if r["env_steps"] < c else c for r in rounds] == boundaries
    for r in rounds:
        b = r["env_steps"] // a * a if r["env_steps"] < c else c
        assert b <= r["env_steps"] <= b + overrun
        assert sum(r["counts"]) == len(r["slots"]) <= workers  # a slow-starting worker may join later
    for r in rounds[:-1]:  # Eq. 8 from the evaluation's returns
        np.testing.assert_allclose(r["probabilities"], allocation_probabilities(r["returns"]), rtol=1e-9)
    last = rounds[-1]
    assert last["reason"] == "elimination"
    survivor = last["survivor"]
    best = [k for k, r in enumerate(last["returns"]) if r == max(last["returns"])]
    assert survivor in best  # a tie is broken by the run's seeded generator, and recorded
    assert last["tie"] == (best if len(best) > 1 else None)
    assert [bool(e) for e in last["eliminated"]] == [k != survivor for k in range(len(last["returns"]))]
    # After elimination every live slot runs the survivor, and only the survivor keeps learning.
    assert len(last["slots"]) == workers
    assert set(last["slots"].values()) == {survivor} and last["counts"][survivor] == workers
    final = run["learner"][-1]
    assert final["live"] == [k == survivor for k in range(len(last["returns"]))]


def check_updates(run: dict, start: int, utd: float) -> None:
    """Lock-step: every learner row (written between iterations) has exactly the updates its
    transitions allow (utd per transition past the start, equal-data)."""
    for row in run["learner"]:
        if row["env_steps"] > start:
            assert row["updates"] == int(utd * (row["env_steps"] - start)), row
    final = run["learner"][-1]
    assert final["updates"] == int(utd * (final["env_steps"] - start))


def test_mam_run_apple_collect_end_to_end(tmp_path: Path) -> None:
    run_name, run_dir = unique_run("e2e-apple"), tmp_path / "run"
    a, c, m, start, steps = 400, 1600, 3, 400, 2400
    proc = mam("run", "--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--schedule", "equal-data",
               "--steps", str(steps), "--workers", str(m),
               "--actors", "3", "--compete-every", str(a), "--eliminate-at", str(c), "--start-steps", str(start),
               "--eval-every", "400", "--seed", "1", *SMALL, "--run", run_name, "--run-dir", str(run_dir))
    assert "elimination" in proc.stdout and "survivor" in proc.stdout
    run = load(run_dir)
    assert_exactly_once(run)
    cfg = run["config"]
    assert run["transport"]["env_steps"] == steps and run["summary"]["exact"] is True
    check_obsolescence(run, a, c, m, m - 1)
    check_updates(run, start, 1.0)
    # The run directory of the design.
    for name in ("config.json", "learner.jsonl", "eval.jsonl", "allocation.jsonl", "summary.json",
                 "checkpoints/learner.pt", "plots/learning_curves.png", "plots/allocation.png"):
        assert (run_dir / name).is_file(), name
    assert run["summary"]["survivor"] == run["allocation"][-1]["survivor"]
    assert cfg["endpoint"].startswith("tcp/127.0.0.1:")
    assert processes_of(run_name) == []


def test_mam_run_paper_schedule_accounting(tmp_path: Path) -> None:
    """Algorithm 1's accounting through the distributed system: T = 500 iterations with M = 3,
    C = 300 and start 100 are 300·3 + 200 = 1,100 transitions and 400 updates; rounds at
    iterations 100 and 200 (transitions 300, 600), the elimination at 300 (900), then one slot."""
    run_name, run_dir = unique_run("e2e-paper"), tmp_path / "run"
    m, t, c, a, start = 3, 500, 300, 100, 100
    mam("run", "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--actors", "2", "--workers", str(m),
        "--steps", str(t), "--eliminate-at", str(c), "--compete-every", str(a), "--start-steps", str(start),
        "--eval-every", "100", "--seed", "3", *SMALL, "--run", run_name, "--run-dir", str(run_dir), "--no-plot")
    run = load(run_dir)
    assert_exactly_once(run)
    clock = Schedule.for_run(resolve("ma-ddpg", actors=2, workers=m, eliminate_at=c, compete_every=a,
                                     start_steps=start), t)
    assert clock.budget == 1100 and clock.total_updates == 400
    env_steps = run["transport"]["env_steps"]
    assert env_steps == 1100
    final = run["learner"][-1]
    assert final["iterations"] == clock.units_at(env_steps) == run["transport"]["iterations"] == t
    assert final["updates"] == clock.updates_allowed(env_steps) == run["transport"]["updates"] == 400
    assert run["summary"]["schedule"] == "paper" and run["summary"]["iterations"] >= t
    for name in ("eval", "allocation", "learner"):  # every record carries the three counts
        assert all({"env_steps", "iterations", "updates"} <= set(row) for row in run[name]), name
    rounds = [r for r in run["allocation"] if r["reason"] in ("round", "elimination")]
    assert [clock.units_at(r["decided_at"]) // a * a for r in rounds] == [100, 200, 300]
    assert [r["decided_at"] for r in rounds] == [300, 600, 900]  # in transitions
    last = rounds[-1]
    assert last["reason"] == "elimination" and len(last["slots"]) == 1  # I_e = 1
    assert list(last["slots"].values()) == [last["survivor"]]
    for row in run["learner"]:  # one update per iteration past the start, never ahead or behind
        if row["iterations"] > start:
            assert row["updates"] == row["iterations"] - start, row
    assert processes_of(run_name) == []


@pytest.mark.slow
def test_mam_run_mujoco_end_to_end(tmp_path: Path) -> None:
    run_name, run_dir = unique_run("e2e-ip"), tmp_path / "run"
    a, c, m, start, steps = 500, 1500, 3, 500, 2500
    mam("run", "--env", "InvertedPendulum-v5", "--algo", "ma-td3", "--schedule", "equal-data", "--steps", str(steps),
        "--workers", str(m),
        "--actors", "2", "--compete-every", str(a), "--eliminate-at", str(c), "--start-steps", str(start),
        "--eval-every", "500", "--seed", "2", *SMALL, "--bias-every", "1250", "--bias-rollouts", "4",
        "--run", run_name, "--run-dir", str(run_dir))
    run = load(run_dir)
    assert_exactly_once(run)
    # Eq. 17, measured by the learner at every 1250 transitions for each live actor, once the
    # critic has had the point's updates; the last point is the budget itself.
    bias = [json.loads(line) for line in (run_dir / "bias.jsonl").read_text().splitlines()]
    assert sorted({r["point"] for r in bias}) == [1250, 2500]
    for point in (1250, 2500):  # every actor live at the measurement (the elimination may come first)
        rows = [r for r in bias if r["point"] == point]
        assert [r["bias"]["actor"] for r in rows] == [k for k, live in enumerate(rows[0]["live"]) if live]
    assert [r["bias"]["actor"] for r in bias if r["point"] == 2500] == [run["summary"]["survivor"]]
    for r in bias:
        b = r["bias"]
        assert r["env_steps"] >= r["point"] and r["updates"] >= r["point"] - start and r["rollouts"] == 4
        assert b["bias"] == pytest.approx(b["q_estimate"] - b["q_true"])
        assert b["bias_rate"] == pytest.approx(b["bias"] / b["q_true"])  # Eq. 17 as printed
        assert b["horizon"] == "critic" and math.isfinite(b["tail"])  # a tail only where the time limit cut
    assert (run_dir / "plots" / "bias.png").is_file()
    check_obsolescence(run, a, c, m, m - 1)
    rounds = [r for r in run["allocation"] if r["reason"] == "round"]
    # Different returns give different P (Eq. 8), and P is not stuck at uniform.
    assert any(not np.allclose(r["probabilities"], 0.5) for r in rounds)
    check_updates(run, start, 1.0)
    assert processes_of(run_name) == []


@pytest.mark.slow  # ~10 s of real processes: the fast suite stays under 5 minutes on 2 cores
def test_late_worker_gets_weights_and_allocation_within_a_second(tmp_path: Path) -> None:
    run = unique_run("late")
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    learner = spawn("learner", "--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--steps", "1000000",
                    "--start-steps", "200", "--compete-every", "300", "--eliminate-at", "100000", *SMALL,
                    "--workers", "1",
                    "--run", run, "--listen", endpoint, "--run-dir", str(tmp_path), log=tmp_path / "learner.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "referee.log")
    worker = spawn("worker", "--run", run, "--connect", endpoint, "--id", "w0", "--run-dir", str(tmp_path),
                   log=tmp_path / "worker.log")
    try:
        conf = bus.make_config(connect=[endpoint])
        with bus.session_scope(conf, retry_for=30) as s:
            alloc = bus.Latest.subscribe(s, keys.allocation(run))
            assert alloc.wait(keys.allocation(run), timeout=60), "no allocation from the referee"
            deadline = time.monotonic() + 60  # the run is going: a round has happened
            while Allocation.from_bytes(alloc.get(keys.allocation(run)).payload).round < 1:
                assert time.monotonic() < deadline, "no allocation round within 60 s"
                time.sleep(0.2)
            alloc.close()
        # A late joiner (a new worker's view) gets every actor's weights and the allocation at once.
        with bus.session_scope(conf) as s:
            t0 = time.monotonic()
            weights = bus.Latest.subscribe(s, keys.weights_all(run))
            allocation = bus.Latest.subscribe(s, keys.allocation(run))
            while len(weights.snapshot()) < 3 or allocation.get(keys.allocation(run)) is None:
                assert time.monotonic() - t0 < 1.0, f"late joiner waited > 1 s: {sorted(weights.snapshot())}"
                time.sleep(0.005)
            elapsed = time.monotonic() - t0
            got = [Weights.from_bytes(weights.get(keys.weights(run, k)).payload) for k in range(3)]
            assert [w.actor for w in got] == [0, 1, 2] and all(w.version >= 0 for w in got)
            assert Allocation.from_bytes(allocation.get(keys.allocation(run)).payload).round >= 1
            weights.close()
            allocation.close()
        assert elapsed < 1.0
        # `mam watch` from another process's point of view: the live view shows P_k, I_k and workers.
        console = Console(record=True, width=160, force_terminal=False)
        state = watch(run, conf, refresh_per_s=4, console=console, duration=3.0, until_done=False)
        assert state.probabilities and abs(sum(state.probabilities) - 1) < 1e-6
        text = console.export_text()
        assert "w0" in text and "alive" in text and "round" in text
    finally:
        stop(worker, referee, learner)
    assert processes_of(run) == []


@pytest.mark.slow  # ~10 s of real processes: the fast suite stays under 5 minutes on 2 cores
def test_two_runs_on_one_router_never_cross(tmp_path: Path) -> None:
    """Two runs share one `mam router`, with the same worker ids: namespaces keep them apart."""
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    runs = [unique_run("iso-a"), unique_run("iso-b")]
    # no referee (K = 1 needs no decision) and two slots: 600 iterations are 1,200 transitions
    common = ["--env", "AppleCollect-v0", "--algo", "ddpg", "--steps", "600", "--start-steps", "300", *SMALL,
              "--workers", "2"]
    procs = [spawn("router", "--listen", endpoint, log=tmp_path / "router.log")]
    try:
        for run in runs:
            procs.append(spawn("learner", *common, "--run", run, "--connect", endpoint,
                               "--run-dir", str(tmp_path / run), log=tmp_path / f"{run}-learner.log"))
        for run in runs:
            for slot, w in enumerate(("w0", "w1")):
                procs.append(spawn("worker", "--run", run, "--connect", endpoint, "--id", w, "--slot", str(slot),
                                   "--run-dir", str(tmp_path / run), log=tmp_path / f"{run}-{w}.log"))
        deadline = time.monotonic() + 180
        while not all((tmp_path / run / "transport.json").is_file() for run in runs):
            assert time.monotonic() < deadline, "runs did not finish"
            time.sleep(0.5)
        for p in procs[1:]:  # learners and workers leave by themselves once their run is done
            p.wait(60)
            assert p.returncode == 0, f"{p.args} exited {p.returncode}"
    finally:
        stop(*reversed(procs))
    for run in runs:
        d = tmp_path / run
        t = load_transport(d)
        assert set(t["per_worker"]) == {"w0", "w1"} and t["rejected"] == {}
        sent = {f"{w['worker']}/{w['incarnation']}" for w in read_reports(d)}
        assert set(t["rows_per_stream"]) == sent  # only its own workers' incarnations
        assert t["env_steps"] == 1200
    assert all(processes_of(run) == [] for run in runs)


def load_transport(run_dir: Path) -> dict:
    import json

    return json.loads((run_dir / "transport.json").read_text())


def read_reports(run_dir: Path) -> list[dict]:
    import json

    return [json.loads(p.read_text()) for p in (run_dir / "workers").glob("*.json")]
