"""The resolved configuration of a run (`RunConfig`: env, budget, the algorithm, service knobs),
what its budget leaves out (`budget_warnings`), and the checks of run names and env kwargs.

`mam run` and `mam-learner` build it from the command line (services/run/options.py); the
learner publishes it on `mam/<run>/config`, so workers, the referee and monitors need only
`--run` and `--connect`, and writes it to RUN_DIR/config.json.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from typing import Any

from mam_core import arithmetic as _arithmetic
from mam_core import schedule as _schedule
from mam_core.config import AlgoConfig
from services.messaging import keys
from services.run import binding as _binding

BIAS_HORIZONS = ("critic", "episode")

# Keys of config.json files written by earlier versions, read and ignored: the asynchronous
# collection and its knobs (the weights period and the rate limiter's band) are gone.
RETIRED_KEYS = frozenset({"collection", "sync_every", "band"})


@dataclass(frozen=True)
class RunConfig:
    """Everything a run needs beyond the algorithm: env, budget, service knobs."""

    run: str
    env_id: str
    steps: int
    algo: AlgoConfig
    checkpoint_every: int = 50_000  # updates between checkpoints (and on exit) ...
    checkpoint_rows: int = 20_000  # ... or transitions received (bounds what workers keep for a resend) ...
    checkpoint_seconds: float = 60.0  # ... or seconds, whichever comes first
    stall_timeout: float = 300.0  # no transition and no update for this long: stalled (0: no watchdog)
    send_batch: int = 32  # transitions per message from a worker
    slots_per_worker: int = 1  # `mam run`: slots each local worker process steps in one loop (services/roles/worker.py)
    save_replay: bool = True  # the replay buffer as append-only chunks beside the checkpoint
    learner_threads: int = 0  # the learner's threads (mam_core/gemm.py): portable: its GEMMs over this many
    # (0: every CPU it may use; the same bits for any count); native: torch threads (0: one)
    endpoint: str = ""  # where clients connect (written to config.json)
    bias_every: int = 0  # Eq. 17 estimation bias every N schedule steps, measured by the learner (0: off)
    bias_rollouts: int = 20  # Monte-Carlo rollouts per bias point (the paper: 20)
    bias_horizon: str = "critic"  # critic: MC return + bootstrap tail at a time limit; episode: cut there
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # gym.make(env_id, **env_kwargs) everywhere
    # portable: pinned kernels, the same run on any x86-64 CPU with AVX2; native: machine-bound
    # (mam_core/arithmetic.py). Default: what this process was started with (MAM_ARITHMETIC).
    arithmetic: str = field(default_factory=lambda: os.environ.get(_arithmetic.ARITHMETIC_ENV) or "portable")
    # worker id (or id prefix*) -> the slots it may claim, "*" or [slots]; {}: any worker any slot
    # (services/run/binding.py; the learner's intake refuses the rest, reason `unbound_slot`)
    slot_binding: dict[str, Any] = field(default_factory=dict)

    @property
    def resend_rows(self) -> int:
        """Most rows a worker keeps for a resend to a restarted learner: what it sent since the
        generation before the learner's newest checkpoint (acknowledgements are one generation
        late, so a fallback to it loses nothing) is at most 2 · `checkpoint_rows` plus one drain of
        the inbox and the time the acknowledgement takes to come back; one interval more and what a
        slot may have staged ahead (the lag) leave room."""
        return 3 * self.checkpoint_rows + 4 * max(4 * self.algo.workers * self.send_batch, 256) + \
            self.algo.workers * (self.algo.lag + 1)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["algo"] = self.algo.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "RunConfig":
        d = {k: v for k, v in d.items() if k not in RETIRED_KEYS}
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown run config keys: {sorted(unknown)}")
        d["algo"] = AlgoConfig.from_dict(d["algo"])
        d["env_kwargs"] = check_env_kwargs(d.get("env_kwargs") or {})
        d["slot_binding"] = _binding.parse(d.get("slot_binding"), d["algo"].workers)
        cfg = cls(**d)
        check_run_name(cfg.run)
        if cfg.steps < 1:
            raise ValueError("steps must be >= 1")
        if cfg.bias_every < 0 or cfg.bias_rollouts < 1:
            raise ValueError("bias_every must be >= 0 and bias_rollouts >= 1")
        if cfg.arithmetic not in _arithmetic.ARITHMETICS:
            raise ValueError(f"arithmetic must be one of {', '.join(_arithmetic.ARITHMETICS)}, not {cfg.arithmetic!r}")
        if cfg.bias_horizon not in BIAS_HORIZONS:
            raise ValueError(f"bias_horizon must be one of {', '.join(BIAS_HORIZONS)}")
        if cfg.checkpoint_every < 1 or cfg.checkpoint_rows < 1 or not cfg.checkpoint_seconds > 0:
            raise ValueError("checkpoint_every, checkpoint_rows and checkpoint_seconds must be positive")
        if cfg.slots_per_worker < 1:
            raise ValueError("slots_per_worker must be >= 1")
        return cfg


def budget_warnings(cfg: RunConfig) -> list[str]:
    """One line for each part of the run the budget leaves out (no update, no round, no
    elimination) and for M < K, in the schedule's units and with the flag to change; [] when
    the run shows everything. `mam run` and `mam-learner` print them at start."""
    algo, steps = cfg.algo, cfg.steps
    clock = _schedule.Schedule.for_run(algo, steps)
    unit = "iterations" if clock.paper else "transitions"
    lines = []
    if no_updates(cfg):
        lines.append(no_updates(cfg))
    c = clock.eliminate_at
    if c is not None:
        first = clock.first_round()
        if first >= min(steps, c):
            end = (f"the budget's end (--steps {steps:,})" if steps <= c
                   else f"the elimination at C = {c:,} (--eliminate-at)")
            why = f"--compete-every {algo.compete_every:,}" + (", --skip-random-rounds" if algo.skip_random_rounds
                                                               else "")
            lines.append(f"no allocation round: the first would be at {unit[:-1]} {first:,} ({why}), at or after "
                         f"{end}; lower --compete-every")
        if c > steps:
            lines.append(f"no elimination: C = {c:,} {unit} (--eliminate-at) is past the budget (--steps "
                         f"{steps:,}); lower --eliminate-at or raise --steps")
    if algo.actors > 1 and algo.workers < algo.actors:
        lines.append(actors_without_slots(algo))
    return lines


def no_updates(cfg: RunConfig) -> str:
    """What is wrong with a budget that ends within the random start phase (no update, a random
    policy's return at the end), with the flags to change; "" for a budget that trains."""
    algo, steps = cfg.algo, cfg.steps
    if algo.start_steps < steps:
        return ""
    unit = "iterations" if _schedule.Schedule.for_run(algo, steps).paper else "transitions"
    return (f"no update: the budget (--steps {steps:,} {unit}) ends within the random start phase "
            f"(--start-steps {algo.start_steps:,}); lower --start-steps or raise --steps")


def curve_points(cfg: RunConfig) -> str:
    """A note when the learning curve would have fewer than 3 points (the default --eval-every is
    the paper's, made for budgets of 10^5 and more), with the flag that gives more; else ""."""
    every = cfg.algo.eval_every
    points = cfg.steps // every if every > 0 else 0
    if points >= 3:
        return ""
    return (f"the learning curve gets {points} point{'s' if points != 1 else ''} (--eval-every {every:,} in "
            f"--steps {cfg.steps:,}); --eval-every {max(cfg.steps // 10, 1):,} gives 10")


def actors_without_slots(algo: AlgoConfig) -> str:
    """M < K is allowed, and explained: each round the M slots are drawn from P_k (Eq. 8), so some
    actors collect nothing in that round; they still learn from the others' transitions (the
    replay is shared, the updates off-policy) and are evaluated and ranked like the others."""
    m, k = algo.workers, algo.actors
    return (f"M = {m} worker slot{'s' if m > 1 else ''} for K = {k} actors: each round draws the {m} slot"
            f"{'s' if m > 1 else ''} from P_k, so at least {k - m} actor{'s' if k - m > 1 else ''} collect"
            f"{'s' if k - m == 1 else ''} nothing in a round (all still learn from the shared replay and are "
            f"evaluated); --workers {k} gives every actor a slot")


def learner_banner(cfg: RunConfig, listen: list[str] | None, connect: list[str] | None) -> str:
    """What `mam-learner` says at start: where it listens (or connects) and what it waits for."""
    run, m = cfg.run, cfg.algo.workers
    where = (f"listening on {', '.join(listen)}" if listen else "") + \
        (f"{' and ' if listen else ''}connecting to {', '.join(connect)}" if connect else "")
    endpoint = (connect or [])[:1] or [e.replace("0.0.0.0", "HOST") for e in (listen or [])[:1]] or ["ENDPOINT"]
    return (f"learner of run {run!r} {where or 'with the --zenoh-config endpoints'}; waiting for a referee "
            f"(mam-referee --run {run} --connect {endpoint[0]}) and M = {m} worker{'s' if m > 1 else ''} "
            f"(mam-worker --run {run} --connect {endpoint[0]} --id NAME --slot I, one for each slot I = 0..{m - 1})")


def check_run_name(name: str) -> str:
    """A run name is one key chunk (services/messaging/keys.py): letters, digits, '_', '.', '-'."""
    return keys.check_name(name, "run name")


def check_env_kwargs(value: Any) -> dict[str, Any]:
    """env kwargs: a JSON object (a dict with string keys and JSON values), or a JSON string of one."""
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except ValueError as e:
            raise ValueError(f"env kwargs {value!r} are not valid JSON: {e}") from None
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ValueError(f"env kwargs must be a JSON object with string keys, not {value!r}")
    try:
        return json.loads(json.dumps(value, allow_nan=False))  # plain JSON types only (they go on the wire)
    except (TypeError, ValueError) as e:
        raise ValueError(f"env kwargs must hold JSON values only: {e}") from None
