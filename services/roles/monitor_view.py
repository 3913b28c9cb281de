"""What `mam watch` shows, without the network: a state fed with decoded messages, and its view.

The monitor service decodes `allocation`, `eval`, `stats/learner` and `done` messages and the
liveliness events of `alive/<role>/<id>`, and hands the bodies (the same fields as the run's
JSONL rows) to `MonitorState`. `render(state)` turns the state into rich tables; the service
redraws it in a `rich.live.Live`. Keeping this part pure lets tests drive it with a fake clock.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from rich.console import Group, RenderableType
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from mam_core.config import AlgoConfig
from mam_core.schedule import Schedule

HISTORY = 8  # allocation rounds kept for the history table


@dataclass
class WorkerView:
    """One env worker slot as the monitor last saw it."""

    alive: bool | None = None  # None: never seen on liveliness (known only from stats/allocation)
    last_seen: float | None = None  # clock time of the last sign of life
    actor: int | None = None
    received: int = 0  # transitions the learner accepted from it
    rate: float | None = None  # transitions/s
    lag: int | None = None  # policy versions behind the learner
    last_seq: int | None = None


@dataclass(frozen=True)
class AllocationRound:
    round: int
    env_steps: int
    probabilities: tuple[float, ...]
    counts: tuple[int, ...]
    reason: str


def _float(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _int(value: Any) -> int | None:
    if isinstance(value, bool) or not isinstance(value, int):
        return None
    return value


def _floats(values: Any) -> list[float | None]:
    return [_float(v) for v in values] if isinstance(values, list) else []


def _ints(values: Any) -> list[int | None]:
    return [_int(v) for v in values] if isinstance(values, list) else []


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def message_body(obj: Any) -> dict[str, Any]:
    """A validated message (services/messaging/codec) as the plain dict (lists, not tuples) the
    state takes: what `mam watch` and `mam run`'s progress view feed it."""
    return {name: _plain(getattr(obj, name)) for name in obj.__dataclass_fields__}


class MonitorState:
    """Everything `mam watch` knows about a run, updated one message at a time."""

    def __init__(
        self,
        run: str = "",
        env_id: str = "",
        algo: str = "",
        steps: int | None = None,
        now: Callable[[], float] = time.monotonic,
        history: int = HISTORY,
    ) -> None:
        self.run, self.env_id, self.algo, self.steps = run, env_id, algo, steps
        self.now = now
        self.probabilities: list[float | None] = []
        self.counts: list[int | None] = []
        self.eliminated: list[bool] = []
        self.survivor: int | None = None
        self.round: int | None = None
        self.history: deque[AllocationRound] = deque(maxlen=history)
        self.last_mean: list[float | None] = []  # last evaluated mean return per actor
        # R_k the elimination was decided on: an eliminated actor's return from then on (later
        # evaluations leave it out, and the monitor may have missed the deciding one)
        self.elimination_returns: list[float | None] = []
        self.slots: dict[str, int | None] = {}  # the last allocation's slots: worker id (or slot name) -> actor
        self.eval_round: int | None = None
        self.last_bias: dict[str, Any] | None = None
        self.stats: dict[str, Any] | None = None
        self.stats_seen: float | None = None
        self.steps_per_s: float | None = None  # learner env steps/s from consecutive stats
        self.updates_per_s: float | None = None
        self.workers: dict[str, WorkerView] = {}
        self.roles: dict[tuple[str, str], tuple[bool, float]] = {}  # (role, id) -> (alive, when)
        self.summary: dict[str, Any] | None = None
        self.schedule: Schedule | None = None  # iterations <-> transitions, from the run's config
        self.last_allocation: dict[str, Any] | None = None
        self.last_eval: dict[str, Any] | None = None

    # --- inputs ------------------------------------------------------------------------------

    def on_config(self, d: Mapping[str, Any]) -> None:
        """A run's `config.json` (if the monitor can read it): names and budget for the header."""
        self.run = str(d.get("run") or self.run)
        self.env_id = str(d.get("env_id") or self.env_id)
        self.algo = str(d.get("algo") or self.algo)
        self.steps = _int(d.get("steps")) or self.steps
        algo = d.get("algo_config")
        if isinstance(algo, Mapping) and self.steps:
            try:
                self.schedule = Schedule.for_run(AlgoConfig.from_dict(dict(algo)), self.steps)
            except (TypeError, ValueError):
                self.schedule = None

    def on_allocation(self, d: Mapping[str, Any]) -> None:
        self.last_allocation = dict(d)
        self.probabilities = _floats(d.get("probabilities")) or self.probabilities
        self.counts = _ints(d.get("counts")) or self.counts
        if isinstance(d.get("eliminated"), list):
            self.eliminated = [bool(e) for e in d["eliminated"]]
        self.survivor = _int(d.get("survivor"))
        self.round = _int(d.get("round"))
        slots = d.get("slots")
        if isinstance(slots, Mapping):  # keyed by worker id, or by slot name (w0, w1 ...) in exact mode:
            self.slots = {str(w): _int(a) for w, a in slots.items()}  # a row only for a worker that exists
            for worker, actor in self.slots.items():
                if worker in self.workers:
                    self.workers[worker].actor = actor
        returns = _floats(d.get("returns"))
        if returns and d.get("reason") == "elimination":
            self.elimination_returns = returns
        self.history.append(
            AllocationRound(
                round=_int(d.get("round")) or 0,
                env_steps=_int(d.get("env_steps")) or 0,
                probabilities=tuple(p if p is not None else math.nan for p in _floats(d.get("probabilities"))),
                counts=tuple(c if c is not None else 0 for c in _ints(d.get("counts"))),
                reason=str(d.get("reason", "")),
            )
        )

    def on_eval(self, d: Mapping[str, Any]) -> None:
        self.last_eval = dict(d)
        means = _floats(d.get("mean"))
        if len(self.last_mean) < len(means):
            self.last_mean += [None] * (len(means) - len(self.last_mean))
        for k, m in enumerate(means):
            if m is not None:  # an actor not evaluated this round keeps its last return
                self.last_mean[k] = m
        self.eval_round = _int(d.get("round"))
        if isinstance(d.get("bias"), Mapping):
            self.last_bias = dict(d["bias"])

    def on_stats(self, d: Mapping[str, Any]) -> None:
        now = self.now()
        previous, previous_t = self.stats, self.stats_seen
        if previous is not None and previous_t is not None and now > previous_t:
            dt = now - previous_t
            steps, steps0 = _int(d.get("env_steps")), _int(previous.get("env_steps"))
            updates, updates0 = _int(d.get("updates")), _int(previous.get("updates"))
            if steps is not None and steps0 is not None:
                self.steps_per_s = max(0, steps - steps0) / dt
            if updates is not None and updates0 is not None:
                self.updates_per_s = max(0, updates - updates0) / dt
        per_worker = d.get("per_worker")
        if isinstance(per_worker, Mapping):
            previous_workers = (previous or {}).get("per_worker")
            previous_workers = previous_workers if isinstance(previous_workers, Mapping) else {}
            for worker, info in per_worker.items():
                if not isinstance(info, Mapping):
                    continue
                view = self._worker(str(worker))
                received = _int(info.get("received")) or 0
                before_info = previous_workers.get(worker)
                before = _int(before_info.get("received")) if isinstance(before_info, Mapping) else None
                if before is None or received > before:
                    view.last_seen = now  # the learner got data from it since the last stats
                rate = _float(info.get("rate"))
                if rate is None and before is not None and previous_t is not None and now > previous_t:
                    rate = max(0, received - before) / (now - previous_t)
                view.received, view.rate = received, rate
                view.actor = _int(info.get("actor")) if info.get("actor") is not None else view.actor
                view.lag = _int(info.get("lag"))
                view.last_seq = _int(info.get("last_seq"))
        self.stats, self.stats_seen = dict(d), now

    def on_alive(self, role: str, id: str, alive: bool) -> None:
        now = self.now()
        self.roles[(role, id)] = (alive, now)
        if role == "worker":
            view = self._worker(id)  # a worker exists once its liveliness token or its data is seen
            view.alive, view.last_seen = alive, now  # a departure is the last time it was up

    def on_done(self, d: Mapping[str, Any]) -> None:
        self.summary = dict(d)
        survivor = _int(d.get("survivor"))
        if survivor is not None:
            self.survivor = survivor

    # --- derived ------------------------------------------------------------------------------

    def _worker(self, worker: str) -> WorkerView:
        if worker not in self.workers:
            self.workers[worker] = WorkerView(actor=self.slots.get(worker))
        return self.workers[worker]

    def shown_return(self, k: int) -> float | None:
        """Actor k's return for the actors table: the one its elimination was decided on once it
        is eliminated, else the last evaluation's."""
        eliminated = k < len(self.eliminated) and self.eliminated[k]
        if eliminated and k < len(self.elimination_returns) and self.elimination_returns[k] is not None:
            return self.elimination_returns[k]
        return self.last_mean[k] if k < len(self.last_mean) else None

    @property
    def n_actors(self) -> int:
        stats = self.stats or {}
        lists = (self.probabilities, self.counts, self.eliminated, self.last_mean,
                 stats.get("q_means") or [], stats.get("versions") or [])
        return max(len(x) for x in lists if isinstance(x, list))

    @property
    def done(self) -> bool:
        return self.summary is not None or bool((self.stats or {}).get("done"))

    def at(self, transitions: int | None) -> str:
        """A point of the run in its schedule's units: "iteration 600 (3,000 transitions)"."""
        if transitions is None:
            return "—"
        clock = self.schedule
        if clock is not None and clock.paper and clock.units_at(transitions) != transitions:
            return f"iteration {clock.units_at(transitions):,} ({transitions:,} transitions)"
        return f"{transitions:,} transitions"

    def progress(self, transitions: int | None) -> list[str]:
        """Progress in one unit per figure: "iteration 1,200 / 4,000", "transitions 6,000 / 16,000"."""
        clock = self.schedule
        if transitions is None:
            return ["transitions —"]
        if clock is None:  # no config yet: the budget's unit is unknown
            return [f"transitions {transitions:,}"]
        out = []
        if clock.paper and clock.budget != clock.steps:
            out.append(f"iteration {clock.units_at(transitions):,} / {clock.steps:,}")
        out.append(f"transitions {transitions:,} / {clock.budget:,}")
        return out

    def seconds_ago(self, when: float | None) -> float | None:
        return None if when is None else max(0.0, self.now() - when)

    def actor_status(self, k: int) -> str:
        if self.survivor == k:
            return "survivor"
        if k < len(self.eliminated) and self.eliminated[k]:
            return "eliminated"
        return "live"


# --- view -------------------------------------------------------------------------------------


def _fmt(value: float | None, spec: str = ".3g") -> str:
    return "—" if value is None else format(value, spec)


def _at(values: Any, k: int) -> Any:
    return values[k] if isinstance(values, list) and k < len(values) else None


def _header(state: MonitorState) -> Panel:
    name = " · ".join(x for x in (state.run, state.algo, state.env_id) if x) or "mam"
    stats = state.stats
    roles = "  ".join(
        f"{role} {id}: " + ("[green]up[/green]" if alive else "[red]gone[/red]")
        for (role, id), (alive, _) in sorted(state.roles.items()) if role != "worker"
    )
    if stats is None:
        body = Text.from_markup("[yellow]waiting for learner…[/yellow]" + (f"\n{roles}" if roles else ""))
        return Panel(body, title=name, border_style="yellow")
    steps = _int(stats.get("env_steps"))
    losses = stats.get("losses") or {}
    lines = [
        *state.progress(steps),
        f"updates [bold]{_int(stats.get('updates')) or 0:,}[/bold]",
        f"transitions/s {_fmt(state.steps_per_s, '.1f')}",
        f"updates/s {_fmt(state.updates_per_s, '.1f')}",
        f"utd {_fmt(_float(stats.get('utd')), '.3f')}",
    ]
    second = [
        f"critic loss {_fmt(_float(losses.get('critic')), '.4g')}",
        f"actor loss (sum) {_fmt(_float(losses.get('actor')), '.4g')}",
        f"iteration {_fmt(_float(stats.get('iteration')), ',.0f')}"
        + ("" if stats.get("exact", True) else f" (not exact: {stats.get('inexact')})"),
        f"last stats {_fmt(state.seconds_ago(state.stats_seen), '.1f')}s ago",
    ]
    rejected = stats.get("rejected") or {}
    if isinstance(rejected, Mapping) and any(rejected.values()):
        second.append("rejected " + ", ".join(f"{r}={n}" for r, n in sorted(rejected.items()) if n))
    text = "   ".join(lines) + "\n" + "   ".join(second)
    if roles:
        text += "\n" + roles
    if state.done:
        text += "\n[bold green]done[/bold green]"
        if state.summary and _float(state.summary.get("wall_time_s")) is not None:
            text += f" in {state.summary['wall_time_s']:.0f}s"
    return Panel(Text.from_markup(text), title=name, border_style="green" if state.done else "blue")


def _actors_table(state: MonitorState) -> Table:
    title = "actors" + (f" (round {state.round})" if state.round is not None else "")
    table = Table(title=title, title_justify="left")
    for col in ("actor", "P_k", "I_k", "mean return", "status", "policy version", "mean Q", "actor loss"):
        table.add_column(col, justify="left" if col in ("actor", "status") else "right")
    stats = state.stats or {}
    losses = stats.get("losses") if isinstance(stats.get("losses"), Mapping) else {}  # actor{k}: Eq. 7 per actor
    if any(state.eliminated) and state.elimination_returns:
        table.caption = "an eliminated actor's mean return: the one its elimination was decided on"
        table.caption_justify = "left"
    if state.n_actors == 0:
        table.add_row("—", "", "", "", "no allocation yet", "", "", "")
    for k in range(state.n_actors):
        status = state.actor_status(k)
        style = {"survivor": "bold green", "eliminated": "dim"}.get(status, "")
        shown = {"survivor": "★ survivor", "eliminated": "✗ eliminated"}.get(status, "live")
        table.add_row(
            f"{k}",
            _fmt(_at(state.probabilities, k), ".3f"),
            _fmt(_at(state.counts, k), "d"),
            _fmt(state.shown_return(k), ".2f"),
            shown,
            _fmt(_int(_at(stats.get("versions"), k)), "d"),
            _fmt(_float(_at(stats.get("q_means"), k)), ".3g"),
            _fmt(None if status == "eliminated" else _float(losses.get(f"actor{k}")), ".4g"),
            style=style,
        )
    return table


def _workers_table(state: MonitorState) -> Table:
    table = Table(title="workers", title_justify="left")
    for col in ("worker", "state", "actor", "transitions", "transitions/s", "policy lag", "last seen"):
        table.add_column(col, justify="left" if col in ("worker", "state") else "right")
    if not state.workers:
        table.add_row("—", "no workers yet", "", "", "", "", "")
    for worker, view in sorted(state.workers.items()):
        alive = {True: "[green]alive[/green]", False: "[red]gone[/red]", None: "[dim]?[/dim]"}[view.alive]
        ago = state.seconds_ago(view.last_seen)
        table.add_row(
            worker,
            Text.from_markup(alive),
            _fmt(view.actor, "d"),
            f"{view.received:,}",
            _fmt(view.rate, ".1f"),
            _fmt(view.lag, "d"),
            "—" if ago is None else f"{ago:.1f}s ago",
            style="dim" if view.alive is False else "",
        )
    return table


def _history_table(state: MonitorState) -> Table:
    table = Table(title="allocation history", title_justify="left")
    for col in ("round", "at", "P", "I", "reason"):
        table.add_column(col, justify="right" if col in ("round", "at") else "left")
    if not state.history:
        table.add_row("—", "", "", "", "no allocation yet")
    for r in reversed(state.history):
        table.add_row(
            str(r.round),
            state.at(r.env_steps),
            "[" + ", ".join(_fmt(p if math.isfinite(p) else None, ".3f") for p in r.probabilities) + "]",
            "[" + ", ".join(str(c) for c in r.counts) + "]",
            r.reason,
        )
    return table


def render(state: MonitorState) -> RenderableType:
    """The whole `mam watch` screen for one state; cheap enough to redraw a few times a second."""
    return Group(_header(state), _actors_table(state), _workers_table(state), _history_table(state))


def _list(values: Any, spec: str) -> str:
    return "[" + " ".join("—" if v is None else format(v, spec) for v in values) + "]"


class PlainLines:
    """`mam watch` without a terminal: one plain line per update (config, allocation, evaluation,
    done; learner progress at most every `every_s` seconds), for logs and pipes."""

    def __init__(self, state: MonitorState, every_s: float = 5.0) -> None:
        self.state, self.every_s = state, every_s
        self.last_progress: float | None = None

    def after(self, kind: str) -> list[str]:
        """The lines to print after the state took a message of `kind` (config, allocation, eval,
        stats, done)."""
        s = self.state
        if kind == "config":
            clock = s.schedule
            if clock is None:
                budget = f"{s.steps:,} schedule steps" if s.steps else "unknown"
            elif clock.paper and clock.budget != clock.steps:
                budget = f"{clock.steps:,} iterations ({clock.budget:,} transitions)"
            else:
                budget = f"{clock.budget:,} transitions"
            return [f"run {s.run} · {s.algo} · {s.env_id}: budget {budget}"]
        if kind == "allocation" and s.last_allocation is not None:
            a = s.last_allocation
            at = s.at(_int(a.get("env_steps")))
            text = f"allocation round {_int(a.get('round'))} ({a.get('reason', '')}) at {at}:"
            if isinstance(a.get("returns"), list):
                text += " R=" + _list(_floats(a["returns"]), ".2f")
            text += " P=" + _list(_floats(a.get("probabilities")), ".2f") + " I=" + _list(_ints(a.get("counts")), "d")
            if s.survivor is not None:
                text += f" survivor {s.survivor}"
            return [text]
        if kind == "eval" and s.last_eval is not None:
            e = s.last_eval
            at = s.at(_int(e.get("env_steps")))
            return [f"evaluation at {at}: mean returns " + _list(_floats(e.get("mean")), ".2f")]
        if kind == "stats" and s.stats is not None:
            now = s.now()
            if self.last_progress is not None and now - self.last_progress < self.every_s and not s.done:
                return []
            self.last_progress = now
            text = "   ".join(s.progress(_int(s.stats.get("env_steps"))))
            text += f"   updates {_int(s.stats.get('updates')) or 0:,}"
            if s.steps_per_s is not None:
                text += f"   {s.steps_per_s:,.1f} transitions/s   {_fmt(s.updates_per_s, ',.1f')} updates/s"
            return [text]
        if kind == "done" and s.summary is not None:
            d = s.summary
            wall = _float(d.get("wall_time_s"))
            text = "done" + (f" in {wall:.0f} s" if wall is not None else "")
            if isinstance(d.get("final_returns"), list):
                text += ": final returns " + _list(_floats(d["final_returns"]), ".2f")
            if s.survivor is not None:
                text += f", survivor {s.survivor}"
            elif s.n_actors > 1:
                text += ", no elimination in this budget"
            return [text]
        return []
