"""`mam router`: a Zenoh router for multi-host runs, with nothing to install beyond this package.

A zenoh-python session in `router` mode routes data, queries and liveliness tokens between its
clients (learner, referee, workers, monitors), so hosts form a star around it. It outlives runs:
many runs (distinct `--run` names) can share one router.

Zenoh's own log goes to stdout at level `warn` (refused TLS handshakes, closed transports);
`RUST_LOG` overrides it, e.g. `RUST_LOG=warn,zenoh::net::routing::interceptor=trace`
shows every access-control decision (deploy/zenoh/router-tls.json5, docs/DEPLOY.md).
"""

from __future__ import annotations

import logging
import threading

import typer

from services.messaging import bus
from services.roles import role
from services.run import options

log = logging.getLogger("mam.router")

app = typer.Typer(add_completion=False, help=__doc__)


def serve(conf, stop: threading.Event, where: str = "") -> None:
    with bus.session_scope(conf) as session:
        log.info("router %s up, listening on %s", session.zid(), where or "its configured endpoints")
        stop.wait()


@app.command(cls=options.PlainFlags)
def router_command(
    listen: options.Listen = None, connect: options.Connect = None, zenoh_config: options.ZenohConfig = None,
) -> None:
    """Run a Zenoh router (default: listen on tcp/0.0.0.0:7447) until SIGTERM / Ctrl-C."""
    role.setup_logging()
    listen = listen or ([] if zenoh_config else [role.LISTEN_ALL])
    conf = bus.make_config(connect=connect, listen=listen, config_file=zenoh_config, mode="router")
    stop = threading.Event()
    role.stop_on_signals(stop.set)
    where = ", ".join(listen) if listen else f"the endpoints of {zenoh_config}"
    serve(conf, stop, where + (f" (connected to {', '.join(connect)})" if connect else ""))


cli = app  # `mam router`


if __name__ == "__main__":
    cli()
