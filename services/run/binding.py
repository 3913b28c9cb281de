"""A run's slot binding (`slot_binding`): which slots each worker id may claim.

The chain certificate -> worker id is the router's access control (docs/DEPLOY.md, section 6:
a certificate per worker host and rules such as `mam/*/transitions/b-$*`); this is the next link,
worker id -> slots. The learner's intake refuses a batch whose worker (the id its key names)
claims a slot its binding does not allow (reason `unbound_slot`, services/roles/intake.py), and a
worker or spare told to take such a slot refuses to start (services/roles/worker.py, spare.py).

Written as `ID=SLOTS` entries separated by commas, e.g. `b0=0,b1=1,spare-a=*` or
`b-*=0-3,c-*=4,5`:

* ID is a worker id, or an id prefix ending in `*` (`b-*`: every id starting with `b-`, as the
  ACL's `b-$*`; `*` alone: every worker). An exact id wins over prefixes, a longer prefix over a
  shorter one: a worker takes the slots of the one entry that matches it best.
* SLOTS is `*` (any slot: a spare), a slot `I`, a range `I-J`, or several, comma-separated
  (a part without `=` adds to the entry before it).
* A binding given, a worker that no entry matches may claim no slot. Several workers may share
  a slot (a replacement, a spare). No binding (the default, ""): any worker may claim any slot.

In a TOML file it may also be a table: `[slot_binding]` with `b0 = 0`, `spare-a = "*"`,
`"b-*" = [0, 1]` or `c = "2-3"`. config.json holds it as {id: "*" or [slots]}.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from services.messaging import keys

ANY = "*"
_RANGE = re.compile(r"(\d+)(?:-(\d+))?")


def parse(value: Any, workers: int) -> dict[str, Any]:
    """The canonical binding ({id or prefix*: "*" or sorted [slots]}) of a string or a table
    (`workers`: M, the slots 0..M-1); ValueError, naming the entry, on bad syntax, an id that is
    no key chunk, a slot outside 0..M-1 and anything named twice."""
    if value is None or value == "" or value == {}:
        return {}
    if isinstance(value, str):
        entries = _split(value)
    elif isinstance(value, Mapping):
        entries = []
        for wid, slots in value.items():
            if isinstance(slots, bool) or not isinstance(slots, (int, str, list, tuple)):
                raise ValueError(f"slot binding: {wid} = {slots!r}: want a slot, a list of slots, \"I-J\" or \"*\"")
            parts = [str(s) for s in slots] if isinstance(slots, (list, tuple)) else str(slots).split(",")
            entries.append((str(wid), [p.strip() for p in parts]))
    else:
        raise ValueError(f"slot binding: want a string such as \"b0=0,b1=1,spare=*\" or a table, not {value!r}")
    out: dict[str, Any] = {}
    for wid, parts in entries:
        _check_id(wid)
        if wid in out:
            raise ValueError(f"slot binding: {wid} is named twice")
        out[wid] = _slots(wid, parts, workers)
    return out


def _split(text: str) -> list[tuple[str, list[str]]]:
    entries: list[tuple[str, list[str]]] = []
    for token in (t.strip() for t in text.split(",")):
        if "=" in token:
            wid, _, first = token.partition("=")
            entries.append((wid.strip(), [first.strip()]))
        elif entries:
            entries[-1][1].append(token)
        else:
            raise ValueError(f"slot binding {text!r}: {token!r} is no ID=SLOTS entry (e.g. \"b0=0,b1=1,spare=*\")")
    return entries


def _check_id(wid: str) -> None:
    prefix = wid[:-1] if wid.endswith("*") else wid
    if prefix == "" and wid == "*":
        return
    try:
        keys.check_name(prefix, "worker id")
    except ValueError as e:
        raise ValueError(f"slot binding: {wid!r}: {e} (an id, or an id prefix ending in *)") from None


def _slots(wid: str, parts: list[str], workers: int) -> Any:
    if parts == [ANY]:
        return ANY
    slots: list[int] = []
    for part in parts:
        m = _RANGE.fullmatch(part)
        if m is None:
            raise ValueError(f"slot binding: {wid}={part!r}: want a slot I, a range I-J or * (all slots)")
        lo, hi = int(m.group(1)), int(m.group(2) if m.group(2) is not None else m.group(1))
        if hi < lo:
            raise ValueError(f"slot binding: {wid}={part}: an empty range")
        if hi >= workers:
            raise ValueError(f"slot binding: {wid}={part}: slot {hi} does not exist (M = {workers} slots: "
                             f"0..{workers - 1})")
        for s in range(lo, hi + 1):
            if s in slots:
                raise ValueError(f"slot binding: {wid}: slot {s} is named twice")
            slots.append(s)
    return sorted(slots)


class SlotBinding:
    """The binding of a run, ready to ask: `allows(worker, slot)`."""

    def __init__(self, table: Mapping[str, Any] | None) -> None:
        self.table = dict(table or {})

    def __bool__(self) -> bool:
        return bool(self.table)

    def entry(self, worker: str) -> str | None:
        """The entry that binds `worker`: its id, else the longest prefix* it starts with; None: none
        (with a binding given: no slot for it)."""
        if worker in self.table:
            return worker
        prefixes = [k for k in self.table if k.endswith("*") and worker.startswith(k[:-1])]
        return max(prefixes, key=len) if prefixes else None

    def allows(self, worker: str, slot: int) -> bool:
        """Whether `worker` may claim `slot` (always, without a binding)."""
        if not self.table:
            return True
        entry = self.entry(worker)
        if entry is None:
            return False
        slots = self.table[entry]
        return slots == ANY or slot in slots

    def describe(self, worker: str) -> str:
        """What `worker` may claim, in words (for a refusal)."""
        entry = self.entry(worker)
        if entry is None:
            return "no slot (no entry of the run's slot_binding matches it)"
        slots = self.table[entry]
        what = "any slot" if slots == ANY else f"slot{'s' if len(slots) > 1 else ''} {', '.join(map(str, slots))}"
        return f"{what} (slot_binding entry {entry})"
