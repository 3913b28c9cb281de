"""Opening Zenoh sessions and the few pub/sub pieces every role uses.

This is the only module (with the services that call it) that imports zenoh.

Topology: a star. The learner (or a ``mode: router`` session) listens; workers, the
referee and monitors connect to it as clients. On one box the launcher picks a free
port and uses ``tcp/127.0.0.1:<port>``. Multicast and gossip scouting are off unless
a config file turns them on, so processes only meet through explicit endpoints.

Delivery rules (see ZENOH.md for the measurements behind them):

* everything is published RELIABLE with CongestionControl.BLOCK (``put`` defaults to
  DROP and lost 5-90% under load);
* "latest value" topics (weights, allocation) use Zenoh's advanced publisher with a
  one-sample cache per key, and subscribers ask for that history when they start or when
  they discover a publisher: a late joiner gets the current value at once
  (``declare_latest_publisher`` / ``Latest.subscribe``);
* subscriber callbacks run on Zenoh's receive thread: they only copy the payload into a
  Python structure (``Inbox`` or ``Latest``) and return; the service loop does the work.

Traps met while building this (zenoh 1.10.2), beyond those in ZENOH.md:

* the advanced publisher refuses to start unless ``timestamping/enabled`` is true;
* with its default per-session timestamp ordering, a wildcard late joiner
  (``weights/*``) silently lost one actor's cached weights when the learner's session
  held two publishers: we turn on per-publisher sequence numbers instead;
* a liveliness token whose Python object is dropped is undeclared at once;
* a subscriber callback that waits on every sample of a stalled consumer stalls the
  link until the publisher's BLOCK gives up and the transport closes (see ``Inbox``).
"""

from __future__ import annotations

import json
import logging
import queue
import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, NamedTuple

import zenoh
from zenoh.ext import (
    AdvancedPublisher,
    CacheConfig,
    HistoryConfig,
    MissDetectionConfig,
    RepliesConfig,
    declare_advanced_publisher,
    declare_advanced_subscriber,
)

from services import keys
from services.codec import MessageError

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")


# --------------------------------------------------------------------------- config & sessions


def init_zenoh_log() -> None:
    """Zenoh's own log (TLS and connection errors) on stderr: RUST_LOG if set, else warnings."""
    try:
        zenoh.init_log_from_env_or("warn")
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
) -> zenoh.Config:
    """A Zenoh config for one role.

    With ``config_file`` (JSON5) the file is the base and ``connect``/``listen``/``mode``
    override it. Multicast scouting, gossip scouting and timestamping (needed by the
    advanced publisher's cache) are set unless the file mentions them. Without ``mode``:
    a file's mode is kept; otherwise ``connect`` alone gives a client, anything else a peer.
    No connect and no listen gives a peer that nobody can reach: tests and launchers
    always pass explicit endpoints.
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
    return conf


def open_session(conf: zenoh.Config, *, retry_for: float = 0.0) -> zenoh.Session:
    """Open a session; a client whose endpoint is not up yet fails at once, so retry
    for up to ``retry_for`` seconds (the launcher starts the learner first, but races happen).

    The caller must close it: prefer ``with open_session(conf) as session:`` or
    ``session_scope``. Never open a session before ``fork`` (ZENOH.md).
    """
    deadline = time.monotonic() + retry_for
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.1)


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


def declare_latest_publisher(session: zenoh.Session, key: str) -> AdvancedPublisher:
    """RELIABLE + BLOCK publisher that keeps its last sample for late joiners.

    Zenoh's advanced publisher with a one-sample cache; ``publisher_detection`` lets
    subscribers that started earlier query it as soon as it appears. Needs
    ``timestamping/enabled`` (``make_config`` sets it).
    """
    block = zenoh.CongestionControl.BLOCK
    return declare_advanced_publisher(
        session,
        key,
        congestion_control=block,
        reliability=zenoh.Reliability.RELIABLE,
        cache=CacheConfig(max_samples=1, replies_config=RepliesConfig(congestion_control=block)),
        # Sequence numbers per publisher instead of the default per-session timestamps:
        # with timestamps, a wildcard subscriber drops the cached sample of one publisher
        # when another publisher of the same session replied with a newer one (seen here
        # with weights/0 and weights/1 declared by the learner's session).
        sample_miss_detection=MissDetectionConfig(),
        publisher_detection=True,
    )


# --------------------------------------------------------------------------- receiving


class _class_or_instance:
    """``Cls.subscribe(session, key, **ctor_kwargs)`` builds and subscribes a new object;
    ``obj.subscribe(session, key)`` subscribes one built earlier. Both return it."""

    def __init__(self, attach: Callable) -> None:
        self._attach = attach
        self.__doc__ = attach.__doc__

    def __get__(self, obj, cls):
        if obj is not None:
            return lambda session, key: self._attach(obj, session, key)
        return lambda session, key, *args, **kwargs: self._attach(cls(*args, **kwargs), session, key)


class Received(NamedTuple):
    """One sample, copied out of Zenoh's buffers."""

    key: str
    payload: bytes
    attachment: bytes | None
    t: float  # time.monotonic() when it was received


def _copy(sample: zenoh.Sample) -> Received:
    att = sample.attachment
    return Received(
        str(sample.key_expr),
        sample.payload.to_bytes(),
        None if att is None else att.to_bytes(),
        time.monotonic(),
    )


class Inbox:
    """A subscription drained into a bounded ``queue.Queue`` (transitions, eval).

    The Zenoh callback copies the sample and puts it in the queue. When the queue is
    full the callback waits, in 50 ms steps, for at most ``put_timeout`` seconds
    (default 1 s): that wait is backpressure (the publisher's BLOCK put waits too).
    If the queue is still full after that, the inbox is *overflowing*: this sample
    and every further one that finds the queue full is dropped at once, counted in
    ``dropped`` and logged, until the consumer makes room again.

    Why not wait longer: the callback runs on the link's receive thread. While it
    waits, the whole link stalls, and once a publisher's push has waited 5 s Zenoh
    closes the transport and everything after is lost without a trace (measured here:
    waiting 0.5 s per message with a stalled consumer killed the link after ~2 s and
    lost ~20k messages, of which only 24 were counted). Bounding the stall per
    overflow episode keeps the link alive and every loss counted. A consumer that
    keeps up (or a rate limiter upstream) never sees a drop.
    """

    def __init__(self, maxsize: int = 4096, *, put_timeout: float = 1.0) -> None:
        self._q: queue.Queue[Received] = queue.Queue(maxsize)
        self.put_timeout = put_timeout
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._overflowing = False
        self._sub = None
        self.received = 0
        self.waits = 0  # times the callback found the queue full and waited
        self.dropped = 0

    @_class_or_instance
    def subscribe(self, session: zenoh.Session, key: str) -> "Inbox":
        """Feed this inbox from ``key``: ``Inbox.subscribe(session, key, maxsize=...)`` or
        ``Inbox(maxsize=...).subscribe(session, key)``."""
        if self._sub is not None:
            raise RuntimeError("inbox already subscribed")
        self._sub = session.declare_subscriber(key, self._on_sample)
        return self

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            self.push(_copy(sample))
        except Exception:  # never let an exception escape into Zenoh's thread
            log.exception("inbox callback failed")

    def push(self, item: Received) -> bool:
        """Enqueue, waiting up to ``put_timeout`` when full (not when overflowing).
        False if the item was dropped."""
        try:
            self._q.put_nowait(item)
            with self._lock:
                self.received += 1
                self._overflowing = False
            return True
        except queue.Full:
            pass
        if not self._overflowing:
            with self._lock:
                self.waits += 1
            deadline = time.monotonic() + self.put_timeout
            while not self._closed.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                try:
                    self._q.put(item, timeout=min(0.05, left))
                    with self._lock:
                        self.received += 1
                    return True
                except queue.Full:
                    continue
        with self._lock:
            self._overflowing = True
            self.dropped += 1
            n = self.dropped
        if n == 1 or n % 1000 == 0:
            log.warning("inbox full for %.1fs: dropped %d message(s) so far (last on %s)",
                        self.put_timeout, n, item.key)
        return False

    @property
    def overflowing(self) -> bool:
        """True while samples are being dropped because the consumer stalled."""
        return self._overflowing

    def get(self, timeout: float | None = None) -> Received | None:
        """The next sample, or None after ``timeout`` seconds (None: wait forever)."""
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            return None

    def drain(self, max_items: int = 1 << 30) -> list[Received]:
        """Everything queued now (at most ``max_items``), without waiting."""
        out: list[Received] = []
        while len(out) < max_items:
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                break
        return out

    def qsize(self) -> int:
        return self._q.qsize()

    def close(self) -> None:
        """Undeclare the subscription; a callback waiting on a full queue gives up at once."""
        self._closed.set()
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __enter__(self) -> "Inbox":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Latest:
    """The newest sample per key, thread-safe (weights, allocation, stats).

    Like a RingChannel of size 1 per key: older samples are simply replaced. ``fresh()``
    returns only what arrived since the previous ``fresh()``, so a worker can poll it
    every step for free. ``subscribe`` asks publishers for their cached last sample
    (late joiner) and keeps following new ones.
    """

    def __init__(self, *, late_join: bool = True) -> None:
        self.late_join = late_join
        self._cond = threading.Condition()
        self._items: dict[str, Received] = {}
        self._fresh: dict[str, Received] = {}
        self._sub = None
        self.received = 0

    @_class_or_instance
    def subscribe(self, session: zenoh.Session, key: str) -> "Latest":
        """Follow ``key``: ``Latest.subscribe(session, key)`` or ``Latest().subscribe(...)``.
        With ``late_join`` the cached last sample of every matching latest-publisher is
        fetched at once and whenever such a publisher appears later."""
        if self._sub is not None:
            raise RuntimeError("already subscribed")
        if self.late_join:
            self._sub = declare_advanced_subscriber(
                session,
                key,
                self._on_sample,
                history=HistoryConfig(detect_late_publishers=True, max_samples=1),
            )
        else:
            self._sub = session.declare_subscriber(key, self._on_sample)
        return self

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            if sample.kind == zenoh.SampleKind.PUT:
                self.put(_copy(sample))
        except Exception:
            log.exception("latest callback failed")

    def put(self, item: Received) -> None:
        with self._cond:
            self._items[item.key] = item
            self._fresh[item.key] = item
            self.received += 1
            self._cond.notify_all()

    def get(self, key: str) -> Received | None:
        with self._cond:
            return self._items.get(key)

    def forget(self, key: str) -> None:
        """Drop the value held for ``key`` (it was invalid)."""
        with self._cond:
            self._items.pop(key, None)
            self._fresh.pop(key, None)

    def snapshot(self) -> dict[str, Received]:
        with self._cond:
            return dict(self._items)

    def fresh(self) -> dict[str, Received]:
        """Samples that arrived since the last call (newest per key)."""
        with self._cond:
            out, self._fresh = self._fresh, {}
            return out

    def wait_fresh(self, timeout: float | None = None) -> bool:
        """Sleep until something arrived since the last ``fresh()`` (not consumed). True if so.
        Lets a loop pause without spinning until new weights/stats come in."""
        with self._cond:
            return self._cond.wait_for(lambda: bool(self._fresh), timeout)

    def wait(self, key: str | None = None, timeout: float | None = None) -> bool:
        """Wait until ``key`` (or any key) has a value. True if it has."""
        with self._cond:
            return self._cond.wait_for(
                lambda: (key in self._items) if key is not None else bool(self._items), timeout
            )

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __enter__(self) -> "Latest":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- liveliness


def declare_alive(session: zenoh.Session, run: str, role: str, id: str) -> zenoh.LivelinessToken:  # noqa: A002
    """Announce this process; the token disappears on ``undeclare``, session close, or death.

    Keep the returned token referenced: when the Python object is garbage collected the
    token is undeclared and the process looks dead (seen here).
    """
    return session.liveliness().declare_token(keys.alive(run, role, id))


class AliveWatch:
    """The set of live ``(role, id)`` of a run, kept up to date from liveliness samples.

    ``on_change(role, id, alive)`` runs on Zenoh's thread: keep it short, never block.
    A frozen (not dead) host disappears only after the lease (10 s by default).
    """

    def __init__(
        self,
        role: str | None = None,
        on_change: Callable[[str, str, bool], None] | None = None,
    ) -> None:
        self.role = role
        self.on_change = on_change
        self._cond = threading.Condition()
        self._members: set[tuple[str, str]] = set()
        self._sub = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            role, id_ = keys.parse_alive(str(sample.key_expr))
        except ValueError:
            log.warning("ignoring liveliness token %s", sample.key_expr)
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._cond:
            before = (role, id_) in self._members
            if alive:
                self._members.add((role, id_))
            else:
                self._members.discard((role, id_))
            self._cond.notify_all()
        if before != alive and self.on_change is not None:
            try:
                self.on_change(role, id_, alive)
            except Exception:
                log.exception("liveliness on_change failed")

    def live(self) -> frozenset[str]:
        """Ids that are up (of the watched role; of every role when watching all)."""
        with self._cond:
            return frozenset(i for r, i in self._members if self.role in (None, r))

    def members(self) -> frozenset[tuple[str, str]]:
        with self._cond:
            return frozenset(self._members)

    def wait_for(self, predicate: Callable[[frozenset[str]], bool], timeout: float | None = None) -> bool:
        """Wait until ``predicate(self.live())`` holds. True if it does."""
        with self._cond:
            return self._cond.wait_for(
                lambda: predicate(frozenset(i for r, i in self._members if self.role in (None, r))),
                timeout,
            )

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None

    def __enter__(self) -> "AliveWatch":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def watch_alive(
    session: zenoh.Session,
    run: str,
    role: str | None = None,
    on_change: Callable[[str, str, bool], None] | None = None,
) -> AliveWatch:
    """Follow the liveliness tokens of ``run`` (one role, or all); tokens already up count."""
    watch = AliveWatch(role, on_change)
    watch._sub = session.liveliness().declare_subscriber(
        keys.alive_all(run, role), watch._on_sample, history=True
    )
    return watch


# --------------------------------------------------------------------------- accounting


IN_ORDER = "in_order"
GAP = "gap"
DUPLICATE = "duplicate"
RECOVERED = "recovered"  # a resent batch that fills an earlier gap (after a learner restart)
REDUNDANT = "redundant"  # a resent batch that was already received (dropped, harmless)

MAX_HOLES = 4096  # gap intervals remembered per stream; older ones stay lost for good


class SequenceTracker:
    """Per-sender sequence numbers: proves nothing was lost or delivered twice.

    Each (sender, incarnation) counts from 0. A seq above the expected one is a gap (the
    missing ones count as ``lost`` and are remembered as holes); one below it is a
    ``duplicate``. Batches a worker *resends* (after a learner restart, flagged as such) are
    different: one that fills a hole is ``RECOVERED`` (``lost`` goes down again), one that was
    already received is ``REDUNDANT`` (dropped, counted apart). A new incarnation (a restarted
    worker) starts its own count. Holes are kept as at most ``MAX_HOLES`` intervals per
    stream, so a forged huge seq costs one interval, not memory per missing number.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._next: dict[tuple[str, str], int] = {}
        self._holes: dict[tuple[str, str], list[list[int]]] = {}  # [start, stop) intervals, sorted
        self._senders: dict[str, dict] = {}
        self.received = 0
        self.lost = 0
        self.duplicates = 0
        self.recovered = 0
        self.redundant = 0

    def observe(self, sender: str, incarnation: str, seq: int, resend: bool = False) -> str:
        with self._lock:
            stream = (sender, incarnation)
            expected = self._next.get(stream, 0)
            s = self._senders.setdefault(
                sender,
                {"received": 0, "lost": 0, "duplicates": 0, "last_seq": -1, "incarnation": incarnation},
            )
            if seq < expected:
                if resend and self._fill(stream, seq):
                    self.lost -= 1
                    s["lost"] -= 1
                    self.recovered += 1
                    s["recovered"] = s.get("recovered", 0) + 1
                    self.received += 1
                    s["received"] += 1
                    return RECOVERED
                if resend:
                    self.redundant += 1
                    s["redundant"] = s.get("redundant", 0) + 1
                    return REDUNDANT
                self.duplicates += 1
                s["duplicates"] += 1
                return DUPLICATE
            self._next[stream] = seq + 1
            self.received += 1
            s["received"] += 1
            s["last_seq"] = seq
            if s["incarnation"] != incarnation:  # a new incarnation: the old stream's holes are its own
                s["incarnation"] = incarnation
                s.pop("holes", None)
            if seq > expected:
                self.lost += seq - expected
                s["lost"] += seq - expected
                holes = self._holes.setdefault(stream, [])
                holes.append([expected, seq])
                if len(holes) > MAX_HOLES:
                    del holes[0]  # the oldest gap can no longer be filled; it stays counted as lost
                s["holes"] = [list(h) for h in holes]
                return GAP
            return IN_ORDER

    def _fill(self, stream: tuple[str, str], seq: int) -> bool:
        holes = self._holes.get(stream)
        if not holes:
            return False
        for i, (a, b) in enumerate(holes):
            if a <= seq < b:
                parts = [[a, seq]] if seq > a else []
                if seq + 1 < b:
                    parts.append([seq + 1, b])
                holes[i:i + 1] = parts
                sender = self._senders.get(stream[0])
                if sender is not None and sender.get("incarnation") == stream[1]:
                    sender["holes"] = [list(h) for h in holes]
                return True
        return False

    def restore(self, per_sender: dict[str, dict]) -> None:
        """Continue from a checkpoint's ``per_sender()``: each sender's last incarnation."""
        with self._lock:
            for sender, s in per_sender.items():
                stream = (sender, s["incarnation"])
                self._next[stream] = int(s["last_seq"]) + 1
                self._holes[stream] = [[int(a), int(b)] for a, b in s.get("holes", [])][-MAX_HOLES:]
                self._senders[sender] = dict(s)
                self.lost += int(s.get("lost", 0))
                self.duplicates += int(s.get("duplicates", 0))
                self.recovered += int(s.get("recovered", 0))
                self.redundant += int(s.get("redundant", 0))

    def expected(self, sender: str, incarnation: str) -> int:
        """The next seq expected from this stream (= how many were seen, when none is lost)."""
        with self._lock:
            return self._next.get((sender, incarnation), 0)

    def contiguous(self, sender: str) -> tuple[str, int] | None:
        """(incarnation, seq) of the sender's last stream: every seq up to `seq` was received."""
        with self._lock:
            s = self._senders.get(sender)
            if s is None:
                return None
            stream = (sender, s["incarnation"])
            holes = self._holes.get(stream)
            upto = holes[0][0] - 1 if holes else self._next.get(stream, 0) - 1
            return s["incarnation"], upto

    def per_sender(self) -> dict[str, dict]:
        """``{sender: {received, lost, duplicates, last_seq, incarnation[, holes, recovered]}}`` (a copy)."""
        with self._lock:
            return {k: {**v, **({"holes": [list(h) for h in v["holes"]]} if "holes" in v else {})}
                    for k, v in self._senders.items()}


def run_is_done(done: "Latest", run: str, rejects: "RejectLog") -> bool:
    """True once a valid end-of-run notice arrived; anything else on the key is rejected."""
    item = done.get(keys.done(run))
    if item is None:
        return False
    from services.codec import Done

    try:
        Done.from_bytes(item.payload)
        return True
    except MessageError as e:
        rejects.reject(keys.parse_last(item.key) if "/" in item.key else "?", e)
        done.forget(item.key)
        return False


class RejectLog:
    """Counts rejected messages by reason; logs the first of each (sender, reason) pair.

    A bad message never crashes a process: it is dropped, counted here, and the operator
    sees one warning per sender and reason rather than a flood.
    """

    MAX_LOGGED_PAIRS = 10_000  # bounded: senders of hostile messages may be arbitrary

    def __init__(self, logger: logging.Logger | None = None, what: str = "message") -> None:
        self._log = logger or log
        self._what = what
        self._lock = threading.Lock()
        self._counts: dict[str, int] = {}
        self._logged: set[tuple[str, str]] = set()

    def reject(self, sender: str | None, error: MessageError | str, detail: str = "") -> None:
        reason = error.reason if isinstance(error, MessageError) else str(error)
        if isinstance(error, MessageError) and not detail:
            detail = error.detail
        sender = sender or "?"
        with self._lock:
            self._counts[reason] = self._counts.get(reason, 0) + 1
            pair = (sender[:256], reason)
            first = pair not in self._logged and len(self._logged) < self.MAX_LOGGED_PAIRS
            if first:
                self._logged.add(pair)
        if first:
            self._log.warning("rejected %s from %s: %s %s (further ones only counted)",
                              self._what, sender[:256], reason, detail[:300])

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())
