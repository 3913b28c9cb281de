"""Learner incarnations cannot deadlock the run (issue: a learner killed before its first
checkpoint hung the run forever): weights carry the learner's incarnation, workers and the
referee follow a new incarnation even when its version counter is lower, rows acted with a dead
incarnation's weights are accepted, and refused rows are told back to their worker."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mam_core.policy import EnvSpec
from services import bus, role
from services.codec import LearnerStats, Weights
from services.plot import read_jsonl
from tests.e2e import ROOT, unique_run

SPEC = EnvSpec(3, 2, (1.0, 1.0))
HIDDEN = (4,)


def _weights(version: int, incarnation: str, value: float) -> bus.Received:
    follower = role.WeightsFollower(1, SPEC, HIDDEN, bus.RejectLog(None))
    params = {name: np.full(shape, value, np.float32) for name, shape in follower.shapes.items()}
    msg = Weights(0, version, params, 3, 2, 1.0, HIDDEN, incarnation)
    return bus.Received("mam/r/weights/0", msg.to_bytes("learner", 1), None, 0.0)


def _stats(incarnation: str, version: int) -> LearnerStats:
    return LearnerStats(env_steps=0, updates=0, accept_until=0, utd=0.0, versions=(version,),
                        incarnation=incarnation)


def test_weights_of_a_new_learner_incarnation_replace_higher_versions_of_the_dead_one():
    follower = role.WeightsFollower(1, SPEC, HIDDEN, bus.RejectLog(None))
    follower.update({"mam/r/weights/0": _weights(2728, "old", 1.0)}, _stats("old", 2728))
    assert follower.versions == [2728]
    # the new learner starts from version 0: loaded, because it is the incarnation the stats name
    assert follower.update({"mam/r/weights/0": _weights(0, "new", 2.0)}, _stats("new", 0)) == [0]
    assert follower.versions == [0] and float(follower.actors.params[0]["w0"][0, 0]) == 2.0
    # a late or cached message of the dead learner is never loaded again, whatever its version
    assert follower.update({"mam/r/weights/0": _weights(9999, "old", 3.0)}, _stats("new", 0)) == []
    assert float(follower.actors.params[0]["w0"][0, 0]) == 2.0
    # within one incarnation: strictly newer only
    assert follower.update({"mam/r/weights/0": _weights(0, "new", 4.0)}, _stats("new", 0)) == []
    assert follower.update({"mam/r/weights/0": _weights(1, "new", 5.0)}, _stats("new", 1)) == [0]


@pytest.mark.slow
def test_a_learner_killed_without_a_checkpoint_and_three_more_times_the_run_finishes(tmp_path: Path) -> None:
    """Asynchronous collection; the first kill also deletes the checkpoints, so the launcher
    starts a fresh learner at version 0 while the workers hold versions in the hundreds (the
    deadlock that was seen); three more kills resume from checkpoints. The run must finish
    its budget."""
    run_dir, name = tmp_path / "kills", unique_run("kills")
    steps = 6000
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(steps), "--workers", "2", "--actors", "2",
            "--schedule", "equal-data", "--start-steps", "500", "--compete-every", "2000", "--eliminate-at", "4000",
            "--eval-episodes", "2", "--hidden", "16,16", "--batch-size", "16", "--seed", "1", "--collection", "async",
            "--checkpoint-seconds", "2", "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)

    def learner_pid() -> int | None:
        out = subprocess.run(["pgrep", "-f", f"services.learner .*{run_dir}"], capture_output=True, text=True).stdout
        return int(out.split()[0]) if out.split() else None

    def updates() -> int:
        path = run_dir / "learner.jsonl"
        rows = read_jsonl(path) if path.is_file() else []
        return rows[-1]["updates"] if rows else 0

    try:
        for kill, at_updates in enumerate((300, 900, 1500, 2500)):
            deadline = time.monotonic() + 180
            while updates() < at_updates and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.2)
            pid = learner_pid()
            assert pid is not None and proc.poll() is None, proc.stdout.read() if proc.poll() is not None else ""
            os.kill(pid, signal.SIGKILL)
            if kill == 0:  # no checkpoint: the launcher starts a fresh learner, versions from 0
                time.sleep(0.3)
                shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)
            time.sleep(3.0)
        out, _ = proc.communicate(timeout=400)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] >= steps and summary["restarts"]["learner"] == 4, summary
