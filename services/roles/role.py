"""What every process role shares: endpoints, logging, signals, the run's config, role stats, weights.

A role module (`learner`, `worker`, `referee`, `monitor`, `router`) builds on this one and never
imports another role module. This module imports neither torch nor matplotlib.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NoReturn

from services.messaging import bus, keys
from services.messaging.codec import LearnerStats, MessageError, Weights, decode, encode
from services.run.config import RunConfig

log = logging.getLogger("mam.role")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"  # where a client role looks for the run when given no --connect
LISTEN_ALL = "tcp/0.0.0.0:7447"  # where the learner and the router listen when given no --listen
CONFIG_WAIT_S = 600.0  # how long a client role waits for a learner to appear
REPORT_EVERY_S = 1.0  # role stats (mam/<run>/stats/<role>-<id>) at most this often
MAX_VERSION_LEAD = 100_000  # weights this far ahead of the learner's reported version are forged


def setup_logging(verbose: bool = False) -> None:
    """Our log lines on stderr (DEBUG with --verbose) and Zenoh's own warnings."""
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus.init_zenoh_log()


def exit_finished(code: int = 0) -> NoReturn:
    """End a role's process once its work is done and its files are closed, without the
    interpreter's teardown: with torch imported that took ~0.45 s after the last line of work
    (2-core AMD EPYC), and `mam run` waits for the learner before it reports. The log handlers and
    stdio are flushed first; nothing else runs at exit (docs/DESIGN-DECISIONS.md, "Supervision")."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def leave_within(seconds: float, what: str) -> None:
    """A role whose work is done and whose files are closed leaves within `seconds` whatever its
    teardown does (undeclaring, closing its Zenoh session): past them it logs so and exits 0
    (`exit_finished`), so that `mam run`, which waits for the learner's exit, is not held by a
    teardown that hangs (seen once in CI: a learner that had written transport.json and logged
    "done" did not exit for 300 s). `what`: the log line's subject."""
    def leave() -> None:
        log.warning("%s: its teardown took over %.0f s after its work was done; leaving without it", what, seconds)
        exit_finished(0)

    timer = threading.Timer(seconds, leave)
    timer.daemon = True
    timer.start()


def refuse_unbound(cfg: RunConfig, worker_id: str, slots: list[int], what: str, log: logging.Logger) -> None:
    """A worker or spare that the run's slot binding (services/run/binding.py) lets claim none of
    `slots`: one line, exit EXIT_CONFIG (78, which `mam run` never restarts); the learner would
    refuse every batch it sent."""
    from services.run.binding import SlotBinding
    from services.run.preflight import EXIT_CONFIG

    bound = SlotBinding(cfg.slot_binding)
    if not any(bound.allows(worker_id, s) for s in slots):
        log.error("worker %s may not take %s of run %s: the run's slot binding allows it %s (the learner refuses "
                  "a batch claiming any other slot; --slot-binding, docs/DEPLOY.md, section 6)", worker_id, what,
                  cfg.run, bound.describe(worker_id))
        raise SystemExit(EXIT_CONFIG)


def client_config(connect: list[str] | None, listen: list[str] | None = None,
                  zenoh_config: Path | None = None, auth_file: Path | None = None) -> Any:
    """The Zenoh config of a client role: `--connect`, else the config file, else DEFAULT_ENDPOINT;
    `auth_file`: a run's secret (default: bus.AUTH_ENV's, if set; services/run/secret.py)."""
    return bus.make_config(connect=connect or ([] if zenoh_config else [DEFAULT_ENDPOINT]), listen=listen,
                           config_file=zenoh_config, auth_file=auth_file)


def serve_role(name: str, conf: Any, build: Callable[[RunConfig | None, Any], Any], *, run: str,
               run_dir: Path | None = None, cfg: RunConfig | None = None, log: logging.Logger = log) -> None:
    """The skeleton every role runs: its run lock (a role with a run directory: one learner and one
    referee per directory and run), the Zenoh session, the run's config (fetched from the
    learner unless given), `build(cfg, session)` making the role, signals, and its `serve()`."""
    from services.run import runlock

    lock: Any = contextlib.nullcontext()
    if run_dir is not None and name in ("learner", "referee"):
        try:  # refused before anything is written
            lock = runlock.lock_role(run_dir, name, run)
        except runlock.RunInUse as e:
            log.error("%s", e)
            raise SystemExit(runlock.EXIT_REFUSED) from None
    with lock, bus.session_scope(conf, retry_for=30.0) as session:  # a router may still be starting
        if cfg is None:
            cfg = fetch_config(session, run, bus.RejectLog(log, "config"))
        process = build(cfg, session)
        stop_on_signals(process)
        process.serve()


def stop_on_signals(target: Any) -> None:
    """SIGTERM and SIGINT set `target.stop_requested` (or call `target` if it is a function): the
    role's loop ends at its next turn and the role leaves cleanly (checkpoint, final report,
    liveliness token undeclared)."""

    def on_signal(_signum: int, _frame: Any) -> None:
        if callable(target):
            target()
        else:
            target.stop_requested = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)


def at_text(paper: bool, iterations: int, transitions: int) -> str:
    """A point of the run in its schedule's unit, the one the allocation lines use: "iteration 100
    (200 transitions)" under the paper schedule, "200 transitions" under equal-data."""
    return f"iteration {iterations:,} ({transitions:,} transitions)" if paper else f"{transitions:,} transitions"


WAIT_NOTE_EVERY_S = 30.0  # "waiting for the learner" at first, then this often


def connected(session: Any) -> bool | None:
    """Whether this session has a link to any router or peer (None: unknown)."""
    try:
        info = session.info
        return bool(list(info.routers_zid()) or list(info.peers_zid()))
    except Exception:  # noqa: BLE001 - an API this zenoh lacks: unknown
        return None


def fetch_config(session: Any, run: str, rejects: bus.RejectLog, timeout: float = CONFIG_WAIT_S,
                 note_every: float = WAIT_NOTE_EVERY_S) -> RunConfig:
    """The run's resolved config from the learner's config topic (waits for a learner).

    While it waits it says so at first and then every `note_every` seconds (not once a second),
    and says when the session has no link at all (the router or the learner's host is gone)."""
    latest = bus.Latest.subscribe(session, keys.config(run))
    started = time.monotonic()
    deadline = started + timeout
    note = Every(note_every)
    try:
        while time.monotonic() < deadline:
            if not latest.wait(keys.config(run), timeout=1.0):
                if note.due():
                    link = connected(session)
                    why = " (no link to any router or peer: is the endpoint up?)" if link is False else ""
                    log.info("waiting for the learner of run %r%s, %.0f s so far ...", run, why,
                             time.monotonic() - started)
                continue
            item = latest.get(keys.config(run))
            try:
                msg = decode(item.payload)
                return RunConfig.from_dict(msg["config"])
            except (MessageError, KeyError, TypeError, ValueError) as e:
                rejects.reject(keys.parse_last(item.key), MessageError("config", str(e)[:200]))
                latest.fresh()
                time.sleep(0.5)
        raise TimeoutError(f"no learner published a config for run {run!r} within {timeout:.0f} s")
    finally:
        latest.close()


class RoleReport:
    """A role's own counters on mam/<run>/stats/<role>-<id> (rejections, faults, rounds ...),
    at most every REPORT_EVERY_S unless forced. Monitors and tests read them."""

    def __init__(self, session: Any, run: str, role: str, id: str, every_s: float = REPORT_EVERY_S) -> None:  # noqa: A002
        self.role, self.id = role, id
        self.pub = bus.declare_reliable_publisher(session, keys.role_stats(run, role, id))
        self.every = Every(every_s)

    def publish(self, fields: Mapping[str, Any], seq: int | Callable[[], int], force: bool = False) -> bool:
        """Put {"role", "id", **fields} if a report is due (or `force`); True if it was put.
        `seq` may be a callable: it is called only when the report is put."""
        if not (self.every.due() or force):
            return False
        body = {"role": self.role, "id": self.id, **fields}
        self.pub.put(encode("role_stats", body, sender=self.id, seq=seq() if callable(seq) else seq))
        return True


class Every:
    """A periodic timer over any growing count (seconds by default, or updates, rows ...):
    `due()` is true at most once per `period` and then starts the next period.

    The first call is due unless `start` is given. `due(now)` takes the count (the clock's
    value by default); `due(now, period)` uses another period for this call (e.g. shorter
    while idle); `elapsed(now)` is the count since the last due tick.
    """

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic, start: float | None = None) -> None:
        self.period = period
        self.clock = clock
        self.last = start

    def due(self, now: float | None = None, period: float | None = None) -> bool:
        now = self.clock() if now is None else now
        if self.last is not None and now - self.last < (self.period if period is None else period):
            return False
        self.last = now
        return True

    def reset(self, now: float | None = None) -> None:
        self.last = self.clock() if now is None else now

    def elapsed(self, now: float | None = None) -> float:
        now = self.clock() if now is None else now
        return float("inf") if self.last is None else now - self.last


def plausible_version(w: Weights, stats: LearnerStats | None) -> bool:
    """Weights may lead the last stats a little (published in between), never by a lot."""
    if stats is None or w.actor >= len(stats.versions):
        return w.version <= MAX_VERSION_LEAD
    return w.version <= stats.versions[w.actor] + MAX_VERSION_LEAD


class Decodes:
    """The values of the last few messages a process decoded, by kind and payload: the slots of
    one worker process (services/roles/worker_group.py) each receive every weights and stats
    message, and decode it once between them, not once each. A value is shared: its users
    read it and never change it. A payload that does not decode keeps nothing (each user
    rejects it and counts it as before)."""

    KEEP = 64  # values kept (a few versions of each actor, the last stats)

    def __init__(self) -> None:
        self._values: dict[tuple[str, bytes], Any] = {}
        self._lock = threading.Lock()  # (screens run in Zenoh's threads, the loop in the main one)

    def get(self, kind: str, payload: bytes, decode: Callable[[], Any]) -> Any:
        key = (kind, payload)
        with self._lock:
            if key in self._values:
                return self._values[key]
        value = decode()
        with self._lock:
            if len(self._values) >= self.KEEP:
                self._values.pop(next(iter(self._values)))
            self._values[key] = value
        return value


def decoded(decodes: Decodes | None, kind: str, payload: bytes | None, decode: Callable[[], Any]) -> Any:
    """`decode()`, shared through `decodes` (keyed by `payload`) where both are given."""
    return decode() if decodes is None or payload is None else decodes.get(kind, payload, decode)


def weights_screen(shapes: Mapping[str, tuple[int, ...]], n_actors: int, rejects: bus.RejectLog,
                   decodes: Decodes | None = None) -> Callable[[bus.Received], bus.Received | None]:
    """A weights subscription's screen (`bus.Inbox(screen=...)`), run in the callback: a message
    that does not decode as weights of the run's shapes is rejected and counted there, so a
    flood of junk on a weights key never takes a queue slot or a valid message's place. What
    it stores carries the decoded Weights (`Received.value`: `decoded_weights` reads it),
    shared through `decodes` where given."""

    def admits(item: bus.Received) -> bus.Received | None:
        try:
            return item._replace(value=decoded(decodes, "weights", item.payload,
                                                lambda: Weights.from_bytes(item.payload, shapes, n_actors)))
        except MessageError as e:
            rejects.reject(keys.parse_last(item.key), e)
            return None

    return admits


def decoded_weights(item: bus.Received, shapes: Mapping[str, tuple[int, ...]], n_actors: int) -> Weights:
    """`item`'s Weights: as its subscription's screen decoded them, else decoded now (MessageError)."""
    if isinstance(item.value, Weights):
        return item.value
    return Weights.from_bytes(item.payload, shapes, n_actors)


def learner_order(incarnation: str) -> tuple[int, str]:
    """How learner incarnations "e<epoch>-<id>" (services/roles/learner.py) are ordered: by epoch,
    which each start of a run's learner raises (then by id, so that every role orders two learners
    of one epoch alike); an incarnation without an epoch comes first."""
    head, _, rest = incarnation.partition("-")
    return (int(head[1:]), rest) if head[:1] == "e" and head[1:].isdigit() and rest else (0, incarnation)


def fresh_learner_stats(latest: bus.Latest, run: str, rejects: bus.RejectLog,
                        decodes: Decodes | None = None) -> LearnerStats | None:
    """The learner's stats if new ones arrived since the last call (a malformed message is
    counted as rejected, never raised), else None; shared through `decodes` where given."""
    item = latest.fresh().get(keys.learner_stats(run))
    if item is None:
        return None
    try:
        return decoded(decodes, "stats", item.payload, lambda: LearnerStats.from_bytes(item.payload))
    except MessageError as e:
        rejects.reject("learner", e)
        return None
