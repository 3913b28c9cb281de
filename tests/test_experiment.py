"""`mam experiment` running grids (mam_lab/scheduler.py, experiment_run.py): retries, parallel runs
on their own cores, Ctrl-C, and one small real grid."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mam_lab.grid import plan
from mam_lab.ledger import (
    run_state,
)
from mam_lab.scheduler import core_slots, default_parallel, run_grid
from services.run.rundir import write_json
from tests.lab_fixtures import (
    PNG_MAGIC,
    ROOT,
    FakeLauncher,
    _mkdir,
    _read,
    _timing,
    finish_fake,
    quiet,
    small_grid,
)


def test_failed_runs_are_retried_and_their_logs_kept(tmp_path):
    specs = plan(small_grid())[:2]
    exp = tmp_path / "exp"
    runner = FakeLauncher("fail")
    result = run_grid(specs, exp, quiet(), launcher=runner, retries=1, cores=[()])
    assert result.finished == specs and not result.failed and len(runner.calls) == 3
    kept = list((exp / "failures").iterdir())
    assert len(kept) == 1 and (kept[0] / "logs" / "learner.log").read_text() == "boom"

    exp2 = tmp_path / "exp2"
    result = run_grid(specs, exp2, quiet(), launcher=FakeLauncher(*["fail"] * 10), retries=1, fail_fast=True,
                      cores=[()])
    assert result.failed == specs[:1] and result.finished == []
    assert run_state(specs[0], exp2) == "partial"  # redone on the next call



def test_a_run_that_exits_130_stops_the_grid(tmp_path):
    specs = plan(small_grid())
    runner = FakeLauncher("interrupt")
    result = run_grid(specs, tmp_path / "exp", quiet(), launcher=runner, cores=[()])
    assert result.interrupted and len(runner.calls) == 1 and not result.finished and not result.failed



@pytest.mark.slow
def test_small_real_grid_in_parallel_then_report_then_resume_from_the_ledger(tmp_path):
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    args = [sys.executable, "-m", "mam_lab.experiment", "--exp-dir", str(exp), "--envs", "AppleCollect-v0",
            "--algos", "ma-ddpg,ddpg", "--seeds", "2", "--steps", "1500", "--schedule", "equal-data",
            "--hidden", "32,32", "--batch-size", "32",
            "--start-steps", "300", "--compete-every", "300", "--eliminate-at", "900", "--eval-every", "300",
            "--eval-episodes", "2", "--no-plot", "--no-report", "--parallel", "2", "--ledger", str(ledger)]
    first = subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True, timeout=600)
    assert first.returncode == 0, first.stdout + first.stderr
    assert "4/4 runs finished (4 now, 0 before), 0 failed" in first.stdout
    assert "2 run(s) at once" in first.stdout
    runs = sorted(exp.glob("AppleCollect-v0/*/seed*/summary.json"))
    assert [p.parent.relative_to(exp).as_posix() for p in runs] == [
        "AppleCollect-v0/ddpg/seed0", "AppleCollect-v0/ddpg/seed1",
        "AppleCollect-v0/ma-ddpg/seed0", "AppleCollect-v0/ma-ddpg/seed1"]
    for p in runs:
        summary = json.loads(p.read_text())
        assert 1500 <= summary["env_steps"] <= 1500 + 5 * 32  # the same budget for both algorithms
        log = (p.parent / "launcher.log").read_text()
        assert "pinned to cores" in log and "done in" in log
        record = json.loads((ledger / p.parent.relative_to(exp) / "record.json").read_text())
        assert record["exit_status"] == 0 and record["parallel"] == 2 and len(record["commit"]) == 40
        assert sum(record["files"].values()) < 300_000
    cfg = {p.parent.parent.name: json.loads((p.parent / "config.json").read_text())["algo"] for p in runs}
    assert (cfg["ma-ddpg"]["actors"], cfg["ma-ddpg"]["workers"], cfg["ddpg"]["actors"]) == (3, 5, 1)
    assert not list(ledger.rglob("*.pt")) and not list(ledger.rglob("*.log"))

    rep = subprocess.run([sys.executable, "-m", "mam_lab.report", str(exp), "--n-boot", "500"], cwd=ROOT, env=env,
                         text=True, capture_output=True, timeout=300)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    text = (exp / "report.md").read_text()
    assert "## AppleCollect-v0" in text and "| ma-ddpg |" in text and "| ddpg |" in text
    assert "P(ma-ddpg > ddpg)" in text and "50 apple" in text
    for name in ("curves_AppleCollect-v0.png", "allocation_AppleCollect-v0.png", "iqm.png"):
        assert (exp / "figures" / name).read_bytes()[:8] == PNG_MAGIC
    assert "ma-ddpg" in rep.stdout and "ddpg" in rep.stdout

    stamps = {p: p.stat().st_mtime_ns for p in runs}
    second = subprocess.run(args, cwd=ROOT, env=env, text=True, capture_output=True, timeout=120)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "4 of 4 runs already finished" in second.stdout and "(0 now, 4 before)" in second.stdout
    assert {p: p.stat().st_mtime_ns for p in runs} == stamps

    # a fresh clone: the experiment directory is gone, the ledger says every run is finished
    fresh = args[:args.index("--exp-dir") + 1] + [str(tmp_path / "fresh")] + args[args.index("--exp-dir") + 2:]
    third = subprocess.run(fresh, cwd=ROOT, env=env, text=True, capture_output=True, timeout=120)
    assert third.returncode == 0, third.stdout + third.stderr
    assert "(0 now, 4 before)" in third.stdout



def test_core_slots_and_default_parallel():
    assert core_slots(2, [0, 1]) == [(0,), (1,)]
    assert core_slots(2, [0, 1, 2, 3, 4]) == [(0, 1), (2, 3)]
    assert core_slots(1, [3, 1]) == [(1, 3)]
    assert core_slots(3, [0, 1]) == [(0,), (1,), (0,)]  # more runs than cores: shared round-robin
    assert default_parallel(1, [0, 1]) == 2 and default_parallel(2, [0, 1, 2, 3, 4]) == 2
    assert default_parallel(4, [0, 1]) == 1
    with pytest.raises(ValueError):
        core_slots(0, [0])



def test_parallel_runs_go_side_by_side_each_on_its_own_cores(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    cores = sorted(os.sched_getaffinity(0))
    slots = [(cores[0],), (cores[-1],)]
    runner = FakeLauncher(delay=1.5)
    result = run_grid(specs, exp, quiet(), launcher=runner, parallel=2, cores=slots)
    assert result.finished == specs and not result.failed and not result.interrupted
    times = [_timing(exp, s) for s in specs]
    # two at a time: runs 0 and 1 overlap, and so do 2 and 3; the third starts after one ended
    assert times[0]["start"] < times[1]["end"] and times[1]["start"] < times[0]["end"]
    assert times[2]["start"] >= min(times[0]["end"], times[1]["end"]) - 0.05
    assert result.elapsed_s < 4 * 1.5  # not one after the other
    # every run on the cores of its slot, and the two concurrent runs on different slots
    assert all(tuple(t["cores"]) in slots for t in times)
    assert set(runner.cores[:2]) == set(slots)



def test_ctrl_c_stops_every_run_and_a_rerun_resumes(tmp_path):
    exp = tmp_path / "exp"
    ledger = tmp_path / "ledger"
    script = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
sys.path.insert(0, {str(Path(__file__).parent)!r})
from pathlib import Path
from lab_fixtures import FakeLauncher, quiet, small_grid
from mam_lab.grid import plan
from mam_lab.scheduler import run_grid
specs = plan(small_grid())
r = run_grid(specs, Path({str(exp)!r}), quiet(), launcher=FakeLauncher("ok", "hang", "hang"), parallel=2,
             cores=[(), ()], ledger=Path({str(ledger)!r}))
print("RESULT", r.interrupted, len(r.finished), len(r.failed), flush=True)
sys.exit(130 if r.interrupted else 0)
"""
    # Ctrl-C as a shell delivers it: the default disposition, whatever this process inherited
    # (an ignored SIGINT survives exec, and Python then never raises KeyboardInterrupt)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    specs = plan(small_grid())
    deadline = time.monotonic() + 60
    # run 0 finishes at once, then runs 1 and 2 hang side by side
    while time.monotonic() < deadline and not all(
            "hanging" in _read(exp / s.path / "launcher.log") for s in specs[1:3]):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out
    assert "RESULT True 1 0" in out  # interrupted, run 0 finished, none failed
    assert run_state(specs[0], exp, ledger) == "done"
    assert [run_state(s, exp) for s in specs[1:]] == ["partial", "partial", "todo"]
    # the hanging runs got SIGTERM and exited: no process of theirs is left
    leftover = subprocess.run(["pgrep", "-f", str(exp)], capture_output=True, text=True)
    assert leftover.stdout.strip() == ""
    # a rerun redoes the partial runs and skips the finished one
    runner = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=runner, parallel=2, cores=[(), ()], ledger=ledger)
    assert result.skipped == specs[:1] and result.finished == specs[1:]
    assert sorted(runner.calls) == sorted(exp / s.path for s in specs[1:])



def test_experiment_run_exit_status_and_pinning(tmp_path):
    """The real run process: pinned to the cores it is given; a run that cannot start exits 1."""
    run_dir = _mkdir(tmp_path / "run")
    core = sorted(os.sched_getaffinity(0))[-1]
    cfg = plan(small_grid())[0].run_config("x").to_dict()
    cfg["algo"]["batch_size"] = 0  # invalid: RunConfig.from_dict refuses it
    write_json(run_dir / "launch.json", {"config": cfg, "cores": [core], "plot": False})
    out = subprocess.run([sys.executable, "-m", "mam_lab.experiment_run", str(run_dir)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1, out.stdout + out.stderr
    assert f"pinned to cores [{core}]" in out.stdout and "Traceback" in out.stderr



def test_only_the_learner_of_a_parallel_run_is_pinned(monkeypatch):
    """`mam experiment --parallel`: the run's cores go to its learner; referee and workers float."""
    from services.run.cluster import LEARNER_CPUS_ENV, _child_setup

    every = sorted(os.sched_getaffinity(0))
    monkeypatch.setenv(LEARNER_CPUS_ENV, str(every[0]))
    code = [sys.executable, "-c", "import os; print(sorted(os.sched_getaffinity(0)))"]
    learner = subprocess.run(code, preexec_fn=_child_setup("learner"), capture_output=True, text=True, check=True)
    worker = subprocess.run(code, preexec_fn=_child_setup("worker-0"), capture_output=True, text=True, check=True)
    assert json.loads(learner.stdout) == [every[0]]
    assert json.loads(worker.stdout) == every



def test_a_stopped_run_continues_only_with_the_same_code_config_and_a_checkpoint(tmp_path):
    """mam_lab.scheduler.continuable: what a rerun of the grid continues rather than redoes."""
    from mam_lab.scheduler import continuable
    from services.run import rundir
    from services.run.config import RunConfig

    spec = plan(small_grid())[0]
    mine = spec.run_config("grid-00001-run")
    run_dir = tmp_path / "run"
    (run_dir / rundir.CHECKPOINTS).mkdir(parents=True)
    write_json(run_dir / rundir.CONFIG, {**mine.to_dict(), "endpoint": "tcp/127.0.0.1:7001"})
    write_json(run_dir / rundir.LAUNCH, {"config": mine.to_dict(), "code": "abc"})
    assert continuable(run_dir, spec.run_config("grid-00002-run"), "abc") is None  # no checkpoint yet
    (run_dir / rundir.CHECKPOINTS / "manifest-000003.json").write_text("{}")
    got = continuable(run_dir, spec.run_config("grid-00002-run"), "abc")
    assert got is not None and got.run == "grid-00001-run"  # its own name: its processes find each other
    assert continuable(run_dir, spec.run_config("x"), "abc+0123") is None  # other code
    other = RunConfig.from_dict({**mine.to_dict(), "steps": mine.steps + 1})
    assert continuable(run_dir, other, "abc") is None  # another budget
    write_json(run_dir / rundir.LAUNCH, {"config": mine.to_dict(), "code": "abc", "failed": True})
    assert continuable(run_dir, mine, "abc") is None  # a failed attempt is redone
    write_json(run_dir / rundir.LAUNCH, {"config": mine.to_dict(), "code": "abc"})
    write_json(run_dir / rundir.SUMMARY, {})
    assert continuable(run_dir, mine, "abc") is None  # finished


HOLD = """
import sys, time
from pathlib import Path
from services.run import runlock
what, where = sys.argv[1], Path(sys.argv[2])
lock = runlock.lock_experiment(where, "first") if what == "experiment" else runlock.lock_run(where, "by-hand")
print("held", flush=True)
time.sleep(120)
"""


def _hold(what: str, where: Path) -> subprocess.Popen:
    """Another live process holding WHERE's lock as `mam experiment` (or `mam run`) does."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, what, str(where)], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_experiment_on_the_same_directory_is_refused_and_touches_nothing(tmp_path):
    """Two grids on one directory would take each other's runs in flight for stopped ones."""
    exp = tmp_path / "exp"
    finish_fake(plan(small_grid())[0], exp)
    before = sorted((p.relative_to(exp).as_posix(), p.stat().st_mtime_ns) for p in exp.rglob("*"))
    first = _hold("experiment", exp)
    try:
        args = ["--exp-dir", str(exp), "--envs", "AppleCollect-v0", "--algos", "ma-ddpg,ddpg", "--seeds", "2",
                "--steps", "300", "--hidden", "8,8", "--batch-size", "8", "--no-ledger", "--no-plot", "--no-report"]
        got = subprocess.run([sys.executable, "-m", "mam_lab.experiment", *args], cwd=ROOT, text=True,
                             capture_output=True, timeout=120, env=dict(os.environ, COLUMNS="300"))
    finally:
        first.kill()
        first.wait()
    assert got.returncode == 73, got.stdout + got.stderr
    assert f"experiment directory {exp} is in use by mam experiment of grid 'first' (pid {first.pid}" in got.stdout
    after = sorted((p.relative_to(exp).as_posix(), p.stat().st_mtime_ns) for p in exp.rglob("*"))
    assert [p for p in after if p[0] != "experiment.lock"] == before  # no manifest, no run touched
    from services.run import runlock

    runlock.lock_experiment(exp, "second").release()  # the killed holder's lock went with it


def test_a_run_directory_held_by_a_live_process_is_neither_continued_nor_redone(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    busy = _mkdir(exp / specs[0].path)
    (busy / "junk").write_text("someone's run")
    holder = _hold("run", busy)
    try:
        runner = FakeLauncher()
        result = run_grid(specs, exp, quiet(), launcher=runner, cores=[()])
    finally:
        holder.kill()
        holder.wait()
    assert result.in_use == specs[:1] and result.finished == specs[1:] and not result.failed
    assert busy not in runner.calls and (busy / "junk").read_text() == "someone's run"
    result = run_grid(specs, exp, quiet(), launcher=FakeLauncher(), cores=[()])  # the holder is gone: redone
    assert result.finished == specs[:1] and not result.in_use
