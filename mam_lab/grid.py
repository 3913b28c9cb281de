"""The grid of `mam experiment`: which runs, with which flags (pure: touches no files, except
`load_grid_file` reading the grid file).

Variants: each algorithm of `--algos` under its own name, and for every multi-actor algorithm
(ma-td3, ma-ddpg) one variant per ablation (`<algo>-no-ot`, `<algo>-no-wt`) and per η of
`--etas` (`<algo>-eta0.05`); then the grid file's named variants, `[variant.NAME]` tables, each
with an `algo` and any run flags. A variant whose resolved configuration equals an earlier one (say
`ma-td3-eta0.1`, which is `ma-td3`) is not run twice. `--variants a,b` runs only those.

Seeds: `seeds` for every env, and a `[env-seeds]` table may give an env its own (`"Hopper-v5" = 10`,
a count, a list or ranges as `seeds`); `--seeds` on the command line applies to every env. Order:
seed by seed across envs (a grid stopped early is balanced), or `order = "env"`: all runs of the
first env of `envs` (seed by seed), then the next.

The budget (`--steps`) is the same T for every run of the grid, in schedule steps: iterations
under `--schedule paper` (so a multi-actor run collects more transitions for the same updates),
transitions under `equal-data`. Flags: paper defaults per algorithm < the grid file's `[common]`
< its `[algo.NAME]` < flags on the command line < the variant's ablation / η / `[variant.NAME]`
flags. The multi-actor flags (`--actors`, `--workers`, `--eliminate-at`, `--compete-every`, `--eta`,
`--single-env-after-elimination`) given on the command line or in `[common]` apply to the
multi-actor algorithms only: TD3 and DDPG keep K=1, M=1 unless their own `[algo.td3]` (or a
`[variant.NAME]` of theirs) says otherwise.
"""

from __future__ import annotations

import functools
import json
import re
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import typer

from mam_core.config import ALGOS, resolve
from mam_core.schedule import Schedule
from services.run import options
from services.run.config import RunConfig
from services.run.rundir import env_dirname

ABLATIONS = {"no-ot": "no_ot", "no-wt": "no_wt"}
# Run options a grid sets for itself (its dimensions), not as flags of a run.
GRID_DIMENSIONS = frozenset({"env", "env_kwargs", "algo", "steps", "seed", "run"})
# Flags of the multi-actor algorithms only: TD3 and DDPG keep K=1, M=1 unless their own sections say otherwise.
MULTI_ACTOR_FLAGS = frozenset({o.name for o in options.RUN_OPTIONS if o.multi_actor} | {"actors", "workers"})
FLAG_NAMES = frozenset(o.name for o in options.RUN_OPTIONS) - GRID_DIMENSIONS  # the option table, less the dimensions
GRID_KEYS = {"name", "exp_dir", "ledger", "envs", "algos", "seeds", "steps", "ablations", "etas", "common", "algo",
             "variant", "env_seeds", "order"}
ORDERS = ("seed", "env")
_VARIANT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")


class GridError(ValueError):
    """The grid (flags or TOML file) is not valid."""


def is_multi_actor(algo: str) -> bool:
    return algo.startswith("ma-")


# --- the grid --------------------------------------------------------------------------------


@dataclass
class Grid:
    """What to run: envs × variants × seeds, each with `steps` env transitions."""

    envs: tuple[str, ...]
    algos: tuple[str, ...]
    seeds: tuple[int, ...]
    steps: int
    ablations: tuple[str, ...] = ()
    etas: tuple[float, ...] = ()
    common: dict[str, Any] = field(default_factory=dict)  # every algorithm (multi-actor flags: MA only)
    per_algo: dict[str, dict[str, Any]] = field(default_factory=dict)  # one algorithm, any flag
    overrides: dict[str, Any] = field(default_factory=dict)  # command-line flags, like `common`, applied last
    name: str = "experiment"
    named: dict[str, tuple[str, dict[str, Any]]] = field(default_factory=dict)  # [variant.NAME]: (algo, flags)
    only: tuple[str, ...] = ()  # --variants: run these variants only (empty: all)
    env_seeds: dict[str, tuple[int, ...]] = field(default_factory=dict)  # [env-seeds]: an env's own seeds
    order: str = "seed"  # "seed": seed by seed across envs; "env": env by env (in `envs` order)

    def seeds_of(self, env: str) -> tuple[int, ...]:
        """The seeds of one env: its [env-seeds] entry, else `seeds`."""
        return self.env_seeds.get(env, self.seeds)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "envs": list(self.envs), "algos": list(self.algos), "seeds": list(self.seeds),
                "steps": self.steps, "ablations": list(self.ablations), "etas": list(self.etas),
                "common": _jsonable(self.common), "per_algo": _jsonable(self.per_algo),
                "overrides": _jsonable(self.overrides),
                "variants": {n: {"algo": a, **_jsonable(f)} for n, (a, f) in self.named.items()},
                "only": list(self.only), "env_seeds": {e: list(v) for e, v in self.env_seeds.items()},
                "order": self.order}


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


@dataclass(frozen=True)
class RunSpec:
    """One run of the grid. `flags` are the option values on top of the algorithm's defaults."""

    env: str
    variant: str
    algo: str
    seed: int
    steps: int
    flags: tuple[tuple[str, Any], ...] = ()

    @property
    def path(self) -> Path:
        """Run directory relative to the experiment directory."""
        return Path(env_dirname(self.env)) / self.variant / f"seed{self.seed}"

    @property
    def label(self) -> str:
        return f"{self.env}/{self.variant}/seed{self.seed}"

    def options(self) -> dict[str, Any]:
        """Values for `options.build_run_config` (what `mam run` would get as flags)."""
        out: dict[str, Any] = {k: list(v) if isinstance(v, tuple) else v for k, v in self.flags}
        out.update(env=self.env, algo=self.algo, steps=self.steps, seed=self.seed)
        return out

    def run_config(self, run_name: str) -> RunConfig:
        return options.build_run_config({**self.options(), "run": run_name}, None)

    @property
    def transitions(self) -> int:
        """The run's budget in transitions, what its learner counts: T itself under equal-data,
        more under the paper schedule (M per iteration before C)."""
        return run_schedule(self.algo, self.steps, self.flags).budget

    @property
    def paper(self) -> bool:
        """T counts iterations (the paper schedule), not transitions (equal-data)."""
        return run_schedule(self.algo, self.steps, self.flags).paper

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "env": self.env, "variant": self.variant, "algo": self.algo,
                "seed": self.seed, "steps": self.steps, "flags": _jsonable(dict(self.flags))}


@functools.lru_cache(maxsize=1024)
def run_schedule(algo: str, steps: int, flags: tuple[tuple[str, Any], ...]) -> Schedule:
    """The schedule of a run of `algo` with `flags` and budget T = `steps` (its unit, its budget in
    transitions); no env is made."""
    algo_flags = {k: v for k, v in flags if options.OPTION[k].target != options.RUN}
    if isinstance(algo_flags.get("hidden"), str):
        algo_flags["hidden"] = tuple(int(h) for h in algo_flags["hidden"].split(",") if h.strip())
    return Schedule.for_run(resolve(algo, **algo_flags), steps)


def _norm_key(key: str) -> str:
    return key.strip().replace("-", "_")


def normalize_flags(flags: Mapping[str, Any], where: str) -> dict[str, Any]:
    """Flag names with `_` (TOML may use `-`), None dropped, lists as tuples; unknown names rejected."""
    out: dict[str, Any] = {}
    for key, value in flags.items():
        k = _norm_key(key)
        if value is None:
            continue
        if k not in FLAG_NAMES:
            hint = " (set it in the grid: envs/algos/seeds/steps)" if k in ("env", "env_id", "algo", "seed",
                                                                              "steps", "run") else ""
            raise GridError(f"{where}: unknown option {key!r}{hint}")
        if k == "hidden" and isinstance(value, str):
            value = tuple(int(h) for h in value.split(",") if h.strip())
        out[k] = tuple(value) if isinstance(value, list) else value
    return out


def parse_seeds(value: Any) -> tuple[int, ...]:
    """`10` or "10": seeds 0..9; "0,3,7" or [0, 3, 7]: those; "5-9": 5..9 inclusive; "0-3,7"."""
    if isinstance(value, bool):
        raise GridError(f"seeds: {value!r} is not a count or a list")
    if isinstance(value, int):
        if value < 1:
            raise GridError("seeds: the count must be >= 1")
        return tuple(range(value))
    if isinstance(value, (list, tuple)):
        seeds = tuple(int(s) for s in value)
    elif isinstance(value, str):
        text = value.strip()
        if re.fullmatch(r"\d+", text):
            return parse_seeds(int(text))
        items: list[int] = []
        for part in (p.strip() for p in text.split(",")):
            m = re.fullmatch(r"(\d+)\s*-\s*(\d+)", part)
            if m and int(m.group(2)) >= int(m.group(1)):
                items += range(int(m.group(1)), int(m.group(2)) + 1)
            elif re.fullmatch(r"\d+", part):
                items.append(int(part))
            else:
                raise GridError(f"seeds: {value!r} is not a count N, or a list of seeds and ranges A-B")
        seeds = tuple(items)
    else:
        raise GridError(f"seeds: {value!r} is not a count, a range or a list")
    if not seeds or any(s < 0 for s in seeds) or len(set(seeds)) != len(seeds):
        raise GridError(f"seeds: need distinct non-negative seeds, got {value!r}")
    return seeds


def _list(value: Any, what: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        items = [v.strip() for v in value.split(",")]
    elif isinstance(value, (list, tuple)):
        items = [str(v).strip() for v in value]
    else:
        raise GridError(f"{what}: expected a list or a comma-separated string, got {value!r}")
    return tuple(v for v in items if v)


def parse_etas(value: Any) -> tuple[float, ...]:
    if value is None:
        return ()
    items = value if isinstance(value, (list, tuple)) else _list(value, "etas")
    try:
        etas = tuple(float(v) for v in items)
    except ValueError as e:
        raise GridError(f"etas: {value!r} is not a list of numbers") from e
    if any(not 0.0 <= e < 1.0 for e in etas):
        raise GridError("etas: every η must be in [0, 1)")
    return etas


def load_grid_file(path: Path) -> dict[str, Any]:
    """A grid TOML file as a dict of grid keys (see deploy/experiments/*.toml)."""
    if not path.is_file():
        raise GridError(f"grid file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise GridError(f"{path}: {e}") from e
    data = {_norm_key(k): v for k, v in data.items()}
    unknown = set(data) - GRID_KEYS
    if unknown:
        dims = {"seed": "seeds", "env": "envs", "eta": "etas", "ablation": "ablations"}  # in the singular
        said = "; ".join(f"{k!r}: the grid dimension is {dims[k]!r} (a list)" for k in sorted(unknown) if k in dims)
        raise GridError(f"{path}: unknown key(s) {sorted(unknown)}; " + (said + "; " if said else "")
                        + "run options go in [common] or [algo.NAME] (deploy/experiments/README.md)")
    data.setdefault("name", path.stem)
    return data


def make_grid(file: Mapping[str, Any] | None = None, **cli: Any) -> Grid:
    """A validated Grid from a grid file's content and command-line values (the command line wins).

    `cli` takes envs, algos, seeds, steps, ablations, etas, name and `flags` (algorithm options
    that apply like `[common]`, after the file's sections).
    """
    file = dict(file or {})
    get = lambda key: cli.get(key) if cli.get(key) is not None else file.get(key)  # noqa: E731
    envs = _list(get("envs"), "envs")
    algos = _list(get("algos"), "algos")
    named = parse_named_variants(file.get("variant"))
    if not envs:
        raise GridError("no envs: give --envs (comma-separated) or `envs` in the grid file")
    if not algos and not named:
        raise GridError("no algos: give --algos (comma-separated), `algos` or [variant.NAME] tables in the grid file")
    bad = [a for a in algos if a not in ALGOS]
    if bad:
        raise GridError(f"unknown algo(s) {bad}; choose from {', '.join(ALGOS)}")
    if len(set(algos)) != len(algos) or len(set(envs)) != len(envs):
        raise GridError("envs and algos must not repeat")
    seeds = parse_seeds(get("seeds") if get("seeds") is not None else 1)
    env_seeds: dict[str, tuple[int, ...]] = {}
    if cli.get("seeds") is None:  # --seeds on the command line applies to every env
        table = file.get("env_seeds") or {}
        if not isinstance(table, Mapping):
            raise GridError("[env-seeds] must be a table: env id = seeds (a count, a list or ranges)")
        for env, value in table.items():
            if env not in envs:
                raise GridError(f"[env-seeds]: {env!r} is not one of the grid's envs {list(envs)}")
            env_seeds[str(env)] = parse_seeds(value)
    order = str(get("order") or "seed")
    if order not in ORDERS:
        raise GridError(f"order: {order!r}; choose from {', '.join(ORDERS)}")
    steps = get("steps")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise GridError(f"steps: need a positive T (iterations under the paper schedule, transitions under "
                        f"equal-data), got {steps!r}")
    ablations = _list(get("ablations"), "ablations")
    bad = [a for a in ablations if a not in ABLATIONS]
    if bad:
        raise GridError(f"unknown ablation(s) {bad}; choose from {', '.join(ABLATIONS)}")
    etas = parse_etas(get("etas"))
    common = normalize_flags(file.get("common") or {}, "[common]")
    per_algo_raw = file.get("algo") or {}
    if not isinstance(per_algo_raw, Mapping):
        raise GridError("[algo.NAME] sections must be tables")
    per_algo = {}
    for name, flags in per_algo_raw.items():
        if name not in ALGOS:
            raise GridError(f"[algo.{name}]: unknown algo; choose from {', '.join(ALGOS)}")
        if not isinstance(flags, Mapping):
            raise GridError(f"[algo.{name}] must be a table of options")
        per_algo[name] = normalize_flags(flags, f"[algo.{name}]")
    overrides = normalize_flags(cli.get("flags") or {}, "command line")
    name = str(cli.get("name") or file.get("name") or "experiment")
    clash = set(named) & {n for n, _, _ in variant_flags(Grid(envs, algos, seeds, int(steps), ablations, etas))}
    if clash:
        raise GridError(f"[variant.NAME]: {sorted(clash)} already name(s) a variant of algos/ablations/etas")
    grid = Grid(envs=envs, algos=algos, seeds=seeds, steps=int(steps), ablations=ablations, etas=etas,
                common=common, per_algo=per_algo, overrides=overrides, name=name, named=named,
                only=_list(cli.get("variants"), "variants"), env_seeds=env_seeds, order=order)
    if grid.only:
        known = [n for n, _, _ in variant_flags(grid)]
        bad = [v for v in grid.only if v not in known]
        if bad:
            raise GridError(f"--variants: unknown variant(s) {bad}; the grid has {', '.join(known)}")
    return grid


def parse_named_variants(tables: Any) -> dict[str, tuple[str, dict[str, Any]]]:
    """`[variant.NAME]` tables: each needs `algo` and may set any run flag. {name: (algo, flags)}."""
    if tables is None:
        return {}
    if not isinstance(tables, Mapping):
        raise GridError("[variant.NAME] sections must be tables")
    out: dict[str, tuple[str, dict[str, Any]]] = {}
    for name, table in tables.items():
        if not _VARIANT_NAME.fullmatch(str(name)):
            raise GridError(f"[variant.{name}]: a variant name is letters, digits, '_', '.', '+', '-' (at most 64)")
        if not isinstance(table, Mapping):
            raise GridError(f"[variant.{name}] must be a table of options")
        table = {_norm_key(k): v for k, v in table.items()}
        algo = table.pop("algo", None)
        if algo not in ALGOS:
            raise GridError(f"[variant.{name}]: `algo` must be one of {', '.join(ALGOS)}, got {algo!r}")
        out[str(name)] = (str(algo), normalize_flags(table, f"[variant.{name}]"))
    return out


def _shared(flags: Mapping[str, Any], algo: str) -> dict[str, Any]:
    """Flags for everyone: the multi-actor ones only reach the multi-actor algorithms."""
    return {k: v for k, v in flags.items() if is_multi_actor(algo) or k not in MULTI_ACTOR_FLAGS}


def variant_flags(grid: Grid) -> list[tuple[str, str, dict[str, Any]]]:
    """(variant name, algo, flags) of every variant, in order, before removing duplicates."""
    out = []
    for algo in grid.algos:
        base = {**_shared(grid.common, algo), **grid.per_algo.get(algo, {}), **_shared(grid.overrides, algo)}
        out.append((algo, algo, base))
        if not is_multi_actor(algo):
            continue
        for ablation in grid.ablations:
            out.append((f"{algo}-{ablation}", algo, {**base, ABLATIONS[ablation]: True}))
        for eta in grid.etas:
            out.append((f"{algo}-eta{eta:g}", algo, {**base, "eta": eta}))
    for name, (algo, flags) in grid.named.items():  # after the algos; its own flags win over all others
        base = {**_shared(grid.common, algo), **grid.per_algo.get(algo, {}), **_shared(grid.overrides, algo)}
        out.append((name, algo, {**base, **flags}))
    return out


def _identity(algo: str, flags: Mapping[str, Any], env: str, steps: int) -> str:
    """What makes two variants the same run: the resolved config (η as applied, seed aside)."""
    cfg = RunSpec(env, "x", algo, 0, steps, tuple(sorted(flags.items()))).run_config("identity")
    a = cfg.algo.to_dict()
    a.update(eta=cfg.algo.effective_eta, no_wt=False, seed=0)
    d = cfg.to_dict()
    d.update(algo=a, run="")
    return json.dumps(d, sort_keys=True)


def variants(grid: Grid) -> tuple[list[tuple[str, str, dict[str, Any]]], dict[str, str]]:
    """The distinct variants and {duplicate name: the variant it equals}. Raises GridError when a
    variant's options are invalid."""
    kept: list[tuple[str, str, dict[str, Any]]] = []
    aliases: dict[str, str] = {}
    seen: dict[str, str] = {}
    for name, algo, flags in variant_flags(grid):
        try:
            key = _identity(algo, flags, grid.envs[0], grid.steps)
        except (ValueError, typer.BadParameter) as e:
            raise GridError(f"variant {name}: {e}") from e
        if key in seen:
            aliases[name] = seen[key]
            continue
        seen[key] = name
        kept.append((name, algo, flags))
    if grid.only:
        wanted = {aliases.get(v, v) for v in grid.only}
        kept = [k for k in kept if k[0] in wanted]
    return kept, aliases


def plan(grid: Grid) -> list[RunSpec]:
    """Every run of the grid: seed by seed (then env, then variant; an env runs only its own seeds,
    see [env-seeds]), or with `order = "env"` env by env (each seed by seed). Pure: touches no files."""
    kept, _ = variants(grid)
    if grid.order == "env":
        cells = [(seed, env) for env in grid.envs for seed in grid.seeds_of(env)]
    else:
        every = sorted({s for env in grid.envs for s in grid.seeds_of(env)},
                       key=lambda s: (s not in grid.seeds, grid.seeds.index(s) if s in grid.seeds else s))
        cells = [(seed, env) for seed in every for env in grid.envs if seed in grid.seeds_of(env)]
    return [RunSpec(env, name, algo, seed, grid.steps, tuple(sorted(flags.items())))
            for seed, env in cells for name, algo, flags in kept]


# --- as text --------------------------------------------------------------------------------


def seeds_text(seeds: Sequence[int]) -> str:
    """0,1,2,3,7 -> "0-3,7"."""
    parts: list[str] = []
    for s in sorted(seeds):
        if parts and "-" in parts[-1] and int(parts[-1].split("-")[1]) == s - 1:
            parts[-1] = f"{parts[-1].split('-')[0]}-{s}"
        elif parts and "-" not in parts[-1] and int(parts[-1]) == s - 1:
            parts[-1] = f"{parts[-1]}-{s}"
        else:
            parts.append(str(s))
    return ",".join(parts)


def flags_text(flags: Iterable[tuple[str, Any]]) -> str:
    """Flags as on a command line: (("no_ot", True), ("hidden", (32, 32))) -> "--no-ot --hidden 32,32"."""
    out = []
    for k, v in flags:
        name = "--" + k.replace("_", "-")
        if v is True:
            out.append(name)
        elif v is not False:
            out.append(f"{name} {','.join(map(str, v)) if isinstance(v, tuple) else v}")
    return " ".join(out)
