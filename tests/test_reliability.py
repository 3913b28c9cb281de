"""Issue 20 end to end: one run per directory and name, the stall watchdog, damaged checkpoints,
a full disk, SIGTERM's exit status, learner kills before its first checkpoint. Real processes,
real Zenoh on loopback, real signals."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mam_core.schedule import Schedule
from services.messaging import bus
from services.roles.checkpoint import generations, load_checkpoint, replay_dir
from services.run import runlock
from services.run.chaos import chaos
from services.run.config import RunConfig
from tests.e2e import ROOT, processes_of, spawn, stop, unique_run
from tests.test_supervision import child_pid, learner_steps, start_mam_run, wait_until

pytestmark = pytest.mark.slow

SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "2"]
APPLE = ["--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--actors", "2", "--start-steps", "150", "--compete-every",
         "400", *SMALL]
ENV = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore")


def budget(run_dir: Path) -> int:
    """The run's budget in transitions."""
    cfg = RunConfig.from_dict(json.loads((run_dir / "config.json").read_text()))
    return Schedule.for_run(cfg.algo, cfg.steps).budget


def flat(path: Path) -> str:
    return " ".join(path.read_text(errors="replace").split())  # rich wraps long lines


def run_module(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=ENV, capture_output=True, text=True,
                          timeout=timeout)


def test_one_run_per_directory_and_sigterm_exits_143(tmp_path: Path) -> None:
    run, run_dir = unique_run("same"), tmp_path / "run"
    proc, out = start_mam_run(run, run_dir, *APPLE, "--steps", "1000000", "--workers", "1")
    try:
        wait_until(lambda: learner_steps(run_dir) > 0, 180, "training", proc)
        config = (run_dir / "config.json").read_bytes()
        logs = {p.name: p.stat().st_size for p in (run_dir / "logs").iterdir()}
        # A second `mam run` of the same name and directory is refused before it writes anything.
        second = run_module("services.cli", "run", *APPLE, "--steps", "1000", "--workers", "1", "--run", run,
                            "--run-dir", str(run_dir), "--no-plot")
        text = " ".join((second.stdout + second.stderr).split())
        assert second.returncode == 1, text
        assert f"run directory {run_dir} is in use by mam run of run '{run}'" in text and "refusing" in text, text
        # ... and so are a learner and a referee started by hand on the live directory.
        learner = run_module("services.roles.learner", "--run-config", str(run_dir / "config.json"), "--run-dir",
                             str(run_dir), "--listen", bus.loopback_endpoint(bus.free_tcp_port()))
        assert learner.returncode == 73 and "already has a live learner" in learner.stderr, learner.stderr[-2000:]
        referee = run_module("services.roles.referee", "--run", run, "--connect", json.loads(config)["endpoint"],
                             "--run-dir", str(run_dir))
        assert referee.returncode == 73 and "already has a live referee" in referee.stderr, referee.stderr[-2000:]
        assert (run_dir / "config.json").read_bytes() == config
        assert {p.name: p.stat().st_size for p in (run_dir / "logs").iterdir() if p.name in logs}.keys() == logs.keys()
        assert proc.poll() is None  # the first run is untouched
        proc.send_signal(signal.SIGTERM)
        proc.wait(90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    assert proc.returncode == 143, flat(out)
    assert "interrupted: stopping all processes" in flat(out)
    assert processes_of(run) == []
    runlock.lock_run(run_dir, run).release()  # the lock went with it: the directory can be used again


def test_a_second_learner_of_a_live_run_name_on_the_network_is_refused(tmp_path: Path) -> None:
    run, endpoint = unique_run("twin"), bus.loopback_endpoint(bus.free_tcp_port())
    first = spawn("learner", "--env", "AppleCollect-v0", "--algo", "td3", "--steps", "1000", *SMALL, "--run", run,
                  "--listen", endpoint, "--run-dir", str(tmp_path / "a"), log=tmp_path / "a.log")
    try:
        deadline = time.monotonic() + 120
        while not (tmp_path / "a" / "learner.jsonl").is_file():
            assert first.poll() is None and time.monotonic() < deadline, (tmp_path / "a.log").read_text()[-3000:]
            time.sleep(0.2)
        second = run_module("services.roles.learner", "--env", "AppleCollect-v0", "--algo", "td3", "--steps", "1000",
                            *SMALL, "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path / "b"))
    finally:
        stop(first)
    assert second.returncode == 73, second.stderr[-3000:]
    assert f"run '{run}' already has a live learner on this Zenoh network" in second.stderr
    assert not (tmp_path / "b" / "config.json").exists()  # refused before it wrote anything
    assert processes_of(run) == []


def test_the_stall_watchdog_restarts_a_frozen_learner(tmp_path: Path) -> None:
    run, run_dir = unique_run("frozen"), tmp_path / "run"
    proc, out = start_mam_run(run, run_dir, *APPLE, "--steps", "2500", "--workers", "2", "--stall-timeout", "8",
                              "--checkpoint-seconds", "2")
    try:
        wait_until(lambda: learner_steps(run_dir) > 800, 180, "800 steps", proc)
        os.kill(child_pid(proc, "learner"), signal.SIGSTOP)  # frozen: alive, its token up, no progress
        frozen_at = time.monotonic()
        wait_until(lambda: "restarted learner" in flat(out), 90, "the watchdog's restart", proc)
        acted_after = time.monotonic() - frozen_at
        proc.wait(300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    text = flat(out)
    assert proc.returncode == 0, text
    assert 8 <= acted_after < 40, acted_after
    assert "stalled: no new transition or update for" in text and "learner stats: not for" in text, text
    assert "restarting learner" in text and "restarted learner (resuming from its checkpoint)" in text, text
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"]["learner"] == 1
    assert json.loads((run_dir / "transport.json").read_text())["env_steps"] >= budget(run_dir)
    assert processes_of(run) == []


def _damage(run_dir: Path, how: str) -> str | None:
    """Damage the newest generation (`how`); the damaged path, or None if it cannot be done now."""
    g = generations(run_dir)[0]
    ck = run_dir / "checkpoints"
    if how == "flip":  # 64 random bytes into the middle of the learner state, in place (learner.pt links to it)
        path = ck / f"learner-{g:06d}.pt"
        with open(path, "r+b") as f:
            f.seek(path.stat().st_size // 2)
            f.write(os.urandom(64))
    elif how == "truncate":
        path = ck / f"learner-{g:06d}.pt"
        os.truncate(path, path.stat().st_size // 2)
    else:  # a replay chunk only the newest generation names
        names = [set(n for n in json.loads((ck / f"manifest-{x:06d}.json").read_text())["files"]
                     if n.startswith("replay/")) for x in (g, g - 1)]
        new = sorted(names[0] - names[1])
        if not new:
            return None
        path = ck / new[-1]
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    return f"{path} (generation {g})"


def test_damaged_checkpoints_resume_from_the_previous_generation(tmp_path: Path) -> None:
    run, run_dir = unique_run("damaged"), tmp_path / "run"
    proc, out = start_mam_run(run, run_dir, *APPLE, "--steps", "6000", "--workers", "2", "--checkpoint-seconds", "1",
                              "--max-restarts", "10")
    log = run_dir / "logs" / "learner.log"
    done: list[str] = []
    try:
        for how in ("flip", "truncate", "chunk"):
            base = learner_steps(run_dir)
            while True:
                wait_until(lambda: learner_steps(run_dir) > base + 400 and len(generations(run_dir)) == 2, 180,
                           f"progress before '{how}'", proc)
                pid = child_pid(proc, "learner")
                os.kill(pid, signal.SIGSTOP)  # no new generation while we damage the newest
                g = generations(run_dir)[0]
                what = _damage(run_dir, how)
                if what is not None:
                    break
                os.kill(pid, signal.SIGCONT)
                base = learner_steps(run_dir)
            os.kill(pid, signal.SIGKILL)
            done.append(what)
            wait_until(lambda: f"resuming from checkpoint generation {g - 1}" in log.read_text(errors="replace"),
                       120, f"the resume after '{how}'", proc)
        proc.wait(400)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    text = log.read_text(errors="replace")
    assert proc.returncode == 0, flat(out)
    for what in done:  # each fallback names the damaged file
        assert what.split(" (")[0] in text, what
    assert "sha256 does not match" in text and "truncated" in text
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts"]["learner"] == 3
    # Nothing lost by the fallbacks: the workers had kept every row after the generation before the
    # newest (acknowledgements are one generation late) and resent them.
    audit = json.loads((run_dir / "transport.json").read_text())["audit"]
    assert audit["lost_rows"] == 0 and audit["duplicated_rows"] == 0, audit
    assert json.loads((run_dir / "transport.json").read_text())["env_steps"] >= budget(run_dir)
    assert load_checkpoint(run_dir)["checkpoint"]["skipped"] == []
    assert processes_of(run) == []


def test_a_full_disk_stops_the_run_naming_the_path_and_free_space(tmp_path: Path, tmpfs: Path) -> None:
    run, run_dir = unique_run("diskfull"), tmpfs / "run"
    out = tmp_path / "out.txt"
    with open(out, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *APPLE, "--steps", "1000000",
                                 "--workers", "2", "--checkpoint-seconds", "1", "--run", run, "--run-dir", str(run_dir),
                                 "--no-plot"], cwd=ROOT, env=ENV, stdout=f, stderr=subprocess.STDOUT)
    try:
        wait_until(lambda: learner_steps(run_dir) > 300 and len(generations(run_dir)) == 2, 180, "2 generations",
                   proc)
        # The disk fills up. Unbuffered: a buffered file keeps the tail of a write the full disk cut
        # short and raises ENOSPC again when the `with` closes it.
        with open(tmpfs / "ballast", "wb", buffering=0) as b:
            try:
                while True:
                    b.write(b"\0" * (1 << 16))
            except OSError:
                pass
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    text = flat(out)
    assert proc.returncode == 1, text
    assert "stopping the run:" in text and f"cannot write to {run_dir}" in text and "free there" in text, text
    assert "Traceback" not in text and "OSError" not in text, text
    ck = run_dir / "checkpoints"
    assert not [p for p in ck.rglob("*") if p.name.endswith(".tmp")], sorted(p.name for p in ck.rglob("*"))
    state = load_checkpoint(run_dir)  # the previous generation is intact
    assert state["checkpoint"]["skipped"] == [] and int(state["counters"]["env_steps"]) > 0
    named = set().union(*({n.split("/")[-1] for n in json.loads(p.read_text())["files"]}
                          for p in ck.glob("manifest-*.json")))
    assert {p.name for p in replay_dir(run_dir).iterdir()} <= named  # no chunk that no generation names
    assert processes_of(run) == []


def test_learner_killed_before_its_first_checkpoint_and_three_more_times(tmp_path: Path) -> None:
    run = unique_run("early")
    args = [*APPLE, "--workers", "2", "--steps", "3000", "--checkpoint-seconds", "2", "--max-restarts", "8",
            "--run", run]
    figures = chaos(args, tmp_path / "run", kill_every=(1e6, 1e6), kill_learner_early=True, timeout=420)
    early = figures["early_kills"]
    assert [k["moment"] for k in early] == ["before the first checkpoint", "at the first transitions",
                                            "at the end of the random phase", "half way"], early
    assert early[0].get("checkpoint_on_disk") is False, early
    # The replay is complete and once, and the per-stream audit is exact: every row a worker sent is
    # in the replay or was skipped (its slot had that iteration), none both. (Before a batch of a
    # slot's owner past the slot's next iteration waited for its resend, such a batch filled the gap
    # and this test saw 2-4 rows filed both ways.) The chaos check also compares the final policy
    # with the fault-free run's: a problem of any kind fails here.
    assert figures["problems"] == [], figures
    assert figures["exit_status"] == 0 and figures["env_steps"] == budget(tmp_path / "run")
    assert figures["replay_rows"] + figures["skipped_rows"] == figures["sent_rows"], figures
    assert figures["lost_rows"] == 0 and figures["duplicated_rows"] == 0, figures
    assert figures["checkpoint_replay_rows"] == figures["env_steps"], figures
    assert figures["restarts"]["learner"] == 4
    assert processes_of(run) == []


def test_sigint_exits_130(tmp_path: Path) -> None:
    run, run_dir = unique_run("sigint"), tmp_path / "run"
    proc, out = start_mam_run(run, run_dir, *APPLE, "--steps", "1000000", "--workers", "1")
    try:
        wait_until(lambda: learner_steps(run_dir) > 0, 180, "training", proc)
        proc.send_signal(signal.SIGINT)
        proc.wait(90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    assert proc.returncode == 130, flat(out)
    assert load_checkpoint(run_dir)["checkpoint"]["skipped"] == []  # the learner's last checkpoint verifies
    assert processes_of(run) == []
