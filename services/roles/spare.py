"""`mam-worker --spare`: a worker that holds no slot, waits, and takes over a slot whose worker is gone.

A spare joins the run like a worker (`--run`, `--connect`), announces itself under
mam/<run>/alive/spare/<id> and watches three things: the learner's stats (`awaiting`: the slots
the learner waits for rows from), the workers' liveliness tokens, and the workers' reports on
mam/<run>/stats/worker-<id> (each says its slot). A slot is *orphaned* while the learner awaits
its rows and no live worker reports it as its slot (a worker whose token is gone holds nothing;
while a live worker has not reported yet, no slot is orphaned).

The rule (`decide`, pure): the orphaned slots, lowest first, go to the live spares in the order
of their ids; a spare with r live spares of smaller id before it watches the r-th orphaned slot
(none if there are fewer). It takes that slot over once the slot it watches has stayed the same,
and orphaned, for longer than `--take-over-after` seconds; any change restarts the count. It then
logs one line, drops its spare token and serves the slot as an ordinary `Worker` (same session,
same id), which finds where the run stands from the learner's stats.

Why two spares do not take the same slot: they see the same orphaned slots and the same spares
(up to a message's delay), so they watch different slots. When spare A takes slot i, its spare
token goes and spare B may move up to watch slot i, but its count starts then: within a second
A's worker report says it holds slot i, long before B's count reaches the limit (at least
MIN_TAKE_OVER_S). Should it happen anyway, the learner keeps the newest incarnation as the
slot's owner. The price of the rule: a slot orphaned before a lower one waits for the lower one
to be taken first (a spare watches one slot at a time).

If the run ends while it waits, a spare exits 0 and says it was not needed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer

from services.messaging import bus, keys
from services.messaging.codec import MessageError, decode
from services.roles import role
from services.run.binding import SlotBinding
from services.run.config import RunConfig

log = logging.getLogger("mam.spare")

MIN_TAKE_OVER_S = 2.0  # twice the workers' report period: a worker that just took a slot has said so
FALLBACK_TAKE_OVER_S = 300.0  # when the run has no stall policy (stall_timeout 0)
POLL_S = 0.2  # how often a waiting spare looks (the learner's stats come 40 times a second while it waits)


@dataclass(frozen=True)
class Watch:
    """The slot a spare would take (None: none for it) and since when, continuously."""

    slot: int | None
    since: float


def orphaned(awaiting: Iterable[int], held: Iterable[int]) -> list[int]:
    """Slots the learner awaits rows from that no live worker holds, lowest first (-1, the
    referee, is not a slot)."""
    return sorted({s for s in awaiting if s >= 0} - set(held))


def decide(awaiting: Iterable[int], held: Iterable[int], ahead: int, watch: Watch | None, now: float,
           limit: float) -> tuple[int | None, Watch]:
    """The rule: (the slot to take now or None, what is watched from now on).

    `awaiting`: the slots the learner awaits rows from; `held`: the slots of live workers;
    `ahead`: the live spares ranked before this one (smaller ids); `watch`: the previous answer."""
    free = orphaned(awaiting, held)
    slot = free[ahead] if ahead < len(free) else None
    if watch is None or watch.slot != slot:
        watch = Watch(slot, now)
    return (slot if slot is not None and now - watch.since > limit else None), watch


def rank(me: str, spares: Iterable[str]) -> int:
    """How many live spares are ranked before `me` (ids in string order)."""
    return sum(1 for s in set(spares) if s < me)


def take_over_limit(cfg: RunConfig, asked: float | None) -> float:
    """--take-over-after, else the run's stall timeout (else FALLBACK_TAKE_OVER_S), at least MIN_TAKE_OVER_S."""
    if asked is not None:
        return max(asked, MIN_TAKE_OVER_S)
    return max(cfg.stall_timeout if cfg.stall_timeout > 0 else FALLBACK_TAKE_OVER_S, MIN_TAKE_OVER_S)


def served(spare: bool, slot: int | None, take_over_after: float | None, run: str, worker_id: str,
           run_dir: Path | None, worker: Callable[..., Any], connect: list[str] | None, listen: list[str] | None,
           zenoh_config: Path | None) -> bool:
    """`mam-worker`'s options: with --spare, serve the run as a spare and say so (True); without it,
    False (the caller serves its --slot)."""
    if not asked(spare, slot, take_over_after):
        return False
    main(run, role.client_config(connect, listen, zenoh_config), worker_id, take_over_after, run_dir, worker)
    return True


def asked(spare: bool, slot: int | None, take_over_after: float | None) -> bool:
    """Whether `mam-worker` runs as a spare; refuses --spare with --slot (and --take-over-after alone)."""
    if spare and slot is not None:
        raise typer.BadParameter("--spare holds no slot until it takes one over: leave out --slot (or --spare)")
    if take_over_after is not None and not spare:
        raise typer.BadParameter("--take-over-after is for a spare: add --spare")
    if take_over_after is not None and take_over_after < 0:
        raise typer.BadParameter("--take-over-after must be >= 0 seconds")
    return spare


class Spare:
    """Waits (liveliness and reports of the workers, the learner's stats), then serves a slot."""

    def __init__(self, cfg: RunConfig, session: Any, spare_id: str, take_over_after: float | None,
                 run_dir: Path | None, worker: Callable[..., Any]) -> None:
        self.cfg, self.session, self.id, self.run_dir, self.make_worker = cfg, session, spare_id, run_dir, worker
        self.limit = take_over_limit(cfg, take_over_after)
        self.binding = SlotBinding(cfg.slot_binding)  # it watches only the slots its binding allows
        self.rejects = bus.RejectLog(log, "message")
        self.slots: dict[str, int] = {}  # worker id -> the slot of its last report
        self.awaiting: tuple[int, ...] = ()
        self.watch: Watch | None = None
        self.silent_since: float | None = None  # since when live workers have not said their slots
        self.said_silent = False
        self.stop_requested = False

    def serve(self) -> None:
        role.refuse_unbound(self.cfg, self.id, list(range(self.cfg.algo.workers)), "any slot as a spare", log)
        slot, gone = self.wait()
        if slot is None:
            return
        log.info("spare %s takes over slot %d: its worker has been gone %.0f s", self.id, slot, gone)
        worker = self.make_worker(self.cfg, self.session, self.id, slot_index=slot, run_dir=self.run_dir)
        role.stop_on_signals(worker)
        worker.stop_requested = self.stop_requested
        worker.serve()

    def wait(self) -> tuple[int | None, float]:
        """(the slot to take, how long it has been orphaned), or (None, 0) when the run is done or
        this process is asked to stop."""
        run, s = self.cfg.run, self.session
        stats = bus.Latest.subscribe(s, keys.learner_stats(run))
        done = bus.Latest.subscribe(s, keys.done(run))
        reports = bus.Latest(late_join=False).subscribe(s, keys.role_stats_all(run, "worker"))
        # who is up already, before the first look judges a slot orphaned
        workers, spares = bus.watch_alive(s, run, "worker", settle=2.0), bus.watch_alive(s, run, keys.SPARE, settle=2.0)
        token = bus.declare_alive(s, run, keys.SPARE, self.id)
        log.info("spare %s waits on run %s: it takes over a slot the learner has awaited with no live worker "
                 "for %.0f s", self.id, run, self.limit)
        try:
            while not self.stop_requested:
                if bus.run_is_done(done, run, self.rejects):
                    log.info("run %s is done: spare %s was not needed", run, self.id)
                    return None, 0.0
                self.read(stats, reports)
                live = workers.live()
                held = {slot for w, slot in self.slots.items() if w in live}
                # a live worker whose report has not come yet (a spare that just joined, a worker that
                # just started) may hold any slot: none is orphaned until it has said which
                now = time.monotonic()
                awaiting = () if self.unreported(live - self.slots.keys(), now) else self.awaiting
                before = self.watch
                slot, self.watch = decide(awaiting, held, rank(self.id, spares.live() - {self.id}), self.watch, now,
                                          self.limit)
                if slot is not None:
                    return slot, now - self.watch.since
                if self.watch.slot is not None and (before is None or before.slot != self.watch.slot):
                    log.info("slot %d: the learner awaits its rows and no live worker holds it; spare %s takes it "
                             "over in %.0f s unless that changes", self.watch.slot, self.id, self.limit)
                done.wait_fresh(timeout=POLL_S)
            log.info("spare %s stopped before it was needed", self.id)
            return None, 0.0
        finally:
            for sub in (stats, done, reports, workers, spares):
                sub.close()
            token.undeclare()

    def unreported(self, silent: frozenset[str] | set[str], now: float) -> bool:
        """Whether live workers have sent no report yet (said once if that lasts: no report can reach
        this spare, e.g. an access-control list that does not let it read mam/<run>/stats/worker-*)."""
        if not silent:
            self.silent_since = None
        elif self.silent_since is None:
            self.silent_since = now
        elif now - self.silent_since > self.limit and not self.said_silent:
            self.said_silent = True
            log.warning("spare %s: live workers %s have sent no report for %.0f s; it takes over nothing while "
                        "it does not know their slots", self.id, sorted(silent), now - self.silent_since)
        return bool(silent)

    def read(self, stats: bus.Latest, reports: bus.Latest) -> None:
        """The learner's awaited slots (of this run's M slots), and each worker's slot from its report."""
        st = role.fresh_learner_stats(stats, self.cfg.run, self.rejects)
        if st is not None:
            self.awaiting = tuple(a for a in st.awaiting
                                  if a < self.cfg.algo.workers and self.binding.allows(self.id, a))
        for item in reports.fresh().values():
            try:
                body = decode(item.payload)
                worker, slot = keys.check_name(body["id"], "worker id"), body["slot"]
                if isinstance(slot, bool) or not isinstance(slot, int):
                    raise ValueError(f"slot {slot!r}")
            except MessageError as e:
                self.rejects.reject(keys.parse_last(item.key), e)
                continue
            except (KeyError, TypeError, ValueError) as e:
                self.rejects.reject(keys.parse_last(item.key), MessageError("role_stats", str(e)[:200]))
                continue
            self.slots[worker] = slot


def main(run: str, conf: Any, spare_id: str, take_over_after: float | None, run_dir: Path | None,
         worker: Callable[..., Any]) -> None:
    """Serve as a spare of `run`; `worker` builds the Worker of the slot it takes over."""
    role.serve_role("worker", conf, lambda cfg, session: Spare(cfg, session, spare_id, take_over_after, run_dir,
                                                               worker), run=run, log=log)
