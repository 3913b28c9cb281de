"""`mam run --resume RUN_DIR`: a stopped run continues to its budget with the options it started
with; nothing to continue, or a flag that contradicts the run, is refused at once, naming the file."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mam_core.config import resolve
from mam_core.policy import read_policy_file
from mam_core.reference import run_reference
from services.run.rundir import earlier_parts, read_jsonl
from tests.e2e import ROOT, processes_of, unique_run

ARGS = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", "1500", "--workers", "3", "--actors", "2",
        "--start-steps", "200", "--compete-every", "300", "--eliminate-at", "900", "--eval-episodes", "2",
        "--eval-every", "300", "--hidden", "16,16", "--batch-size", "16", "--seed", "4", "--checkpoint-seconds", "2",
        "--no-plot"]


def mam_run(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                          capture_output=True, timeout=timeout, env=dict(os.environ, COLUMNS="200"))


def kill_past_a_checkpoint(run_dir: Path, proc: subprocess.Popen) -> None:
    """Once the run has a checkpoint past its start and launcher.json counts the part, SIGKILL
    `proc`'s group and every process naming the run directory (the run's roles, in sessions of
    their own), as a reboot would. They are stopped first, all at once, and nothing waits a fixed
    time: a fast box runs this budget's last 1,000 iterations in 2 s, and a CI run once finished
    during such a wait."""
    deadline = time.monotonic() + 180
    while not (checkpointed(run_dir) > 0 and earlier_parts(run_dir)["wall_s"] > 0):
        assert time.monotonic() < deadline and proc.poll() is None, "the run did not get going"
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGSTOP)  # restarts nothing meanwhile
    pids = [int(pid) for pid in subprocess.run(["pgrep", "-f", str(run_dir)], capture_output=True,
                                                text=True).stdout.split()]
    for sig in (signal.SIGSTOP, signal.SIGKILL):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(30)
    assert not (run_dir / "summary.json").exists(), "the run finished before it could be stopped"


def checkpointed(run_dir: Path) -> int:
    """The most updates a checkpoint of the run holds (its manifests), 0 before one past the start."""
    updates = [0]
    for manifest in (run_dir / "checkpoints").glob("manifest-*.json"):
        with contextlib.suppress(OSError, ValueError):
            updates.append(int(json.loads(manifest.read_text())["updates"]))
    return max(updates)


def test_resume_refuses_a_directory_with_nothing_to_continue(tmp_path: Path) -> None:
    got = mam_run("--resume", str(tmp_path / "nowhere"))
    assert got.returncode == 2 and "no config.json there" in got.stderr, got.stderr
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text("{}")
    got = mam_run("--resume", str(run_dir))
    assert got.returncode == 2 and "no verified checkpoint in" in got.stderr and str(run_dir) in got.stderr


def test_a_learner_resumed_with_other_gemm_kernels_stops_and_says_how_to_resume(tmp_path: Path) -> None:
    """The learner's GEMM kernels come from the environment (MAM_PORTABLE_GEMM), not the run's
    config: a checkpoint records them, and a learner that would resume it with others exits 78
    after one line naming the variable, instead of computing another run from there on."""
    from services.roles.checkpoint import load_checkpoint
    from services.run.preflight import CONFIG_ERROR, EXIT_CONFIG

    run_dir = tmp_path / "run"
    env = dict(os.environ, COLUMNS="200", MAM_PORTABLE_GEMM="openblas")
    flags = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", "60", "--start-steps", "40", "--workers", "1",
             "--actors", "2", "--hidden", "16,16", "--batch-size", "16", "--eval-episodes", "1", "--no-plot"]
    got = subprocess.run([sys.executable, "-m", "services.cli", "run", *flags, "--run", unique_run("gemm"), "--run-dir",
                          str(run_dir)], cwd=ROOT, text=True, capture_output=True, timeout=300, env=env)
    assert got.returncode == 0, got.stdout[-2000:] + got.stderr[-2000:]
    assert load_checkpoint(run_dir)["gemm"] == "openblas-haswell"
    env.pop("MAM_PORTABLE_GEMM")
    learner = subprocess.run([sys.executable, "-m", "services.roles.learner", "--resume", str(run_dir), "--listen",
                              "tcp/127.0.0.1:0"], cwd=ROOT, text=True, capture_output=True, timeout=120, env=env)
    lines = [line for line in (learner.stdout + learner.stderr).splitlines() if CONFIG_ERROR in line]
    assert learner.returncode == EXIT_CONFIG and len(lines) == 1, learner.stdout[-2000:] + learner.stderr[-2000:]
    assert "computed its GEMMs with openblas-haswell" in lines[0] and "MAM_PORTABLE_GEMM=openblas" in lines[0]


@pytest.mark.slow
def test_a_killed_mam_run_continues_with_resume_to_its_budget(tmp_path: Path) -> None:
    run, run_dir = unique_run("resume"), tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *ARGS, "--run", run, "--run-dir",
                             str(run_dir)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        kill_past_a_checkpoint(run_dir, proc)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    time.sleep(1.0)
    assert not (run_dir / "summary.json").exists()
    part1 = json.loads((run_dir / "launcher.json").read_text())
    assert part1["parts"] == 1 and part1["wall_s"] > 0  # the killed part's time counts
    # A new run in its directory would resume its learner under the old name, the other roles under
    # the new one (they never met: a 300 s stall): refused, pointing at --resume
    got = mam_run(*ARGS, "--run-dir", str(run_dir))
    assert got.returncode == 2 and f"holds {run}'s checkpoint" in got.stderr and "--resume" in got.stderr, got.stderr
    got = mam_run("--resume", str(run_dir), "--seed", "5")  # contradicts the run's seed 4
    assert got.returncode == 2 and "--seed 5 contradicts the run's 4" in got.stderr, got.stderr
    got = mam_run("--resume", str(run_dir), "--seed", "4")  # agreeing flags are fine
    assert got.returncode == 0, got.stdout + got.stderr
    assert "resuming" in got.stdout and "part 2" in got.stdout
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["iterations"] == 1500  # the budget, in iterations (3 slots until C = 900, then 1)
    assert summary["parts"] == 2 and summary["exact"] is True, summary
    assert summary["launcher_wall_time_s"] > part1["wall_s"]  # both parts
    transport = json.loads((run_dir / "transport.json").read_text())
    assert transport["duplicates"] == 0 and transport["env_steps"] == summary["env_steps"]
    elimination = [a for a in read_jsonl(run_dir / "allocation.jsonl") if a["reason"] == "elimination"]
    assert [a["iterations"] for a in elimination] == [900]  # exactly at C, across the two parts
    got = mam_run("--resume", str(run_dir))
    assert got.returncode == 2 and "the run finished" in got.stderr
    got = mam_run(*ARGS, "--run-dir", str(run_dir))
    assert got.returncode == 2 and f"holds {run}, finished" in got.stderr, got.stderr
    assert processes_of(run) == []
    # The resumed run is the uninterrupted one: the one-process reference, bit for bit.
    cfg = resolve("ma-ddpg", workers=3, actors=2, start_steps=200, compete_every=300, eliminate_at=900,
                  eval_episodes=2, eval_every=300, hidden=(16, 16), batch_size=16, seed=4)
    ref = run_reference("AppleCollect-v1", cfg, 1500)
    assert [e["returns"] for e in read_jsonl(run_dir / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)


@pytest.mark.slow
def test_a_grid_killed_mid_run_continues_the_run_from_its_checkpoint_exactly(tmp_path: Path) -> None:
    """`mam experiment` SIGKILLed with everything it started (a session's end, a reboot): run
    again, it continues the stopped run from its checkpoint instead of redoing it, and the run
    is the uninterrupted one (the one-process reference) bit for bit."""
    exp = tmp_path / "exp"
    args = [sys.executable, "-m", "mam_lab.experiment", "--exp-dir", str(exp), "--envs", "AppleCollect-v1",
            "--algos", "ma-ddpg", "--seeds", "1", *[a for a in ARGS if a not in ("--env", "AppleCollect-v1",
                                                                               "--algo", "ma-ddpg", "--seed", "4")],
            "--no-report", "--parallel", "1", "--no-ledger"]
    run_dir = exp / "AppleCollect-v1" / "ma-ddpg" / "seed0"
    env = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore")
    proc = subprocess.Popen(args, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        kill_past_a_checkpoint(run_dir, proc)  # the grid and its run's own session: everything
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    part1 = json.loads((run_dir / "launcher.json").read_text())
    again = subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True, timeout=400)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "continuing AppleCollect-v1/ma-ddpg/seed0 from its checkpoint" in again.stdout, again.stdout[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["parts"] == 2 and summary["exact"] is True, summary
    assert summary["launcher_wall_time_s"] > part1["wall_s"] > 0  # both parts: the killed one counts
    assert json.loads((run_dir / "record.json").read_text())["run_wall_s"] >= summary["launcher_wall_time_s"]
    cfg = resolve("ma-ddpg", workers=3, actors=2, start_steps=200, compete_every=300, eliminate_at=900,
                  eval_episodes=2, eval_every=300, hidden=(16, 16), batch_size=16, seed=0)
    ref = run_reference("AppleCollect-v1", cfg, 1500)
    assert [e["returns"] for e in read_jsonl(run_dir / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
