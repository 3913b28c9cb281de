"""Several slots of a run in one worker process, stepped by one loop (`mam-worker --slot 0,1,2`,
`mam run --slots-per-worker N`; each slot a services/roles/worker.py `Worker`), and the command
line's slots and ids."""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Callable, Iterator
from typing import Any

import typer

from services.messaging import keys
from services.roles import role

WaitFor = Callable[[], Any]  # what a slot's loop waits on before its next pass (`Worker.passes`)


class WorkerGroup:
    """Several slots in one process, stepped by one loop in one thread (`mam-worker --slot 0,1,2`).

    Each slot is a whole `Worker` (its id, incarnation, subscriptions, kept batches and reports), so
    the learner, the referee and a spare see the same slots as from separate processes, and each
    stays exact through the same recovery paths. The loop gives every slot a pass in turn and
    waits only when none could step, until a sample arrives on any slot's subscriptions (`wake`):
    the process wakes once for a weights version, not once per slot, decodes each weights and
    stats message once for all its slots (`role.Decodes`), and shares one interpreter
    and one Zenoh session (on two cores, 0.87x the wall time of a six-slot run, the same bits:
    docs/PERFORMANCE.md). A slot rebuilding itself (`Worker.take_over`, after a restart) holds
    the others for as long as its query takes; a killed process takes all its slots with it
    (`mam run` restarts it with them)."""

    WAIT_S = 0.05  # the longest wait without a sample (a slot's own waits are 0.05-0.1 s)

    def __init__(self, make: Callable[[str, int, threading.Event, role.Decodes], Any], ids: list[str],
                 slots: list[int]) -> None:
        """`make(id, slot, wake, decodes)`: the slot's `Worker`, its subscriptions setting `wake`,
        its messages decoded through `decodes` (one for the group)."""
        self.wake, self.decodes = threading.Event(), role.Decodes()
        self.workers = [make(wid, slot, self.wake, self.decodes) for wid, slot in zip(ids, slots)]

    @property
    def stop_requested(self) -> bool:
        return any(w.stop_requested for w in self.workers)

    @stop_requested.setter
    def stop_requested(self, value: bool) -> None:  # (role.stop_on_signals)
        for w in self.workers:
            w.stop_requested = value

    def serve(self) -> None:
        running: list[tuple[Any, Iterator[WaitFor | None]]] = []
        try:
            for w in self.workers:
                w.open()
                running.append((w, w.passes()))
            while running:
                self.wake.clear()  # (a sample arriving during the round sets it: no wait after it)
                stepped, left = False, []
                for w, loop in running:
                    try:
                        stepped |= next(loop) is None
                    except StopIteration:
                        w.close()  # done, or the slot is another's now
                        continue
                    left.append((w, loop))
                running = left
                if running and not stepped:
                    self.wake.wait(self.WAIT_S)
        finally:
            for w, _ in running:
                w.close()


def parse_slots(text: str) -> list[int]:
    """`--slot`: I, or several slots as I,J,... and ranges I-J, each once."""
    slots: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise typer.BadParameter(f"--slot {text!r}: want a slot I, or slots I,J,... and ranges I-J")
        for s in range(int(lo), int(hi if sep else lo) + 1):
            if s in slots:
                raise typer.BadParameter(f"--slot {text!r}: slot {s} is named twice")
            slots.append(s)
    if not slots:
        raise typer.BadParameter(f"--slot {text!r}: an empty range")
    return slots


def slot_ids(id_text: str | None, slots: list[int]) -> list[str]:
    """`--id`: one id a slot, comma-separated in the order of --slot (default HOST-PID, and
    HOST-PID-sI for each slot I of several)."""
    if id_text is None:
        base = f"{socket.gethostname()}-{os.getpid()}"
        ids = [base] if len(slots) == 1 else [f"{base}-s{s}" for s in slots]
    else:
        ids = [i.strip() for i in id_text.split(",")]
    if len(ids) != len(slots):
        raise typer.BadParameter(f"--id names {len(ids)} worker(s) for {len(slots)} slot(s): give one id a slot")
    if len(set(ids)) != len(ids):
        raise typer.BadParameter("--id: each slot needs its own worker id")
    try:
        return [keys.check_name(i, "worker id") for i in ids]
    except ValueError as e:
        raise typer.BadParameter(f"--id: {e}") from None


def serve(run: str, conf: Any, ids: list[str], slots: list[int], make: Callable[..., Any]) -> None:
    """Serve `slots` as the workers `ids`, each built by `make(cfg, session, id, slot, wake,
    decodes)`: one slot alone (its waits its own, `wake` and `decodes` None), several in a
    `WorkerGroup`."""
    def build(cfg: Any, session: Any) -> Any:
        if len(slots) == 1:
            return make(cfg, session, ids[0], slots[0], None, None)
        return WorkerGroup(lambda wid, slot, wake, decodes: make(cfg, session, wid, slot, wake, decodes), ids, slots)

    role.serve_role("worker", conf, build, run=run, log=logging.getLogger("mam.worker"))
