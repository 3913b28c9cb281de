"""`mam run` supervises its children: kill -9 any of them and the run still finishes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import AlgoConfig
from services.roles.checkpoint import load_replay
from services.run.chaos import children_of
from services.run.rundir import read_jsonl
from tests.e2e import ROOT, assert_exactly_once, load, processes_of, unique_run

pytestmark = pytest.mark.slow

SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "3"]


def start_mam_run(run: str, run_dir: Path, *args: str) -> tuple[subprocess.Popen, Path]:
    out = run_dir.parent / f"{run}.out"
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    with open(out, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args, "--run", run,
                                 "--run-dir", str(run_dir), "--no-plot"], cwd=ROOT, env=env, stdout=f,
                                stderr=subprocess.STDOUT)
    return proc, out


def child_pid(proc: subprocess.Popen, module: str, *must: str) -> int:
    """The pid of the live `services.<module>` child of `mam run` (with `must` in its command line)."""
    for pid, role in children_of(proc.pid):
        args = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
        if role == module and all(m in args for m in must):
            return pid
    raise AssertionError(f"no live {module} {must} among {children_of(proc.pid)}")


def learner_steps(run_dir: Path) -> int:
    rows = read_jsonl(run_dir / "learner.jsonl")
    return rows[-1]["env_steps"] if rows else 0


def wait_until(predicate, timeout: float, what: str, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"mam run exited ({proc.returncode}) while waiting for {what}"
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.2)


def test_kill_9_of_a_worker_the_referee_and_the_learner_and_the_run_finishes(tmp_path: Path) -> None:
    run, run_dir = unique_run("supervised"), tmp_path / "run"
    steps = 9000
    proc, out = start_mam_run(run, run_dir, "--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--steps", str(steps),
                              "--workers", "3", "--start-steps", "300", "--compete-every", "1000",
                              "--eliminate-at", "6000", "--checkpoint-seconds", "3", *SMALL)
    try:
        wait_until(lambda: learner_steps(run_dir) > 1500, 180, "1500 steps", proc)
        os.kill(child_pid(proc, "worker", "w1"), signal.SIGKILL)
        wait_until(lambda: learner_steps(run_dir) > 3000, 180, "3000 steps", proc)
        os.kill(child_pid(proc, "referee"), signal.SIGKILL)
        referee_killed = time.time()
        # a checkpoint written after both kills (the learner writes one at start too): it holds the
        # killed worker's rows, which no worker can resend any more
        ckpt = run_dir / "checkpoints" / "learner.pt"
        wait_until(lambda: learner_steps(run_dir) > 4500 and ckpt.is_file() and ckpt.stat().st_mtime > referee_killed,
                   180, "4500 steps and a checkpoint", proc)
        killed_learner_at = learner_steps(run_dir)
        os.kill(child_pid(proc, "learner"), signal.SIGKILL)
        proc.wait(400)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(60)
    text = out.read_text()
    assert proc.returncode == 0, text
    # Every restart is printed ...
    assert "worker-1 exited with -9 (SIGKILL)" in text and "restarted worker-1" in text
    assert "referee exited with -9 (SIGKILL)" in text and "restarted referee" in text
    assert "learner exited with -9 (SIGKILL)" in text and "restarted learner (resuming from its checkpoint)" in text
    # ... and counted in summary.json.
    r = load(run_dir)
    summary = r["summary"]
    assert summary["restarts"] == {"learner": 1, "referee": 1, "worker-0": 0, "worker-1": 1, "worker-2": 0}
    assert summary["restarts_total"] == 3
    # The budget was reached by one run that went on: the resumed learner continued past the kill.
    assert steps <= r["transport"]["env_steps"] and summary["env_steps"] >= steps
    assert max(row["env_steps"] for row in r["learner"]) >= killed_learner_at
    assert "recovered referee state" in (run_dir / "logs" / "referee.log").read_text()
    # Exactly once, over all incarnations of the learner and of the workers: the killed worker's
    # log of sent batches against the replay's rows per stream (kept through the checkpoints).
    # Rows the SIGKILLed worker had logged but not yet put on the wire die with it (docs/RELIABILITY.md):
    # they may only be missing from its first incarnation's stream, within its credit band. Every other
    # stream (the learner's and the referee's kills included) is exact.
    audit = r["transport"]["audit"]
    w1 = sorted((s for s in audit["per_stream"] if s.startswith("w1/")),
                key=lambda s: (run_dir / "workers" / f"w1-{s.split('/')[1]}.batches").stat().st_mtime)
    assert len(w1) == 2
    killed = audit["per_stream"][w1[0]]
    # Rows a replacement sent for iterations its slot already had are skipped, and counted.
    lost = killed["sent"] - killed["in_replay"] - killed["skipped"]
    assert 0 <= lost <= 256, audit
    assert all(d["sent"] == d["in_replay"] + d["skipped"] for s, d in audit["per_stream"].items() if s != w1[0]), audit
    assert audit["duplicated_rows"] == 0 and r["transport"]["duplicates"] == 0, audit
    assert audit["lost_rows"] == lost == summary["transport"]["lost_rows"]
    assert audit["sent_rows"] == audit["replay_rows"] + audit["skipped_rows"] + audit["lost_rows"]
    assert audit["replay_rows"] == r["transport"]["env_steps"]
    # The run directory is complete and the final checkpoint (with its replay) loads.
    for name in ("config.json", "learner.jsonl", "eval.jsonl", "allocation.jsonl", "summary.json", "transport.json",
                 "referee_state.json", "checkpoints/learner.pt", "logs/learner.log", "logs/referee.log"):
        assert (run_dir / name).is_file(), name
    state = torch.load(run_dir / "checkpoints" / "learner.pt", weights_only=True)
    agent = MultiActorAgent(AlgoConfig.from_dict(r["config"]["algo"]), EnvSpec.from_env_id("AppleCollect-v0"))
    agent.load_state_dict(state["agent"])
    assert agent.updates == r["transport"]["updates"]
    assert len(load_replay(run_dir, state=state)) == r["transport"]["env_steps"]
    assert processes_of(run) == []


def test_a_child_that_keeps_dying_stops_the_run_naming_it_and_its_log(tmp_path: Path) -> None:
    run, run_dir = unique_run("keeps-dying"), tmp_path / "run"
    # Every reset of this env raises in worker processes: the worker gives up, is restarted, gives up ...
    proc, out = start_mam_run(run, run_dir, "--env", "tests.faulty_env:BrokenResetWorkers-v0", "--algo", "td3",
                              "--steps", "5000", "--allow-no-updates", "--workers", "1", "--max-restarts", "2",
                              "--restart-window", "300",
                              *SMALL)
    try:
        proc.wait(300)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = " ".join(out.read_text().split())  # rich wraps long lines
    assert proc.returncode == 1, text
    assert text.count("restarted worker-0") == 2
    assert "worker-0 keeps dying" in text and "2 restarts within 300 s" in text
    assert str(run_dir / "logs" / "worker-0.log") in text
    assert "no usable reset" in (run_dir / "logs" / "worker-0.log").read_text()
    assert processes_of(run) == []


def test_workers_survive_simulator_faults_in_a_mam_run(tmp_path: Path) -> None:
    run, run_dir = unique_run("sim-faults"), tmp_path / "run"
    proc, out = start_mam_run(run, run_dir, "--env", "tests.faulty_env:FaultyPendulumWorkers-v0", "--algo", "td3",
                              "--steps", "3000", "--workers", "2", "--start-steps", "500", *SMALL)
    proc.wait(300)
    assert proc.returncode == 0, out.read_text()
    r = load(run_dir)
    assert_exactly_once(r)
    assert r["summary"]["restarts_total"] == 0
    faults = {k: sum(w["env_faults"][k] for w in r["workers"]) for k in r["workers"][0]["env_faults"]}
    assert all(n > 0 for n in faults.values()), faults
    # lock-step: a faulty step is retried on a reset env (no row dropped); the run says it is not the seed's
    assert r["summary"]["exact"] is False and "simulator faults" in r["summary"]["inexact"], r["summary"]
    assert processes_of(run) == []
