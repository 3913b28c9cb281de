"""Issue 38: recovery without holes. A resume at any lag, a learner restarted after a resume,
... end exact and equal to the fault-free run (the one-process reference), or stop with a clear
error. Real `mam run` processes on loopback, real signals."""

from __future__ import annotations

import json
import os
import re
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
from services.run.chaos import children_of
from services.run.rundir import read_jsonl
from tests.e2e import ROOT, processes_of, unique_run

ENV = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore")
# AppleCollect-v1 MA-DDPG, K=2, M=3, 4,000 iterations with the elimination at 2,400: about 30 s a part.
SMALL = dict(workers=3, actors=2, start_steps=200, compete_every=600, eliminate_at=2400, eval_episodes=2,
             eval_every=600, hidden=(16, 16), batch_size=16, seed=4)
STEPS = 4000


def apple(steps: int = STEPS, compete_every: int = 600, eliminate_at: int = 2400, eval_every: int = 600) -> list[str]:
    """`mam run`'s flags for SMALL (checkpoints at the default cadence unless a test adds its own)."""
    return ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(steps), "--workers", "3", "--actors", "2",
            "--start-steps", "200", "--compete-every", str(compete_every), "--eliminate-at", str(eliminate_at),
            "--eval-episodes", "2", "--eval-every", str(eval_every), "--hidden", "16,16", "--batch-size", "16",
            "--seed", "4", "--no-plot"]


def start(run_dir: Path, *args: str, out: Path) -> subprocess.Popen:
    """`mam run ARGS` in its own process group (a group kill takes every child with it)."""
    with open(out, "ab") as f:
        return subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, env=ENV, stdout=f,
                                stderr=subprocess.STDOUT, start_new_session=True)


def iterations(run_dir: Path, after: int = 0) -> int:
    """The most iterations learner.jsonl shows in its rows after the first `after`."""
    rows = read_jsonl(run_dir / "learner.jsonl") if (run_dir / "learner.jsonl").is_file() else []
    return max((r.get("iterations", 0) for r in rows[after:]), default=0)


def wait_until(predicate, timeout: float, what: str, proc: subprocess.Popen, out: Path) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"mam run exited ({proc.returncode}) while waiting for {what}: " \
            f"{out.read_text(errors='replace')[-3000:]}"
        assert time.monotonic() < deadline, f"timed out waiting for {what}: {out.read_text(errors='replace')[-3000:]}"
        time.sleep(0.2)


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL `mam run` and every child, as a reboot would (the children run in sessions of their
    own: a kill of the launcher's group alone would let them stop on SIGTERM, checkpointing)."""
    os.kill(proc.pid, signal.SIGSTOP)  # restarts nothing meanwhile
    for pid, _role in children_of(proc.pid):
        os.kill(pid, signal.SIGKILL)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(30)


def learner_pid(proc: subprocess.Popen) -> int:
    pids = [pid for pid, role in children_of(proc.pid) if role == "learner"]
    assert pids, children_of(proc.pid)
    return pids[0]


def checkpointed(run_dir: Path) -> int:
    """The iteration of the learner's last checkpoint (its log), 0 before the first."""
    return checkpointed_in(run_dir / "logs" / "learner.log")


def checkpointed_in(log: Path) -> int:
    """The iteration of the last checkpoint a learner's log names, 0 before the first."""
    found = re.findall(r"checkpoint \S+ at iteration (\d+)", log.read_text(errors="replace")) if log.is_file() else []
    return int(found[-1]) if found else 0


def resumed_at(run_dir: Path) -> list[int]:
    """The iterations each resume of the learner started at (its log)."""
    text = (run_dir / "logs" / "learner.log").read_text(errors="replace")
    return [int(m) for m in re.findall(r"resumed at iteration (\d+)", text)]


def assert_equals_reference(run_dir: Path, **changes) -> None:
    """Exact, and every evaluation's returns and every final policy array equal the reference's."""
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exact"] is True, summary
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", **{**SMALL, **changes}), STEPS)
    assert [e["returns"] for e in read_jsonl(run_dir / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    transport = json.loads((run_dir / "transport.json").read_text())
    assert transport["lost"] == 0 and transport["duplicates"] == 0, transport


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_lag_1_group_kill_resume_then_a_learner_kill_in_the_resumed_part_equals_the_reference(tmp_path: Path) -> None:
    """Items 1 and 2: at `--lag 1` the resumed learner publishes the version before its own (the
    workers' first iteration acts with it), and the learner killed in the resumed part comes back
    on that part's endpoint, not the first part's."""
    run, run_dir, out = unique_run("lag1-resume"), tmp_path / "run", tmp_path / "mam.out"
    args = [*apple(), "--checkpoint-seconds", "2", "--lag", "1", "--stall-timeout", "60"]
    proc = start(run_dir, *args, "--run", run, "--run-dir", str(run_dir), out=out)
    try:
        wait_until(lambda: iterations(run_dir) >= 300 and list((run_dir / "checkpoints").glob("manifest-*.json")),
                   180, "iteration 300 and a checkpoint", proc, out)
        time.sleep(2.5)  # a checkpoint past the random phase
        kill_group(proc)
        first_endpoint = json.loads((run_dir / "config.json").read_text())["endpoint"]
        proc = start(run_dir, "--resume", str(run_dir), out=out)
        wait_until(lambda: (run_dir / "logs" / "learner.log").is_file() and resumed_at(run_dir), 120,
                   "the resume", proc, out)
        resumed, rows = resumed_at(run_dir)[-1], len(read_jsonl(run_dir / "learner.jsonl"))
        assert resumed > 200, resumed  # past the random phase: its first iteration acts with a learned version
        endpoint = json.loads((run_dir / "config.json").read_text())["endpoint"]
        assert endpoint != first_endpoint  # the resumed part's own port, in config.json for a later restart
        wait_until(lambda: iterations(run_dir, after=rows) >= resumed + 300 and
                   checkpointed(run_dir) > resumed + 100, 120, "progress and a checkpoint after the resume", proc, out)
        os.kill(learner_pid(proc), signal.SIGKILL)
        wait_until(lambda: len(resumed_at(run_dir)) >= 2, 120, "the learner's restart", proc, out)
        assert resumed_at(run_dir)[-1] > resumed + 100  # from a checkpoint the resumed part wrote
        proc.wait(300)
    finally:
        if proc.poll() is None:
            kill_group(proc)
    text = out.read_text(errors="replace")
    assert proc.returncode == 0, text[-3000:]
    assert json.loads((run_dir / "config.json").read_text())["endpoint"] == endpoint
    log = (run_dir / "logs" / "learner.log").read_text(errors="replace")
    assert f"listening on {endpoint}" in log.split("restart 1 ---")[-1], log[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["parts"] == 2 and summary["restarts"]["learner"] == 1, summary
    assert "stalled" not in text, text[-3000:]
    assert_equals_reference(run_dir, lag=1)
    assert processes_of(run) == []


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_learner_killed_long_after_its_checkpoint_at_the_default_cadence_stays_exact(tmp_path: Path) -> None:
    """Item 4: at the default 60 s checkpoint cadence the learner is killed 20 s after its first
    checkpoint. The workers resend thousands of rows; none decides it is out of step while the
    learner catches up (no slot is stepped again), the run ends exact and equal to the
    reference, and progress never stops for 30 s."""
    run, run_dir, out = unique_run("cadence"), tmp_path / "run", tmp_path / "mam.out"
    steps, small = 9000, {**SMALL, "compete_every": 1500, "eliminate_at": 6000, "eval_every": 3000}
    args = apple(steps, compete_every=1500, eliminate_at=6000, eval_every=3000)
    proc = start(run_dir, *args, "--run", run, "--run-dir", str(run_dir), out=out)
    try:
        log = run_dir / "logs" / "learner.log"
        wait_until(lambda: log.is_file() and "checkpoint " in log.read_text(errors="replace"), 120,
                   "the learner's first checkpoint", proc, out)
        time.sleep(20)
        assert len(list((run_dir / "checkpoints").glob("manifest-*.json"))) == 1  # still the first one
        os.kill(learner_pid(proc), signal.SIGKILL)
        longest, last, changed = 0.0, None, time.monotonic()
        deadline = changed + 400
        while proc.poll() is None and time.monotonic() < deadline:  # how long progress stops at most
            rows = read_jsonl(run_dir / "learner.jsonl")
            now = time.monotonic()
            if rows and rows[-1]["env_steps"] != last:
                last, changed = rows[-1]["env_steps"], now
            longest = max(longest, now - changed)
            time.sleep(0.5)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            kill_group(proc)
    text = out.read_text(errors="replace")
    assert proc.returncode == 0, text[-3000:]
    assert resumed_at(run_dir) == [0], resumed_at(run_dir)  # everything after it came from the workers' resend
    reports = [json.loads(p.read_text()) for p in (run_dir / "workers").glob("*.json")]
    assert sum(r["resent_rows"] for r in reports) > 3000, reports
    workers = " ".join(p.read_text(errors="replace") for p in (run_dir / "logs").glob("worker-*.log"))
    assert "rebuilding the slot there" not in workers
    assert longest < 30, longest  # the kill, the restart and the catch-up included
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exact"] is True, summary
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", **small), steps)
    assert [e["returns"] for e in read_jsonl(run_dir / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    assert processes_of(run) == []


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_group_kill_while_the_referee_is_behind_the_checkpoint_resumes_exactly(tmp_path: Path) -> None:
    """Item 3: the referee falls behind (SIGSTOPped after the elimination) while the learner
    checkpoints past a curve point; the whole group is killed. The resumed learner publishes the
    snapshots of the evaluations the referee had not reported done (from its checkpoint): the
    resumed run ends exact and equal to the reference."""
    run, run_dir, out = unique_run("referee-behind"), tmp_path / "run", tmp_path / "mam.out"
    steps = 6000
    proc = start(run_dir, *apple(steps), "--checkpoint-seconds", "2", "--stall-timeout", "60", "--run", run,
                 "--run-dir", str(run_dir), out=out)
    try:
        wait_until(lambda: any(a["reason"] == "elimination" for a in read_jsonl(run_dir / "allocation.jsonl")), 180,
                   "the elimination", proc, out)
        referee = [pid for pid, role in children_of(proc.pid) if role == "referee"][0]
        os.kill(referee, signal.SIGSTOP)  # alive, behind: the learner goes on past the curve point at 3,000
        wait_until(lambda: checkpointed(run_dir) > 3100, 120, "a checkpoint past iteration 3,100", proc, out)
        kill_group(proc)
        state = json.loads((run_dir / "referee_state.json").read_text())
        assert checkpointed(run_dir) < steps  # killed mid-run ...
        assert state["events_done"] <= 8, state  # ... with the referee behind: the curve point at 3,000 not done
        proc = start(run_dir, "--resume", str(run_dir), out=out)
        proc.wait(300)
    finally:
        if proc.poll() is None:
            kill_group(proc)
    text = out.read_text(errors="replace")
    assert proc.returncode == 0, text[-3000:]
    assert resumed_at(run_dir)[-1] > 3100
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["parts"] == 2, summary
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", **SMALL), steps)
    assert [e["returns"] for e in read_jsonl(run_dir / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    assert summary["exact"] is True, summary
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    assert processes_of(run) == []


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_paused_worker_whose_slot_a_spare_took_is_told_and_leaves(tmp_path: Path) -> None:
    """Item 5, in part: w1 is SIGSTOPped until its token lapses and a spare takes slot 1 over, then
    SIGCONT. The learner's stats name each slot's owner: w1 sees another owner of its slot, says
    so and exits 0 instead of waiting forever; none of its rows after the takeover is inserted,
    and the run is exact and equal to the reference."""
    from services.messaging import bus
    from tests.e2e import spawn, stop

    run, endpoint = unique_run("stale-owner"), bus.loopback_endpoint(bus.free_tcp_port())
    steps, small = 3000, {**SMALL, "compete_every": 600, "eliminate_at": 2400, "eval_every": 600}
    learner = spawn("learner", *apple(steps)[:-1], "--run", run, "--listen", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "learner.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "referee.log")
    ws = {f"w{i}": spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i),
                         "--run-dir", str(tmp_path), log=tmp_path / f"w{i}.log") for i in range(3)}
    spare_log, w1_log = tmp_path / "spare.log", tmp_path / "w1.log"
    spare = spawn("worker", "--run", run, "--connect", endpoint, "--id", "spare-0", "--spare", "--take-over-after",
                  "3", "--run-dir", str(tmp_path), log=spare_log)
    procs = [*ws.values(), spare, referee, learner]
    try:
        deadline = time.monotonic() + 180
        while iterations(tmp_path) < 300:
            assert time.monotonic() < deadline and learner.poll() is None, "the run did not reach iteration 300"
            time.sleep(0.2)
        ws["w1"].send_signal(signal.SIGSTOP)  # its token lapses after the 10 s lease; the spare takes slot 1
        deadline = time.monotonic() + 60
        while "takes over slot 1" not in spare_log.read_text(errors="replace"):
            assert time.monotonic() < deadline, spare_log.read_text(errors="replace")[-2000:]
            time.sleep(0.2)
        time.sleep(2.0)  # the spare's rows are in: it owns the slot
        ws["w1"].send_signal(signal.SIGCONT)
        assert ws["w1"].wait(30) == 0, w1_log.read_text(errors="replace")[-2000:]
        assert not (tmp_path / "summary.json").exists()  # it left at once, not when the run was done
        deadline = time.monotonic() + 240
        while not (tmp_path / "summary.json").is_file():
            assert time.monotonic() < deadline and learner.poll() in (None, 0), "the run did not finish"
            time.sleep(0.3)
        assert learner.wait(60) == 0
    finally:
        for p in procs:
            if p.poll() is None and p is ws["w1"]:
                p.send_signal(signal.SIGCONT)
        stop(*procs)
    text = w1_log.read_text(errors="replace")
    assert "slot 1 was taken over by spare-0/" in text and "this worker leaves the slot and exits" in text, text[-2000:]
    took = int(re.findall(r"taking slot 1 over at iteration (\d+)", spare_log.read_text(errors="replace"))[0])
    transport = json.loads((tmp_path / "transport.json").read_text())
    w1 = [rows for stream, rows in transport["rows_per_stream"].items() if stream.startswith("w1/")]
    assert w1 == [took - 1], (w1, took)  # slot 1's rows of iterations 1..took-1 only: none after the takeover
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["exact"] is True, summary
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", **small), steps)
    assert [e["returns"] for e in read_jsonl(tmp_path / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(tmp_path / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    assert processes_of(run) == []


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_frozen_learner_replaced_by_one_of_a_higher_epoch_stops_when_it_comes_back(tmp_path: Path) -> None:
    """Item 5, in part: learner incarnations are epochs. The learner (epoch 1) is SIGSTOPped; once
    its token lapses a second learner resumes the run from a copy of its directory (epoch 2) and
    the workers follow it. SIGCONT: the first one sees the higher epoch and stops (exit 73)
    without a checkpoint, the workers ignore its stats and weights meanwhile, and the run ends
    exact and equal to the reference."""
    import shutil

    from services.messaging import bus
    from tests.e2e import spawn, stop

    run, endpoint = unique_run("epochs"), bus.loopback_endpoint(bus.free_tcp_port())
    first, second = tmp_path / "a", tmp_path / "b"
    router = spawn("router", "--listen", endpoint, log=tmp_path / "router.log")
    l1 = spawn("learner", *apple()[:-1], "--checkpoint-seconds", "2", "--run", run, "--connect", endpoint,
               "--run-dir", str(first), log=tmp_path / "l1.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(first),
                    log=tmp_path / "referee.log")
    ws = [spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i), "--run-dir",
                str(first), log=tmp_path / f"w{i}.log") for i in range(3)]
    l2 = None
    try:
        deadline = time.monotonic() + 180
        while iterations(first) < 500 or checkpointed_in(tmp_path / "l1.log") < 300:
            assert time.monotonic() < deadline and l1.poll() is None, "the run did not get going"
            time.sleep(0.2)
        l1.send_signal(signal.SIGSTOP)  # frozen: its token lapses after the lease
        frozen_at = iterations(first)
        shutil.copytree(first, second)
        copied = len(read_jsonl(second / "learner.jsonl"))
        l2 = spawn("learner", "--resume", str(second), "--connect", endpoint, log=tmp_path / "l2.log")
        deadline = time.monotonic() + 120
        while iterations(second, after=copied) < frozen_at + 300:
            assert time.monotonic() < deadline and l2.poll() is None, (tmp_path / "l2.log").read_text()[-3000:]
            time.sleep(0.2)
        # The workers pause (not a fault) while the first learner comes back, so that the run cannot
        # end meanwhile: once the second learner has left, nothing would show a higher epoch (CI
        # saw the run end 10 s after SIGCONT, before the first learner's session was back).
        for w in ws:
            w.send_signal(signal.SIGSTOP)
        l1.send_signal(signal.SIGCONT)
        assert l1.wait(60) == 73, (tmp_path / "l1.log").read_text(errors="replace")[-3000:]
        assert not (first / "summary.json").exists()  # it stopped while the run went on
        for w in ws:
            w.send_signal(signal.SIGCONT)
        assert l2.wait(300) == 0, (tmp_path / "l2.log").read_text(errors="replace")[-3000:]
    finally:
        for proc in (l1, *ws):
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
        stop(*ws, referee, *([l2] if l2 is not None else []), l1, router)
    text = (tmp_path / "l1.log").read_text(errors="replace")
    assert "(a higher epoch) serves run" in text and "is stale" in text, text[-3000:]
    assert json.loads((second / "learner_epoch.json").read_text()) == {"epoch": 2}
    workers = " ".join((tmp_path / f"w{i}.log").read_text(errors="replace") for i in range(3))
    assert "learner e2-" in workers and "rebuilding the slot there" not in workers
    summary = json.loads((first / "summary.json").read_text())  # the referee's run directory
    assert summary["exact"] is True, summary
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", **SMALL), STEPS)
    assert [e["returns"] for e in read_jsonl(first / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(second / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    assert processes_of(run) == []
