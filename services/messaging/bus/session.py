"""Zenoh configs, sessions and publishers (RELIABLE + BLOCK; latest-value with a cache)."""

from __future__ import annotations

import json
import os
import socket
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import zenoh
from zenoh.ext import (
    AdvancedPublisher,
    CacheConfig,
    MissDetectionConfig,
    RepliesConfig,
    declare_advanced_publisher,
)

MODES = ("peer", "client", "router")
# The file of a run's credentials, one `user:password` line (services/run/secret.py): a session
# opened with it set presents them, and one that listens admits only sessions that present them.
AUTH_ENV = "MAM_ZENOH_AUTH"
# Where a listening session says whom it refused (Zenoh logs it at debug only): "UsrPwd extension -
# Recv InitSyn. Expected extension." (no credentials), "... Recv OpenSyn. Invalid password." (or
# "Invalid user."); and one "New transport link accepted from <zid> ..." line per session it admits.
REFUSALS_LOG = "zenoh_transport::unicast::establishment::accept=debug"


# --------------------------------------------------------------------------- config & sessions


def init_zenoh_log() -> None:
    """Zenoh's own log (TLS and connection errors) on stderr: RUST_LOG if set, else warnings, and
    in a process that holds a run's credentials (AUTH_ENV) also the connections it accepted or
    refused (REFUSALS_LOG): a process without them that tries to join shows in the learner's log."""
    try:
        zenoh.init_log_from_env_or("warn" + ("," + REFUSALS_LOG if os.environ.get(AUTH_ENV) else ""))
    except Exception:  # already initialised in this process
        pass


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind to :0, read it back, release it).

    Zenoh cannot report the port of a ``:0`` listener, so we pick one first.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{int(port)}"


def make_config(
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    config_file: str | Path | None = None,
    mode: str | None = None,
    auth_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config for one role.

    With ``config_file`` (JSON5) the file is the base and ``connect``/``listen``/``mode``
    override it. Multicast scouting, gossip scouting and timestamping (needed by the
    advanced publisher's cache) are set unless the file mentions them. Without ``mode``:
    a file's mode is kept; otherwise ``connect`` alone gives a client, anything else a peer.
    No connect and no listen gives a peer that nobody can reach: tests and launchers
    always pass explicit endpoints.

    ``auth_file`` (default: the file named by ``$MAM_ZENOH_AUTH``, if set) holds one
    ``user:password`` line: the session presents it when it connects (Zenoh's user-password
    authentication), and takes the file as its dictionary, so when it listens it admits only
    sessions that present the same (``mam run``'s per-run secret, services/run/secret.py).
    """
    if mode is not None and mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    text = ""
    if config_file is not None:
        text = Path(config_file).read_text()
        conf = zenoh.Config.from_file(str(config_file))
    else:
        conf = zenoh.Config()
    if "multicast" not in text:
        conf.insert_json5("scouting/multicast/enabled", "false")
    if "gossip" not in text:
        conf.insert_json5("scouting/gossip/enabled", "false")
    if "multicast" not in text and "gossip" not in text and "delay" not in text:
        # No scouting, so nobody to wait for: a peer or router's open returns at once (Zenoh's
        # default `scouting/delay` holds it 500 ms, paid by every learner start)
        conf.insert_json5("scouting/delay", "0")
    if "timestamping" not in text:
        conf.insert_json5("timestamping/enabled", "true")
    if mode is None and "mode" not in text:
        # A session that only listens is the hub of a star: it must route between its clients
        # (a peer forwards data but not every liveliness/query path), so it is a router.
        mode = "client" if connect and not listen else ("router" if listen and not connect else "peer")
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    auth = auth_file if auth_file is not None else os.environ.get(AUTH_ENV)
    if auth:
        use_credentials(conf, Path(auth))
    return conf


def use_credentials(conf: zenoh.Config, path: Path) -> None:
    """Present `path`'s `user:password` when connecting, and admit only sessions that present it
    (the file is also Zenoh's dictionary, what a listening session checks the credentials against)."""
    try:
        user, sep, password = path.read_text().strip().partition(":")
    except OSError as e:
        raise ValueError(f"cannot read the run's credentials {path} ({AUTH_ENV}): {e.strerror or e}") from None
    if not (sep and user and password):
        raise ValueError(f"{path} ({AUTH_ENV}) is not one user:password line")
    conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
    conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(path)))


def open_session(conf: zenoh.Config, *, retry_for: float = 0.0) -> zenoh.Session:
    """Open a session; a client whose endpoint is not up yet fails at once, so retry
    for up to ``retry_for`` seconds (the launcher starts the learner first, but races happen).

    The caller must close it: prefer ``with open_session(conf) as session:`` or
    ``session_scope``. Never open a session before ``fork`` (docs/ZENOH-NOTES.md).
    """
    deadline = time.monotonic() + retry_for
    while True:
        if time.monotonic() < deadline and refused(conf):
            time.sleep(0.1)  # quietly: each try of Zenoh's own logs two warnings (`mam run` starts every role at once)
            continue
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.1)


def refused(conf: zenoh.Config) -> bool:
    """Whether every endpoint `conf` connects to is a TCP port that refuses connections (nothing
    listens there yet). False for any other transport, or where anything else happens: Zenoh then
    tries, and logs why it could not connect. A port that accepts is closed again at once; a
    listener that logs the connections it accepts (REFUSALS_LOG) shows it as an early end of file."""
    try:
        endpoints = json.loads(conf.get_json("connect/endpoints"))
    except Exception:
        return False
    if not endpoints or not isinstance(endpoints, list):
        return False
    for endpoint in endpoints:
        proto, _, rest = str(endpoint).partition("/")
        host, _, port = rest.split("?")[0].split("#")[0].rpartition(":")
        if proto != "tcp" or not port.isdigit():
            return False
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
                return False
        except ConnectionRefusedError:
            continue
        except OSError:
            return False
    return True


@contextmanager
def session_scope(conf: zenoh.Config, *, retry_for: float = 0.0) -> Iterator[zenoh.Session]:
    """``with session_scope(conf) as s:`` — the session is closed however the block ends."""
    session = open_session(conf, retry_for=retry_for)
    try:
        yield session
    finally:
        session.close()


# --------------------------------------------------------------------------- publishers


def declare_reliable_publisher(
    session: zenoh.Session,
    key: str,
    *,
    express: bool = False,
    priority: zenoh.Priority | None = None,
) -> zenoh.Publisher:
    """RELIABLE + BLOCK: a put waits for queue room instead of dropping (transitions, stats).

    ``express`` skips batching (lower latency for small, rare messages).
    """
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
        express=express,
        priority=priority,
    )


def declare_latest_publisher(session: zenoh.Session, key: str, *, drop: bool = False) -> AdvancedPublisher:
    """RELIABLE + BLOCK publisher that keeps its last sample for late joiners.

    Zenoh's advanced publisher with a one-sample cache; ``publisher_detection`` lets
    subscribers that started earlier query it as soon as it appears. Needs
    ``timestamping/enabled`` (``make_config`` sets it). ``drop``: a put that finds the
    queue full drops the sample after ~1 ms (50 ms for a fragmented one) instead of
    blocking up to ``wait_before_close`` (5 s): for topics re-published every fraction
    of a second, whose latest value is all that counts (the learner's stats and config;
    docs/ZENOH-NOTES.md, "Congestion"). Replies to late joiners still block.
    """
    block = zenoh.CongestionControl.BLOCK
    return declare_advanced_publisher(
        session,
        key,
        congestion_control=zenoh.CongestionControl.DROP if drop else block,
        reliability=zenoh.Reliability.RELIABLE,
        cache=CacheConfig(max_samples=1, replies_config=RepliesConfig(congestion_control=block)),
        # Sequence numbers per publisher instead of the default per-session timestamps:
        # with timestamps, a wildcard subscriber drops the cached sample of one publisher
        # when another publisher of the same session replied with a newer one (seen here
        # with weights/0 and weights/1 declared by the learner's session).
        sample_miss_detection=MissDetectionConfig(),
        publisher_detection=True,
    )
