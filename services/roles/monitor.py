"""`mam-monitor` / `mam watch`: a live terminal view of one run, from anywhere on the network.

It only subscribes: config, allocation, eval, learner stats and liveliness of every role.
Messages are validated like everywhere else; a bad one is counted and skipped.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.live import Live

from services.messaging import bus, keys
from services.messaging.codec import Allocation, Done, Eval, LearnerStats, MessageError, decode
from services.roles import role
from services.roles.monitor_view import MonitorState, PlainLines, message_body, render
from services.run import config, options, registry, secret
from services.run.config import RunConfig

log = logging.getLogger("mam.monitor")


class NoRun(Exception):
    """`mam watch` found no run to watch within its --timeout (the message says where it looked)."""


def watch(run: str, conf: Any, refresh_per_s: float = 4.0, until_done: bool = True,
          console: Console | None = None, duration: float | None = None, timeout: float | None = None,
          plain: bool | None = None) -> MonitorState:
    """Watch `run` until it is done (or `duration` s). Raises NoRun when no session opens, or no
    message of the run arrives, within `timeout` s. `plain` prints one line per update instead of
    the live view (`mam watch` asks for it when its output is not a terminal)."""
    console = console or Console()
    plain = bool(plain)
    state = MonitorState(run=run)
    rejects = bus.RejectLog(log, "message")
    try:
        session_cm = bus.session_scope(conf, retry_for=30.0 if timeout is None else max(timeout, 0.1))
        session = session_cm.__enter__()
    except Exception as e:  # zenoh.ZError: nothing listens there
        raise NoRun(f"nothing listens at the run's endpoint, or it refused this process: a local run admits only "
                    f"its own processes and its user's `mam watch` ({type(e).__name__}: {str(e)[:200]})") from None
    try:
        alive = bus.watch_alive(session, run, None, lambda role, id_, up: state.on_alive(role, id_, up))
        subs = {name: bus.Latest.subscribe(session, key) for name, key in (
            ("config", keys.config(run)), ("allocation", keys.allocation(run)), ("eval", keys.eval(run)),
            ("stats", keys.learner_stats(run)), ("done", keys.done(run)))}
        started = time.monotonic()
        last_payload: dict[str, bytes] = {}
        lines = PlainLines(state)
        try:
            with (_Plain() if plain else Live(render(state), console=console, refresh_per_second=refresh_per_s)) \
                    as live:
                if plain:
                    console.print(f"watching run {run}: waiting for its learner", highlight=False)
                while duration is None or time.monotonic() - started < duration:
                    for name, sub in subs.items():
                        for item in sub.fresh().values():
                            if last_payload.get(item.key) == item.payload:
                                continue  # a heartbeat re-publication: nothing new
                            last_payload[item.key] = item.payload
                            try:
                                apply(state, name, item.payload)
                            except MessageError as e:
                                rejects.reject(keys.parse_last(item.key), e)
                                continue
                            if plain:
                                for line in lines.after(name):
                                    console.print(line, highlight=False, soft_wrap=True)
                    if not plain:
                        live.update(render(state))
                    if until_done and state.done:
                        break
                    if timeout is not None and not last_payload and time.monotonic() - started > timeout:
                        raise NoRun(f"no message of run {run!r} within {timeout:g} s (its learner is not up, "
                                    "or the run has ended)")
                    time.sleep(1.0 / refresh_per_s)
        finally:
            for sub in subs.values():
                sub.close()
            alive.close()
    finally:
        session_cm.__exit__(None, None, None)
    return state


class _Plain:
    """The no-terminal stand-in for rich's Live: nothing to redraw."""

    def __enter__(self) -> "_Plain":
        return self

    def __exit__(self, *exc: Any) -> None:
        return None


def find_endpoint(run: str, run_dir: Path | None, timeout: float, console: Console) -> tuple[str, Path | None]:
    """Where a local run listens and its secret (None if it has none this user can read): its
    config.json or the registry `mam run` writes (services/run/registry.py), and its run directory
    (services/run/secret.py), waiting up to `timeout` s for it to appear. NoRun if it does not."""
    deadline = time.monotonic() + timeout
    said = False
    while True:
        found = registry.lookup(run, run_dir)
        if found is not None:
            endpoint, where, found_dir = found
            auth = secret.of_run(found_dir)
            console.print(f"run {run}: {endpoint} (from {where}{'; with its secret' if auth else ''})",
                          highlight=False)
            return endpoint, auth
        if time.monotonic() >= deadline:
            raise NoRun(f"no local run {run!r} within {timeout:g} s (looked in {registry.places(run, run_dir)}); "
                        "for a run on another host pass --connect ENDPOINT")
        if not said:
            console.print(f"waiting for run {run} to start (up to {timeout:g} s; looking in "
                          f"{registry.places(run, run_dir)}) …", highlight=False)
            said = True
        time.sleep(0.5)


def apply(state: MonitorState, name: str, payload: bytes) -> None:
    k = state.n_actors or None
    if name == "config":
        try:
            cfg = RunConfig.from_dict(decode(payload)["config"])
        except (KeyError, TypeError, ValueError) as e:
            raise MessageError("config", str(e)[:200]) from None
        state.on_config(cfg.to_dict() | {"algo": cfg.algo.algo, "algo_config": cfg.algo.to_dict()})
    elif name == "allocation":
        state.on_allocation(message_body(Allocation.from_bytes(payload, k)))
    elif name == "eval":
        state.on_eval(message_body(Eval.from_bytes(payload, k)))
    elif name == "stats":
        state.on_stats(message_body(LearnerStats.from_bytes(payload)))
    elif name == "done":
        state.on_done(message_body(Done.from_bytes(payload)))


app = typer.Typer(add_completion=False, help=__doc__)


def watch_command(run: str | None, connect: list[str] | None, zenoh_config: Path | None, run_dir: Path | None,
                  timeout: float, keep: bool, plain: bool | None) -> None:
    """`mam watch` / `mam-monitor`: a bad name is a usage error (exit 2); no run within --timeout
    exits 1 with where it looked; without --connect it finds a local run by its name."""
    if not run:
        raise typer.BadParameter("--run NAME is required (printed by `mam run`, in RUN_DIR/config.json)",
                                 param_hint="--run")
    try:
        config.check_run_name(run)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--run") from None
    if timeout <= 0:
        raise typer.BadParameter("must be > 0 seconds", param_hint="--timeout")
    console = Console()
    plain = not console.is_terminal if plain is None else plain
    try:
        auth = secret.of_run(run_dir)  # a local run admits its own user's `mam watch` (its secret)
        if not connect and not zenoh_config:
            endpoint, auth = find_endpoint(run, run_dir, timeout, console)
            connect = [endpoint]
        watch(run, role.client_config(connect, None, zenoh_config, auth), until_done=not keep, console=console,
              timeout=timeout, plain=plain)
    except NoRun as e:
        console.print(f"[red]mam watch:[/] {e}", highlight=False)
        raise typer.Exit(1) from None
    except KeyboardInterrupt:
        raise typer.Exit(130) from None


Timeout = typer.Option(60.0, "--timeout", help="seconds to wait for the run to appear (and for its first message)")
Plain = typer.Option(None, "--plain/--live", show_default=False,
                     help="one line per update, or the live view (default: plain when the output is not a terminal)")
WatchRunDir = typer.Option(None, "--run-dir", help="the run's directory (its config.json says where it listens); "
                                                  "default: the registry of local runs, then runs/NAME")
Keep = typer.Option(False, "--keep", help="keep watching after the run is done")


@app.command(cls=options.PlainFlags)
def monitor_command(
    run: options.Run = None, connect: options.Connect = None, zenoh_config: options.ZenohConfig = None,
    run_dir: Path = WatchRunDir, timeout: float = Timeout, keep: bool = Keep, plain: bool = Plain,
) -> None:
    """Live view of a run: allocation (P_k, I_k), evaluations, workers, learner progress."""
    watch_command(run, connect, zenoh_config, run_dir, timeout, keep, plain)


cli = app  # the `mam-monitor` entry point


if __name__ == "__main__":
    cli()
