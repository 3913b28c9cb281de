"""How `mam run` hands its directory over: its Ctrl-C stops the learner before the workers (the
learner's last checkpoint may need rows of updates it made ahead), and a `mam run --resume`
waits for the children of a killed `mam run` that are still checkpointing. Real processes, real
signals, real locks."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rich.console import Console

from mam_core.config import resolve
from services.run import runlock
from services.run.cluster import Child, LocalCluster
from services.run.config import RunConfig
from tests.e2e import ROOT

# A child that writes when SIGTERM reached it, and leaves `linger` seconds later.
STOPPING_CHILD = """
import signal, sys, time
path, linger = sys.argv[1], float(sys.argv[2])
def on_term(*_):
    open(path, "w").write(repr(time.monotonic()))
    time.sleep(linger)
    sys.exit(0)
signal.signal(signal.SIGTERM, on_term)
time.sleep(120)
"""


def test_stop_signals_the_workers_only_after_the_learner_has_left(tmp_path: Path) -> None:
    cfg = RunConfig(run="order", env_id="AppleCollect-v0", steps=2000, algo=resolve("ma-ddpg", actors=2, workers=2))
    cluster = LocalCluster(cfg, tmp_path, "tcp/127.0.0.1:1", console=Console(file=io.StringIO()))
    for role in ("worker-0", "learner", "referee", "worker-1"):
        proc = subprocess.Popen([sys.executable, "-c", STOPPING_CHILD, str(tmp_path / role), "1.0"])
        cluster.children.append(Child(role, proc, tmp_path / f"{role}.log"))
    time.sleep(1.0)  # the children have set their handlers
    try:
        cluster.stop(grace=10.0)
    finally:
        for child in cluster.children:
            if child.proc.poll() is None:
                child.proc.kill()
    assert [c.proc.returncode for c in cluster.children] == [0, 0, 0, 0]
    told = {role: float((tmp_path / role).read_text()) for role in ("learner", "referee", "worker-0", "worker-1")}
    assert all(told[role] >= told["learner"] + 0.9 for role in ("referee", "worker-0", "worker-1")), told


def hold_role_lock(run_dir: Path, linger: float, launcher: str) -> subprocess.Popen:
    """A learner's lock on `run_dir`, held `linger` seconds by another process (started by a
    `mam run` with token `launcher`, or by hand if it is empty)."""
    code = ("import sys, time; from pathlib import Path; from services.run import runlock; "
            "lock = runlock.lock_role(Path(sys.argv[1]), 'learner', 'held'); print('locked', flush=True); "
            "time.sleep(float(sys.argv[2]))")
    env = {k: v for k, v in os.environ.items() if k != runlock.LOCK_ENV}
    proc = subprocess.Popen([sys.executable, "-c", code, str(run_dir), str(linger)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, env=dict(env, **({runlock.LOCK_ENV: launcher} if launcher else {})))
    assert proc.stdout is not None and proc.stdout.readline().strip() == "locked"
    return proc


def test_a_resume_waits_for_the_learner_of_a_killed_mam_run(tmp_path: Path) -> None:
    proc = hold_role_lock(tmp_path, 2.0, launcher="token-of-a-dead-mam-run")
    said: list[str] = []
    try:
        t0 = time.monotonic()
        runlock.lock_run(tmp_path, "held", orphan_wait_s=30.0, waiting=said.append).release()
        waited = time.monotonic() - t0
    finally:
        proc.kill()
        proc.wait()
    assert 1.0 < waited < 20.0
    assert len(said) == 1 and f"waiting for the stopping learner of run 'held' (pid {proc.pid}" in said[0], said


def test_a_learner_started_by_hand_is_not_waited_for(tmp_path: Path) -> None:
    proc = hold_role_lock(tmp_path, 60.0, launcher="")
    try:
        t0 = time.monotonic()
        with pytest.raises(runlock.RunInUse, match=f"in use by learner of run 'held' \\(pid {proc.pid}"):
            runlock.lock_run(tmp_path, "held", orphan_wait_s=30.0)
        assert time.monotonic() - t0 < 5.0
    finally:
        proc.kill()
        proc.wait()
    runlock.lock_run(tmp_path, "held").release()  # the lock went with it


def test_a_child_of_a_killed_mam_run_that_does_not_stop_is_refused_after_the_wait(tmp_path: Path) -> None:
    proc = hold_role_lock(tmp_path, 60.0, launcher="token-of-a-dead-mam-run")
    try:
        with pytest.raises(runlock.RunInUse, match="in use by learner of run 'held'"):
            runlock.lock_run(tmp_path, "held", orphan_wait_s=1.0)
        assert runlock.in_use(tmp_path, (runlock.RUN_LOCK,)) is None  # the refused `mam run` let its lock go
    finally:
        proc.kill()
        proc.wait()
