"""The progress view of `mam experiment`: the grid's bar (runs, transitions, elapsed, ETA, the
--stop-by deadline) and one line per run in progress with its estimated wall time, and the table
of the planned runs with the estimated wall time per run of each row (mam_lab.ledger.wall_estimates)."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from mam_lab.grid import RunSpec, flags_text, seeds_text
from mam_lab.ledger import run_state
from services.run import rundir


def _tail_row(path: Path, max_bytes: int = 16384) -> dict[str, Any] | None:
    """The last complete JSON row of a JSONL file (None if there is none)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - max_bytes))
            data = f.read().decode("utf-8", errors="replace")
    except OSError:
        return None
    for line in reversed(data.splitlines()):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict):
            return row
    return None


def hms(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "–"
    s = int(max(seconds, 0))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


class GridView:
    """Rich progress of the whole grid: runs done / total, transitions, elapsed, ETA, and one line per
    run in progress (P of them with --parallel P). Every count is in transitions (env steps, what the
    learner counts; a run's budget T is in iterations under the paper schedule, `RunSpec.transitions`).

    The scheduler runs in the main thread; a background thread reads each current run's
    learner.jsonl / eval.jsonl once a second.
    """

    def __init__(self, console: Console, specs: Sequence[RunSpec], done: Iterable[RunSpec],
                 stop_by: float | None = None) -> None:
        from rich.progress import BarColumn, Progress, TextColumn

        self.console = console
        self.total_runs = len(specs)
        self.total_steps = sum(s.transitions for s in specs)
        done = list(done)
        self.done_runs = len(done)
        self.done_steps = sum(s.transitions for s in done)
        self.session_steps = 0  # finished this session (runs, counted by their budget)
        self.failed = 0
        self.started = time.monotonic()
        self.current: dict[int, tuple[RunSpec, Path]] = {}  # slot -> the run in it
        self.current_steps: dict[int, int] = {}
        self.tasks: dict[int, Any] = {}  # slot -> progress task
        self.estimates: dict[int, float | None] = {}  # slot -> estimated wall time of its run
        self.stop_by = stop_by
        self.deferred = 0
        self.lock = threading.Lock()
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(bar_width=28),
                                 TextColumn("{task.fields[info]}"), console=console, refresh_per_second=2,
                                 transient=False)
        self.grid_task = self.progress.add_task("[bold]grid", total=max(self.total_steps, 1),
                                                completed=self.done_steps, info="")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="grid-view", daemon=True)

    def __enter__(self) -> "GridView":
        self.progress.start()
        self._thread.start()
        self.refresh()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.refresh()
        self.progress.stop()

    def _running_steps(self) -> int:
        return sum(self.current_steps.values())

    def eta(self) -> float | None:
        elapsed = time.monotonic() - self.started
        steps = self.session_steps + self._running_steps()
        if steps <= 0 or elapsed <= 0:
            return None
        remaining = self.total_steps - self.done_steps - self._running_steps()
        return remaining / (steps / elapsed)

    def grid_info(self) -> str:
        failed = f" · [red]{self.failed} failed[/]" if self.failed else ""
        running = f" · {len(self.current)} running" if len(self.current) > 1 else ""
        deadline = ""
        if self.stop_by is not None:
            deadline = f" · stop by {time.strftime('%H:%M', time.localtime(self.stop_by))}"
            deadline += f" ({self.deferred} not started)" if self.deferred else ""
        return (f"{self.done_runs}/{self.total_runs} runs{running} · {self.done_steps + self._running_steps():,}/"
                f"{self.total_steps:,} transitions · elapsed {hms(time.monotonic() - self.started)} · "
                f"ETA {hms(self.eta())}{deadline}{failed}")

    def refresh(self) -> None:
        with self.lock:
            self.progress.update(self.grid_task, completed=self.done_steps + self._running_steps(),
                                 info=self.grid_info())

    def start_run(self, spec: RunSpec, run_dir: Path, index: int, slot: int = 0, cores: Sequence[int] = (),
                  estimate_s: float | None = None) -> None:
        where = f" [dim]cores {seeds_text(cores)}[/]" if cores else ""
        with self.lock:
            self.current[slot] = (spec, run_dir)
            self.current_steps[slot] = 0
            self.estimates[slot] = estimate_s
            if slot not in self.tasks:
                self.tasks[slot] = self.progress.add_task("", total=1, completed=0, info="")
            self.progress.update(self.tasks[slot], description=f"run {index}: {spec.label}{where}",
                                 total=spec.transitions, completed=0, info=f"starting · {estimate_text(estimate_s)}",
                                 visible=True)
        self.refresh()

    def defer_run(self, spec: RunSpec, estimate_s: float | None) -> None:
        """A run --stop-by does not start: its estimated wall time would end after the deadline."""
        with self.lock:
            self.deferred += 1
        self.progress.console.print(f"[yellow]not started[/] {spec.label}: {estimate_text(estimate_s)} would end "
                                    f"after --stop-by" if estimate_s is not None else
                                    f"[yellow]not started[/] {spec.label}: --stop-by has passed")
        self.refresh()

    def end_run(self, spec: RunSpec, ok: bool, message: str, count_failure: bool = True, slot: int = 0) -> None:
        with self.lock:
            self.current.pop(slot, None)
            self.current_steps.pop(slot, None)
            self.estimates.pop(slot, None)
            if ok:
                self.done_runs += 1
                self.done_steps += spec.transitions
                self.session_steps += spec.transitions
            elif count_failure:
                self.failed += 1
            if slot in self.tasks:
                self.progress.update(self.tasks[slot], visible=False)
        self.progress.console.print(message)
        self.refresh()

    def _poll(self) -> None:
        while not self._stop.wait(1.0):
            with self.lock:
                current = dict(self.current)
            for slot, (spec, run_dir) in current.items():
                row = _tail_row(run_dir / rundir.LEARNER_LOG) or {}
                steps = row.get("env_steps") if isinstance(row.get("env_steps"), int) else 0
                updates = row.get("updates") if isinstance(row.get("updates"), int) else 0
                ev = _tail_row(run_dir / rundir.EVAL) or {}
                means = [m for m in (ev.get("mean") or []) if isinstance(m, (int, float))]
                best = f" · best eval {max(means):.1f}" if means else ""
                with self.lock:
                    if self.current.get(slot, (None,))[0] is not spec:
                        continue
                    self.current_steps[slot] = min(steps, spec.transitions)
                    self.progress.update(self.tasks[slot], completed=self.current_steps[slot],
                                         info=f"{steps:,}/{spec.transitions:,} transitions · upd {updates:,}{best} · "
                                              f"{estimate_text(self.estimates.get(slot))}")
            self.refresh()


def budget_text(spec: RunSpec) -> str:
    """A run's budget in its own unit and in transitions: "600 iterations (1,800 transitions)"."""
    if spec.paper:
        return f"{spec.steps:,} iterations ({spec.transitions:,} transitions)"
    return f"{spec.transitions:,} transitions"


def estimate_text(estimate_s: float | None) -> str:
    """The estimated wall time of a run, as the view shows it."""
    return "no estimate" if estimate_s is None else f"est. {hms(estimate_s)}"


def budget_notes(spec: RunSpec) -> list[str]:
    """The budget notes of `mam run` (services/run/config.py) for one planned run: no update, no
    round, no elimination, M < K, a learning curve of fewer than 3 points."""
    from services.run.config import budget_warnings, curve_points

    cfg = spec.run_config("plan")
    return [*budget_warnings(cfg), *filter(None, [curve_points(cfg)])]


def describe_plan(specs: Sequence[RunSpec], aliases: Mapping[str, str], exp_dir: Path, console: Console,
                  ledger: Path | None = None, estimates: Mapping[tuple[str, str], Sequence[float]] | None = None,
                  ) -> None:
    from mam_lab.ledger import estimate_wall_s
    from mam_lab.tables import print_table

    rows = []
    groups: dict[tuple[str, str], list[RunSpec]] = {}
    for s in specs:
        groups.setdefault((s.env, s.variant), []).append(s)
    for (env, variant), ss in groups.items():
        done = sum(run_state(s, exp_dir, ledger) == "done" for s in ss)
        times = list((estimates or {}).get((env, variant), []))
        wall = estimate_text(estimate_wall_s(times)) + (f" (median of {len(times)})" if times else "")
        rows.append([env, variant, seeds_text([s.seed for s in ss]), budget_text(ss[0]),
                     flags_text(ss[0].flags) or "(paper defaults)", f"{done}/{len(ss)}", wall])
    print_table(console, f"{len(specs)} runs in {exp_dir}",
                ("env", "variant", "seeds", "budget (T)", "options", "finished", "wall/run"), rows, fold=True)
    for dup, same in aliases.items():
        console.print(f"[dim]{dup} is the same configuration as {same}: run once[/]")
    for (env, variant), ss in groups.items():  # what a variant's budget leaves out, as `mam run` says it
        for line in budget_notes(ss[0]):
            console.print(f"note: {env} {variant}: {line}", highlight=False)
