"""Liveliness: who is up right now (tokens under mam/<run>/alive/<role>/<id>)."""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import zenoh

from services.messaging import keys

log = logging.getLogger("services.messaging.bus")


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
        self.settled: bool | None = None  # watch_alive(settle=...): whether the first look was complete

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
    settle: float | None = None,
) -> AliveWatch:
    """Follow the liveliness tokens of ``run`` (one role, or all); tokens already up count.

    The subscriber's history comes on Zenoh's thread, some time after this returns. A caller that
    judges "nobody is up" from its first look passes ``settle`` (seconds): a liveliness query finds
    the tokens up now, and this returns once the watch holds them all (``watch.settled``), or the time
    runs out. The query goes first: asked after a liveliness subscriber of the same keys exists on the
    session (even a closed one), Zenoh answered it with nothing or a part (docs/ZENOH-NOTES.md)."""
    watch = AliveWatch(role, on_change)
    up: set[tuple[str, str]] = set()
    deadline = time.monotonic() + (settle or 0.0)
    if settle is not None:
        for reply in session.liveliness().get(keys.alive_all(run, role), timeout=settle):
            try:
                up.add(keys.parse_alive(str(reply.ok.key_expr)))
            except (ValueError, AttributeError, TypeError):
                continue
    watch._sub = session.liveliness().declare_subscriber(
        keys.alive_all(run, role), watch._on_sample, history=True
    )
    if settle is not None:  # a token the query found that goes away meanwhile is not added: False
        with watch._cond:
            watch.settled = watch._cond.wait_for(lambda: up <= watch._members, max(deadline - time.monotonic(), 0.0))
    return watch
