"""What `mam run` shows while a run goes and when it ends: the progress bar with the allocation, the
done line and the outcome line (`follow`, `done_text`, `outcome_text`)."""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import zenoh
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from mam_core.envs.apple_collect import best_apple_return
from services.roles.monitor_view import MonitorState, message_body
from services.run import rundir
from services.run.errors import RunStopped

if TYPE_CHECKING:
    from services.run.launcher import LocalCluster
from mam_core.schedule import Schedule
from services.messaging import bus, keys
from services.messaging.codec import Allocation, Eval, LearnerStats, MessageError, decode
from services.run.config import RunConfig


def done_text(cfg: RunConfig, summary: dict[str, Any], cluster: LocalCluster) -> str:
    """The done line: wall time (and when the budget was reached: the progress bar's last time),
    the final returns, the survivor or "no elimination in this budget". A resumed run's wall time
    counts every part; the bar's clock only the last, and the line says so."""
    wall, parts = summary["launcher_wall_time_s"], int(summary.get("parts") or 1)
    text = f"[bold green]done[/] in {wall:.0f} s"
    if cluster.done_at is not None and parts > 1:  # the wall time counts every part, the bar's clock this one
        text += (f" over {parts} parts (this part reached the budget {clock_text(cluster.done_at - cluster.started_at)}"
                 " after it started, then the final evaluation)")
    elif cluster.done_at is not None:
        text += f" (budget reached at {clock_text(cluster.done_at - cluster.started_at)}, then the final evaluation)"
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


def waited_on(stuck: list[Any], waits: dict[str, str], learner: Any, referee: Any) -> tuple[str, list[Any]]:
    """What the workers of the awaited slots say they wait for (their reports' `waits`), as text
    for the stall diagnosis, and the children to restart for it: the learner when each waits for
    weights (a version the learner does not publish; restarted, it publishes the versions its
    checkpoint keeps), the referee when each waits for an allocation, else none (the workers)."""
    said = [(c.role, waits[c.role]) for c in stuck if waits.get(c.role)]
    if not stuck or len(said) < len(stuck):
        return "", []
    text = "; " + ", ".join(f"{role} waits for {what}" for role, what in said)
    for child, what, why in ((learner, "actor ", "the learner does not publish it"),
                             (referee, "the allocation", "the referee has not decided it")):
        if child is not None and child.proc.poll() is None and all(w.startswith(what) for _, w in said):
            return f"{text} ({why})", [child]
    return text, []


def note_waits(cluster: LocalCluster, reports: bus.Latest) -> None:
    """What each worker's latest report says it waits for, by role (worker-<slot>)."""
    for item in reports.fresh().values():
        try:
            body = decode(item.payload)
            slot, waits = body.get("slot"), body.get("waits", "")
        except MessageError:
            continue
        if isinstance(slot, int) and not isinstance(slot, bool) and isinstance(waits, str):
            cluster.waits[f"worker-{slot}"] = waits[:200]


def follow(cfg: RunConfig, endpoint: str, cluster: LocalCluster, console: Console) -> bool:
    """Progress bar and supervision until the learner has finished the run (True).

    Children that die meanwhile are restarted (`LocalCluster.supervise`, which raises
    RoleKeepsDying when one dies too often).
    """
    conf = bus.make_config(connect=[endpoint], auth_file=cluster.secret_file)  # the run's secret, if any
    with supervised_session(conf, cluster) as session:  # a learner that dies before we connect is restarted
        stats = bus.Latest.subscribe(session, keys.learner_stats(cfg.run))
        allocation = bus.Latest.subscribe(session, keys.allocation(cfg.run))
        evals = bus.Latest.subscribe(session, keys.eval(cfg.run))
        roles = bus.watch_alive(session, cfg.run)
        reports = bus.Latest(late_join=False).subscribe(session, keys.role_stats_all(cfg.run, "worker"))
        with console.status("starting learner and referee"):
            while not {"learner", "referee"} <= {role for role, _ in roles.members()}:
                cluster.supervise()
                time.sleep(0.1)
        roles.close()
        cluster.start_workers()
        # What is known of the run: `mam watch`'s own state (services/roles/monitor_view.py), fed the same messages
        state = MonitorState(run=cfg.run, env_id=cfg.env_id, algo=cfg.algo.algo, steps=cfg.steps)
        state.on_config(cfg.to_dict() | {"algo": cfg.algo.algo, "algo_config": cfg.algo.to_dict()})
        # the clock counts from the launcher's start and stops when the budget is reached, as the done line says
        columns = (TextColumn("[bold]transitions"), BarColumn(bar_width=16), MofNCompleteColumn(),
                   TextColumn("[yellow]{task.fields[clock]}"), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))
        try:
            with Progress(*columns, console=console, transient=False) as progress:
                cluster.console = progress.console
                budget = Schedule.for_run(cfg.algo, cfg.steps).budget  # in transitions, what the bar counts
                task = progress.add_task("train", total=budget, info="starting",
                                         clock=clock_text(time.monotonic() - cluster.started_at))
                while True:
                    note_waits(cluster, reports)  # for the stall watchdog's diagnosis
                    cluster.supervise()
                    if cluster.finished():
                        progress.update(task, info="done")
                        return True
                    if cluster.done_at is None:
                        progress.update(task, clock=clock_text(time.monotonic() - cluster.started_at))
                    item = allocation.fresh().get(keys.allocation(cfg.run))
                    if item is not None:
                        try:
                            new = Allocation.from_bytes(item.payload, cfg.algo.actors)
                            if state.last_allocation is None or (new.round, new.survivor) != (state.round,
                                                                                               state.survivor):
                                progress.console.print(f"[magenta]{new.reason}[/] at {at_text(cfg, new.env_steps)}: "
                                                       f"{describe_allocation(new)}", highlight=False)
                            state.on_allocation(message_body(new))
                        except MessageError:
                            pass
                    item = evals.fresh().get(keys.eval(cfg.run))
                    if item is not None:
                        try:
                            state.on_eval(message_body(Eval.from_bytes(item.payload, cfg.algo.actors)))
                        except MessageError:
                            pass
                    item = stats.fresh().get(keys.learner_stats(cfg.run))
                    if item is not None:
                        try:
                            st = LearnerStats.from_bytes(item.payload)
                            cluster.observe(st)  # the stall watchdog (supervise -> check_stall)
                            state.on_stats(message_body(st))
                            rates = None if state.steps_per_s is None else (state.steps_per_s,
                                                                             state.updates_per_s or 0.0)
                            if st.done and not cluster.done:  # the budget is reached: the bar's last line
                                cluster.done, cluster.done_at = True, time.monotonic()
                                progress.update(task, completed=min(st.env_steps, budget),
                                                clock=clock_text(cluster.done_at - cluster.started_at),
                                                info=f"{progress_text(cfg, st.env_steps, st.updates, None)}  "
                                                     "budget reached: final evaluation")
                            elif not cluster.done:  # after done the rates only fall to 0: not shown
                                last_eval = "" if not state.last_mean else "R=[" + " ".join(
                                    "—" if m is None else f"{m:.2f}" for m in state.last_mean) + "]"
                                info = (f"{progress_text(cfg, st.env_steps, st.updates, rates)}  "
                                        f"{last_eval}")  # I_k: on the allocation lines above
                                progress.update(task, completed=min(st.env_steps, budget), info=info)
                        except MessageError:
                            pass
                    time.sleep(0.2)
        finally:
            cluster.console = console
            for sub in (stats, allocation, evals, reports):
                sub.close()


@contextlib.contextmanager
def supervised_session(conf: Any, cluster: LocalCluster, timeout: float = 120.0) -> Iterator[Any]:
    """The launcher's session to its learner, opened while supervising: a learner killed before the
    launcher could connect (before its first checkpoint) is restarted meanwhile, not waited for."""
    deadline = time.monotonic() + timeout
    while True:
        cluster.supervise()
        try:
            session = bus.open_session(conf)
            break
        except zenoh.ZError as e:
            if time.monotonic() > deadline:
                restarts = len(cluster.restarts.get("learner", []))
                raise RunStopped(f"no connection to the learner at {cluster.endpoint} within {timeout:.0f} s "
                                 f"({restarts} restarts of it meanwhile; {e}); see "
                                 f"{cluster.run_dir / rundir.role_log('learner')}") from e
            time.sleep(0.2)
    try:
        yield session
    finally:
        session.close()
