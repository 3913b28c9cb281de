"""`mam experiment --stop-by TIME` (issue 18, item 5): the deadline rule, TIME's formats, the wall-time
estimates from the ledger's records, and the scheduler with real child processes standing in for runs
(tests/lab_fixtures.py's FakeLauncher): runs that would end after TIME are not started, a run in
flight at TIME is allowed to finish and is recorded."""

from __future__ import annotations

import json
import shutil
import time
from datetime import datetime, timedelta, timezone

import pytest

from mam_lab.grid import make_grid, plan
from mam_lab.ledger import estimate_wall_s, record_wall_s, run_state, wall_estimates
from mam_lab.scheduler import may_start, parse_stop_by, run_grid
from mam_lab.view import estimate_text
from services.run.rundir import write_json
from tests.lab_fixtures import FakeLauncher, quiet, small_grid


def test_the_deadline_rule():
    assert may_start(100.0, None, 1e9)  # no deadline: everything starts
    assert may_start(100.0, 200.0, 100.0)  # ends exactly at the deadline: starts
    assert not may_start(100.0, 200.0, 100.5)  # would end after it: not started
    assert may_start(100.0, 200.0, None)  # no estimate yet, the deadline ahead: starts (it makes the estimate)
    assert not may_start(200.0, 200.0, None)  # at or after the deadline nothing starts
    assert not may_start(250.0, 200.0, 0.0)


def test_stop_by_formats():
    tz = timezone(timedelta(hours=1))
    now = datetime(2026, 12, 1, 18, 40, 30, tzinfo=tz)
    assert parse_stop_by("20:30", now) == datetime(2026, 12, 1, 20, 30, tzinfo=tz)  # today, local time
    assert parse_stop_by(" 9:05 ", datetime(2026, 12, 1, 8, 0, tzinfo=tz)) == datetime(2026, 12, 1, 9, 5, tzinfo=tz)
    assert parse_stop_by("2026-12-02T07:15", now) == datetime(2026, 12, 2, 7, 15, tzinfo=tz)  # naive: local
    assert parse_stop_by("2026-12-01T19:00:00+00:00", now) == datetime(2026, 12, 1, 20, 0, tzinfo=tz)
    # HH:MM is the next time the clock shows it: past today means tomorrow (22:05 -> "00:05" is tonight's)
    assert parse_stop_by("18:40", now) == datetime(2026, 12, 2, 18, 40, tzinfo=tz)
    late = datetime(2026, 12, 31, 22, 5, tzinfo=tz)
    assert parse_stop_by("00:05", late) == datetime(2027, 1, 1, 0, 5, tzinfo=tz)
    with pytest.raises(ValueError, match="already passed"):
        parse_stop_by("2026-12-01T18:00", now)
    with pytest.raises(ValueError, match="HH:MM"):
        parse_stop_by("25:00", now)
    with pytest.raises(ValueError, match="HH:MM"):
        parse_stop_by("tonight", now)


def _record(d, wall=None, steps=300, **extra):
    d.mkdir(parents=True, exist_ok=True)
    write_json(d / "record.json", {"run_wall_s": wall, "spec": {"steps": steps}, **extra})


def test_wall_estimates_from_the_ledger_and_the_experiment_directory(tmp_path):
    specs = plan(small_grid())  # AppleCollect-v0, ma-ddpg and ddpg, seeds 0-1, 300 steps
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    ma = specs[0].path.parent  # AppleCollect-v0/ma-ddpg
    _record(ledger / ma / "seed0", 100.0)
    _record(ledger / ma / "seed1", 300.0)
    _record(ledger / ma / "seed7", 60.0, steps=100)  # another budget: scaled × 300/100 = 180
    _record(exp / ma / "seed1", 200.0)  # the experiment directory wins over the ledger for seed 1
    _record(ledger / specs[1].path.parent / "seed0", None, launcher_wall_time_s=50.0)  # ddpg: the launcher's
    est = wall_estimates(specs, exp, ledger)
    assert sorted(est[("AppleCollect-v0", "ma-ddpg")]) == [100.0, 180.0, 200.0]
    assert est[("AppleCollect-v0", "ddpg")] == [50.0]
    assert estimate_wall_s(est[("AppleCollect-v0", "ma-ddpg")]) == 180.0  # the median
    assert estimate_wall_s([]) is None
    assert record_wall_s({"run_wall_s": None, "launcher_wall_time_s": 0, "wall_time_s": 7}) == 7.0
    assert estimate_text(180.0) == "est. 0:03:00" and estimate_text(None) == "no estimate"
    assert wall_estimates(specs, tmp_path / "none", None) == {("AppleCollect-v0", "ma-ddpg"): [],
                                                             ("AppleCollect-v0", "ddpg"): []}


def test_runs_that_would_end_after_the_deadline_are_not_started(tmp_path):
    specs = plan(small_grid())  # seed 0: ma-ddpg, ddpg; seed 1: ma-ddpg, ddpg
    exp = tmp_path / "exp"
    estimates = {("AppleCollect-v0", "ma-ddpg"): [3600.0], ("AppleCollect-v0", "ddpg"): [1.0]}
    runner = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=runner, cores=[()], stop_by=time.time() + 600,
                      estimates=estimates)
    # an hour's estimate does not fit in 10 minutes; a second does
    assert result.deferred == [specs[0], specs[2]] and result.finished == [specs[1], specs[3]]
    assert runner.calls == [exp / specs[1].path, exp / specs[3].path]
    assert [run_state(s, exp) for s in specs] == ["todo", "done", "todo", "done"]
    # the next invocation, without the deadline, runs what was left
    result = run_grid(specs, exp, quiet(), launcher=FakeLauncher(), cores=[()])
    assert result.finished == [specs[0], specs[2]] and not result.deferred


def test_a_run_in_flight_at_the_deadline_finishes_and_is_recorded(tmp_path):
    specs = plan(small_grid())
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    runner = FakeLauncher(delay=2.0)
    deadline = time.time() + 1.0  # passes while the first run (no estimate yet: it starts) is in flight
    result = run_grid(specs, exp, quiet(), launcher=runner, cores=[()], stop_by=deadline, ledger=ledger)
    assert time.time() > deadline
    assert result.finished == [specs[0]] and result.deferred == specs[1:] and not result.failed
    assert len(runner.calls) == 1
    record = json.loads((ledger / specs[0].path / "record.json").read_text())  # finished past TIME: recorded
    assert record["run_wall_s"] >= 2.0
    assert result.run_wall_s[specs[0].label] >= 2.0


def test_estimates_grow_as_runs_finish(tmp_path):
    # parallel 1: ma-ddpg's hour never fits; ddpg seed 0 has no estimate and starts, taking a little over
    # 5 s; then ddpg seed 1's estimate is that run's wall time, which no longer fits in the ~4.6 s left
    # before the deadline: not started, although the deadline has not passed yet
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    deadline = time.time() + 10.0
    result = run_grid(specs, exp, quiet(), launcher=FakeLauncher(delay=5.0), cores=[()], stop_by=deadline,
                      estimates={("AppleCollect-v0", "ma-ddpg"): [3600.0]})
    assert time.time() < deadline  # refused on its estimate, not on the clock
    assert result.finished == [specs[1]] and result.deferred == [specs[0], specs[2], specs[3]]
    assert result.run_wall_s[specs[1].label] >= 5.0


def test_the_plan_table_shows_each_rows_estimate(tmp_path):
    import io

    from rich.console import Console

    from mam_lab.view import describe_plan

    specs = plan(small_grid())
    ledger = tmp_path / "ledger"
    _record(ledger / specs[0].path.parent / "seed0", 100.0)
    _record(ledger / specs[0].path.parent / "seed1", 260.0)
    out = io.StringIO()
    describe_plan(specs, {}, tmp_path / "exp", Console(file=out, width=250), ledger,
                  wall_estimates(specs, tmp_path / "exp", ledger))
    text = out.getvalue()
    assert "est. 0:03:00 (median of 2)" in text  # median of 100 s and 260 s
    assert "no estimate" in text  # ddpg: none finished


def test_a_stopped_run_is_estimated_by_what_its_checkpoint_leaves(tmp_path):
    """A run stopped with 90 % of its updates checkpointed goes on from there: --stop-by weighs the
    10 % left, not a whole run (grid e's MA-SAC runs, stopped near their end, were deferred whole)."""
    from mam_core.algorithm1 import Algorithm1
    from mam_lab.provenance import ROOT, code_fingerprint
    from mam_lab.scheduler import remaining_share
    from services.run import rundir

    specs = plan(make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=300,
                           flags={"hidden": "8,8", "batch_size": 8, "start_steps": 50}))
    exp = tmp_path / "exp"
    run_dir, cfg = exp / specs[0].path, specs[0].run_config("x00001-stopped")
    whole = Algorithm1.for_run(cfg.algo, cfg.steps)
    total = whole.updates_after(whole.iterations)
    assert total > 0
    (run_dir / rundir.CHECKPOINTS).mkdir(parents=True)
    write_json(run_dir / rundir.CONFIG, cfg.to_dict())
    write_json(run_dir / rundir.LAUNCH, {"config": cfg.to_dict(), "code": code_fingerprint(ROOT)})
    assert remaining_share(run_dir, cfg) == 1.0  # no checkpoint yet
    write_json(run_dir / rundir.CHECKPOINTS / "manifest-000006.json", {"updates": total // 2})
    write_json(run_dir / rundir.CHECKPOINTS / "manifest-000007.json", {"updates": total * 9 // 10})
    assert remaining_share(run_dir, cfg) == pytest.approx(1 - (total * 9 // 10) / total)  # the newest
    estimates = {("AppleCollect-v0", "ma-ddpg"): [3600.0], ("AppleCollect-v0", "ddpg"): [1.0]}
    runner = FakeLauncher()

    def launcher(job):  # FAKE_RUN writes a finished run's checkpoints/ itself
        shutil.rmtree(job.run_dir / rundir.CHECKPOINTS, ignore_errors=True)
        return runner(job)

    result = run_grid(specs, exp, quiet(), launcher=launcher, cores=[()], stop_by=time.time() + 600,
                      estimates=estimates)
    # ~360 s of the stopped run fit in 10 minutes; a fresh ma-ddpg run's hour does not
    assert result.finished == [specs[0], specs[1], specs[3]] and result.deferred == [specs[2]]
    assert runner.calls[0] == run_dir
    # with other code the stopped run would be redone whole: its estimate is the whole run's again
    write_json(run_dir / rundir.LAUNCH, {"config": cfg.to_dict(), "code": "another-commit"})
    (run_dir / rundir.SUMMARY).unlink()
    write_json(run_dir / rundir.CHECKPOINTS / "manifest-000007.json", {"updates": total * 9 // 10})
    result = run_grid(specs[:1], exp, quiet(), launcher=FakeLauncher(), cores=[()], stop_by=time.time() + 600,
                      estimates=estimates)
    assert result.deferred == [specs[0]]
