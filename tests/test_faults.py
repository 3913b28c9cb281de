"""Faults with real processes and `kill -9`: workers, the referee and the learner die and come back."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.algorithm1 import Algorithm1
from mam_core.config import AlgoConfig, resolve
from mam_core.policy import read_policy_file
from mam_core.reference import run_reference
from services.messaging import bus, keys
from services.messaging.codec import Allocation, LearnerStats
from services.roles.checkpoint import load_replay
from services.run.rundir import read_jsonl
from tests.e2e import ROOT, processes_of, spawn, stop, unique_run

pytestmark = pytest.mark.slow

SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "3"]


class RunView:
    """A client of the run: latest learner stats and allocation."""

    def __init__(self, run: str, endpoint: str) -> None:
        self.run = run
        self.session = bus.open_session(bus.make_config(connect=[endpoint]), retry_for=30)
        self.stats = bus.Latest.subscribe(self.session, keys.learner_stats(run))
        self.alloc = bus.Latest.subscribe(self.session, keys.allocation(run))

    def learner(self) -> LearnerStats | None:
        item = self.stats.get(keys.learner_stats(self.run))
        return None if item is None else LearnerStats.from_bytes(item.payload)

    def allocation(self) -> Allocation | None:
        item = self.alloc.get(keys.allocation(self.run))
        return None if item is None else Allocation.from_bytes(item.payload)

    def wait(self, predicate, timeout: float = 120.0, what: str = "condition"):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = predicate()
            if value:
                return value
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}")

    def steps(self) -> int:
        st = self.learner()
        return st.env_steps if st else 0

    def close(self) -> None:
        self.stats.close()
        self.alloc.close()
        self.session.close()


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def start_run(tmp_path: Path, run: str, endpoint: str, steps: int, extra: list[str] = (), workers: int = 3):
    learner = spawn("learner", "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--schedule", "equal-data",
                    "--steps", str(steps),
                    "--start-steps", "300", "--compete-every", "500", "--eliminate-at", "1000000", *SMALL, *extra,
                    "--workers", str(workers), "--seed", "5", "--run", run, "--listen", endpoint,
                    "--run-dir", str(tmp_path), log=tmp_path / "learner.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "referee.log")
    ws = {f"w{i}": spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i),
                         "--run-dir", str(tmp_path), log=tmp_path / f"w{i}.log") for i in range(workers)}
    return learner, referee, ws


def wait_for_file(path: Path, timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.is_file():
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.2)


def test_worker_killed_and_restarted(tmp_path: Path) -> None:
    """Lock-step: the run waits for the dead worker's slot; a new worker on that slot takes it
    over where the learner stands, rebuilding the slot from its current episode: the run is
    still the seed's, equal to the one-process reference."""
    run, endpoint = unique_run("kill-worker"), bus.loopback_endpoint(bus.free_tcp_port())
    learner, referee, ws = start_run(tmp_path, run, endpoint, steps=5000)
    view = RunView(run, endpoint)
    try:
        view.wait(lambda: view.steps() > 1500 and view.learner().per_worker.get("w1", {}).get("received"),
                  what="1500 steps, some from w1")
        ws["w1"].send_signal(signal.SIGKILL)
        ws["w1"].wait()
        time.sleep(2.0)
        stalled = view.steps()
        time.sleep(2.0)
        assert view.steps() == stalled  # every iteration needs slot 1's transition
        assert 1 in view.learner().awaiting
        ws["w1"] = spawn("worker", "--run", run, "--connect", endpoint, "--id", "w1", "--slot", "1",
                         "--run-dir", str(tmp_path), log=tmp_path / "w1-again.log")
        view.wait(lambda: view.steps() > stalled + 300, 60, "progress with the new w1")
        wait_for_file(tmp_path / "transport.json")
        wait_for_file(tmp_path / "summary.json")
        for p in ws.values():
            p.wait(30)
    finally:
        view.close()
        stop(*ws.values(), referee, learner)
    transport = json.loads((tmp_path / "transport.json").read_text())
    reports = [json.loads(p.read_text()) for p in (tmp_path / "workers").glob("*.json")]
    streams = transport["rows_per_stream"]
    assert len([s for s in streams if s.startswith("w1/")]) == 2  # two incarnations of w1
    assert transport["duplicates"] == 0 and transport["rejected"] == {}
    for r in reports:  # every surviving incarnation: what it sent is in the replay, but for the
        # first rows of the new w1 that repeat iterations its predecessor's rows had already filled
        assert streams[f"{r['worker']}/{r['incarnation']}"] <= r["sent_rows"]
    assert sum(streams.values()) == transport["env_steps"] == 5000
    summary = json.loads((tmp_path / "summary.json").read_text())
    again = (tmp_path / "w1-again.log").read_text()
    assert "taking slot 1 over at iteration" in again and "every observation equal" in again, again[-2000:]
    assert summary["exact"] is True, summary  # the new w1 rebuilt slot 1 from its episode: the seed's run
    cfg = resolve("ma-ddpg", schedule="equal-data", start_steps=300, compete_every=500, eliminate_at=1_000_000,
                  hidden=(32, 32), batch_size=32, eval_episodes=3, workers=3, seed=5)
    _equals_reference(tmp_path, run_reference("AppleCollect-v1", cfg, 5000))
    assert processes_of(run) == []


def test_referee_killed_and_restarted(tmp_path: Path) -> None:
    """A restarted referee goes on from its state (the allocation stream's included): it
    evaluates exactly the plan's events, and the run stays exact, equal to the reference."""
    run, endpoint = unique_run("kill-referee"), bus.loopback_endpoint(bus.free_tcp_port())
    steps = 4500
    learner, referee, ws = start_run(tmp_path, run, endpoint, steps=steps)
    view = RunView(run, endpoint)
    try:
        view.wait(lambda: (a := view.allocation()) and a.round >= 2, what="round 2")
        referee.send_signal(signal.SIGKILL)
        referee.wait()
        kept = view.allocation()
        time.sleep(3.0)  # the slots need the next decision B + 1 iterations after its competition
        assert view.allocation().round == kept.round
        referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                        log=tmp_path / "referee-again.log")
        view.wait(lambda: (a := view.allocation()) and a.round > kept.round, 60, "a round after the restart")
        wait_for_file(tmp_path / "summary.json")
        for p in ws.values():
            p.wait(60)
    finally:
        view.close()
        stop(*ws.values(), referee, learner)
    assert "recovered referee state" in (tmp_path / "referee-again.log").read_text()
    cfg = resolve("ma-ddpg", schedule="equal-data", start_steps=300, compete_every=500, eliminate_at=1_000_000,
                  hidden=(32, 32), batch_size=32, eval_episodes=3, workers=3, seed=5)
    plan = Algorithm1.for_run(cfg, steps)
    evals = read_jsonl(tmp_path / "eval.jsonl")
    assert [(e["iterations"], e["purpose"]) for e in evals] == \
        [(plan.iteration(i).units[1], purpose) for i, purpose in plan.events()]  # each event once, in order
    rounds = [r["round"] for r in read_jsonl(tmp_path / "allocation.jsonl") if r["reason"] == "round"]
    assert rounds == list(range(1, len(rounds) + 1))
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["exact"] is True, summary
    _equals_reference(tmp_path, run_reference("AppleCollect-v1", cfg, steps))
    assert processes_of(run) == []


def _equals_reference(run_dir: Path, ref) -> None:
    """Every evaluation's returns and every final policy array equal the one-process reference's."""
    evals = read_jsonl(run_dir / "eval.jsonl")
    assert [e["returns"] for e in evals] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)


def test_learner_killed_and_resumed(tmp_path: Path) -> None:
    run, endpoint = unique_run("kill-learner"), bus.loopback_endpoint(bus.free_tcp_port())
    learner, referee, ws = start_run(tmp_path, run, endpoint, steps=4000,
                                     extra=["--checkpoint-every", "300", "--save-replay"])
    view = RunView(run, endpoint)
    try:
        # Killed between the checkpoint at 900 updates and the next at 1200, after the weights
        # published at 1000: workers then hold weights newer than the checkpoint's versions.
        view.wait(lambda: (st := view.learner()) and st.updates > 1010, what="1010 updates")
        learner.send_signal(signal.SIGKILL)
        learner.wait()
        time.sleep(1.0)
        # Workers pause rather than spin: little CPU while the learner is away.
        cpu0 = {w: cpu_seconds(p.pid) for w, p in ws.items()}
        time.sleep(3.0)
        for w, p in ws.items():
            assert cpu_seconds(p.pid) - cpu0[w] < 0.9, f"{w} spins while the learner is gone"
        checkpoint = torch.load(tmp_path / "checkpoints" / "learner.pt", weights_only=True)
        saved_updates = checkpoint["agent"]["updates"]
        saved_rows = checkpoint["counters"]["env_steps"]
        # The replay is on disk as chunks beside the checkpoint: every row the checkpoint counts.
        replay = load_replay(tmp_path, state=checkpoint)
        assert saved_updates > 0 and len(replay) == saved_rows > 0
        learner = spawn("learner", "--resume", str(tmp_path), "--listen", endpoint, log=tmp_path / "learner-again.log")
        wait_for_file(tmp_path / "transport.json")
        for p in ws.values():
            p.wait(30)
    finally:
        view.close()
        stop(*ws.values(), referee, learner)
    rows = read_jsonl(tmp_path / "learner.jsonl")
    resumed = [r for r in rows if r["updates"] >= saved_updates]
    assert resumed and rows[-1]["env_steps"] == 4000  # the run went on to the same budget
    transport = json.loads((tmp_path / "transport.json").read_text())
    assert transport["duplicates"] == 0 and transport["rejected"] == {}
    again = (tmp_path / "learner-again.log").read_text()
    # The resumed learner trains on the replay it had ...
    assert f": {saved_rows} transitions, {saved_updates} updates (replay rows: {saved_rows})" in again
    # ... and the workers resent what it had not checkpointed: every iteration's rows once, in order
    # (rows the workers stepped again from the learner's iteration fill nothing twice).
    reports = [json.loads(p.read_text()) for p in (tmp_path / "workers").glob("*.json")]
    assert sum(r["resent_rows"] for r in reports) > 0
    assert transport["lost"] == 0
    for r in reports:
        assert transport["rows_per_stream"][f"{r['worker']}/{r['incarnation']}"] <= r["sent_rows"]
    assert sum(transport["rows_per_stream"].values()) == transport["env_steps"] == transport["replay_rows"]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["exact"] is True, summary
    assert len(load_replay(tmp_path)) == transport["env_steps"]
    cfg = resolve("ma-ddpg", schedule="equal-data", start_steps=300, compete_every=500, eliminate_at=1_000_000,
                  hidden=(32, 32), batch_size=32, eval_episodes=3, workers=3, seed=5)
    _equals_reference(tmp_path, run_reference("AppleCollect-v1", cfg, 4000))
    assert processes_of(run) == []


def test_ctrl_c_on_mam_run_leaves_nothing_and_a_usable_checkpoint(tmp_path: Path) -> None:
    run, run_dir = unique_run("ctrl-c"), tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", "--env", "AppleCollect-v1", "--algo",
                             "ma-ddpg", "--steps", "1000000", "--start-steps", "300", *SMALL, "--run", run,
                             "--run-dir", str(run_dir)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while not any(r.get("updates", 0) > 200 for r in read_jsonl(run_dir / "learner.jsonl")):
            assert time.monotonic() < deadline and proc.poll() is None, "run did not start training"
            time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert processes_of(run) == []
    cfg = json.loads((run_dir / "config.json").read_text())
    state = torch.load(run_dir / "checkpoints" / "learner.pt", weights_only=True)
    agent = MultiActorAgent(AlgoConfig.from_dict(cfg["algo"]), EnvSpec.from_env_id("AppleCollect-v1"))
    agent.load_state_dict(state["agent"])
    assert agent.updates > 200
