#!/usr/bin/env python3
"""Can this host reach the mam router with this Zenoh config? And who is up in a run?

    .venv/bin/python deploy/check-connection.py --connect tls/ROUTER:7447 \\
        --zenoh-config /etc/mam/zenoh/worker-tls.json5 [--run NAME]

Opens a Zenoh session the way `mam-learner/-worker/-referee` and `mam watch` do (the same
config file and endpoint), with Zenoh's own log on stdout at level `warn` (`RUST_LOG` overrides):
a refused TLS handshake is explained there ("invalid peer certificate: UnknownIssuer", ...),
where the mam commands only say "Unable to connect". With --run, lists the liveliness tokens of
the run (learner, referee, workers), as far as this certificate's role may see them.
Exit status: 0 connected, 1 not connected. See docs/DEPLOY.md, "Troubleshooting".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

from services.messaging import bus, keys  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connect", action="append", help="endpoint, e.g. tls/mam-router:7447 (repeatable)")
    parser.add_argument("--zenoh-config", type=Path, help="the role's Zenoh JSON5 config")
    parser.add_argument("--run", help="list the liveliness tokens of this run")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for answers")
    args = parser.parse_args(argv)
    zenoh.init_log_from_env_or("warn")
    if args.run:
        keys.check_name(args.run, "run")
    conf = bus.make_config(connect=args.connect or None, config_file=args.zenoh_config, mode="client")
    endpoints = args.connect or conf.get_json("connect/endpoints")
    try:
        session = bus.open_session(conf)
    except zenoh.ZError as e:
        print(f"NOT CONNECTED to {endpoints}: {e}".split(" at /")[0], file=sys.stderr)
        print("the Zenoh warnings on stdout say why; docs/DEPLOY.md lists the usual causes", file=sys.stderr)
        return 1
    with session:
        routers = [str(z) for z in session.info.routers_zid()]
        print(f"connected to {endpoints}: this session {session.info.zid()}, router(s) {', '.join(routers)}")
        if args.run:
            found = sorted(str(r.ok.key_expr) for r in session.liveliness().get(
                keys.alive_all(args.run), timeout=args.timeout) if r.ok is not None)
            if not found:
                print(f"run {args.run!r}: no liveliness token visible (nobody up, a wrong run name, "
                      "or this role may not watch tokens: workers may not)")
            for key in found:
                role, id_ = keys.parse_alive(key)
                print(f"run {args.run!r}: {role:8s} {id_}")
        time.sleep(0.1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
