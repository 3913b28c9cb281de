"""What `mam run` shows while a run goes and when it ends: the progress bar's columns and text
(`bar_columns`, `bar_info`), the allocation lines, the done line and the outcome line (`done_text`,
`outcome_text`). View only: functions of the run's config, what is known of the run (`mam watch`'s
`MonitorState`, services/roles/monitor_view.py) and its summary, to text; the launcher's loop
(launcher.py) feeds them and prints what they return."""

from __future__ import annotations

import os
import shutil
import sys
from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, ProgressColumn, TextColumn, TimeRemainingColumn

from mam_core.envs.apple_collect import best_apple_return
from mam_core.schedule import Schedule
from services.messaging.codec import Allocation
from services.roles.monitor_view import MonitorState
from services.run.config import RunConfig


def done_text(cfg: RunConfig, summary: dict[str, Any], reached_s: float | None) -> str:
    """The done line: wall time (and when the budget was reached, `reached_s` after the launcher
    started: the progress bar's last time), the final returns, the survivor or "no elimination in
    this budget". A resumed run's wall time counts every part; the bar's clock only the last, and
    the line says so."""
    wall, parts = summary["launcher_wall_time_s"], int(summary.get("parts") or 1)
    text = f"[bold green]done[/] in {wall:.0f} s"
    if reached_s is not None and parts > 1:  # the wall time counts every part, the bar's clock this one
        text += (f" over {parts} parts (this part reached the budget {clock_text(reached_s)}"
                 " after it started, then the final evaluation)")
    elif reached_s is not None:
        text += f" (budget reached at {clock_text(reached_s)}, then the final evaluation)"
    returns = ", ".join("—" if r is None else f"{r:.2f}" for r in summary.get("final_returns") or [])
    text += f": final returns [{returns}]"
    if isinstance(summary.get("survivor"), int) and cfg.algo.actors > 1:
        text += f", survivor {summary['survivor']}"
    elif cfg.algo.actors > 1:
        text += ", no elimination in this budget"
    return text


def clock_text(seconds: float) -> str:
    s = int(max(seconds, 0))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def budget_text(cfg: RunConfig) -> str:
    """The budget as the user set it and in transitions: "4,000 iterations (16,000 transitions)"."""
    transitions = Schedule.for_run(cfg.algo, cfg.steps).budget
    if cfg.algo.schedule == "paper" and transitions != cfg.steps:
        return f"{cfg.steps:,} iterations ({transitions:,} transitions)"
    return f"{transitions:,} transitions"


def describe_allocation(alloc: Allocation | None) -> str:
    """One allocation: the returns R_k it was decided on, P_k (Eq. 8), I_k, the survivor and the tie
    (actors sharing the best return; at C the run's seeded generator picks the survivor among them)."""
    if alloc is None:
        return "waiting for the referee"
    p = " ".join(f"{x:.2f}" for x in alloc.probabilities)
    i = " ".join(str(c) for c in alloc.counts)
    text = f"round {alloc.round}"
    if alloc.returns is not None:
        text += "  R=[" + " ".join(f"{r:.2f}" for r in alloc.returns) + "]"
    text += f"  P=[{p}]  I=[{i}]"
    if alloc.survivor is not None:
        text += f"  survivor {alloc.survivor}"
    tie = tied_best(alloc)
    if tie and alloc.survivor is not None and alloc.reason == "elimination":
        names = ", ".join(str(k) for k in tie)
        text += f"  (tie: actors {names} share the best return; the run's seeded generator picked {alloc.survivor})"
    return text


def at_text(cfg: RunConfig, transitions: int) -> str:
    """A point of the run in the schedule's units: "iteration 600 (3,000 transitions)"."""
    clock = Schedule.for_run(cfg.algo, cfg.steps)
    if clock.paper and clock.units_at(transitions) != transitions:
        return f"iteration {clock.units_at(transitions):,} ({transitions:,} transitions)"
    return f"{transitions:,} transitions"


def progress_text(cfg: RunConfig, transitions: int, updates: int, rates: tuple[float, float] | None) -> str:
    """The progress bar's text: iterations (paper), updates, transitions/s and updates/s."""
    clock = Schedule.for_run(cfg.algo, cfg.steps)
    text = f"it {clock.units_at(transitions):,}/{cfg.steps:,} " if clock.paper else ""
    text += f"upd {updates:,}"
    if rates is not None:
        text += f" {rates[0]:,.0f} transitions/s {rates[1]:,.0f} upd/s"
    return text


def bar_columns() -> tuple[ProgressColumn, ...]:
    """The progress bar: transitions done of the budget, the clock (from the launcher's start; it
    stops when the budget is reached, as the done line says), the time left, `bar_info`'s text."""
    return (TextColumn("[bold]transitions"), BarColumn(bar_width=16), MofNCompleteColumn(),
            TextColumn("[yellow]{task.fields[clock]}"), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))


def bar_info(cfg: RunConfig, state: MonitorState) -> str:
    """The progress bar's text from what is known of the run: progress and rates (`progress_text`)
    and the last evaluation's returns R=[...]; once the learner's stats say the budget is reached,
    its progress then and "budget reached: final evaluation". (I_k: on the allocation lines.)"""
    stats = state.stats or {}
    transitions, updates = int(stats.get("env_steps") or 0), int(stats.get("updates") or 0)
    if stats.get("done"):
        return f"{progress_text(cfg, transitions, updates, None)}  budget reached: final evaluation"
    rates = None if state.steps_per_s is None else (state.steps_per_s, state.updates_per_s or 0.0)
    last_eval = "" if not state.last_mean else "R=[" + " ".join(
        "—" if m is None else f"{m:.2f}" for m in state.last_mean) + "]"
    return f"{progress_text(cfg, transitions, updates, rates)}  {last_eval}"


def allocation_line(cfg: RunConfig, alloc: Allocation) -> str:
    """The line printed above the bar for a new allocation: why it was made, when, and what."""
    return f"[magenta]{alloc.reason}[/] at {at_text(cfg, alloc.env_steps)}: {describe_allocation(alloc)}"


def tied_best(alloc: Allocation) -> list[int]:
    """The actors that share the best return of an allocation decided on returns, if more than one."""
    if alloc.returns is None or len(alloc.returns) < 2:
        return []
    best = max(alloc.returns)
    tie = [k for k, r in enumerate(alloc.returns) if abs(r - best) <= 1e-9 * max(1.0, abs(best))]
    return tie if len(tie) > 1 else []


def command_name() -> str:
    """How to call `mam` again: "mam" when that is the one on PATH, else the path it was started by
    (".venv/bin/mam" after `make`)."""
    argv0 = sys.argv[0] if sys.argv else ""
    if os.path.basename(argv0) != "mam":
        return "mam"
    found = shutil.which("mam")
    if found and os.path.realpath(found) == os.path.realpath(argv0):
        return "mam"
    relative = os.path.relpath(argv0)
    return relative if not relative.startswith("..") else argv0


# The mean and std of a uniform random policy's undiscounted return over 100 seeded episodes
# (benchmarks/random_policy_returns.py, gymnasium 1.x with MuJoCo; docs/RESULTS.md, "Reference
# returns"): the floor a MuJoCo outcome is printed beside.
RANDOM_POLICY_RETURNS: dict[str, tuple[float, float]] = {
    "HalfCheetah-v5": (-293.1, 96.2), "Hopper-v5": (18.8, 18.1), "Walker2d-v5": (1.9, 5.6),
    "Ant-v5": (-63.1, 98.5), "Humanoid-v5": (111.6, 33.0), "Reacher-v5": (-42.8, 3.7),
    "InvertedPendulum-v5": (5.1, 2.9), "InvertedDoublePendulum-v5": (46.6, 14.9), "Swimmer-v5": (-0.6, 10.6),
}


def outcome_text(cfg: RunConfig, summary: dict[str, Any]) -> str:
    """The run's outcome in the task's words on AppleCollect ("survivor 0 reaches the 50 apple in
    6 steps: 49.94 of 49.94 possible"), beside a uniform random policy's return on the MuJoCo
    tasks of RANDOM_POLICY_RETURNS; "" for other envs (the done line has the returns)."""
    returns = summary.get("final_returns") or []
    survivor = summary.get("survivor")
    known = [(r, k) for k, r in enumerate(returns) if r is not None]
    if not known:
        return ""
    if isinstance(survivor, int) and 0 <= survivor < len(returns) and returns[survivor] is not None:
        k, who = survivor, f"survivor {survivor}"
    else:
        k = max(known, key=lambda rk: (rk[0], -rk[1]))[1]
        who = f"actor {k}" if len(returns) == 1 else f"best actor {k} (no elimination)"
    r = float(returns[k])
    if cfg.env_id in RANDOM_POLICY_RETURNS and not cfg.env_kwargs:
        mean, std = RANDOM_POLICY_RETURNS[cfg.env_id]
        return (f"{who}: mean return {r:,.1f}; a uniform random policy scores {mean:,.1f} ± {std:,.1f} on "
                f"{cfg.env_id} (docs/RESULTS.md, \"Reference returns\")")
    best = best_apple_return(cfg.env_id, cfg.env_kwargs)
    if best is None:
        return ""
    of = f"{r:.2f} of {best:.2f} possible"
    for apple in (50.0, 10.0):
        steps = round((apple - r) / 0.01)
        if 1 <= steps <= 100 and abs(apple - 0.01 * steps - r) < 1e-6:
            if apple == 50.0:
                return f"{who} reaches the 50 apple in {steps} steps: {of}"
            return f"{who} settles for a 10 apple in {steps} steps: {of} (the 50 apple is missed)"
    if abs(r + 1.0) < 1e-6:
        return f"{who} reaches no apple (100 steps without one, or it leaves the square): {of}"
    return f"{who}'s mean return: {of}"
