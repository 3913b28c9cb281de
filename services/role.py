"""What every process role shares: endpoints, logging, signals, the run's config, role stats, weights.

A role module (`learner`, `worker`, `referee`, `monitor`, `router`) builds on this one and never
imports another role module. This module imports neither torch nor matplotlib.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from mam_core.policy import NumpyActors
from services import bus, keys
from services.codec import LearnerStats, MessageError, Weights, decode, encode
from services.options import RunConfig

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


def client_config(connect: list[str] | None, listen: list[str] | None = None,
                  zenoh_config: Path | None = None) -> Any:
    """The Zenoh config of a client role: `--connect`, else the config file, else DEFAULT_ENDPOINT."""
    return bus.make_config(connect=connect or ([] if zenoh_config else [DEFAULT_ENDPOINT]), listen=listen,
                           config_file=zenoh_config)


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


class WeightsFollower:
    """A role's CPU copy of every actor, kept up to date from the learner's weights topic
    (the worker acts with it, the referee evaluates it); like Acme's variable client.

    Rule: a message is loaded only if its version is strictly newer than the copy's, or if
    it comes from the learner incarnation the stats name and the copy is from another one. A
    version names one set of parameters of one learner incarnation: the learner re-publishes
    the current weights (heartbeats, after an elimination, at the end) and the publishers'
    caches replay them to late joiners, so an equal version carries the same parameters and
    loading it again is wasted work; an older one is a reordered or cached stale message. A
    new learner incarnation (a restart, with or without a checkpoint) counts its own versions:
    its weights replace a dead incarnation's even when their counter is lower, and once the
    stats name the new incarnation nothing of the old one is loaded again. Malformed messages
    and versions implausibly far ahead of the learner's stats are rejected and counted.
    """

    def __init__(self, n_actors: int, spec: Any, hidden: tuple[int, ...], rejects: bus.RejectLog,
                 gaussian: bool = False) -> None:
        self.actors = NumpyActors(n_actors, spec, hidden, gaussian)  # gaussian: SAC's actors (mean and log σ heads)
        self.shapes = self.actors.shapes
        self.n_actors = n_actors
        self.versions = [-1] * n_actors  # -1: no weights yet
        self.incarnations = [""] * n_actors  # the learner incarnation each copy came from
        self.rejects = rejects

    @classmethod
    def for_algo(cls, algo: Any, spec: Any, rejects: bus.RejectLog) -> "WeightsFollower":
        """The follower of a run's K actors (an `AlgoConfig`): SAC's with their mean and log σ heads."""
        return cls(algo.actors, spec, algo.hidden, rejects, algo.stochastic)

    def admits(self, item: bus.Received) -> bool:
        """The subscription's screen (`bus.Latest(screen=...)`): a message that does not decode
        as weights of this run's shapes is rejected here, in the callback, so a flood of junk on a
        weights key never takes the place of the learner's last valid message before it is read."""
        try:
            Weights.from_bytes(item.payload, self.shapes, self.n_actors)
        except MessageError as e:
            self.rejects.reject(keys.parse_last(item.key), e)
            return False
        return True

    def update(self, items: Mapping[str, bus.Received], stats: LearnerStats | None) -> list[int]:
        """Load the newer weights among `items` (key -> sample); the actors that changed."""
        loaded = []
        for key, item in items.items():
            sender = keys.parse_last(key)
            try:
                w = Weights.from_bytes(item.payload, self.shapes, self.n_actors)
            except MessageError as e:
                self.rejects.reject(sender, e)
                continue
            current = stats.incarnation if stats is not None and stats.incarnation else ""
            if current and w.incarnation and w.incarnation != current:
                continue  # a dead learner's weights (cached or late): never loaded once its successor is known
            newer_learner = bool(w.incarnation) and w.incarnation != self.incarnations[w.actor] and \
                (not current or w.incarnation == current)
            if not newer_learner and not plausible_version(w, stats):
                self.rejects.reject(sender, MessageError("future_version", f"v{w.version}"))
                continue
            if w.version > self.versions[w.actor] or newer_learner:
                self.actors.load_member(w.actor, w.params)
                self.versions[w.actor] = w.version
                self.incarnations[w.actor] = w.incarnation
                loaded.append(w.actor)
        return loaded

    def follow(self, sub: bus.Latest, stats: LearnerStats | None) -> list[int]:
        """`update` with what arrived on the weights subscription since the last call."""
        return self.update(sub.fresh(), stats)
