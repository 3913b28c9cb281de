"""The ledger of `mam experiment`: compact records of finished runs, to be committed, and what
a rerun resumes from.

The ledger (`--ledger DIR` or a grid file's `ledger = "DIR"`, relative to the current directory;
none by default, and `--no-ledger` drops the file's) keeps a compact record of each finished run, to be
committed (the project's evidence grids name docs/results/<name>/runs):
DIR/<env>/<variant>/seed<k>/ with config.json, summary.json, eval.jsonl, allocation.jsonl,
bias.jsonl (where present), learner.jsonl thinned to LEARNER_ROWS rows, train_returns.jsonl (every
learner row with a training-episode return, unthinned) and record.json (the commit the run ran at, with
a dirty flag, versions, wall time, the spec, the exit status); no checkpoints, no logs.
DIR/experiment.json lists every run planned into that ledger. A run recorded in the ledger counts
as finished even when EXP_DIR does not have it (a fresh clone continues the grid).
A record made before records had train_returns.jsonl gets it from the run's directory with
`python -m mam_lab.ledger RUN_DIR RECORD_DIR` (add_train_returns).

Resumable: a run whose `summary.json` exists, or whose record is in the ledger, is skipped (after
checking that its config matches the grid); a run directory without either is continued from its
checkpoint when it was interrupted with the same code and config (mam_lab.scheduler.continuable),
else (a failed run, other code) removed and redone. Runs are ordered seed by seed (all envs and variants of seed 0,
then seed 1, ...), so a grid stopped early still has balanced results across algorithms.

Wall-time estimates (`wall_estimates`, for `--stop-by`): the record.json wall times of the
finished runs of each env and variant, here and in the ledger; a run's estimate is their median.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import typer
from rich.console import Console

from mam_lab.grid import Grid, GridError, RunSpec
from mam_lab.provenance import ROOT, code_version, versions
from services.run import rundir
from services.run.rundir import read_json, read_jsonl, write_json

RECORD = rundir.RECORD  # written last: its presence marks a finished run in the ledger
LEDGER_FILES = (rundir.CONFIG, rundir.SUMMARY, rundir.EVAL, rundir.ALLOCATION, rundir.BIAS)


LEARNER_ROWS = 200  # learner.jsonl is thinned to at most this many rows in the ledger
TRAIN_RETURNS = rundir.TRAIN_RETURNS
TRAIN_KEYS = ("iterations", "env_steps", "train_return", "train_episodes")
RECORD_FORMAT = 1


def thin_indices(n: int, max_rows: int) -> list[int]:
    """At most `max_rows` indices of 0..n-1, evenly spaced, always the first and the last."""
    if max_rows < 2:
        raise ValueError("max_rows must be >= 2")
    if n <= max_rows:
        return list(range(n))
    return sorted({round(i * (n - 1) / (max_rows - 1)) for i in range(max_rows)})


def thin_jsonl(src: Path, dest: Path, max_rows: int = LEARNER_ROWS) -> tuple[int, int]:
    """Copy the JSON-object rows of `src` to `dest`, thinned (see thin_indices); (kept, of)."""
    lines = []
    for line in Path(src).read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            if isinstance(json.loads(line), dict):
                lines.append(line)
        except json.JSONDecodeError:
            continue
    keep = thin_indices(len(lines), max_rows)
    dest.write_text("".join(lines[i] + "\n" for i in keep), encoding="utf-8")
    return len(keep), len(lines)


def extract_train_returns(src: Path, dest: Path) -> int:
    """Copy every learner.jsonl row that has a training-episode return (`train_return`: the mean return
    of the training episodes that ended since the row before) to `dest`, with only TRAIN_KEYS. The
    thinned learner.jsonl keeps few of them, and they show what the behaviour policy did between
    evaluations. Returns the number of rows."""
    rows = [row for row in read_jsonl(src) if "train_return" in row]
    dest.write_text("".join(json.dumps({k: row[k] for k in TRAIN_KEYS if k in row}) + "\n" for row in rows),
                    encoding="utf-8")
    return len(rows)


def compact_allocation(src: Path, dest: Path) -> tuple[int, int]:
    """Copy allocation.jsonl without its repeats: a "workers-changed" row that leaves round, P,
    slots, elimination and survivor as the row before it says nothing new (the referee of commit
    99feae5 re-published one every loop while workers waited after the elimination). Every round,
    elimination and real change is kept. Returns (kept, of)."""
    rows = [line for line in src.read_text(errors="replace").splitlines() if line.strip()]
    kept: list[str] = []
    last: tuple[Any, ...] | None = None
    for line in rows:
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if not isinstance(row, dict):
            continue
        key = tuple(json.dumps(row.get(k), sort_keys=True) for k in
                    ("round", "probabilities", "slots", "eliminated", "survivor"))
        if row.get("reason") == "workers-changed" and key == last:
            continue
        kept.append(line)
        last = key
    dest.write_text("".join(line + "\n" for line in kept))
    return len(kept), len(rows)


def make_record(spec: RunSpec, run_dir: Path, *, code: Mapping[str, Any], exit_status: int,
                run_wall_s: float | None, experiment: str, **extra: Any) -> dict[str, Any]:
    """record.json of a finished run: which code ran it, with what, how long."""
    summary = read_json(run_dir / rundir.SUMMARY)
    return {"format": RECORD_FORMAT, "experiment": experiment, "path": spec.path.as_posix(),
            "spec": spec.to_dict(), "commit": code.get("commit"), "dirty": bool(code.get("dirty")),
            "modified": list(code.get("modified") or []), "versions": versions(), "exit_status": exit_status,
            "wall_time_s": summary.get("wall_time_s"), "launcher_wall_time_s": summary.get("launcher_wall_time_s"),
            "run_wall_s": None if run_wall_s is None else round(run_wall_s, 2),
            "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **extra}


def write_ledger_record(run_dir: Path, dest: Path, record: Mapping[str, Any],
                        max_rows: int = LEARNER_ROWS) -> Path:
    """Copy a finished run's compact record to `dest` (the run's directory in the ledger).

    Files go to a temporary directory first, which then replaces `dest`: a reader sees the old
    record or the new one, never half of it; record.json (with the files' sizes) comes last."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    files: dict[str, int] = {}
    for name in LEDGER_FILES:
        if (run_dir / name).is_file():
            shutil.copyfile(run_dir / name, tmp / name)
    record = dict(record)
    if (run_dir / rundir.LEARNER_LOG).is_file():
        kept, total = thin_jsonl(run_dir / rundir.LEARNER_LOG, tmp / rundir.LEARNER_LOG, max_rows)
        record["learner_rows"] = {"kept": kept, "of": total}
        record["train_return_rows"] = extract_train_returns(run_dir / rundir.LEARNER_LOG, tmp / TRAIN_RETURNS)
    if (run_dir / rundir.ALLOCATION).is_file():
        kept, total = compact_allocation(run_dir / rundir.ALLOCATION, tmp / rundir.ALLOCATION)
        record["allocation_rows"] = {"kept": kept, "of": total}
    for p in sorted(tmp.iterdir()):
        files[p.name] = p.stat().st_size
    record["files"] = files
    write_json(tmp / RECORD, record)
    old = dest.parent / f".{dest.name}.old-{os.getpid()}"
    if dest.exists():
        dest.rename(old)
    tmp.rename(dest)
    if old.exists():
        shutil.rmtree(old)
    return dest


def read_record(run_dir: Path) -> dict[str, Any]:
    return read_json(Path(run_dir) / RECORD)


def add_train_returns(run_dir: Path, record_dir: Path) -> int:
    """Add train_returns.jsonl to a ledger record written before records had it, from the run's own
    directory (which still has the whole learner.jsonl). The run directory must be the recorded run:
    its config.json and summary.json are the record's, byte for byte, and every row of the record's
    thinned learner.jsonl is one of its rows. record.json then lists the file, the row count and
    `train_returns_added` (the commit that added it, and when). Returns the number of rows."""
    run_dir, record_dir = Path(run_dir), Path(record_dir)
    record = read_record(record_dir)
    if not record:
        raise GridError(f"{record_dir} is not a ledger record (no {RECORD})")
    for name in (rundir.CONFIG, rundir.SUMMARY):
        mine, theirs = run_dir / name, record_dir / name
        if not mine.is_file() or not theirs.is_file() or mine.read_bytes() != theirs.read_bytes():
            raise GridError(f"{run_dir} is not the run recorded in {record_dir}: {name} differs or is missing")
    full = run_dir / rundir.LEARNER_LOG
    if not full.is_file():
        raise GridError(f"{run_dir} has no {rundir.LEARNER_LOG}")
    lines = set(full.read_text(encoding="utf-8", errors="replace").splitlines())
    thinned_log = record_dir / rundir.LEARNER_LOG
    thinned = thinned_log.read_text(encoding="utf-8").splitlines() if thinned_log.is_file() else []
    if not thinned or any(line not in lines for line in thinned):
        raise GridError(f"{run_dir}'s {rundir.LEARNER_LOG} does not hold the record's rows")
    tmp = record_dir / f".{TRAIN_RETURNS}.tmp"
    rows = extract_train_returns(full, tmp)
    os.replace(tmp, record_dir / TRAIN_RETURNS)
    files = dict(record.get("files") or {})
    files[TRAIN_RETURNS] = (record_dir / TRAIN_RETURNS).stat().st_size
    write_json(record_dir / RECORD, {**record, "files": files, "train_return_rows": rows,
                                      "train_returns_added": {"commit": code_version(ROOT).get("commit"),
                                                              "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}})
    return rows


def write_manifest(exp_dir: Path, grid: Grid, specs: Sequence[RunSpec], aliases: Mapping[str, str],
                   ledger: Path | None = None, **extra: Any) -> None:
    """EXP_DIR/experiment.json, and a copy in the ledger (its planned runs: the union over the
    invocations that wrote to that ledger, so a subset run with --variants keeps the others)."""
    path = Path(exp_dir) / rundir.EXPERIMENT
    old = read_json(path)
    body = {"name": grid.name, "grid": grid.to_dict(), "aliases": dict(aliases),
            "runs": [s.to_dict() for s in specs], "versions": versions(),
            "created": old.get("created") or time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": sys.argv,
            "ledger": str(Path(ledger).resolve()) if ledger is not None else None, **extra}
    write_json(path, body)
    if ledger is not None:
        lpath = Path(ledger) / rundir.EXPERIMENT
        lold = read_json(lpath)
        runs = [r for r in lold.get("runs") or [] if isinstance(r, dict)]
        have = {r.get("path") for r in runs}
        runs += [r for r in body["runs"] if r["path"] not in have]
        write_json(lpath, {**body, "runs": runs, "ledger": None, "exp_dir": None,
                           "created": lold.get("created") or body["created"]})


def backfill_ledger(done: Sequence[RunSpec], exp_dir: Path, ledger: Path, experiment: str,
                     console: Console) -> None:
    """Runs finished here but not in the ledger (a ledger added later, or a failed copy): copy them,
    with the record written when they finished if there is one."""
    for spec in done:
        run_dir = Path(exp_dir) / spec.path
        if in_ledger(spec, ledger) or not (run_dir / rundir.SUMMARY).is_file():
            continue
        record = read_record(run_dir)
        if not record:  # finished before records existed: the commit is the one running now, flagged
            record = make_record(spec, run_dir, code=code_version(ROOT), exit_status=0, run_wall_s=None,
                                 experiment=experiment, backfilled=True)
        try:
            write_ledger_record(run_dir, Path(ledger) / spec.path, record)
            console.print(f"ledger: copied {spec.label}" + (" (commit unknown: recorded as the current one)"
                                                            if record.get("backfilled") else ""))
        except OSError as e:
            console.print(f"[yellow]ledger: could not copy {spec.label}: {e}[/]")


# --- resuming --------------------------------------------------------------------------------


def in_ledger(spec: RunSpec, ledger: Path | None) -> bool:
    return ledger is not None and (Path(ledger) / spec.path / RECORD).is_file()


def run_state(spec: RunSpec, exp_dir: Path, ledger: Path | None = None) -> str:
    """'done' (summary.json in the experiment directory, or a record in the ledger), 'partial'
    (a run directory without either) or 'todo'."""
    d = Path(exp_dir) / spec.path
    if (d / rundir.SUMMARY).is_file() or in_ledger(spec, ledger):
        return "done"
    return "partial" if d.exists() else "todo"


def finished_dir(spec: RunSpec, exp_dir: Path, ledger: Path | None = None) -> Path | None:
    """Where a finished run's config.json is: the experiment directory, else the ledger."""
    d = Path(exp_dir) / spec.path
    if (d / rundir.SUMMARY).is_file():
        return d
    if in_ledger(spec, ledger):
        return Path(ledger) / spec.path
    return None


def config_mismatch(spec: RunSpec, run_dir: Path) -> list[str]:
    """Differences between a finished run's config.json and what the grid asks for (device aside)."""
    try:
        have = json.loads((run_dir / rundir.CONFIG).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return ["config.json missing or unreadable"]
    want = spec.run_config("x").to_dict()
    problems = []
    for key in ("env_id", "steps"):
        if have.get(key) != want[key]:
            problems.append(f"{key}: run {have.get(key)!r}, grid {want[key]!r}")
    have_algo = have.get("algo") if isinstance(have.get("algo"), dict) else {}
    for key, value in want["algo"].items():
        if key == "device" or key not in have_algo:  # a field newer than the run: not a mismatch
            continue
        if have_algo[key] != value:
            problems.append(f"{key}: run {have_algo[key]!r}, grid {value!r}")
    return problems


def check_resume(specs: Sequence[RunSpec], exp_dir: Path, ledger: Path | None = None) -> None:
    """Refuse to mix grids: every finished run (here or in the ledger) must match the grid's configuration."""
    bad = []
    for spec in specs:
        d = finished_dir(spec, exp_dir, ledger)
        if d is not None:
            problems = config_mismatch(spec, d)
            if problems:
                bad.append(f"{d}: " + "; ".join(problems[:4]))
    if bad:
        raise GridError(f"{exp_dir} or the ledger {ledger} holds finished runs of a different grid (use another "
                        "--exp-dir / --ledger, or remove them):\n  " + "\n  ".join(bad[:10]))


# --- wall-time estimates (mam experiment --stop-by) -----------------------------------------


def record_wall_s(record: Mapping[str, Any]) -> float | None:
    """A finished run's wall time: the scheduler's (`run_wall_s`), else the launcher's, else the referee's."""
    for key in ("run_wall_s", "launcher_wall_time_s", "wall_time_s"):
        value = record.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0:
            return float(value)
    return None


def wall_estimates(specs: Sequence[RunSpec], exp_dir: Path, ledger: Path | None = None,
                   ) -> dict[tuple[str, str], list[float]]:
    """{(env, variant): wall times of its finished runs}, from the record.json of every seed of that
    env and variant in the experiment directory and the ledger (the experiment directory wins for a
    seed both have). A record made with another budget is scaled to the grid's (× steps / its steps)."""
    out: dict[tuple[str, str], list[float]] = {}
    for spec in specs:
        key = (spec.env, spec.variant)
        if key in out:
            continue
        seen: set[str] = set()
        times: list[float] = []
        for root in (Path(exp_dir), Path(ledger) if ledger is not None else None):
            if root is None:
                continue
            for path in sorted((root / spec.path.parent).glob(f"seed*/{RECORD}")):
                if path.parent.name in seen:
                    continue
                record = read_json(path)
                wall = record_wall_s(record)
                if wall is None:
                    continue
                seen.add(path.parent.name)
                steps = (record.get("spec") or {}).get("steps") if isinstance(record.get("spec"), dict) else None
                if isinstance(steps, int) and steps > 0 and steps != spec.steps:
                    wall *= spec.steps / steps
                times.append(wall)
        out[key] = times
    return out


def estimate_wall_s(times: Sequence[float]) -> float | None:
    """The estimated wall time of a run: the median of its variant's finished runs (None without any)."""
    return float(statistics.median(times)) if times else None


def main(run_dir: Path = typer.Argument(..., help="the run's directory (it has the whole learner.jsonl)"),
         record_dir: Path = typer.Argument(..., help="its record in the ledger")) -> None:
    """Add train_returns.jsonl to a ledger record made before records had it (see add_train_returns)."""
    try:
        rows = add_train_returns(run_dir, record_dir)
    except GridError as e:
        Console(stderr=True).print(f"[red]{e}[/]")
        raise typer.Exit(1) from None
    Console().print(f"{record_dir}: {TRAIN_RETURNS} with {rows} row(s)")


if __name__ == "__main__":
    typer.run(main)
