"""Learner incarnations cannot deadlock the run (issue: a learner killed before its first
checkpoint hung the run forever): weights carry the learner's incarnation, workers and the
referee prefer a new incarnation's copy of a version, rows acted with a dead incarnation's
weights are accepted, and workers step on from the new learner's iteration."""

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

from mam_core.policy import EnvSpec, NumpyActors
from services.cli.plot import read_jsonl
from services.roles.lockstep import WeightsHistory
from tests.e2e import ROOT, unique_run

SPEC = EnvSpec(3, 2, (1.0, 1.0))
HIDDEN = (4,)


def test_a_new_learner_incarnations_copy_of_a_version_replaces_the_dead_ones():
    """Versions are the plan's, so a restarted learner publishes the same version numbers again,
    with its own parameters: a role keeps the successor's copy once the stats name it, and a
    late or cached message of the dead learner never replaces it."""
    shapes = NumpyActors(1, SPEC, HIDDEN).shapes
    history = WeightsHistory(1)

    def params(value: float) -> dict[str, np.ndarray]:
        return {name: np.full(shape, value, np.float32) for name, shape in shapes.items()}

    assert history.add(0, 40, params(1.0), "old", prefer="old")
    assert history.add(0, 40, params(2.0), "new", prefer="new")
    assert history.source(0, 40) == "new" and float(history.get(0, 40)["w0"][0, 0]) == 2.0
    assert not history.add(0, 40, params(3.0), "old", prefer="new")
    assert float(history.get(0, 40)["w0"][0, 0]) == 2.0


@pytest.mark.slow
def test_a_learner_killed_without_a_checkpoint_and_three_more_times_the_run_finishes(tmp_path: Path) -> None:
    """The first kill also deletes the checkpoints, so the launcher starts a fresh learner at
    iteration 0 while the workers are hundreds of iterations on (they step on from the new
    learner's iteration; what is missing is filled by the rows that come); three more kills
    resume from checkpoints. The run goes on in lock-step, finishes its budget, and says it is
    not exact."""
    run_dir, name = tmp_path / "kills", unique_run("kills")
    steps = 6000
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(steps), "--workers", "2", "--actors", "2",
            "--schedule", "equal-data", "--start-steps", "500", "--compete-every", "2000", "--eliminate-at", "4000",
            "--eval-episodes", "2", "--hidden", "16,16", "--batch-size", "16", "--seed", "1",
            "--checkpoint-seconds", "2", "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)

    def learner_pid() -> int | None:
        pattern = f"services.roles.learner .*{run_dir}"
        out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout
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
    assert summary["env_steps"] == steps and summary["restarts"]["learner"] == 4, summary
    assert summary["exact"] is False and "the learner restarted" in summary["inexact"], summary
