"""The command line's run options: one table for `mam run`, `mam-learner` and TOML files, their `--help`.

Precedence: paper defaults for `--algo` < TOML file (`--config`) < flags on the command line.
The learner publishes the resolved `RunConfig` on `mam/<run>/config`, so workers, the referee
and monitors need only `--run` and `--connect`.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import json
import os
import re
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from typer.core import TyperCommand

from mam_core.config import AFTER_ELIMINATION, ALGOS, SCHEDULES, AlgoConfig, defaults_for, resolve
from mam_core.family import builtin_families, family_for
from services.run import binding
from services.run.config import RETIRED_KEYS, RunConfig, check_env_kwargs, check_run_name

# -- the run options: one table -----------------------------------------------------------------
ALGO, RUN = "algo", "run"  # where a run option lands: an AlgoConfig field or a RunConfig field
# `--help` panels (typer's rich_help_panel): a RunOption's `panel`, else PANELS by name, else RUN_PANEL
ALGORITHM_PANEL, SCHEDULE_PANEL, RUN_PANEL = "Algorithm (the paper's symbols)", "Schedule", "Run"
SUPERVISION_PANEL, DISTRIBUTION_PANEL = "Checkpoints and supervision", "Distribution"
HELP_PANELS = (ALGORITHM_PANEL, SCHEDULE_PANEL, RUN_PANEL, SUPERVISION_PANEL, DISTRIBUTION_PANEL)


@dataclass(frozen=True)
class RunOption:
    """One run option: the same flag on `mam run` and `mam-learner` (and `mam experiment`), the
    same key in a TOML file. Per-algorithm defaults live in mam_core.config (`defaults_for`),
    the service defaults in `RunConfig`; a flag left out is None and takes them."""

    name: str  # the TOML key and `build_run_config` key (`-` in a TOML key reads as `_`)
    type: type  # str, int, float or bool
    help: str
    target: str = ALGO  # ALGO: an AlgoConfig field; RUN: a RunConfig field
    symbol: str = ""  # the paper's symbol, shown in brackets in the help
    multi_actor: bool = False  # only meaningful with K > 1 actors
    flags: tuple[str, ...] = ()  # the command-line declaration; default --name-with-dashes
    cli: bool = True  # False: TOML only (no flag)
    aliases: tuple[str, ...] = ()  # other accepted keys (TOML and build_run_config)
    panel: str = ""  # the `--help` panel; "" → PANELS[name], else RUN_PANEL

    @property
    def decls(self) -> tuple[str, ...]:
        return self.flags or ("--" + self.name.replace("_", "-"),)

    @property
    def help_panel(self) -> str:
        return self.panel or PANELS.get(self.name, RUN_PANEL)

    @property
    def help_text(self) -> str:
        """The help with the paper's symbol in front and the default (per --algo where they differ)
        behind; `\\[` keeps rich from reading `[default: …]` as markup."""
        text = f"[{self.symbol}] {self.help}" if self.symbol else self.help
        default = default_text(self)
        return f"{text}  \\[default: {default}]" if default else text

    @property
    def annotation(self) -> Any:
        """The typer parameter type: Optional[type] with the flag, its help and its panel (a bool
        shows no `<bool>` tag: the commands are `PlainFlags`)."""
        return Annotated[Optional[self.type], typer.Option(*self.decls, help=self.help_text,
                                                           rich_help_panel=self.help_panel)]


def _opt(name: str, type_: type, help: str, **kw: Any) -> RunOption:  # noqa: A002
    return RunOption(name, type_, help, **kw)


_SCHEDULE_HELP = (f"{' or '.join(SCHEDULES)}: paper = Algorithm 1, --steps, --start-steps, "
                  "--compete-every, --eliminate-at, --eval-every, --bias-every count iterations (M transitions "
                  "and one update each before C, one transition after); equal-data = they count transitions "
                  "and --utd gives updates per transition")

RUN_OPTIONS: tuple[RunOption, ...] = (
    _opt("env", str, "required (a flag or the --config file): Gymnasium env id, e.g. HalfCheetah-v5 or "
         "AppleCollect-v1, or module.path:EnvId (the module registers the env when imported; it must import on every "
         "host)", target=RUN, aliases=("env_id",)),
    _opt("env_kwargs", str, 'JSON object of keyword arguments for gym.make, e.g. \'{"ctrl_cost_weight": 0.05}\' '
         "(in TOML: a table)", target=RUN),
    _opt("algo", str, f"one of {', '.join(ALGOS)}, or module.path:Name, an algorithm family in your module "
         "(mam_core/family.py; it must import on every host); defaults: "
         + "; ".join(f.help for f in builtin_families())),
    _opt("steps", int, "required (a flag or the --config file): the budget in schedule steps, iterations "
         "(--schedule paper) or transitions (equal-data)",
         symbol="T", target=RUN),
    _opt("actors", int, "number of actors", symbol="K"),
    _opt("workers", int, "environment slots (worker processes)", symbol="M"),
    _opt("eliminate_at", int, "schedule step (iteration or transition) of the elimination", symbol="C",
         multi_actor=True),
    _opt("compete_every", int, "schedule steps between allocation rounds", symbol="A", multi_actor=True),
    _opt("eta", float, "weight of the other actors' Q-values (Eq. 9)", symbol="η", multi_actor=True),
    _opt("eval_episodes", int, "episodes per actor per evaluation"),
    _opt("eval_every", int, "schedule steps between learning-curve evaluations"),
    _opt("start_steps", int, "first schedule steps use uniform random actions (and no updates)"),
    _opt("batch_size", int, "mini-batch size"),
    _opt("utd", float, "gradient updates per schedule step (per iteration, or per transition)"),
    _opt("alpha", float, "SAC temperature, fixed at this value (sac, ma-sac); left out, each actor's α_k is tuned "
         "towards the target entropy −|A| from α = 1 (SAC v2)", symbol="α"),
    _opt("no_ot", bool, "ablation: uniform fixed allocation, no elimination", multi_actor=True),
    _opt("no_wt", bool, "ablation: no Q-value weighting (η = 0)", multi_actor=True),
    _opt("seed", int, "random seed"),
    _opt("device", str, "the learner's: auto, cpu, cuda or cuda:N (CUDA_VISIBLE_DEVICES picks the GPUs torch sees)"),
    _opt("hidden", str, "hidden layer sizes, e.g. 256,256"),
    _opt("precision", str, "learner GEMMs: fp32, or bf16 (mixed precision: every layer but the head computes in "
         "bfloat16; parameters, optimiser and the head stay float32)"),
    _opt("single_env_after_elimination", bool, "the survivor runs one slot only (implied by --schedule paper)",
         multi_actor=True),
    _opt("schedule", str, _SCHEDULE_HELP),
    _opt("shared_batch", bool, "one mini-batch for all actors (off: one per actor, as in Algorithm 1)",
         multi_actor=True),
    _opt("after_elimination", str, f"{', '.join(AFTER_ELIMINATION)}: the eliminated actors' "
         "critics after C stay frozen in Eq. 9, keep training, or leave Eq. 9 (η → 0)", multi_actor=True),
    _opt("skip_random_rounds", bool, "no allocation round during the random start phase (off: rounds from A on)",
         multi_actor=True),
    _opt("bias_every", int, "measure the Eq. 17 estimation bias every N schedule steps in the learner (0: off)",
         target=RUN),
    _opt("bias_rollouts", int, "Monte-Carlo rollouts per bias measurement (the paper: 20)", target=RUN),
    _opt("bias_horizon", str, "Eq. 17's Monte-Carlo Q*: critic (adds the bootstrap tail γ^T·Q(s_T, π(s_T)) "
         "at a time limit, the critic's own horizon) or episode (cut at the time limit)", target=RUN),
    _opt("lag", int, "iteration t acts with the actors after iteration t-1-B's updates and an allocation applies "
         "B iterations after it is drawn: workers step up to B iterations ahead of the learner (0: Algorithm 1 as "
         "printed). Every B is one deterministic run of its seed, equal to mam_core.reference with the same B",
         symbol="B"),
    _opt("arithmetic", str, "portable (default): kernels pinned and the learner's GEMMs in mam's own (built with the "
         "C compiler), so the run reruns from --seed on any x86-64 CPU with AVX2 (its learner at 0.94-0.96x native's "
         "updates/s with two threads on an Intel Xeon with AVX-512, where mam run --algo td3 took 1.08x native's "
         "wall time, and 1.49-1.53x with 0.89x on an AMD EPYC Zen 5: docs/PERFORMANCE.md); "
         "native: the fastest kernels of this CPU, the run reruns only here (sets MAM_ARITHMETIC for the children; "
         "for roles started by hand export MAM_ARITHMETIC=native)", target=RUN),
    _opt("run", str, "run name: the key-expression namespace mam/<run>/...", target=RUN),
    _opt("save_replay", bool, "persist the replay buffer beside the checkpoint as append-only chunks",
         target=RUN, flags=("--save-replay/--no-save-replay",)),
    _opt("checkpoint_every", int, "checkpoint every N updates ...", target=RUN),
    _opt("checkpoint_rows", int, "... or N transitions ...", target=RUN),
    _opt("checkpoint_seconds", float, "... or N seconds, whichever comes first", target=RUN),
    _opt("stall_timeout", float, "seconds without a new transition or update before the run counts as stalled: "
         "`mam run` logs what each side waits for and restarts the stuck child (0: no watchdog)", target=RUN),
    _opt("slot_binding", str, "which slots each worker id may claim, e.g. b0=0,b1=1,spare-a=* or b-*=0-3 (an id "
         "prefix ending in *; slots: I, I-J, several comma-separated, or * for any): the learner refuses a batch "
         "claiming another slot, and a worker with no entry may claim none (in TOML also a table; default: any "
         "worker any slot; docs/DEPLOY.md, section 6)", target=RUN, panel=DISTRIBUTION_PANEL),
    # TOML only: knobs of the algorithm and the services that no command line needs
    _opt("send_batch", int, "transitions per message from a worker", target=RUN, cli=False),
    _opt("slots_per_worker", int, "slots each local worker process steps, in one loop (`mam run`; default 1: a process "
         "a slot): fewer processes waking for each weights version, cheaper where slots outnumber cores "
         "(docs/PERFORMANCE.md); the same run, bit for bit", target=RUN, panel=DISTRIBUTION_PANEL),
    _opt("learner_threads", int, "the learner's threads: portable arithmetic spreads its GEMMs over them (0: every "
         "CPU it may use; the bits do not depend on it), native gives them to torch (0: one)",
         target=RUN, cli=False),
    _opt("critics_per_actor", int, "critics per actor", symbol="n", cli=False),
    _opt("lr", float, "actor, critic (and SAC's α) learning rate (Adam)", cli=False),
    _opt("tau", float, "soft target update rate (Eq. 4)", symbol="τ", cli=False),
    _opt("gamma", float, "discount", symbol="γ", cli=False),
    _opt("explore_noise", float, "σ of the Gaussian exploration noise, times max_action", cli=False),
    _opt("policy_noise", float, "σ̃ of the target policy smoothing, times max_action", cli=False),
    _opt("noise_clip", float, "clip of the smoothing noise, times max_action", symbol="c", cli=False),
    _opt("target_smoothing", bool, "TD3's target policy smoothing", cli=False),
    _opt("policy_delay", int, "actor and target updates every d critic updates", symbol="d", cli=False),
    _opt("buffer_size", int, "replay buffer capacity", cli=False),
)
OPTION = {o.name: o for o in RUN_OPTIONS}
# `mam run --help`'s closing lines: the keys only a --config file takes (README, "Run options a file only takes").
FILE_ONLY_EPILOG = ("Keys only a --config TOML file takes (no flag): "
                    + ", ".join(o.name for o in RUN_OPTIONS if not o.cli)
                    + ". Defaults and meaning: README, \"Run options a file only takes\".")
_KEYS = {alias: o.name for o in RUN_OPTIONS for alias in (o.name, *o.aliases)}

# The `--help` panel of each run option without a `panel` of its own (an option in neither: RUN_PANEL).
PANELS = {
    **dict.fromkeys(("algo", "actors", "workers", "eliminate_at", "compete_every", "eta", "alpha", "batch_size", "utd",
                     "no_ot", "no_wt", "hidden", "single_env_after_elimination", "shared_batch",
                     "after_elimination"), ALGORITHM_PANEL),
    **dict.fromkeys(("steps", "schedule", "start_steps", "eval_episodes", "eval_every", "skip_random_rounds",
                     "bias_every", "bias_rollouts", "bias_horizon"), SCHEDULE_PANEL),
    **dict.fromkeys(("save_replay", "checkpoint_every", "checkpoint_rows", "checkpoint_seconds", "stall_timeout",
                     "max_restarts", "restart_window"), SUPERVISION_PANEL),
    **dict.fromkeys(("lag", "arithmetic", "send_batch"), DISTRIBUTION_PANEL),
}


def _shown(value: Any) -> str:
    if value is None:  # AlgoConfig's one optional field, alpha: None is "tuned"
        return "tuned"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def default_text(option: RunOption) -> str:
    """What a run option is when left out: "3" or, where the algorithms differ, "ma-td3, td3: 300000;
    ma-ddpg, ddpg: 24000" (mam_core.config `defaults_for`); "" where there is none to show."""
    if option.target == ALGO:
        if option.name == "algo":
            return AlgoConfig().algo
        groups: dict[str, list[str]] = {}
        for algo in ALGOS:
            groups.setdefault(_shown(getattr(defaults_for(algo), option.name)), []).append(algo)
        if len(groups) == 1:
            return next(iter(groups))
        return "; ".join(f"{', '.join(algos)}: {value}" for value, algos in groups.items())
    run_config = globals().get("RunConfig")  # None while this module is still being imported
    if run_config is None:
        return ""
    if option.name == "run":
        return "ALGO-ENV-DATE-TIME-PID"
    if option.name == "arithmetic":  # a default_factory: what MAM_ARITHMETIC says, else portable
        return "portable (or $MAM_ARITHMETIC)"
    fields = {f.name: f for f in dataclasses.fields(run_config)}
    f = fields.get(option.name)
    if f is None or f.default is dataclasses.MISSING:
        return ""
    return _shown(f.default)


def cli_options(exclude: tuple[str, ...] | frozenset[str] = ()) -> tuple[RunOption, ...]:
    """The run options that are command-line flags, less `exclude`."""
    return tuple(o for o in RUN_OPTIONS if o.cli and o.name not in exclude)


def run_options(exclude: tuple[str, ...] = ()) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator for a typer command: adds one keyword parameter per run option (less
    `exclude`) and calls the command with them gathered in `run_opts` (name -> value or None).

        @app.command()
        @options.run_options()
        def run(run_opts: dict[str, Any], config: options.ConfigFile = None) -> None: ...
    """

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        table = cli_options(frozenset(exclude))
        own = [p for p in inspect.signature(fn, eval_str=True).parameters.values() if p.name != "run_opts"]
        clash = {p.name for p in own} & {o.name for o in table}
        if clash:
            raise TypeError(f"{fn.__name__}: parameters {sorted(clash)} clash with run options")
        params = [inspect.Parameter(o.name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=o.annotation)
                  for o in table]
        own = [p.replace(kind=inspect.Parameter.KEYWORD_ONLY) for p in own]

        @functools.wraps(fn)
        def command(**kwargs: Any) -> Any:
            run_opts = {o.name: kwargs.pop(o.name) for o in table}
            return fn(run_opts=run_opts, **kwargs)

        command.__signature__ = inspect.Signature(params + own)  # type: ignore[attr-defined]
        command.__annotations__ = {p.name: p.annotation for p in params + own}
        del command.__wrapped__  # typer reads the signature above, not fn's
        return command

    return wrap


# -- Annotated types of single flags (other commands and `mam experiment` use them) ---------------
Env, EnvKwargs, Algo, Steps = (OPTION[n].annotation for n in ("env", "env_kwargs", "algo", "steps"))
Actors, Workers, EliminateAt, CompeteEvery, Eta = (
    OPTION[n].annotation for n in ("actors", "workers", "eliminate_at", "compete_every", "eta"))
EvalEpisodes, EvalEvery, StartSteps, BatchSize, Utd = (
    OPTION[n].annotation for n in ("eval_episodes", "eval_every", "start_steps", "batch_size", "utd"))
NoOt, NoWt, Seed, Device, Hidden, Precision = (
    OPTION[n].annotation for n in ("no_ot", "no_wt", "seed", "device", "hidden", "precision"))
BiasEvery, BiasRollouts, BiasHorizon = (OPTION[n].annotation for n in ("bias_every", "bias_rollouts", "bias_horizon"))
SingleEnv, Schedule, SharedBatch, AfterElimination, SkipRandomRounds = (
    OPTION[n].annotation for n in ("single_env_after_elimination", "schedule", "shared_batch", "after_elimination",
                                   "skip_random_rounds"))
ConfigFile = Annotated[Optional[Path], typer.Option("--config", help="TOML file holding any of the run options "
                                                   "(flags win over it)", rich_help_panel=RUN_PANEL)]


class PlainFlags(TyperCommand):
    """typer's command with plain flags: no `<bool>` tag beside `--help` or any on/off flag
    (every mam command uses it)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for param in self.params:
            if getattr(param, "is_flag", False) and getattr(param, "is_bool_flag", True):
                param.metavar = ""

    def get_help_option(self, ctx: Any) -> Any:
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option


# -- network flags ----------------------------------------------------------------------------
# The processes that join a run (worker, referee, monitor) name it: no generated default, which could
# never match a run. `mam run` and `mam-learner` take OPTION["run"], whose default is a new name.
Run = Annotated[Optional[str], typer.Option(
    "--run", metavar="NAME", help="the run to join: the learner's --run (`mam run` prints it at start)",
    rich_help_panel=RUN_PANEL)]
Connect = Annotated[Optional[list[str]], typer.Option(
    "--connect", metavar="ENDPOINT", help="Zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable)",
    rich_help_panel=DISTRIBUTION_PANEL)]
Listen = Annotated[Optional[list[str]], typer.Option(
    "--listen", metavar="ENDPOINT", help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    rich_help_panel=DISTRIBUTION_PANEL)]
ZenohConfig = Annotated[Optional[Path], typer.Option("--zenoh-config", help="Zenoh JSON5 config file",
                                                    rich_help_panel=DISTRIBUTION_PANEL)]
RunDir = Annotated[Optional[Path], typer.Option("--run-dir", help="directory for this process's logs and outputs "
                                                "(default runs/RUN)", rich_help_panel=RUN_PANEL)]

# -- `mam-worker --spare` (services/roles/spare.py) ---------------------------------------------
Spare = Annotated[bool, typer.Option("--spare", help="hold no slot: wait, and take over a slot whose worker is gone "
                                     "(not with --slot; docs/DEPLOY.md)")]
TakeOver = Annotated[Optional[float], typer.Option(
    "--take-over-after", metavar="SECONDS", help="with --spare: take a slot over once the learner has awaited its rows "
    "with no live worker on it for this long (default: the run's --stall-timeout, from the learner; at least 2)")]


def default_run_name(env_id: str, algo: str) -> str:
    env = re.sub(r"[^A-Za-z0-9]+", "", env_id.split(":")[-1].split("-")[0]).lower()
    algo = re.sub(r"[^A-Za-z0-9-]+", "", algo.split(":")[-1]).lower()  # a user's family: module:Name -> name
    return f"{algo}-{env}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid() % 10000}"


def _canonical(key: str, where: str) -> str:
    """The table name of an option key (`-` read as `_`, aliases resolved); unknown: BadParameter."""
    name = _KEYS.get(key.replace("-", "_"))
    if name is None and key.replace("-", "_") in RETIRED_KEYS:
        raise typer.BadParameter(f"{where}: {key!r} was removed with the asynchronous collection: every run is "
                                 "lock-step Algorithm 1; `--lag B` lets workers run B iterations ahead")
    if name is None:
        dashed = {k.replace("_", "-"): k for k in _KEYS}
        close = difflib.get_close_matches(key.replace("_", "-"), list(dashed), n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise typer.BadParameter(f"{where}: unknown option {key!r}{hint} (`mam run --help` lists the run options; "
                                 "a TOML key is the flag without its dashes)")
    return name


def load_toml(path: Path | None) -> dict[str, Any]:
    """A TOML file's run options by table name (`eliminate-at` == `eliminate_at`). Sections
    (e.g. [obsolescence]) only group options; `env_kwargs` is a table of gym.make arguments,
    `slot_binding` one of worker ids and their slots."""
    if path is None:
        return {}
    if not path.is_file():
        raise typer.BadParameter(f"config file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise typer.BadParameter(f"{path}: {e}") from e
    flat: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict) and key.replace("-", "_") not in ("env_kwargs", "slot_binding"):
            flat.update({_canonical(k, str(path)): v for k, v in value.items()})
        else:
            flat[_canonical(key, str(path))] = value
    return flat


def build_run_config(cli: dict[str, Any], config_file: Path | None) -> RunConfig:
    """Merge TOML and command-line values (command line wins) into a validated RunConfig.
    `cli` maps run option names (or aliases) to values; None means not given."""
    merged = load_toml(config_file)
    merged.update({_canonical(k, "command line"): v for k, v in cli.items() if v is not None})
    env_id = merged.pop("env", None)
    if not env_id:
        raise typer.BadParameter("--env is required (in a flag or the --config file)")
    try:
        env_kwargs = check_env_kwargs(merged.pop("env_kwargs", None) or {})
    except ValueError as e:
        raise typer.BadParameter(f"--env-kwargs: {e}") from None
    check_env_id(env_id, env_kwargs)
    algo_name = merged.pop("algo", None) or "ma-td3"
    try:
        family_for(algo_name)
    except ValueError as e:
        raise typer.BadParameter(f"--algo: {e}") from None
    steps = merged.pop("steps", None)
    if steps is None or int(steps) < 1:
        paper = (merged.get("schedule") or AlgoConfig().schedule) == "paper"
        unit = "iterations (under --schedule paper)" if paper else "transitions (under --schedule equal-data)"
        got = "" if steps is None else f", not {steps}"
        raise typer.BadParameter(f"--steps [T] must be a positive number of {unit}{got}")
    run_fields = {k: merged.pop(k) for k in list(merged) if OPTION[k].target == RUN}
    if env_kwargs:
        run_fields["env_kwargs"] = env_kwargs
    if isinstance(merged.get("hidden"), str):
        merged["hidden"] = tuple(int(h) for h in merged["hidden"].split(",") if h.strip())
    try:
        algo = resolve(algo_name, **merged)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    run = run_fields.pop("run", None) or default_run_name(env_id, algo_name)
    try:
        check_run_name(run)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    try:
        return RunConfig.from_dict({"run": run, "env_id": env_id, "steps": int(steps), "algo": algo.to_dict(),
                                    **run_fields})
    except (TypeError, ValueError) as e:
        raise typer.BadParameter(str(e)) from e


def resume_config(run_dir: Path, cli: dict[str, Any], config_file: Path | None,
                  code: dict[str, Any], allow_other_code: bool = False) -> tuple[RunConfig, list[str]]:
    """The config of the stopped run in `run_dir` (its config.json), for `mam run --resume`, and
    how `code` (this code: mam_lab.provenance.run_code) differs from the run's
    (services/run/codecheck.py): typer.BadParameter naming
    the file when there is nothing to continue (no run, a finished run, no verified checkpoint),
    when a given option contradicts the run's, or when the run ran other code or libraries
    (naming both) unless `allow_other_code`."""
    from services.run import codecheck, rundir

    path = run_dir / rundir.CONFIG
    if not path.is_file():
        raise typer.BadParameter(f"--resume {run_dir}: no {path.name} there; not a run directory `mam run` wrote")
    if (run_dir / rundir.SUMMARY).is_file():
        raise typer.BadParameter(f"--resume {run_dir}: the run finished ({run_dir / rundir.SUMMARY}); "
                                 "nothing to continue")
    if not rundir.has_checkpoint(run_dir):
        raise typer.BadParameter(f"--resume {run_dir}: no verified checkpoint in {run_dir / rundir.CHECKPOINTS} "
                                 "(the run stopped before its first one, or they are damaged); start it again "
                                 "without --resume")
    try:
        cfg = RunConfig.from_dict(json.loads(path.read_text()))
    except (ValueError, TypeError, KeyError) as e:
        raise typer.BadParameter(f"--resume {run_dir}: {path} is not a run config: {e}") from None
    given = load_toml(config_file)
    given.update({_canonical(k, "command line"): v for k, v in cli.items() if v is not None})
    have = {**cfg.to_dict(), **cfg.algo.to_dict(), "env": cfg.env_id}
    for name, value in given.items():
        if name == "slot_binding":
            try:
                value = binding.parse(value, cfg.algo.workers)
            except ValueError as e:
                raise typer.BadParameter(f"--slot-binding: {e}") from None
        if isinstance(value, str) and isinstance(have.get(name), (list, tuple)):
            value = [int(h) for h in value.split(",") if h.strip()]
        if name not in have or _same(have[name], value):
            continue
        flag = "--" + name.replace("_", "-")
        raise typer.BadParameter(f"--resume {run_dir}: {flag} {value} contradicts the run's {have[name]} ({path}); "
                                 "a resumed run keeps the options it started with")
    other = codecheck.differences(run_dir, code) + codecheck.missing_fields(json.loads(path.read_text()))
    if other and not allow_other_code:
        raise typer.BadParameter(f"--resume {run_dir}: the run ran other code ({run_dir / rundir.CODE}, {path.name}): "
                                 f"{'; '.join(other)}. A resumed run equals the uninterrupted one only on the same "
                                 "code and libraries; --allow-other-code continues it anyway, and the run records "
                                 "exact: false")
    return cfg, other


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) or isinstance(b, (list, tuple)):
        return list(a) == list(b)
    return a == b or (isinstance(a, (int, float)) and isinstance(b, (int, float)) and float(a) == float(b))


def check_env_id(env_id: str, env_kwargs: dict[str, Any] | None = None) -> None:
    """A clear error before any process starts: an unknown id, a module that does not import,
    kwargs the env does not take, an action space mam cannot train on (not a Box, unbounded,
    asymmetric) or observations that are not a 1-D Box. Makes the env once to find out."""
    from mam_core.envs import EnvError
    from mam_core.policy import EnvSpec

    try:
        EnvSpec.from_env_id(env_id, env_kwargs)
    except EnvError as e:
        raise typer.BadParameter(f"--env: {e}") from None


