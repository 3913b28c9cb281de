"""Running the grid of `mam experiment`: P runs at once, each its own process whose learner is
pinned to its own cores, its outcome in its exit status; Ctrl-C (or SIGTERM) stops them all, and a rerun resumes.

Every run of the grid is a full local cluster (`services.run.launcher.run_local`: learner, referee
and M workers over loopback Zenoh), started as its own process (`python -m mam_lab.experiment_run`)
whose exit status is the run's outcome (0 finished, 130 interrupted, else failed). `--parallel P`
runs P of them at once (default: cores ÷ `--cores-per-run`, at least 1); each run's learner is
pinned by CPU affinity to the run's own len(cores) // P cores and uses one torch thread, while its
referee and workers (light, bursty) may use any core: measured faster than pinning whole runs
(docs/PERFORMANCE.md). One progress view shows the grid and every run in progress; Ctrl-C (or SIGTERM)
sends SIGTERM to every run, whose launcher stops its processes, and a rerun resumes.

A deadline (`--stop-by TIME`, `may_start`): a run starts only if its estimated wall time (the
median of the finished runs of the same env and variant in the experiment directory and the
ledger, mam_lab.ledger.wall_estimates, updated as runs finish; for a stopped run that goes on
from its checkpoint, the share its checkpoint leaves: `remaining_share`) ends by TIME; a run with no
estimate yet (its variant has never finished) starts while TIME is still ahead, since finishing
one is how its estimate is made; after TIME nothing starts. A run still in flight at TIME is
allowed to finish and is recorded when it does. Runs not started are reported
(`GridResult.deferred`) and left for the next invocation.

A run that was stopped (Ctrl-C, SIGTERM, a SIGKILL of everything at a session's end, a reboot)
continues from its checkpoint when the grid runs again (`continuable`): the same code (commit),
the same config but for the run's name, a verified checkpoint and no summary.json. The launcher
resumes it as `mam run --resume` does, and a resumed run is the uninterrupted one bit for bit
(docs/RELIABILITY.md). Anything else about a partial run directory (a failed attempt, other code,
another config) redoes the run from the start, unless a live process holds it (runlock.in_use: a
`mam run` started there by hand): that run is neither continued nor redone (`GridResult.in_use`).
One grid per experiment directory is the caller's lock (`mam experiment` takes
runlock.lock_experiment before it writes anything there).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from pathlib import Path
from typing import IO, Any

from rich.console import Console

from mam_core.algorithm1 import Algorithm1
from mam_lab.grid import RunSpec
from mam_lab.ledger import RECORD, backfill_ledger, estimate_wall_s, make_record, run_state, write_ledger_record
from mam_lab.provenance import ROOT, code_fingerprint, code_version, run_code
from mam_lab.view import GridView, hms
from services.run import codecheck, config, rundir, runlock
from services.run.config import RunConfig
from services.run.rundir import env_dirname, read_json, write_json

STOP_WAIT_S = 60.0  # after SIGTERM, how long a run may take to stop before it is killed


@dataclass
class Launch:
    """What a run process needs: `launch(job)` starts it and returns its Popen."""

    spec: RunSpec
    cfg: RunConfig
    run_dir: Path
    cores: tuple[int, ...]  # CPU affinity of the run (empty: not pinned)
    plot: bool
    log: IO[bytes]  # the run's launcher.log: the process's stdout and stderr
    code: str = ""  # mam_lab.provenance.code_fingerprint of the grid's code


Launcher = Callable[[Launch], subprocess.Popen]


def start_run_process(job: Launch) -> subprocess.Popen:
    """`python -m mam_lab.experiment_run RUN_DIR` (see there): one run, its outcome in the exit status.

    Its own session (the terminal's Ctrl-C reaches the grid, which stops each run with SIGTERM) and
    SIGTERM when the grid dies; the grid's code first on PYTHONPATH, so every run runs it."""
    from services.run.cluster import die_with_parent

    write_json(job.run_dir / rundir.LAUNCH, {"config": job.cfg.to_dict(), "cores": list(job.cores) or None,
                                           "plot": job.plot, "code": job.code})
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return subprocess.Popen([sys.executable, "-m", "mam_lab.experiment_run", str(job.run_dir.resolve())],
                            stdout=job.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                            start_new_session=True, preexec_fn=die_with_parent)


def available_cores() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def default_parallel(cores_per_run: int = 1, cores: Sequence[int] | None = None) -> int:
    """What the machine affords: cores ÷ cores per run, at least 1."""
    n = len(cores) if cores is not None else len(available_cores())
    return max(1, n // max(1, cores_per_run))


def core_slots(parallel: int, cores: Sequence[int] | None = None) -> list[tuple[int, ...]]:
    """The cores of each of `parallel` concurrent runs: disjoint sets of len(cores) // parallel
    cores; with more runs than cores, runs share single cores round-robin."""
    if parallel < 1:
        raise ValueError("parallel must be >= 1")
    cores = sorted(cores if cores is not None else available_cores())
    per = len(cores) // parallel
    if per == 0:
        return [(cores[i % len(cores)],) for i in range(parallel)]
    return [tuple(cores[i * per:(i + 1) * per]) for i in range(parallel)]


def run_name_for(spec: RunSpec, tag: str) -> str:
    env = re.sub(r"[^A-Za-z0-9]+", "", spec.env.split("-")[0]).lower()[:16]
    return config.check_run_name(f"x{tag}-{spec.variant}-{env}-s{spec.seed}"[:128])


@dataclass
class GridResult:
    skipped: list[RunSpec] = field(default_factory=list)
    finished: list[RunSpec] = field(default_factory=list)
    failed: list[RunSpec] = field(default_factory=list)
    interrupted: bool = False
    elapsed_s: float = 0.0
    run_wall_s: dict[str, float] = field(default_factory=dict)  # label -> wall time of its finished attempt
    deferred: list[RunSpec] = field(default_factory=list)  # not started: they would end after --stop-by
    in_use: list[RunSpec] = field(default_factory=list)  # not touched: another process holds the run directory


# --- the deadline ----------------------------------------------------------------------------


def may_start(now: float, stop_by: float | None, estimate_s: float | None) -> bool:
    """The deadline rule: without a deadline every run starts; at or after it none does; before
    it, a run starts if its estimated wall time ends by the deadline (now + estimate ≤ stop_by),
    and a run without an estimate starts (its variant has never finished: running it makes one)."""
    if stop_by is None:
        return True
    if now >= stop_by:
        return False
    return estimate_s is None or now + estimate_s <= stop_by


def remaining_share(run_dir: Path, cfg: RunConfig) -> float:
    """What part of a run is still to do: 1 for a fresh one; for a stopped one that goes on from
    its checkpoint, the updates its newest checkpoint leaves of the run's (the learner's updates are
    most of a run's time), so --stop-by lets a run 90 % done finish instead of deferring it as a
    whole run."""
    total = Algorithm1.for_run(cfg.algo, cfg.steps)
    total_updates = total.updates_after(total.iterations)
    done = 0
    for path in (run_dir / rundir.CHECKPOINTS).glob(rundir.MANIFEST_GLOB):
        updates = (read_json(path) or {}).get("updates")
        if isinstance(updates, int) and not isinstance(updates, bool):
            done = max(done, updates)
    return min(max(1.0 - done / total_updates, 0.0), 1.0) if total_updates > 0 else 1.0


def parse_stop_by(text: str, now: datetime | None = None) -> datetime:
    """--stop-by TIME: "HH:MM" (local time, the next time the clock shows it: "00:30" typed at
    22:00 is tonight's) or an ISO datetime ("2026-12-02T18:30", local time unless it names its
    offset); an aware datetime. An ISO datetime already past is an error."""
    now = now if now is not None else datetime.now().astimezone()
    text = text.strip()
    m = re.fullmatch(r"(\d{1,2}):(\d{2})", text)
    try:
        if m:
            when = now.replace(hour=int(m.group(1)), minute=int(m.group(2)), second=0, microsecond=0)
            if when <= now:  # that time today is past: the next one, tomorrow
                when = (now + timedelta(days=1)).replace(hour=when.hour, minute=when.minute, second=0,
                                                         microsecond=0)
        else:
            when = datetime.fromisoformat(text)
            if when.tzinfo is None:
                when = when.replace(tzinfo=now.tzinfo)
    except ValueError as e:
        raise ValueError(f"--stop-by {text!r}: give HH:MM (local time) or an ISO datetime ({e})") from e
    if when <= now:
        raise ValueError(f"--stop-by {text!r}: {when.isoformat(timespec='minutes')} has already passed")
    return when


def continuable(run_dir: Path, cfg: RunConfig, code: str) -> RunConfig | None:
    """The config to continue a stopped run in `run_dir` with (its own, run name included), or
    None when it must be redone: it finished or failed, has no checkpoint, ran other code than
    `code` (mam_lab.provenance.code_fingerprint), other library versions (its code.json) or
    another config than `cfg`."""
    launch, saved = read_json(run_dir / rundir.LAUNCH), read_json(run_dir / rundir.CONFIG)
    if not launch or not saved or (run_dir / rundir.SUMMARY).exists() or not rundir.has_checkpoint(run_dir):
        return None
    if launch.get("failed") or not code or launch.get("code") != code:
        return None
    if codecheck.differences(run_dir, run_code()):  # other library versions (services/run/codecheck.py)
        return None
    try:
        have = RunConfig.from_dict(saved)
    except (ValueError, TypeError, KeyError):
        return None
    mine, want = have.to_dict(), cfg.to_dict()
    for key in ("run", "endpoint"):  # its own name and port: the resumed learner comes back where it was
        mine.pop(key, None)
        want.pop(key, None)
    return have if mine == want else None


def _keep_failure(exp_dir: Path, spec: RunSpec, run_dir: Path, attempt: int) -> Path | None:
    """Copy a failed attempt's logs to EXP_DIR/failures/ before its directory is redone."""
    dest = Path(exp_dir) / rundir.FAILURES / f"{env_dirname(spec.env)}_{spec.variant}_seed{spec.seed}_{attempt}_" \
                                        f"{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        dest.mkdir(parents=True, exist_ok=True)
        for name in (rundir.LAUNCHER_LOG, rundir.CONFIG, rundir.TRANSPORT):
            if (run_dir / name).is_file():
                shutil.copy2(run_dir / name, dest / name)
        if (run_dir / rundir.LOGS).is_dir():
            shutil.copytree(run_dir / rundir.LOGS, dest / rundir.LOGS, dirs_exist_ok=True)
        return dest
    except OSError:
        return None


@dataclass
class _Active:
    spec: RunSpec
    run_dir: Path
    attempt: int
    index: int
    slot: int
    cores: tuple[int, ...]
    proc: subprocess.Popen
    log: IO[bytes]
    code: dict[str, Any]
    started: float


INTERRUPTED_STATUS = frozenset({130, -signal.SIGINT, -signal.SIGTERM})


def _raise_keyboard_interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def run_grid(specs: Sequence[RunSpec], exp_dir: Path, console: Console, *, plot_runs: bool = True,
             retries: int = 1, fail_fast: bool = False, launcher: Launcher | None = None,
             tag: str | None = None, parallel: int = 1, cores: Sequence[Sequence[int]] | None = None,
             ledger: Path | None = None, experiment: str = "experiment", stop_by: float | None = None,
             estimates: dict[tuple[str, str], list[float]] | None = None,
             clock: Callable[[], float] = time.time) -> GridResult:
    """Run every spec not finished yet, `parallel` at a time, each as its own process; returns what
    happened. `cores`: the affinity of each of the `parallel` slots (None: core_slots; [] per slot:
    unpinned). A finished run's record goes to RUN_DIR/record.json and, with `ledger`, to the ledger.

    `stop_by` (seconds since the epoch, on `clock`): the deadline (may_start); `estimates`: {(env,
    variant): wall times of finished runs} (mam_lab.ledger.wall_estimates), extended as runs finish.

    Ctrl-C (or SIGTERM to the grid) sends SIGTERM to every run in progress and waits for them to stop."""
    launch = launcher or start_run_process
    exp_dir = Path(exp_dir)
    tag = tag or f"{int(time.time()) % 100000:05d}"
    parallel = max(1, int(parallel))
    slots = [tuple(c) for c in cores] if cores is not None else core_slots(parallel)
    if len(slots) < parallel:
        raise ValueError(f"{parallel} runs at once need {parallel} core sets, got {len(slots)}")
    order = {spec: i for i, spec in enumerate(specs)}
    result = GridResult()
    started = time.monotonic()
    todo = []
    for spec in specs:
        (result.skipped if run_state(spec, exp_dir, ledger) == "done" else todo).append(spec)
    if result.skipped:
        console.print(f"resuming: {len(result.skipped)} of {len(specs)} runs already finished, skipped")
        if ledger is not None:
            backfill_ledger(result.skipped, exp_dir, ledger, experiment, console)
    queue: deque[tuple[RunSpec, int]] = deque((spec, 1) for spec in todo)
    index_of: dict[RunSpec, int] = {}
    free = list(range(parallel))
    active: dict[int, _Active] = {}
    stopping = False
    estimates = {k: list(v) for k, v in (estimates or {}).items()}

    def estimate_of(spec: RunSpec) -> float | None:
        whole = estimate_wall_s(estimates.get((spec.env, spec.variant), []))
        run_dir = exp_dir / spec.path
        if whole is None or not run_dir.is_dir():
            return whole
        cfg = spec.run_config(run_name_for(spec, tag))  # a stopped run goes on only with this code and config
        if continuable(run_dir, cfg, code_fingerprint(ROOT)) is None:
            return whole
        return whole * remaining_share(run_dir, cfg)

    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt) if in_main else None

    def start(spec: RunSpec, attempt: int, slot: int) -> None:
        index = index_of.setdefault(spec, len(result.skipped) + len(index_of) + 1)
        run_dir = exp_dir / spec.path
        code, fingerprint = code_version(ROOT), code_fingerprint(ROOT)
        cfg = spec.run_config(run_name_for(spec, tag))
        resumed = continuable(run_dir, cfg, fingerprint) if run_dir.exists() and attempt == 1 else None
        if resumed is not None:  # stopped, with a checkpoint: it goes on from there, exactly
            cfg = resumed
            console.print(f"continuing {spec.label} from its checkpoint ({run_dir})", highlight=False)
        elif run_dir.exists():  # a partial run that cannot go on (failed, other code or config): redo it
            shutil.rmtree(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        log = open(run_dir / rundir.LAUNCHER_LOG, "ab" if resumed is not None else "wb")
        view.start_run(spec, run_dir, index, slot, slots[slot], estimate_s=estimate_of(spec))
        try:
            proc = launch(Launch(spec, cfg, run_dir, slots[slot], plot_runs, log, fingerprint))
        except Exception:  # could not even start: a failed attempt
            log.write(traceback.format_exc().encode())
            log.close()
            finish(_Active(spec, run_dir, attempt, index, slot, slots[slot], _NoProcess(), log, code,
                           time.monotonic()), 1)
            return
        active[slot] = _Active(spec, run_dir, attempt, index, slot, slots[slot], proc, log, code, time.monotonic())

    def finish(a: _Active, status: int) -> None:
        nonlocal stopping
        a.log.close()
        free.append(a.slot)
        free.sort()
        summary = read_json(a.run_dir / rundir.SUMMARY)
        took = max(time.monotonic() - a.started, float((summary or {}).get("launcher_wall_time_s") or 0.0))
        if status == 0 and summary:
            record = make_record(a.spec, a.run_dir, code=a.code, exit_status=status, run_wall_s=took,
                                 experiment=experiment, attempt=a.attempt, cores=list(a.cores), parallel=parallel)
            write_json(a.run_dir / RECORD, record)
            where = ""
            if ledger is not None:
                try:
                    write_ledger_record(a.run_dir, Path(ledger) / a.spec.path, record)
                    where = " → ledger"
                except OSError as e:  # the run is finished here; the next invocation copies it
                    where = f" [yellow](ledger: {e})[/]"
            finals = summary.get("final_returns") or []
            best = max((f for f in finals if isinstance(f, (int, float))), default=None)
            score = "–" if best is None else f"{best:.2f}"
            view.end_run(a.spec, True, f"[green]✓[/] {a.spec.label}  final {score}  survivor "
                                       f"{summary.get('survivor')}  {summary.get('env_steps', 0):,} transitions  "
                                       f"{hms(took)}{where}", slot=a.slot)
            result.finished.append(a.spec)
            result.run_wall_s[a.spec.label] = took
            estimates.setdefault((a.spec.env, a.spec.variant), []).append(took)
            return
        if status in INTERRUPTED_STATUS or (result.interrupted and status == -signal.SIGKILL):
            result.interrupted = True
            stopping = True
            view.end_run(a.spec, False, f"[yellow]interrupted[/] {a.spec.label} (it continues from its checkpoint "
                                        "when the grid runs again)",
                         count_failure=False, slot=a.slot)
            return
        launch = read_json(a.run_dir / rundir.LAUNCH)
        if launch:  # a failed run is redone, never continued
            write_json(a.run_dir / rundir.LAUNCH, {**launch, "failed": True})
        kept = _keep_failure(exp_dir, a.spec, a.run_dir, a.attempt)
        last = a.attempt > max(retries, 0)
        view.end_run(a.spec, False, f"[red]✗[/] {a.spec.label} failed (exit status {status}, attempt {a.attempt}"
                                    f"{'' if last or stopping else ', retrying'}); logs: {kept or a.run_dir}",
                     count_failure=last, slot=a.slot)
        if last:
            result.failed.append(a.spec)
            stopping = stopping or fail_fast
        elif not stopping:
            queue.appendleft((a.spec, a.attempt + 1))

    def reap() -> None:
        for slot, a in list(active.items()):
            status = a.proc.poll()
            if status is not None:
                del active[slot]
                finish(a, status)

    try:
        with GridView(console, specs, result.skipped, stop_by=stop_by) as view:
            try:
                while True:
                    while queue and free and not stopping:
                        spec, attempt = queue.popleft()
                        estimate = estimate_of(spec)
                        if not may_start(clock(), stop_by, estimate):
                            result.deferred.append(spec)
                            view.defer_run(spec, estimate)
                            continue
                        holder = runlock.in_use(exp_dir / spec.path)
                        if holder is not None:  # neither continued nor redone: it is someone's live run
                            result.in_use.append(spec)
                            view.progress.console.print(f"[red]not started[/] {spec.label}: its run directory "
                                                        f"{exp_dir / spec.path} is in use by {holder}",
                                                        highlight=False)
                            continue
                        start(spec, attempt, free.pop(0))
                    if not active and (stopping or not queue):
                        break
                    time.sleep(0.2)
                    reap()
            except KeyboardInterrupt:
                result.interrupted = stopping = True
                view.progress.console.print(f"[yellow]interrupted: stopping {len(active)} run(s)[/]")
            if active:  # interrupted (the grid or a run): stop every run in progress and wait for it
                _stop_runs(active, reap)
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    result.finished.sort(key=order.__getitem__)
    result.deferred.sort(key=order.__getitem__)
    result.failed.sort(key=order.__getitem__)
    result.in_use.sort(key=order.__getitem__)
    result.elapsed_s = time.monotonic() - started
    return result


class _NoProcess:
    """Stands in for a process that could not be started."""

    returncode = 1

    def poll(self) -> int:
        return 1


def _stop_runs(active: dict[int, _Active], reap: Callable[[], None]) -> None:
    """SIGTERM to every run (its launcher stops the run's processes), SIGKILL after STOP_WAIT_S or
    at a second Ctrl-C; `reap` records each run as it ends."""
    for a in active.values():
        if a.proc.poll() is None:
            a.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_WAIT_S
    try:
        while active and time.monotonic() < deadline:
            time.sleep(0.2)
            reap()
    except KeyboardInterrupt:
        pass
    for a in active.values():
        if a.proc.poll() is None:
            a.proc.kill()  # its children get SIGTERM from the kernel (PDEATHSIG)
    for a in list(active.values()):
        a.proc.wait()
    reap()
