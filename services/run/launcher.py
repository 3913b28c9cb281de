"""`mam run`: a whole run on one box — learner, referee and M workers as child processes.

The learner listens on a free loopback port; the referee and workers connect to it as clients
(no multicast scouting, a unique run name, a per-run secret that keeps other processes out:
services/run/secret.py). The launcher is one more client: its loop (`follow`) feeds what it hears
to the progress view (progress.py) and supervises the children (cluster.py: one that dies is
restarted with backoff, the learner with `--resume`: RestartPolicy; the stall watchdog); it
stops them on Ctrl-C or at the end of the budget, reconciles what the workers sent with what the
replay holds (`audit_transport`), draws plots. Its exceptions are in errors.py.
"""

from __future__ import annotations

import contextlib
import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zenoh
from rich.console import Console
from rich.progress import Progress

from mam_core import arithmetic
from mam_core.schedule import Schedule
from services.messaging import bus, keys
from services.messaging.codec import Allocation, Eval, LearnerStats, MessageError, decode
from services.roles.monitor_view import MonitorState, message_body
from services.run import codecheck, preflight, registry, rundir, runlock, secret
from services.run.audit import audit_transport
from services.run.cluster import LocalCluster, RestartPolicy, slots_note
from services.run.config import RunConfig, budget_warnings
from services.run.errors import Interrupted, RunStopped, describe_exit
from services.run.progress import (
    allocation_line,
    bar_columns,
    bar_info,
    budget_text,
    clock_text,
    command_name,
    done_text,
    outcome_text,
)
from services.run.rundir import disk_free, write_json


def _raise_interrupted(signum: int, _frame: Any) -> None:
    raise Interrupted(signum)


def run_local(cfg: RunConfig, run_dir: Path, console: Console | None = None, plot: bool = True,
              outcome: dict[str, Any] | None = None, policy: RestartPolicy | None = None,
              code: dict[str, Any] | None = None, forced_code: list[str] | None = None,
              new_run: bool = False) -> dict[str, Any]:
    """Train `cfg` on this box; returns summary.json's content (empty if the run was stopped
    or did not finish). Children that die are restarted (`policy`). `code`, `forced_code`: what
    RUN_DIR/code.json records (services/run/codecheck.py: `record_part`). `new_run`: `run_dir`
    must not hold another run's checkpoint (preflight.ConfigError, checked once the run lock
    is held, so that no run can start there between the check and the lock).

    `outcome`, when given, gets "interrupted": whether SIGINT / SIGTERM stopped the run."""
    console = console or Console()
    arithmetic.for_children(cfg.arithmetic)  # the children pin their kernels, or not, as they start
    try:  # one run per directory: refused before anything is written (services/run/runlock.py)
        lock = runlock.lock_run(run_dir, cfg.run, waiting=lambda line: console.print(line, highlight=False))
    except runlock.RunInUse as e:
        console.print(f"[red]{e}[/]")
        if outcome is not None:
            outcome["interrupted"] = False
        return {}
    try:
        if new_run and (held := preflight.held_run(run_dir)):
            raise preflight.ConfigError(held)
        return _run_locked(cfg, run_dir, console, plot, outcome, policy, lock, code, forced_code or [])
    finally:
        lock.release()


def _run_locked(cfg: RunConfig, run_dir: Path, console: Console, plot: bool, outcome: dict[str, Any] | None,
                policy: RestartPolicy | None, lock: runlock.DirLock, code: Any, forced_code: list) -> dict[str, Any]:
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    cfg = RunConfig.from_dict({**cfg.to_dict(), "endpoint": endpoint})
    try:  # the secret first: whoever finds the endpoint in config.json can find it too, if allowed
        auth = secret.create(run_dir)
        write_json(run_dir / rundir.CONFIG, cfg.to_dict())
    except OSError as e:
        console.print(f"[red]cannot write {run_dir / rundir.CONFIG}: {e.strerror or e} ({disk_free(run_dir)} free)[/]")
        return {}
    if code is not None and (why := codecheck.record_part(run_dir, code, forced_code)):
        console.print(why, highlight=False)  # the forced differences, or why code.json cannot be written
        if why.startswith("[red]"):
            return {}
    cluster = LocalCluster(cfg, run_dir, endpoint, policy=policy or RestartPolicy(), console=console,
                           lock_token=lock.token, secret_file=auth)
    console.print(f"[bold]run[/] {cfg.run}  [bold]env[/] {cfg.env_id}  [bold]algo[/] {cfg.algo.algo} "
                  f"K={cfg.algo.actors} M={cfg.algo.workers}  budget {budget_text(cfg)}")
    for line in budget_warnings(cfg):  # no silent no-op: what the budget leaves out, and M < K
        console.print(f"[yellow]note:[/] {line}", highlight=False)
    if note := slots_note(cfg.algo.workers, cfg.slots_per_worker, arithmetic.usable_cores()):
        console.print(f"[yellow]note:[/] {note}", highlight=False)
    registry.register(cfg.run, endpoint, run_dir)  # `mam watch --run NAME` finds it without --connect
    console.print(f"run dir {run_dir}   watch live: [cyan]{command_name()} watch --run {cfg.run}[/]")
    before = rundir.earlier_parts(run_dir)  # a resumed run: what its earlier parts took and restarted
    cluster.parts = rundir.RunParts(run_dir, before)  # this part counts even if it is killed
    cluster.parts.save({})
    if rundir.has_checkpoint(run_dir):
        console.print(f"[bold]resuming[/] the run in {run_dir} from its last checkpoint (part {before['parts'] + 1}; "
                      f"the learner logs the iteration it resumes at)")
    interrupted = False
    gave_up: RunStopped | None = None
    previous = {sig: signal.signal(sig, _raise_interrupted) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        cluster.start()
        try:
            if follow(cfg, endpoint, cluster, console):
                cluster.wait(60.0, supervise=True)  # referee (final evaluation) and workers exit on their own
        except RunStopped as e:
            gave_up = e
            Console(stderr=True).print(f"[red]stopping the run: {e}[/]", highlight=False, soft_wrap=True)
        except (Interrupted, KeyboardInterrupt) as e:
            interrupted = True
            if outcome is not None:
                outcome["signal"] = e.signum if isinstance(e, Interrupted) else signal.SIGINT
            console.print("[yellow]interrupted: stopping all processes (the learner writes a checkpoint)[/]")
            console.print(f"continue it with: [cyan]{command_name()} run --resume {run_dir}[/]", highlight=False)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        cluster.stop()
        secret.remove(auth)  # the part is over: nobody joins it any more
        registry.unregister(cfg.run)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if outcome is not None:
        outcome["interrupted"] = interrupted
    failed = [c for c in cluster.children if c.proc.returncode not in (0, -signal.SIGTERM, None)]
    for c in failed:
        console.print(f"[red]{c.role} exited with {describe_exit(c.proc.returncode)}[/]: see {c.log}")
    state = cluster.parts.save(cluster.restart_counts())  # the next part of a resumed run adds to these
    restarts, wall = state["restarts"], state["wall_s"]
    summary_path = run_dir / rundir.SUMMARY
    summary: dict[str, Any] = {}
    finished = cluster.finished() and gave_up is None and not interrupted
    if summary_path.is_file() and finished:
        summary = json.loads(summary_path.read_text())
        summary["launcher_wall_time_s"] = round(wall, 2)  # every part of the run
        summary["parts"] = state["parts"]
        summary["restarts"] = restarts
        summary["restarts_total"] = sum(restarts.values())
        summary["restarts_cancelled"] = dict(cluster.cancelled)  # died in their backoff as the run finished
        audit = audit_transport(run_dir)
        if audit:
            summary["transport"] = {k: v for k, v in audit.items() if k != "per_stream"}
        write_json(summary_path, summary)
    elif finished:
        console.print(f"[red]the run reached its budget but the referee wrote no summary.json[/]: see "
                      f"{run_dir / 'logs' / 'referee.log'}")
    if plot and summary:
        from services.run.plot import plot_run
        for p in plot_run(run_dir):
            console.print(f"plot {p}")
    if summary:
        total = summary["restarts_total"]
        text = ", ".join(f"{r} {n}" for r, n in restarts.items() if n) if total else "none"
        if cluster.cancelled:
            text += "; not restarted, the run finished first: " + ", ".join(
                f"{r} {n}" for r, n in cluster.cancelled.items())
        reached = None if cluster.done_at is None else cluster.done_at - cluster.started_at  # the bar's last time
        console.print(done_text(cfg, summary, reached) + f"; restarts: {text}", highlight=False)
        if "transport" in summary:
            t = summary["transport"]
            skipped = f", {t['skipped_rows']:,} skipped (iterations already filled)" if t.get("skipped_rows") else ""
            console.print(f"transport: {t['sent_rows']:,} rows sent, {t['replay_rows']:,} in the replay{skipped}, "
                          f"{t['lost_rows']} lost, {t['duplicated_rows']} duplicated")
        verdict = outcome_text(cfg, summary)
        if verdict:
            console.print(f"[bold]{verdict}[/]", highlight=False)
    return summary


def follow(cfg: RunConfig, endpoint: str, cluster: LocalCluster, console: Console) -> bool:
    """Progress bar and supervision until the learner has finished the run (True).

    Children that die meanwhile are restarted (`LocalCluster.supervise`, which raises
    RoleKeepsDying when one dies too often). What is heard of the run feeds `mam watch`'s own
    state (MonitorState); the bar shows what progress.py makes of it.
    """
    conf = bus.make_config(connect=[endpoint], auth_file=cluster.secret_file)  # the run's secret, if any
    with supervised_session(conf, cluster) as session:  # a learner that dies before we connect is restarted
        stats = bus.Latest.subscribe(session, keys.learner_stats(cfg.run))
        allocation = bus.Latest.subscribe(session, keys.allocation(cfg.run))
        evals = bus.Latest.subscribe(session, keys.eval(cfg.run))
        roles = bus.watch_alive(session, cfg.run)
        reports = bus.Latest(late_join=False).subscribe(session, keys.role_stats_all(cfg.run, "worker"))
        with console.status("starting learner and referee"):
            while not {"learner", "referee"} <= {role for role, _ in roles.members()} and not cluster.finished():
                cluster.supervise()  # (a learner that finished the run before both were seen has left)
                time.sleep(0.1)
        roles.close()
        # What is known of the run: `mam watch`'s own state (services/roles/monitor_view.py), fed the same messages
        state = MonitorState(run=cfg.run, env_id=cfg.env_id, algo=cfg.algo.algo, steps=cfg.steps)
        state.on_config(cfg.to_dict() | {"algo": cfg.algo.algo, "algo_config": cfg.algo.to_dict()})
        try:
            with Progress(*bar_columns(), console=console, transient=False) as progress:
                cluster.console = progress.console
                budget = Schedule.for_run(cfg.algo, cfg.steps).budget  # in transitions, what the bar counts
                task = progress.add_task("train", total=budget, info="starting",
                                         clock=clock_text(time.monotonic() - cluster.started_at))
                while True:
                    note_waits(cluster, reports)  # for the stall watchdog's diagnosis
                    cluster.supervise()
                    finished = cluster.finished()  # asked first: what the roles sent before they left is read below
                    if cluster.done_at is None:
                        progress.update(task, clock=clock_text(time.monotonic() - cluster.started_at))
                    item = allocation.fresh().get(keys.allocation(cfg.run))
                    if item is not None:
                        try:
                            new = Allocation.from_bytes(item.payload, cfg.algo.actors)
                            if state.last_allocation is None or (new.round, new.survivor) != (state.round,
                                                                                               state.survivor):
                                progress.console.print(allocation_line(cfg, new), highlight=False)
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
                            if st.done and not cluster.done:  # the budget is reached: the bar's last line
                                cluster.done, cluster.done_at = True, time.monotonic()
                                progress.update(task, completed=min(st.env_steps, budget),
                                                clock=clock_text(cluster.done_at - cluster.started_at),
                                                info=bar_info(cfg, state))
                            elif not cluster.done:  # after done the rates only fall to 0: not shown
                                progress.update(task, completed=min(st.env_steps, budget), info=bar_info(cfg, state))
                        except MessageError:
                            pass
                    if finished:
                        progress.update(task, info="done")
                        return True
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


def note_waits(cluster: LocalCluster, reports: bus.Latest) -> None:
    """What each worker's latest report says it waits for, by the role that steps its slot."""
    for item in reports.fresh().values():
        try:
            body = decode(item.payload)
            slot, waits = body.get("slot"), body.get("waits", "")
        except MessageError:
            continue
        if isinstance(slot, int) and not isinstance(slot, bool) and isinstance(waits, str):
            cluster.waits[cluster.slot_role(slot)] = waits[:200]
