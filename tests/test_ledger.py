"""The ledger (mam_lab/ledger.py): compact records of finished runs, resuming from them."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mam_lab.grid import GridError, make_grid, plan
from mam_lab.ledger import (
    LEARNER_ROWS,
    check_resume,
    config_mismatch,
    in_ledger,
    run_state,
    thin_indices,
    thin_jsonl,
)
from mam_lab.scheduler import run_grid
from tests.lab_fixtures import (
    ROOT,
    FakeLauncher,
    _mkdir,
    finish_fake,
    quiet,
    small_grid,
)


def test_resume_skips_finished_runs_and_redoes_partial_ones(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    assert [run_state(s, exp) for s in specs] == ["todo"] * 4
    done, partial = specs[0], specs[1]
    finish_fake(done, exp)
    _mkdir(exp / partial.path)
    (exp / partial.path / "junk").write_text("left by an interrupted run")
    assert run_state(done, exp) == "done" and run_state(partial, exp) == "partial"
    check_resume(specs, exp)

    runner = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=runner, cores=[()])
    assert result.skipped == [done] and result.finished == specs[1:] and not result.failed
    assert runner.calls == [exp / s.path for s in specs[1:]]
    assert all(run_state(s, exp) == "done" for s in specs)
    assert (exp / partial.path / "launcher.log").is_file()

    again = FakeLauncher()
    result = run_grid(specs, exp, quiet(), launcher=again, cores=[()])
    assert again.calls == [] and result.skipped == specs and result.finished == []



def test_resume_refuses_finished_runs_of_another_grid(tmp_path):
    specs = plan(small_grid())
    exp = tmp_path / "exp"
    finish_fake(specs[0], exp)
    other = plan(make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=600,
                           flags={"hidden": "8,8", "batch_size": 8}))
    assert config_mismatch(other[0], exp / other[0].path) == ["steps: run 300, grid 600"]
    with pytest.raises(GridError, match="different grid"):
        check_resume(other, exp)



def test_thin_indices_keep_first_last_and_even_spacing():
    assert thin_indices(5, 300) == [0, 1, 2, 3, 4]
    assert thin_indices(0, 300) == []
    assert thin_indices(11, 3) == [0, 5, 10]
    idx = thin_indices(10_000, 300)
    assert len(idx) == 300 and idx[0] == 0 and idx[-1] == 9999
    gaps = np.diff(idx)
    assert gaps.min() >= 33 and gaps.max() <= 34



def test_thin_jsonl_skips_corrupt_lines(tmp_path):
    src = tmp_path / "a.jsonl"
    src.write_text("".join(json.dumps({"i": i}) + "\n" for i in range(1000)) + "not json\n[1]\n")
    kept, total = thin_jsonl(src, tmp_path / "b.jsonl", 100)
    rows = [json.loads(line) for line in (tmp_path / "b.jsonl").read_text().splitlines()]
    assert (kept, total) == (100, 1000) and len(rows) == 100
    assert rows[0] == {"i": 0} and rows[-1] == {"i": 999}



def test_finished_runs_go_to_the_ledger_and_a_fresh_clone_resumes_from_it(tmp_path):
    specs = plan(small_grid())
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    result = run_grid(specs[:2], exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger,
                      experiment="toy")
    assert result.finished == specs[:2]
    for spec in specs[:2]:
        rec_dir = ledger / spec.path
        names = {p.name for p in rec_dir.iterdir()}
        assert names == {"config.json", "summary.json", "eval.jsonl", "learner.jsonl", "record.json",
                         "train_returns.jsonl"}
        train = [json.loads(line) for line in (rec_dir / "train_returns.jsonl").read_text().splitlines()]
        assert train == [{"env_steps": i, "train_return": i / 10, "train_episodes": 2} for i in range(99, 1000, 100)]
        rows = (rec_dir / "learner.jsonl").read_text().splitlines()
        assert len(rows) == LEARNER_ROWS and json.loads(rows[-1])["env_steps"] == 999
        record = json.loads((rec_dir / "record.json").read_text())
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        assert record["commit"] == head and isinstance(record["dirty"], bool)
        assert record["exit_status"] == 0 and record["experiment"] == "toy"
        assert record["spec"]["variant"] == spec.variant and record["spec"]["seed"] == spec.seed
        assert record["learner_rows"] == {"kept": LEARNER_ROWS, "of": 1000} and record["train_return_rows"] == 10
        assert record["files"]["learner.jsonl"] == (rec_dir / "learner.jsonl").stat().st_size
        assert record["run_wall_s"] > 0 and "torch" in record["versions"]
        assert (exp / spec.path / "record.json").is_file()  # and beside the run
    # a fresh clone: no experiment directory, only the ledger
    fresh = tmp_path / "fresh"
    assert [run_state(s, fresh, ledger) for s in specs] == ["done", "done", "todo", "todo"]
    check_resume(specs, fresh, ledger)
    runner = FakeLauncher()
    result = run_grid(specs, fresh, quiet(), launcher=runner, cores=[()], ledger=ledger)
    assert result.skipped == specs[:2] and result.finished == specs[2:]
    assert runner.calls == [fresh / s.path for s in specs[2:]]
    assert all(in_ledger(s, ledger) for s in specs)
    # the config check applies to ledger records too
    other = plan(make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=600,
                           flags={"hidden": "8,8", "batch_size": 8}))
    with pytest.raises(GridError, match="different grid"):
        check_resume(other, tmp_path / "another", ledger)



def test_runs_finished_before_the_ledger_are_copied_to_it(tmp_path):
    specs = plan(small_grid())[:1]
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    finish_fake(specs[0], exp)
    result = run_grid(specs, exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger)
    assert result.skipped == specs
    record = json.loads((ledger / specs[0].path / "record.json").read_text())
    assert record["backfilled"] is True and record["commit"]



def test_a_record_made_before_train_returns_gets_them_from_its_own_run_directory_only(tmp_path):
    specs = plan(small_grid())[:2]
    exp, ledger = tmp_path / "exp", tmp_path / "ledger"
    run_grid(specs, exp, quiet(), launcher=FakeLauncher(), cores=[()], ledger=ledger, experiment="toy")
    rec_dir = ledger / specs[0].path
    (rec_dir / "train_returns.jsonl").unlink()  # as the records of commits before the file existed
    old = json.loads((rec_dir / "record.json").read_text())
    del old["train_return_rows"], old["files"]["train_returns.jsonl"]
    (rec_dir / "record.json").write_text(json.dumps(old))

    def add(run_dir):
        return subprocess.run([sys.executable, "-m", "mam_lab.ledger", str(run_dir), str(rec_dir)], cwd=ROOT,
                              capture_output=True, text=True, timeout=60)

    other = add(exp / specs[1].path)  # another run's directory: refused, the record untouched
    assert other.returncode == 1 and "is not the run recorded" in other.stderr
    assert not (rec_dir / "train_returns.jsonl").exists()
    assert json.loads((rec_dir / "record.json").read_text()) == old
    mine = exp / specs[0].path
    rows = (mine / "learner.jsonl").read_text().splitlines()
    (mine / "learner.jsonl").write_text("\n".join(rows[:500]) + "\n")  # cut short: not the recorded log
    assert add(mine).returncode == 1 and not (rec_dir / "train_returns.jsonl").exists()
    (mine / "learner.jsonl").write_text("\n".join(rows) + "\n")
    done = add(mine)
    assert done.returncode == 0, done.stderr
    train = [json.loads(line) for line in (rec_dir / "train_returns.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in train] == list(range(99, 1000, 100))
    record = json.loads((rec_dir / "record.json").read_text())
    assert record["train_return_rows"] == 10 and record["train_returns_added"]["commit"] == old["commit"]
    assert record["files"]["train_returns.jsonl"] == (rec_dir / "train_returns.jsonl").stat().st_size
    assert {k: v for k, v in record.items() if k not in ("files", "train_return_rows", "train_returns_added")} == \
        {k: v for k, v in old.items() if k != "files"}



def test_ledger_compacts_repeated_allocation_rows(tmp_path):
    from mam_lab.ledger import compact_allocation

    def row(reason, round_, slots, survivor=None, t=0.0):
        return json.dumps({"t": t, "round": round_, "probabilities": [0.5, 0.5], "slots": slots,
                           "eliminated": [False, False], "survivor": survivor, "reason": reason})

    src, dest = tmp_path / "allocation.jsonl", tmp_path / "out.jsonl"
    src.write_text("\n".join([
        row("initial", 0, {"w0": 0}), row("workers-changed", 0, {"w0": 0, "w1": 1}),
        row("workers-changed", 0, {"w0": 0, "w1": 1}, t=1.0),  # a repeat: dropped
        row("round", 1, {"w0": 1, "w1": 1}), row("round", 1, {"w0": 1, "w1": 1}, t=2.0),  # rounds always kept
        row("workers-changed", 1, {"w0": 1}), "not json", ""]) + "\n")
    assert compact_allocation(src, dest) == (5, 7)
    kept = [json.loads(line) for line in dest.read_text().splitlines()]
    assert [r["reason"] for r in kept] == ["initial", "workers-changed", "round", "round", "workers-changed"]

