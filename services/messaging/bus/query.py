"""Queries: a role answers questions on a key (`Answers`), another asks and waits (`ask`).

The queryable hands each query to a bounded channel; the answering role takes them in its own
loop (`poll`), so no Zenoh callback ever runs role code. A query not answered in time, or one
dropped because the channel was full, is simply asked again by the asker.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh

log = logging.getLogger("services.messaging.bus")


class Answers:
    """A queryable on `key` whose queries are answered by whoever calls `poll`."""

    def __init__(self, session: zenoh.Session, key: str, depth: int = 64) -> None:
        self.queryable = session.declare_queryable(key, handler=zenoh.handlers.FifoChannel(depth))

    def poll(self, answer: Callable[[str, bytes], bytes | None], max_queries: int = 16) -> int:
        """Answer the queries waiting: `answer(key, payload)` gives the reply's payload (None:
        no reply, the asker times out). The number answered."""
        n = 0
        for _ in range(max_queries):
            query = self.queryable.try_recv()
            if query is None:
                break
            try:
                reply = answer(str(query.key_expr), query.payload.to_bytes() if query.payload is not None else b"")
                if reply is not None:
                    query.reply(query.key_expr, reply)
                    n += 1
            except Exception:  # a question this role cannot answer never stops it; the asker asks again
                log.exception("no answer to a query on %s", query.key_expr)
            finally:
                query.drop()  # the asker's get ends now, not at its timeout
        return n

    def close(self) -> None:
        self.queryable.undeclare()


def ask_all(session: zenoh.Session, key: str, timeout: float, payload: bytes = b"") -> list[bytes]:
    """Every answer to a query on `key` (each queryable's), within `timeout` seconds: the caller
    decides what to do when they disagree, rather than take whichever came first."""
    replies = session.get(key, payload=payload, timeout=timeout, target=zenoh.QueryTarget.ALL,
                          consolidation=zenoh.ConsolidationMode.NONE)  # each queryable's, none merged away
    return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]


def ask(session: zenoh.Session, key: str, timeout: float, payload: bytes = b"") -> bytes | None:
    """The first answer to a query on `key`, or None when none came within `timeout` seconds."""
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
    return None
