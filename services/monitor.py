"""`mam-monitor` / `mam watch`: a live terminal view of one run, from anywhere on the network.

It only subscribes: config, allocation, eval, learner stats and liveliness of every role.
Messages are validated like everywhere else; a bad one is counted and skipped.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import typer
from rich.console import Console
from rich.live import Live

from services import bus, keys, options, role
from services.codec import Allocation, Done, Eval, LearnerStats, MessageError, decode
from services.monitor_view import MonitorState, render
from services.options import RunConfig

log = logging.getLogger("mam.monitor")


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _body(obj: Any) -> dict[str, Any]:
    """A validated message as the plain dict (lists, not tuples) MonitorState takes."""
    return {name: _plain(getattr(obj, name)) for name in obj.__dataclass_fields__}


def watch(run: str, conf: Any, refresh_per_s: float = 4.0, until_done: bool = True,
          console: Console | None = None, duration: float | None = None) -> MonitorState:
    console = console or Console()
    state = MonitorState(run=run)
    rejects = bus.RejectLog(log, "message")
    with bus.session_scope(conf, retry_for=30.0) as session:
        alive = bus.watch_alive(session, run, None, lambda role, id_, up: state.on_alive(role, id_, up))
        subs = {name: bus.Latest.subscribe(session, key) for name, key in (
            ("config", keys.config(run)), ("allocation", keys.allocation(run)), ("eval", keys.eval(run)),
            ("stats", keys.learner_stats(run)), ("done", keys.done(run)))}
        started = time.monotonic()
        last_payload: dict[str, bytes] = {}
        try:
            with Live(render(state), console=console, refresh_per_second=refresh_per_s) as live:
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
                    live.update(render(state))
                    if until_done and state.done:
                        break
                    time.sleep(1.0 / refresh_per_s)
        finally:
            for sub in subs.values():
                sub.close()
            alive.close()
    return state


def apply(state: MonitorState, name: str, payload: bytes) -> None:
    k = state.n_actors or None
    if name == "config":
        try:
            cfg = RunConfig.from_dict(decode(payload)["config"])
        except (KeyError, TypeError, ValueError) as e:
            raise MessageError("config", str(e)[:200]) from None
        state.on_config(cfg.to_dict() | {"algo": cfg.algo.algo, "algo_config": cfg.algo.to_dict()})
    elif name == "allocation":
        state.on_allocation(_body(Allocation.from_bytes(payload, k)))
    elif name == "eval":
        state.on_eval(_body(Eval.from_bytes(payload, k)))
    elif name == "stats":
        state.on_stats(_body(LearnerStats.from_bytes(payload)))
    elif name == "done":
        state.on_done(_body(Done.from_bytes(payload)))


app = typer.Typer(add_completion=False, help=__doc__)


@app.command()
def monitor_command(
    run: options.Run = None, connect: options.Connect = None, zenoh_config: options.ZenohConfig = None,
    keep: bool = typer.Option(False, help="keep watching after the run is done"),
) -> None:
    """Live view of a run: allocation (P_k, I_k), evaluations, workers, learner progress."""
    if not run:
        raise typer.BadParameter("--run NAME is required")
    options.check_run_name(run)
    watch(run, role.client_config(connect, None, zenoh_config), until_done=not keep)


cli = app  # the `mam-monitor` entry point


if __name__ == "__main__":
    cli()
