"""Receiving: subscriber callbacks only copy samples into an `Inbox` (a bounded queue) or a
`Latest` (the newest sample per key); the service loop does the work.

Either may take a *screen*: a cheap check run in the callback, before the sample is stored. A
sample it refuses (malformed, from anyone on the bus) is dropped there and counted by the screen,
so it can neither take a valid sample's place in a `Latest` nor a queue slot in an `Inbox`."""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any, Callable, NamedTuple

import zenoh
from zenoh.ext import HistoryConfig, declare_advanced_subscriber

log = logging.getLogger("services.messaging.bus")

# What to store of a sample: the sample itself, or it with what the screen decoded in `value` (so the
# reader does not decode it again); None: drop it (the screen counts it).
Screen = Callable[["Received"], "Received | None"]


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
    value: Any = None  # the payload as the subscription's screen decoded it (None: not decoded)


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

    def __init__(self, maxsize: int = 4096, *, put_timeout: float = 1.0, screen: Screen | None = None,
                 wake: threading.Event | None = None) -> None:
        self._q: queue.Queue[Received] = queue.Queue(maxsize)
        self.screen = screen
        self.wake = wake  # set whenever a sample is queued (a loop waiting on several subscriptions)
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
            item = _copy(sample)
            if self.screen is not None:
                item = self.screen(item)
            if item is not None:
                self.push(item)
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
            if self.wake is not None:
                self.wake.set()
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
                    if self.wake is not None:
                        self.wake.set()
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

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

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

    def __init__(self, *, late_join: bool = True, screen: Screen | None = None,
                 wake: threading.Event | None = None) -> None:
        self.late_join = late_join
        self.screen = screen
        self.wake = wake  # set whenever a sample arrives (a loop waiting on several subscriptions)
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
                item = _copy(sample)
                if self.screen is not None:
                    item = self.screen(item)
                if item is not None:
                    self.put(item)
        except Exception:
            log.exception("latest callback failed")

    def put(self, item: Received) -> None:
        with self._cond:
            self._items[item.key] = item
            self._fresh[item.key] = item
            self.received += 1
            self._cond.notify_all()
        if self.wake is not None:
            self.wake.set()

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
