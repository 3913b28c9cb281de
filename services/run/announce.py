"""What `mam-learner` says about itself: where it listens, what it waits for, what the budget
leaves out (services/run/options.py `budget_warnings`), and a split-role run with fewer workers than M.

`mam run` starts M workers itself and prints the budget notes on its own terminal; a learner
started by hand (`mam-learner`, roles spread over machines) says the same in its log.
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any

from services.messaging import bus
from services.run.config import RunConfig, budget_warnings, learner_banner

WORKER_GRACE_S = 30.0  # how long after start a split-role learner waits before it counts its workers
WORKER_GRACE_ENV = "MAM_WORKER_GRACE_S"  # another grace in seconds (tests)


def announce_learner(cfg: RunConfig, listen: list[str] | None, connect: list[str] | None,
                     log: logging.Logger) -> None:
    """One line on where the learner listens and what it waits for; one per budget note."""
    log.info("%s", learner_banner(cfg, listen, connect))
    for line in budget_warnings(cfg):
        log.warning("note: %s", line)
    if cfg.slot_binding:  # services/run/binding.py: batches claiming another slot are refused (unbound_slot)
        log.info("slot binding: %s; a worker no entry matches may claim no slot",
                 ", ".join(f"{wid}={slots if slots == '*' else ','.join(map(str, slots))}"
                           for wid, slots in cfg.slot_binding.items()))


class WorkerCount:
    """Warns once when, `grace_s` after start, fewer than M workers of the run are up (liveliness),
    and again if the count falls below M after all M had joined. `close()` stops it."""

    def __init__(self, session: Any, cfg: RunConfig, log: logging.Logger, grace_s: float | None = None) -> None:
        if grace_s is None:
            grace_s = float(os.environ.get(WORKER_GRACE_ENV) or WORKER_GRACE_S)
        self.cfg, self.log, self.grace_s = cfg, log, grace_s
        self.watch = bus.watch_alive(session, cfg.run, "worker")
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="worker-count", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        m, run = self.cfg.algo.workers, self.cfg.run
        if self.stop.wait(self.grace_s):
            return
        warned, full = False, False
        while not self.stop.is_set():
            up = len(self.watch.live())
            full = full or up >= m
            if up < m and not warned:
                self.log.warning("only %d of M = %d workers of run %r are up %s: the run waits for the missing "
                                 "slots (every iteration needs each of them); start them (mam-worker --run %s "
                                 "--connect ENDPOINT --id NAME --slot I, for each missing slot I) or run with "
                                 "--workers %d",
                                 up, m, run, "any more" if full else f"{self.grace_s:.0f} s after the start",
                                 run, max(up, 1))
                warned = True
            elif up >= m:
                warned = False
            self.stop.wait(5.0)

    def close(self) -> None:
        if not self.stop.is_set():  # once (the learner closes it at its budget, and on leaving)
            self.stop.set()
            self.watch.close()
