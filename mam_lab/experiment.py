"""`mam experiment`: a grid of algorithms × seeds × envs through the distributed system.

Every run of the grid is a full local cluster (`services.launcher.run_local`: learner, referee
and M workers over loopback Zenoh), started as its own process (`python -m services.experiment_run`)
whose exit status is the run's outcome (0 finished, 130 interrupted, else failed). `--parallel P`
runs P of them at once (default: cores ÷ `--cores-per-run`, at least 1), each pinned by CPU
affinity to its own len(cores) // P cores (every process of a run inherits it; the learner uses one
torch thread). One progress view shows the grid and every run in progress; Ctrl-C (or SIGTERM)
sends SIGTERM to every run, whose launcher stops its processes, and a rerun resumes.

    EXP_DIR/experiment.json             the grid, the planned runs, versions, the ledger
    EXP_DIR/<env>/<variant>/seed<k>/    a run directory (config.json, eval.jsonl, summary.json, ...)
    EXP_DIR/<env>/<variant>/seed<k>/launcher.log   what `mam run` would have printed
    EXP_DIR/<env>/<variant>/seed<k>/record.json    which code ran it (commit), with what, how long
    EXP_DIR/failures/...                logs of failed attempts
    EXP_DIR/report.md, EXP_DIR/figures/ `mam report EXP_DIR` (run at the end unless --no-report)

The ledger (`--ledger DIR`, default docs/results/<name>/runs relative to the current directory;
`--no-ledger`: none) keeps a compact record of each finished run, to be committed:
DIR/<env>/<variant>/seed<k>/ with config.json, summary.json, eval.jsonl, allocation.jsonl,
bias.jsonl (where present), learner.jsonl thinned to LEARNER_ROWS rows and record.json (the commit
the run ran at, with a dirty flag, versions, wall time, the spec, the exit status); no checkpoints,
no logs. DIR/experiment.json lists every run planned into that ledger. A run recorded in the
ledger counts as finished even when EXP_DIR does not have it (a fresh clone continues the grid).

Variants: each algorithm of `--algos` under its own name, and for every multi-actor algorithm
(ma-td3, ma-ddpg) one variant per ablation (`<algo>-no-ot`, `<algo>-no-wt`) and per η of
`--etas` (`<algo>-eta0.05`); then the grid file's named variants, `[variant.NAME]` tables, each
with an `algo` and any run flags. A variant whose resolved configuration equals an earlier one (say
`ma-td3-eta0.1`, which is `ma-td3`) is not run twice. `--variants a,b` runs only those.

The budget (`--steps`, env transitions received by the learner from all slots together) is the
same for every run of the grid. Flags: paper defaults per algorithm < the grid file's `[common]`
< its `[algo.NAME]` < flags on the command line < the variant's ablation / η / `[variant.NAME]`
flags. The multi-actor flags (`--actors`, `--workers`, `--eliminate-at`, `--compete-every`, `--eta`,
`--single-env-after-elimination`) given on the command line or in `[common]` apply to the
multi-actor algorithms only: TD3 and DDPG keep K=1, M=1 unless their own `[algo.td3]` (or a
`[variant.NAME]` of theirs) says otherwise.

Resumable: a run whose `summary.json` exists, or whose record is in the ledger, is skipped (after
checking that its config matches the grid); a run directory without either (an interrupted or
failed run) is removed and redone. Runs are ordered seed by seed (all envs and variants of seed 0,
then seed 1, ...), so a grid stopped early still has balanced results across algorithms.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Annotated, Any, Optional

import typer
from rich.console import Console

from mam_core.config import ALGOS, AlgoConfig
from services import options
from services.options import RunConfig, write_json

ABLATIONS = {"no-ot": "no_ot", "no-wt": "no_wt"}
MULTI_ACTOR_FLAGS = frozenset({"actors", "workers", "eliminate_at", "compete_every", "eta",
                               "single_env_after_elimination", "no_ot", "no_wt", "shared_batch",
                               "after_elimination", "skip_random_rounds"})
RUN_FLAGS = frozenset({"sync_every", "checkpoint_every", "send_batch", "band", "save_replay", "learner_threads",
                       "bias_every", "bias_rollouts", "bias_horizon"})
_ALGO_FLAGS = frozenset(f.name for f in dataclasses.fields(AlgoConfig)) - {"algo", "seed"}
FLAG_NAMES = _ALGO_FLAGS | RUN_FLAGS
GRID_KEYS = {"name", "exp_dir", "envs", "algos", "seeds", "steps", "ablations", "etas", "common", "algo", "variant"}
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

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "envs": list(self.envs), "algos": list(self.algos), "seeds": list(self.seeds),
                "steps": self.steps, "ablations": list(self.ablations), "etas": list(self.etas),
                "common": _jsonable(self.common), "per_algo": _jsonable(self.per_algo),
                "overrides": _jsonable(self.overrides),
                "variants": {n: {"algo": a, **_jsonable(f)} for n, (a, f) in self.named.items()},
                "only": list(self.only)}


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

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "env": self.env, "variant": self.variant, "algo": self.algo,
                "seed": self.seed, "steps": self.steps, "flags": _jsonable(dict(self.flags))}


def env_dirname(env: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", env)


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
        raise GridError(f"{path}: unknown key(s) {sorted(unknown)}; algorithm options go in [common] or "
                        f"[algo.NAME]")
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
    steps = get("steps")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise GridError(f"steps: need a positive number of env transitions, got {steps!r}")
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
                only=_list(cli.get("variants"), "variants"))
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
    """Every run of the grid, seed by seed (then env, then variant). Pure: touches no files."""
    kept, _ = variants(grid)
    return [RunSpec(env, name, algo, seed, grid.steps, tuple(sorted(flags.items())))
            for seed in grid.seeds for env in grid.envs for name, algo, flags in kept]


# --- the ledger: compact records of finished runs ---------------------------------------------

RECORD = "record.json"  # written last: its presence marks a finished run in the ledger
LEDGER_FILES = ("config.json", "summary.json", "eval.jsonl", "allocation.jsonl", "bias.jsonl")
LEARNER_ROWS = 200  # learner.jsonl is thinned to at most this many rows in the ledger
RECORD_FORMAT = 1


def default_ledger(name: str) -> Path:
    """docs/results/<exp name>/runs, relative to the current directory."""
    return Path("docs") / "results" / name / "runs"


def thin_indices(n: int, max_rows: int) -> list[int]:
    """At most `max_rows` indices of 0..n-1, evenly spaced, always the first and the last."""
    if max_rows < 2:
        raise ValueError("max_rows must be >= 2")
    if n <= max_rows:
        return list(range(n))
    return sorted({round(i * (n - 1) / (max_rows - 1)) for i in range(max_rows)})


def thin_jsonl(src: Path, dest: Path, max_rows: int = LEARNER_ROWS) -> tuple[int, int]:
    """Copy the JSON-object rows of `src` to `dest`, thinned (see thin_indices); (kept, of)."""
    lines = []
    for line in Path(src).read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            if isinstance(json.loads(line), dict):
                lines.append(line)
        except json.JSONDecodeError:
            continue
    keep = thin_indices(len(lines), max_rows)
    dest.write_text("".join(lines[i] + "\n" for i in keep), encoding="utf-8")
    return len(keep), len(lines)


def code_version(root: Path | None = None) -> dict[str, Any]:
    """The commit of the code that runs: {"commit": full hash or None, "dirty": tracked files
    modified, "modified": [those files]}."""
    root = root or Path(__file__).resolve().parents[1]
    out: dict[str, Any] = {"commit": None, "dirty": False, "modified": []}
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        if head.returncode != 0 or not head.stdout.strip():
            return out
        out["commit"] = head.stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                 capture_output=True, text=True, timeout=20)
        if changed.returncode == 0:
            out["modified"] = [line[3:] for line in changed.stdout.splitlines() if line.strip()]
            out["dirty"] = bool(out["modified"])
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def commit_label(record: Mapping[str, Any]) -> str:
    """"abc1234" or "abc1234+modified" (a dirty tree) or "unknown"."""
    commit = record.get("commit")
    if not isinstance(commit, str) or not commit:
        return "unknown"
    return commit[:12] + ("+modified" if record.get("dirty") else "")


def make_record(spec: RunSpec, run_dir: Path, *, code: Mapping[str, Any], exit_status: int,
                run_wall_s: float | None, experiment: str, **extra: Any) -> dict[str, Any]:
    """record.json of a finished run: which code ran it, with what, how long."""
    summary = _read_json(run_dir / "summary.json")
    return {"format": RECORD_FORMAT, "experiment": experiment, "path": spec.path.as_posix(),
            "spec": spec.to_dict(), "commit": code.get("commit"), "dirty": bool(code.get("dirty")),
            "modified": list(code.get("modified") or []), "versions": versions(), "exit_status": exit_status,
            "wall_time_s": summary.get("wall_time_s"), "launcher_wall_time_s": summary.get("launcher_wall_time_s"),
            "run_wall_s": None if run_wall_s is None else round(run_wall_s, 2),
            "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **extra}


def write_ledger_record(run_dir: Path, dest: Path, record: Mapping[str, Any],
                        max_rows: int = LEARNER_ROWS) -> Path:
    """Copy a finished run's compact record to `dest` (the run's directory in the ledger).

    Files go to a temporary directory first, which then replaces `dest`: a reader sees the old
    record or the new one, never half of it; record.json (with the files' sizes) comes last."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    files: dict[str, int] = {}
    for name in LEDGER_FILES:
        if (run_dir / name).is_file():
            shutil.copyfile(run_dir / name, tmp / name)
    record = dict(record)
    if (run_dir / "learner.jsonl").is_file():
        kept, total = thin_jsonl(run_dir / "learner.jsonl", tmp / "learner.jsonl", max_rows)
        record["learner_rows"] = {"kept": kept, "of": total}
    for p in sorted(tmp.iterdir()):
        files[p.name] = p.stat().st_size
    record["files"] = files
    write_json(tmp / RECORD, record)
    old = dest.parent / f".{dest.name}.old-{os.getpid()}"
    if dest.exists():
        dest.rename(old)
    tmp.rename(dest)
    if old.exists():
        shutil.rmtree(old)
    return dest


def read_record(run_dir: Path) -> dict[str, Any]:
    return _read_json(Path(run_dir) / RECORD)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return data if isinstance(data, dict) else {}


# --- resuming --------------------------------------------------------------------------------


def in_ledger(spec: RunSpec, ledger: Path | None) -> bool:
    return ledger is not None and (Path(ledger) / spec.path / RECORD).is_file()


def run_state(spec: RunSpec, exp_dir: Path, ledger: Path | None = None) -> str:
    """'done' (summary.json in the experiment directory, or a record in the ledger), 'partial'
    (a run directory without either) or 'todo'."""
    d = Path(exp_dir) / spec.path
    if (d / "summary.json").is_file() or in_ledger(spec, ledger):
        return "done"
    return "partial" if d.exists() else "todo"


def finished_dir(spec: RunSpec, exp_dir: Path, ledger: Path | None = None) -> Path | None:
    """Where a finished run's config.json is: the experiment directory, else the ledger."""
    d = Path(exp_dir) / spec.path
    if (d / "summary.json").is_file():
        return d
    if in_ledger(spec, ledger):
        return Path(ledger) / spec.path
    return None


def config_mismatch(spec: RunSpec, run_dir: Path) -> list[str]:
    """Differences between a finished run's config.json and what the grid asks for (device aside)."""
    try:
        have = json.loads((run_dir / "config.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return ["config.json missing or unreadable"]
    want = spec.run_config("x").to_dict()
    problems = []
    for key in ("env_id", "steps"):
        if have.get(key) != want[key]:
            problems.append(f"{key}: run {have.get(key)!r}, grid {want[key]!r}")
    have_algo = have.get("algo") if isinstance(have.get("algo"), dict) else {}
    for key, value in want["algo"].items():
        if key == "device" or key not in have_algo:  # a field newer than the run: not a mismatch
            continue
        if have_algo[key] != value:
            problems.append(f"{key}: run {have_algo[key]!r}, grid {value!r}")
    return problems


def check_resume(specs: Sequence[RunSpec], exp_dir: Path, ledger: Path | None = None) -> None:
    """Refuse to mix grids: every finished run (here or in the ledger) must match the grid's configuration."""
    bad = []
    for spec in specs:
        d = finished_dir(spec, exp_dir, ledger)
        if d is not None:
            problems = config_mismatch(spec, d)
            if problems:
                bad.append(f"{d}: " + "; ".join(problems[:4]))
    if bad:
        raise GridError(f"{exp_dir} or the ledger {ledger} holds finished runs of a different grid (use another "
                        "--exp-dir / --ledger, or remove them):\n  " + "\n  ".join(bad[:10]))


# --- progress view ---------------------------------------------------------------------------


def _tail_row(path: Path, max_bytes: int = 16384) -> dict[str, Any] | None:
    """The last complete JSON row of a JSONL file (None if there is none)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - max_bytes))
            data = f.read().decode("utf-8", errors="replace")
    except OSError:
        return None
    for line in reversed(data.splitlines()):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict):
            return row
    return None


def _hms(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "–"
    s = int(max(seconds, 0))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


class GridView:
    """Rich progress of the whole grid: runs done / total, env steps, elapsed, ETA, and one line per
    run in progress (P of them with --parallel P).

    The scheduler runs in the main thread; a background thread reads each current run's
    learner.jsonl / eval.jsonl once a second.
    """

    def __init__(self, console: Console, specs: Sequence[RunSpec], done: Iterable[RunSpec]) -> None:
        from rich.progress import BarColumn, Progress, TextColumn

        self.console = console
        self.total_runs = len(specs)
        self.total_steps = sum(s.steps for s in specs)
        done = list(done)
        self.done_runs = len(done)
        self.done_steps = sum(s.steps for s in done)
        self.session_steps = 0  # finished this session (runs, counted by their budget)
        self.failed = 0
        self.started = time.monotonic()
        self.current: dict[int, tuple[RunSpec, Path]] = {}  # slot -> the run in it
        self.current_steps: dict[int, int] = {}
        self.tasks: dict[int, Any] = {}  # slot -> progress task
        self.lock = threading.Lock()
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(bar_width=28),
                                 TextColumn("{task.fields[info]}"), console=console, refresh_per_second=2,
                                 transient=False)
        self.grid_task = self.progress.add_task("[bold]grid", total=max(self.total_steps, 1),
                                                completed=self.done_steps, info="")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="grid-view", daemon=True)

    def __enter__(self) -> "GridView":
        self.progress.start()
        self._thread.start()
        self.refresh()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.refresh()
        self.progress.stop()

    def _running_steps(self) -> int:
        return sum(self.current_steps.values())

    def eta(self) -> float | None:
        elapsed = time.monotonic() - self.started
        steps = self.session_steps + self._running_steps()
        if steps <= 0 or elapsed <= 0:
            return None
        remaining = self.total_steps - self.done_steps - self._running_steps()
        return remaining / (steps / elapsed)

    def grid_info(self) -> str:
        failed = f" · [red]{self.failed} failed[/]" if self.failed else ""
        running = f" · {len(self.current)} running" if len(self.current) > 1 else ""
        return (f"{self.done_runs}/{self.total_runs} runs{running} · {self.done_steps + self._running_steps():,}/"
                f"{self.total_steps:,} steps · elapsed {_hms(time.monotonic() - self.started)} · "
                f"ETA {_hms(self.eta())}{failed}")

    def refresh(self) -> None:
        with self.lock:
            self.progress.update(self.grid_task, completed=self.done_steps + self._running_steps(),
                                 info=self.grid_info())

    def start_run(self, spec: RunSpec, run_dir: Path, index: int, slot: int = 0, cores: Sequence[int] = ()) -> None:
        where = f" [dim]cores {seeds_text(cores)}[/]" if cores else ""
        with self.lock:
            self.current[slot] = (spec, run_dir)
            self.current_steps[slot] = 0
            if slot not in self.tasks:
                self.tasks[slot] = self.progress.add_task("", total=1, completed=0, info="")
            self.progress.update(self.tasks[slot], description=f"run {index}: {spec.label}{where}",
                                 total=spec.steps, completed=0, info="starting", visible=True)
        self.refresh()

    def end_run(self, spec: RunSpec, ok: bool, message: str, count_failure: bool = True, slot: int = 0) -> None:
        with self.lock:
            self.current.pop(slot, None)
            self.current_steps.pop(slot, None)
            if ok:
                self.done_runs += 1
                self.done_steps += spec.steps
                self.session_steps += spec.steps
            elif count_failure:
                self.failed += 1
            if slot in self.tasks:
                self.progress.update(self.tasks[slot], visible=False)
        self.progress.console.print(message)
        self.refresh()

    def _poll(self) -> None:
        while not self._stop.wait(1.0):
            with self.lock:
                current = dict(self.current)
            for slot, (spec, run_dir) in current.items():
                row = _tail_row(run_dir / "learner.jsonl") or {}
                steps = row.get("env_steps") if isinstance(row.get("env_steps"), int) else 0
                updates = row.get("updates") if isinstance(row.get("updates"), int) else 0
                ev = _tail_row(run_dir / "eval.jsonl") or {}
                means = [m for m in (ev.get("mean") or []) if isinstance(m, (int, float))]
                best = f" · best eval {max(means):.1f}" if means else ""
                with self.lock:
                    if self.current.get(slot, (None,))[0] is not spec:
                        continue
                    self.current_steps[slot] = min(steps, spec.steps)
                    self.progress.update(self.tasks[slot], completed=self.current_steps[slot],
                                         info=f"{steps:,}/{spec.steps:,} steps · upd {updates:,}{best}")
            self.refresh()


# --- running the grid ------------------------------------------------------------------------

ROOT = Path(__file__).resolve().parents[1]  # the code every run of the grid runs
STOP_WAIT_S = 60.0  # after SIGTERM, how long a run may take to stop before it is killed


@dataclass
class Launch:
    """What a run process needs: `launch(job)` starts it and returns its Popen."""

    spec: RunSpec
    cfg: RunConfig
    run_dir: Path
    cores: tuple[int, ...]  # CPU affinity of the run (empty: not pinned)
    plot: bool
    log: IO[bytes]  # the run's launcher.log: the process's stdout and stderr


Launcher = Callable[[Launch], subprocess.Popen]


def start_run_process(job: Launch) -> subprocess.Popen:
    """`python -m services.experiment_run RUN_DIR` (see there): one run, its outcome in the exit status.

    Its own session (the terminal's Ctrl-C reaches the grid, which stops each run with SIGTERM) and
    SIGTERM when the grid dies; the grid's code first on PYTHONPATH, so every run runs it."""
    from services.experiment_run import LAUNCH_FILE
    from services.launcher import _die_with_parent

    write_json(job.run_dir / LAUNCH_FILE, {"config": job.cfg.to_dict(), "cores": list(job.cores) or None,
                                           "plot": job.plot})
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return subprocess.Popen([sys.executable, "-m", "services.experiment_run", str(job.run_dir.resolve())],
                            stdout=job.log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                            start_new_session=True, preexec_fn=_die_with_parent)


def available_cores() -> list[int]:
    return sorted(os.sched_getaffinity(0))


def default_parallel(cores_per_run: int = 1, cores: Sequence[int] | None = None) -> int:
    """What the machine affords: cores ÷ cores per run, at least 1."""
    n = len(cores) if cores is not None else len(available_cores())
    return max(1, n // max(1, cores_per_run))


def core_slots(parallel: int, cores: Sequence[int] | None = None) -> list[tuple[int, ...]]:
    """The cores of each of `parallel` concurrent runs: disjoint sets of len(cores) // parallel
    cores; with more runs than cores, runs share single cores round-robin."""
    if parallel < 1:
        raise ValueError("parallel must be >= 1")
    cores = sorted(cores if cores is not None else available_cores())
    per = len(cores) // parallel
    if per == 0:
        return [(cores[i % len(cores)],) for i in range(parallel)]
    return [tuple(cores[i * per:(i + 1) * per]) for i in range(parallel)]


def run_name_for(spec: RunSpec, tag: str) -> str:
    env = re.sub(r"[^A-Za-z0-9]+", "", spec.env.split("-")[0]).lower()[:16]
    return options.check_run_name(f"x{tag}-{spec.variant}-{env}-s{spec.seed}"[:128])


@dataclass
class GridResult:
    skipped: list[RunSpec] = field(default_factory=list)
    finished: list[RunSpec] = field(default_factory=list)
    failed: list[RunSpec] = field(default_factory=list)
    interrupted: bool = False
    elapsed_s: float = 0.0
    run_wall_s: dict[str, float] = field(default_factory=dict)  # label -> wall time of its finished attempt


def versions() -> dict[str, str]:
    """Library versions that change results (MuJoCo trajectories differ across releases)."""
    from importlib import metadata

    out = {"python": platform.python_version()}
    for dist in ("mam", "torch", "numpy", "gymnasium", "mujoco", "eclipse-zenoh"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    code = code_version(ROOT)
    if code["commit"]:
        out["git"] = code["commit"][:7]
        if code["dirty"]:  # tracked files modified: say so
            out["git"] += "+modified(" + ",".join(code["modified"]) + ")"
    return out


def write_manifest(exp_dir: Path, grid: Grid, specs: Sequence[RunSpec], aliases: Mapping[str, str],
                   ledger: Path | None = None, **extra: Any) -> None:
    """EXP_DIR/experiment.json, and a copy in the ledger (its planned runs: the union over the
    invocations that wrote to that ledger, so a subset run with --variants keeps the others)."""
    path = Path(exp_dir) / "experiment.json"
    old = _read_json(path)
    body = {"name": grid.name, "grid": grid.to_dict(), "aliases": dict(aliases),
            "runs": [s.to_dict() for s in specs], "versions": versions(),
            "created": old.get("created") or time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": sys.argv,
            "ledger": str(Path(ledger).resolve()) if ledger is not None else None, **extra}
    write_json(path, body)
    if ledger is not None:
        lpath = Path(ledger) / "experiment.json"
        lold = _read_json(lpath)
        runs = [r for r in lold.get("runs") or [] if isinstance(r, dict)]
        have = {r.get("path") for r in runs}
        runs += [r for r in body["runs"] if r["path"] not in have]
        write_json(lpath, {**body, "runs": runs, "ledger": None, "exp_dir": None,
                           "created": lold.get("created") or body["created"]})


def _keep_failure(exp_dir: Path, spec: RunSpec, run_dir: Path, attempt: int) -> Path | None:
    """Copy a failed attempt's logs to EXP_DIR/failures/ before its directory is redone."""
    dest = Path(exp_dir) / "failures" / f"{env_dirname(spec.env)}_{spec.variant}_seed{spec.seed}_{attempt}_" \
                                        f"{time.strftime('%Y%m%d-%H%M%S')}"
    try:
        dest.mkdir(parents=True, exist_ok=True)
        for name in ("launcher.log", "config.json", "transport.json"):
            if (run_dir / name).is_file():
                shutil.copy2(run_dir / name, dest / name)
        if (run_dir / "logs").is_dir():
            shutil.copytree(run_dir / "logs", dest / "logs", dirs_exist_ok=True)
        return dest
    except OSError:
        return None


@dataclass
class _Active:
    spec: RunSpec
    run_dir: Path
    attempt: int
    index: int
    slot: int
    cores: tuple[int, ...]
    proc: subprocess.Popen
    log: IO[bytes]
    code: dict[str, Any]
    started: float


INTERRUPTED_STATUS = frozenset({130, -signal.SIGINT, -signal.SIGTERM})


def _raise_keyboard_interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def run_grid(specs: Sequence[RunSpec], exp_dir: Path, console: Console, *, plot_runs: bool = True,
             retries: int = 1, fail_fast: bool = False, launcher: Launcher | None = None,
             tag: str | None = None, parallel: int = 1, cores: Sequence[Sequence[int]] | None = None,
             ledger: Path | None = None, experiment: str = "experiment") -> GridResult:
    """Run every spec not finished yet, `parallel` at a time, each as its own process; returns what
    happened. `cores`: the affinity of each of the `parallel` slots (None: core_slots; [] per slot:
    unpinned). A finished run's record goes to RUN_DIR/record.json and, with `ledger`, to the ledger.

    Ctrl-C (or SIGTERM to the grid) sends SIGTERM to every run in progress and waits for them to stop."""
    launch = launcher or start_run_process
    exp_dir = Path(exp_dir)
    tag = tag or f"{int(time.time()) % 100000:05d}"
    parallel = max(1, int(parallel))
    slots = [tuple(c) for c in cores] if cores is not None else core_slots(parallel)
    if len(slots) < parallel:
        raise ValueError(f"{parallel} runs at once need {parallel} core sets, got {len(slots)}")
    order = {spec: i for i, spec in enumerate(specs)}
    result = GridResult()
    started = time.monotonic()
    todo = []
    for spec in specs:
        (result.skipped if run_state(spec, exp_dir, ledger) == "done" else todo).append(spec)
    if result.skipped:
        console.print(f"resuming: {len(result.skipped)} of {len(specs)} runs already finished, skipped")
        if ledger is not None:
            _backfill_ledger(result.skipped, exp_dir, ledger, experiment, console)
    queue: deque[tuple[RunSpec, int]] = deque((spec, 1) for spec in todo)
    index_of: dict[RunSpec, int] = {}
    free = list(range(parallel))
    active: dict[int, _Active] = {}
    stopping = False
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt) if in_main else None

    def start(spec: RunSpec, attempt: int, slot: int) -> None:
        index = index_of.setdefault(spec, len(result.skipped) + len(index_of) + 1)
        run_dir = exp_dir / spec.path
        if run_dir.exists():  # a partial run (interrupted, or a failed attempt): redo it
            shutil.rmtree(run_dir)
        run_dir.mkdir(parents=True)
        log = open(run_dir / "launcher.log", "wb")
        code = code_version(ROOT)
        view.start_run(spec, run_dir, index, slot, slots[slot])
        try:
            proc = launch(Launch(spec, spec.run_config(run_name_for(spec, tag)), run_dir, slots[slot], plot_runs,
                                 log))
        except Exception:  # could not even start: a failed attempt
            log.write(traceback.format_exc().encode())
            log.close()
            finish(_Active(spec, run_dir, attempt, index, slot, slots[slot], _NoProcess(), log, code,
                           time.monotonic()), 1)
            return
        active[slot] = _Active(spec, run_dir, attempt, index, slot, slots[slot], proc, log, code, time.monotonic())

    def finish(a: _Active, status: int) -> None:
        nonlocal stopping
        a.log.close()
        free.append(a.slot)
        free.sort()
        took = time.monotonic() - a.started
        summary = _read_json(a.run_dir / "summary.json")
        if status == 0 and summary:
            record = make_record(a.spec, a.run_dir, code=a.code, exit_status=status, run_wall_s=took,
                                 experiment=experiment, attempt=a.attempt, cores=list(a.cores), parallel=parallel)
            write_json(a.run_dir / RECORD, record)
            where = ""
            if ledger is not None:
                try:
                    write_ledger_record(a.run_dir, Path(ledger) / a.spec.path, record)
                    where = " → ledger"
                except OSError as e:  # the run is finished here; the next invocation copies it
                    where = f" [yellow](ledger: {e})[/]"
            finals = summary.get("final_returns") or []
            best = max((f for f in finals if isinstance(f, (int, float))), default=None)
            score = "–" if best is None else f"{best:.2f}"
            view.end_run(a.spec, True, f"[green]✓[/] {a.spec.label}  final {score}  survivor "
                                       f"{summary.get('survivor')}  {summary.get('env_steps', 0):,} steps  "
                                       f"{_hms(took)}{where}", slot=a.slot)
            result.finished.append(a.spec)
            result.run_wall_s[a.spec.label] = took
            return
        if status in INTERRUPTED_STATUS or (result.interrupted and status == -signal.SIGKILL):
            result.interrupted = True
            stopping = True
            view.end_run(a.spec, False, f"[yellow]interrupted[/] {a.spec.label} (it is redone on resume)",
                         count_failure=False, slot=a.slot)
            return
        kept = _keep_failure(exp_dir, a.spec, a.run_dir, a.attempt)
        last = a.attempt > max(retries, 0)
        view.end_run(a.spec, False, f"[red]✗[/] {a.spec.label} failed (exit status {status}, attempt {a.attempt}"
                                    f"{'' if last or stopping else ', retrying'}); logs: {kept or a.run_dir}",
                     count_failure=last, slot=a.slot)
        if last:
            result.failed.append(a.spec)
            stopping = stopping or fail_fast
        elif not stopping:
            queue.appendleft((a.spec, a.attempt + 1))

    def reap() -> None:
        for slot, a in list(active.items()):
            status = a.proc.poll()
            if status is not None:
                del active[slot]
                finish(a, status)

    try:
        with GridView(console, specs, result.skipped) as view:
            try:
                while True:
                    while queue and free and not stopping:
                        spec, attempt = queue.popleft()
                        start(spec, attempt, free.pop(0))
                    if not active and (stopping or not queue):
                        break
                    time.sleep(0.2)
                    reap()
            except KeyboardInterrupt:
                result.interrupted = stopping = True
                view.progress.console.print(f"[yellow]interrupted: stopping {len(active)} run(s)[/]")
            if active:  # interrupted (the grid or a run): stop every run in progress and wait for it
                _stop_runs(active, reap)
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    result.finished.sort(key=order.__getitem__)
    result.failed.sort(key=order.__getitem__)
    result.elapsed_s = time.monotonic() - started
    return result


class _NoProcess:
    """Stands in for a process that could not be started."""

    returncode = 1

    def poll(self) -> int:
        return 1


def _stop_runs(active: dict[int, _Active], reap: Callable[[], None]) -> None:
    """SIGTERM to every run (its launcher stops the run's processes), SIGKILL after STOP_WAIT_S or
    at a second Ctrl-C; `reap` records each run as it ends."""
    for a in active.values():
        if a.proc.poll() is None:
            a.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_WAIT_S
    try:
        while active and time.monotonic() < deadline:
            time.sleep(0.2)
            reap()
    except KeyboardInterrupt:
        pass
    for a in active.values():
        if a.proc.poll() is None:
            a.proc.kill()  # its children get SIGTERM from the kernel (PDEATHSIG)
    for a in list(active.values()):
        a.proc.wait()
    reap()


def _backfill_ledger(done: Sequence[RunSpec], exp_dir: Path, ledger: Path, experiment: str,
                     console: Console) -> None:
    """Runs finished here but not in the ledger (a ledger added later, or a failed copy): copy them,
    with the record written when they finished if there is one."""
    for spec in done:
        run_dir = Path(exp_dir) / spec.path
        if in_ledger(spec, ledger) or not (run_dir / "summary.json").is_file():
            continue
        record = read_record(run_dir)
        if not record:  # finished before records existed: the commit is the one running now, flagged
            record = make_record(spec, run_dir, code=code_version(ROOT), exit_status=0, run_wall_s=None,
                                 experiment=experiment, backfilled=True)
        try:
            write_ledger_record(run_dir, Path(ledger) / spec.path, record)
            console.print(f"ledger: copied {spec.label}" + (" (commit unknown: recorded as the current one)"
                                                            if record.get("backfilled") else ""))
        except OSError as e:
            console.print(f"[yellow]ledger: could not copy {spec.label}: {e}[/]")


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


def describe_plan(specs: Sequence[RunSpec], aliases: Mapping[str, str], exp_dir: Path, console: Console,
                  ledger: Path | None = None) -> None:
    from rich.table import Table

    table = Table(title=f"{len(specs)} runs in {exp_dir}")
    for h in ("env", "variant", "seeds", "steps", "options", "finished"):
        table.add_column(h, overflow="fold")
    groups: dict[tuple[str, str], list[RunSpec]] = {}
    for s in specs:
        groups.setdefault((s.env, s.variant), []).append(s)
    for (env, variant), ss in groups.items():
        done = sum(run_state(s, exp_dir, ledger) == "done" for s in ss)
        table.add_row(env, variant, seeds_text([s.seed for s in ss]), f"{ss[0].steps:,}",
                      flags_text(ss[0].flags) or "(paper defaults)", f"{done}/{len(ss)}")
    console.print(table)
    for dup, same in aliases.items():
        console.print(f"[dim]{dup} is the same configuration as {same}: run once[/]")


# --- command ---------------------------------------------------------------------------------


def experiment_command(
    config: Annotated[Optional[Path], typer.Option(
        "--config", help="grid TOML file (see deploy/experiments/); flags given here win over it")] = None,
    exp_dir: Annotated[Optional[Path], typer.Option(
        "--exp-dir", help="experiment directory (default: the grid file's exp-dir, else runs/experiments/<name>); "
                          "run again with the same directory to resume")] = None,
    envs: Annotated[Optional[str], typer.Option("--envs", help="comma-separated env ids, e.g. "
                                                                "HalfCheetah-v5,Hopper-v5")] = None,
    algos: Annotated[Optional[str], typer.Option("--algos", help=f"comma-separated, of {', '.join(ALGOS)}")] = None,
    seeds: Annotated[Optional[str], typer.Option("--seeds", help="N (seeds 0..N-1), A-B, or a list 0,3,7")] = None,
    steps: Annotated[Optional[int], typer.Option(
        "--steps", help="budget of every run: env transitions received by the learner (all slots)")] = None,
    ablations: Annotated[Optional[str], typer.Option(
        "--ablations", help="extra variants of each multi-actor algo: no-ot, no-wt (comma-separated)")] = None,
    etas: Annotated[Optional[str], typer.Option(
        "--etas", help="η sweep: one variant per value for each multi-actor algo, e.g. 0.05,0.1,0.2")] = None,
    actors: options.Actors = None, workers: options.Workers = None, eliminate_at: options.EliminateAt = None,
    compete_every: options.CompeteEvery = None, eta: options.Eta = None, eval_episodes: options.EvalEpisodes = None,
    eval_every: options.EvalEvery = None, start_steps: options.StartSteps = None,
    batch_size: options.BatchSize = None, utd: options.Utd = None, device: options.Device = None,
    hidden: options.Hidden = None, single_env_after_elimination: options.SingleEnv = None,
    bias_every: options.BiasEvery = None, bias_rollouts: options.BiasRollouts = None,
    precision: options.Precision = None, schedule: options.Schedule = None, shared_batch: options.SharedBatch = None,
    after_elimination: options.AfterElimination = None, skip_random_rounds: options.SkipRandomRounds = None,
    bias_horizon: options.BiasHorizon = None,
    name: Annotated[Optional[str], typer.Option("--name", help="experiment name (default: the grid file's)")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="print the planned runs and exit")] = False,
    retries: Annotated[int, typer.Option("--retries", help="attempts after a failed run")] = 1,
    fail_fast: Annotated[bool, typer.Option("--fail-fast", help="stop at the first run that fails")] = False,
    no_plot: Annotated[bool, typer.Option("--no-plot", help="no per-run PNGs (RUN_DIR/plots)")] = False,
    no_report: Annotated[bool, typer.Option("--no-report", help="skip `mam report` at the end")] = False,
    parallel: Annotated[Optional[int], typer.Option(
        "--parallel", help="runs at once, each its own process pinned to its own cores (default: cores ÷ "
                           "--cores-per-run, at least 1)")] = None,
    cores_per_run: Annotated[int, typer.Option("--cores-per-run", help="cores per run for the default --parallel")] = 1,
    pin: Annotated[bool, typer.Option("--pin/--no-pin", help="CPU affinity per run (cores ÷ P each)")] = True,
    ledger: Annotated[Optional[Path], typer.Option(
        "--ledger", help="directory of the compact records of finished runs (default docs/results/<name>/runs, "
                         "relative to the current directory); a run recorded there is finished")] = None,
    no_ledger: Annotated[bool, typer.Option("--no-ledger", help="keep no ledger")] = False,
    variants_opt: Annotated[Optional[str], typer.Option(
        "--variants", help="run only these variants of the grid (comma-separated names)")] = None,
) -> None:
    """Run a grid of algorithms × seeds × envs through the distributed system; resumable.

    The multi-actor flags (--actors, --workers, --eliminate-at, --compete-every, --eta,
    --single-env-after-elimination) apply to ma-td3 / ma-ddpg only; the others to every run.
    """
    import logging

    logging.basicConfig(level=logging.WARNING)
    console = Console()
    try:
        file = load_grid_file(config) if config is not None else {}
        flags = dict(actors=actors, workers=workers, eliminate_at=eliminate_at, compete_every=compete_every,
                     eta=eta, eval_episodes=eval_episodes, eval_every=eval_every, start_steps=start_steps,
                     batch_size=batch_size, utd=utd, device=device, hidden=hidden,
                     single_env_after_elimination=single_env_after_elimination, bias_every=bias_every,
                     bias_rollouts=bias_rollouts, precision=precision, schedule=schedule,
                     shared_batch=shared_batch, after_elimination=after_elimination,
                     skip_random_rounds=skip_random_rounds, bias_horizon=bias_horizon)
        grid = make_grid(file, envs=envs, algos=algos, seeds=seeds, steps=steps, ablations=ablations, etas=etas,
                         name=name, flags=flags, variants=variants_opt)
        specs = plan(grid)
        for spec in specs:  # before anything starts: bf16 where it would only be slower
            if dict(spec.flags).get("precision") == "bf16":
                options.check_precision(spec.run_config("check"))
        _, aliases = variants(grid)
        if exp_dir is None:
            if file.get("exp_dir"):
                exp_dir = Path(str(file["exp_dir"]))
            elif config is not None or name:
                exp_dir = Path("runs") / "experiments" / grid.name
            else:
                raise GridError("--exp-dir is required without a grid file or --name")
        if no_ledger:
            ledger = None
        elif ledger is None:
            ledger = default_ledger(grid.name)
        if parallel is not None and parallel < 1:
            raise GridError("--parallel must be >= 1")
        if cores_per_run < 1:
            raise GridError("--cores-per-run must be >= 1")
        parallel = parallel or default_parallel(cores_per_run)
        check_resume(specs, exp_dir, ledger)
    except GridError as e:
        raise typer.BadParameter(str(e)) from e
    describe_plan(specs, aliases, exp_dir, console, ledger)
    slots = core_slots(parallel) if pin else [()] * parallel
    code = code_version(ROOT)
    console.print(f"{parallel} run(s) at once" + (", cores " + "; ".join(seeds_text(c) for c in slots) if pin else
                                                  ", not pinned")
                  + (f"; ledger {ledger}" if ledger is not None else "; no ledger")
                  + f"; code {ROOT} at {commit_label(code)}")
    if dry_run:
        return
    exp_dir.mkdir(parents=True, exist_ok=True)
    write_manifest(exp_dir, grid, specs, aliases, ledger, parallel=parallel)
    try:
        result = run_grid(specs, exp_dir, console, plot_runs=not no_plot, retries=retries, fail_fast=fail_fast,
                          parallel=parallel, cores=slots, ledger=ledger, experiment=grid.name)
    except KeyboardInterrupt:
        result = GridResult(interrupted=True)
    console.print(f"[bold]{len(result.skipped) + len(result.finished)}/{len(specs)}[/] runs finished "
                  f"({len(result.finished)} now, {len(result.skipped)} before), {len(result.failed)} failed "
                  f"in {_hms(result.elapsed_s)}")
    if not no_report and (result.finished or result.skipped):
        from services.report import print_tables, write_report

        report, md, pngs = write_report(exp_dir)
        print_tables(report, console)
        console.print(f"[green]report[/] {md} ({len(pngs)} figures)")
    if result.interrupted:
        console.print(f"[yellow]interrupted[/]: run the same command again to resume ({exp_dir})")
        raise typer.Exit(130)
    if result.failed:
        raise typer.Exit(1)


if __name__ == "__main__":
    typer.run(experiment_command)
