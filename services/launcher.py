"""`mam run`: a whole run on one box — learner, referee and M workers as child processes.

The learner listens on a free loopback port; the referee and workers connect to it as clients
(multicast scouting off, a unique run name). The launcher itself is one more client: it shows
a progress bar of env steps with the current allocation, stops every child on Ctrl-C or at the
end of the budget, and draws the plots. Children are started with `subprocess` (Zenoh sessions
do not survive `fork`), each logging to RUN_DIR/logs/<role>.log.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from services import bus, keys
from services.codec import Allocation, Eval, LearnerStats, MessageError
from services.options import RunConfig, write_json

STOP_GRACE_S = 15.0
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Runs in the child before exec: SIGTERM it if the launcher dies (even by SIGKILL)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


class Interrupted(Exception):
    """SIGTERM / SIGINT reached the launcher."""


def _raise_interrupted(signum: int, _frame: Any) -> None:
    raise Interrupted(signal.Signals(signum).name)


@dataclass
class Child:
    role: str
    proc: subprocess.Popen
    log: Path


@dataclass
class LocalCluster:
    """Child processes of one local run; `stop()` leaves nothing running."""

    cfg: RunConfig
    run_dir: Path
    endpoint: str
    children: list[Child] = field(default_factory=list)

    def spawn(self, role: str, args: list[str]) -> Child:
        log_path = self.run_dir / "logs" / f"{role}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "ab") as out:
            proc = subprocess.Popen([sys.executable, "-m", f"services.{role.split('-')[0]}", *args],
                                    stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, preexec_fn=_die_with_parent)
        child = Child(role, proc, log_path)
        self.children.append(child)
        return child

    def start_learner_and_referee(self) -> None:
        run, rd = self.cfg.run, str(self.run_dir)
        self.spawn("learner", ["--run-config", str(self.run_dir / "config.json"), "--listen", self.endpoint,
                               "--run-dir", rd])
        self.spawn("referee", ["--run", run, "--connect", self.endpoint, "--run-dir", rd])

    def start_workers(self) -> None:
        """After the referee is up, so the first allocation round is a barrier from step 0."""
        run, rd = self.cfg.run, str(self.run_dir)
        for i in range(self.cfg.algo.workers):
            self.spawn(f"worker-{i}", ["--run", run, "--connect", self.endpoint, "--id", f"w{i}", "--slot", str(i),
                                         "--run-dir", rd])

    def failed(self) -> list[Child]:
        """Children that exited with an error."""
        return [c for c in self.children if c.proc.poll() not in (None, 0)]

    def running(self) -> list[Child]:
        return [c for c in self.children if c.proc.poll() is None]

    def wait(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while self.running() and time.monotonic() < deadline:
            time.sleep(0.1)
        return not self.running()

    def stop(self, grace: float = STOP_GRACE_S) -> None:
        """SIGTERM (the learner checkpoints), then SIGKILL what is still up after `grace`."""
        for c in self.running():
            c.proc.send_signal(signal.SIGTERM)
        if not self.wait(grace):
            for c in self.running():
                c.proc.kill()
            self.wait(5.0)


def run_local(cfg: RunConfig, run_dir: Path, console: Console | None = None, plot: bool = True,
              outcome: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train `cfg` on this box; returns summary.json's content (empty if the run was stopped).

    `outcome`, when given, gets "interrupted": whether SIGINT / SIGTERM stopped the run."""
    console = console or Console()
    run_dir.mkdir(parents=True, exist_ok=True)
    port = bus.free_tcp_port()
    endpoint = bus.loopback_endpoint(port)
    cfg = RunConfig.from_dict({**cfg.to_dict(), "endpoint": endpoint})
    write_json(run_dir / "config.json", cfg.to_dict())
    cluster = LocalCluster(cfg, run_dir, endpoint)
    console.print(f"[bold]run[/] {cfg.run}  [bold]env[/] {cfg.env_id}  [bold]algo[/] {cfg.algo.algo} "
                  f"K={cfg.algo.actors} M={cfg.algo.workers}  budget {cfg.steps:,} transitions")
    console.print(f"run dir {run_dir}   watch live: [cyan]mam watch --run {cfg.run} --connect {endpoint}[/]")
    started = time.monotonic()
    interrupted = False
    previous = {sig: signal.signal(sig, _raise_interrupted) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        cluster.start_learner_and_referee()
        try:
            finished = follow(cfg, endpoint, cluster, console)
            if finished:
                cluster.wait(60.0)  # learner, referee (final evaluation) and workers exit on their own
        except (Interrupted, KeyboardInterrupt):
            interrupted = True
            console.print("[yellow]interrupted: stopping all processes (the learner writes a checkpoint)[/]")
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        cluster.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if outcome is not None:
        outcome["interrupted"] = interrupted
    failed = [c for c in cluster.children if c.proc.returncode not in (0, -signal.SIGTERM, None)]
    for c in failed:
        console.print(f"[red]{c.role} exited with {c.proc.returncode}[/]: see {c.log}")
    summary_path = run_dir / "summary.json"
    summary: dict[str, Any] = {}
    if summary_path.is_file():
        import json
        summary = json.loads(summary_path.read_text())
        summary["launcher_wall_time_s"] = round(time.monotonic() - started, 2)
        write_json(summary_path, summary)
    if plot and not interrupted:
        from services.plot import plot_run
        for p in plot_run(run_dir):
            console.print(f"plot {p}")
    if summary:
        console.print(f"[bold green]done[/] in {summary['launcher_wall_time_s']:.0f} s: final returns "
                      f"{summary.get('final_returns')}, survivor {summary.get('survivor')}")
    return summary


def describe_allocation(alloc: Allocation | None) -> str:
    if alloc is None:
        return "waiting for the referee"
    p = " ".join(f"{x:.2f}" for x in alloc.probabilities)
    i = " ".join(str(c) for c in alloc.counts)
    text = f"round {alloc.round}  P=[{p}]  I=[{i}]"
    if alloc.survivor is not None:
        text += f"  survivor {alloc.survivor}"
    return text


def follow(cfg: RunConfig, endpoint: str, cluster: LocalCluster, console: Console) -> bool:
    """Progress bar until the learner says done (True) or a child fails (False)."""
    conf = bus.make_config(connect=[endpoint])
    with bus.session_scope(conf, retry_for=60.0) as session:
        stats = bus.Latest.subscribe(session, keys.learner_stats(cfg.run))
        allocation = bus.Latest.subscribe(session, keys.allocation(cfg.run))
        evals = bus.Latest.subscribe(session, keys.eval(cfg.run))
        roles = bus.watch_alive(session, cfg.run)
        with console.status("starting learner and referee"):
            while not {"learner", "referee"} <= {role for role, _ in roles.members()}:
                if cluster.failed():
                    return False
                time.sleep(0.1)
        roles.close()
        cluster.start_workers()
        alloc: Allocation | None = None
        last_eval = ""
        columns = (TextColumn("[bold]steps"), BarColumn(bar_width=24), MofNCompleteColumn(), TimeElapsedColumn(),
                   TimeRemainingColumn(), TextColumn("{task.fields[info]}"))
        try:
            with Progress(*columns, console=console, transient=False) as progress:
                task = progress.add_task("train", total=cfg.steps, info="starting")
                while True:
                    if cluster.failed():
                        return False
                    item = allocation.fresh().get(keys.allocation(cfg.run))
                    if item is not None:
                        try:
                            new = Allocation.from_bytes(item.payload, cfg.algo.actors)
                            if alloc is None or new.round != alloc.round or new.survivor != alloc.survivor:
                                progress.console.print(f"[magenta]allocation[/] at {new.env_steps:,} steps "
                                                       f"({new.reason}): {describe_allocation(new)}")
                            alloc = new
                        except MessageError:
                            pass
                    item = evals.fresh().get(keys.eval(cfg.run))
                    if item is not None:
                        try:
                            ev = Eval.from_bytes(item.payload, cfg.algo.actors)
                            last_eval = "R=[" + " ".join("-" if m is None else f"{m:.1f}" for m in ev.mean) + "]"
                        except MessageError:
                            pass
                    item = stats.get(keys.learner_stats(cfg.run))
                    if item is not None:
                        try:
                            st = LearnerStats.from_bytes(item.payload)
                            info = f"upd {st.updates:,}  I={list(alloc.counts) if alloc else '-'}  {last_eval}"
                            progress.update(task, completed=min(st.env_steps, cfg.steps), info=info)
                            if st.done:
                                return True
                        except MessageError:
                            pass
                    time.sleep(0.2)
        finally:
            for sub in (stats, allocation, evals):
                sub.close()
