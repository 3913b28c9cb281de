"""Every Zenoh key expression of a run, in one place.

All keys live under ``mam/<run>/`` so two runs on the same router never see each
other's messages::

    mam/<run>/weights/<k>             learner -> *        actor k's parameters + version
    mam/<run>/weights/<k>/eval        learner -> referee  exact mode: the version an evaluation needs
    mam/<run>/transitions/<worker>    worker  -> learner  a batch of transitions
    mam/<run>/allocation              referee -> *        slots, P_k, I_k, elimination
    mam/<run>/eval                    referee -> *        per-actor evaluation returns
    mam/<run>/stats/learner           learner -> *        env steps, updates, credit
    mam/<run>/config                  learner -> *        the resolved run config
    mam/<run>/done                    learner -> *        end of the run
    mam/<run>/episode/w<i>            query to the learner  slot i's current episode (a takeover)
    mam/<run>/alive/<role>/<id>       liveliness tokens   who is up right now
    mam/<run>/alive/spare/<id>        a waiting spare     `mam-worker --spare` (services/roles/spare.py)

Names (run, worker, role, id) are single key chunks: non-empty, at most 128
characters of ``[A-Za-z0-9_.-]``. Anything else (``/``, ``*``, ``$``, ``?``, ``#``,
spaces, empty) raises ``ValueError`` here, before it can widen a subscription or
publish outside the run. This module must not import zenoh (the codec uses it).
"""

from __future__ import annotations

import re

ROOT = "mam"
ROLES = ("learner", "worker", "referee", "monitor")
SPARE = "spare"  # the liveliness role of a waiting `mam-worker --spare`; it is a "worker" once it holds a slot
MAX_NAME_LEN = 128

_NAME = re.compile(r"[A-Za-z0-9_.\-]+")


def check_name(value: object, what: str = "name") -> str:
    """Return ``value`` if it is a valid single key chunk, else raise ValueError."""
    if not isinstance(value, str):
        raise ValueError(f"{what} must be a str, got {type(value).__name__}")
    if not value:
        raise ValueError(f"{what} must not be empty")
    if len(value) > MAX_NAME_LEN:
        raise ValueError(f"{what} longer than {MAX_NAME_LEN} characters")
    if not _NAME.fullmatch(value):
        raise ValueError(f"{what} {value!r} may only contain [A-Za-z0-9_.-]")
    return value


def _actor_index(k: object) -> int:
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise ValueError(f"actor index must be an int >= 0, got {k!r}")
    return k


_BASES: dict[str, str] = {}  # run -> its checked base (a role builds its run's keys on every pass of its loop)


def _base(run: str) -> str:
    base = _BASES.get(run) if isinstance(run, str) else None
    if base is None:
        base = f"{ROOT}/{check_name(run, 'run')}"
        if len(_BASES) < 64:
            _BASES[run] = base
    return base


def weights(run: str, k: int) -> str:
    return f"{_base(run)}/weights/{_actor_index(k)}"


def eval_weights(run: str, k: int) -> str:
    """Exact mode: snapshots of actor k at the versions the referee's evaluations need."""
    return f"{weights(run, k)}/eval"


def eval_weights_all(run: str) -> str:
    return f"{_base(run)}/weights/*/eval"


def slot_name(slot: int) -> str:
    """Exact mode: the allocation's name of environment slot `slot` (what `mam run` calls its worker)."""
    return f"w{int(slot)}"


def weights_all(run: str) -> str:
    return f"{_base(run)}/weights/*"


def transitions(run: str, worker: str) -> str:
    return f"{_base(run)}/transitions/{check_name(worker, 'worker')}"


def transitions_all(run: str) -> str:
    return f"{_base(run)}/transitions/*"


def episode(run: str, slot: int) -> str:
    """Queryable (learner): slot `slot`'s current episode, for a worker taking the slot over."""
    return f"{_base(run)}/episode/{slot_name(slot)}"


def episode_all(run: str) -> str:
    return f"{_base(run)}/episode/*"


def allocation(run: str) -> str:
    return f"{_base(run)}/allocation"


def eval(run: str) -> str:  # noqa: A001 - the topic's name in the design
    return f"{_base(run)}/eval"


def learner_stats(run: str) -> str:
    return f"{_base(run)}/stats/learner"


def role_stats(run: str, role: str, id: str) -> str:  # noqa: A002
    """Counters of a worker or the referee (rejections), next to the learner's."""
    return f"{_base(run)}/stats/{check_name(role, 'role')}-{check_name(id, 'id')}"


def stats_all(run: str) -> str:
    return f"{_base(run)}/stats/*"


def config(run: str) -> str:
    """The resolved run config, published by the learner for late joiners."""
    return f"{_base(run)}/config"


def done(run: str) -> str:
    return f"{_base(run)}/done"


def role_stats_all(run: str, role: str) -> str:
    """The counters of every process of one role (the learner waits for the referee's final one)."""
    return f"{_base(run)}/stats/{check_name(role, 'role')}-$*"  # $* : within one chunk


def alive(run: str, role: str, id: str) -> str:  # noqa: A002
    return f"{_base(run)}/alive/{check_name(role, 'role')}/{check_name(id, 'id')}"


def alive_all(run: str, role: str | None = None) -> str:
    """All liveliness tokens of the run, or only those of one role."""
    if role is None:
        return f"{_base(run)}/alive/*/*"
    return f"{_base(run)}/alive/{check_name(role, 'role')}/*"


def parse_alive(key: str) -> tuple[str, str]:
    """``mam/<run>/alive/<role>/<id>`` -> ``(role, id)``; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    check_name(parts[1], "run")
    return check_name(parts[3], "role"), check_name(parts[4], "id")


def parse_last(key: str) -> str:
    """Last chunk of a run key (the ``<k>`` of weights, the ``<worker>`` of transitions)."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"not a {ROOT}/<run>/... key: {key!r}")
    return check_name(parts[-1], "last key chunk")


def parse_actor(key: str) -> int:
    """``mam/<run>/weights/<k>`` -> ``k``; ValueError otherwise."""
    last = parse_last(key)
    if not last.isdigit() or (len(last) > 1 and last[0] == "0"):
        raise ValueError(f"not an actor index: {key!r}")
    return int(last)
