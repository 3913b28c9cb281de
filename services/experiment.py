"""`mam experiment`: a grid of algorithms × seeds × envs through the distributed system.

Every run of the grid is a full local cluster (`services.launcher.run_local`: learner, referee
and M workers over loopback Zenoh), one after the other, each in its own run directory:

    EXP_DIR/experiment.json             the grid, the planned runs, versions
    EXP_DIR/<env>/<variant>/seed<k>/    a run directory (config.json, eval.jsonl, summary.json, ...)
    EXP_DIR/<env>/<variant>/seed<k>/launcher.log   what `mam run` would have printed
    EXP_DIR/failures/...                logs of failed attempts
    EXP_DIR/report.md, EXP_DIR/figures/ `mam report EXP_DIR` (run at the end unless --no-report)

Variants: each algorithm of `--algos` under its own name, and for every multi-actor algorithm
(ma-td3, ma-ddpg) one variant per ablation (`<algo>-no-ot`, `<algo>-no-wt`) and per η of
`--etas` (`<algo>-eta0.05`). A variant whose resolved configuration equals an earlier one (say
`ma-td3-eta0.1`, which is `ma-td3`) is not run twice.

The budget (`--steps`, env transitions received by the learner from all slots together) is the
same for every run of the grid. Flags: paper defaults per algorithm < the grid file's `[common]`
< its `[algo.NAME]` < flags on the command line < the variant's ablation / η. The multi-actor
flags (`--actors`, `--workers`, `--eliminate-at`, `--compete-every`, `--eta`,
`--single-env-after-elimination`) given on the command line or in `[common]` apply to the
multi-actor algorithms only: TD3 and DDPG keep K=1, M=1 unless their own `[algo.td3]` says otherwise.

Resumable: a run whose `summary.json` exists is skipped (after checking that its config matches
the grid); a run directory without one (an interrupted or failed run) is removed and redone.
Runs are ordered seed by seed (all envs and variants of seed 0, then seed 1, ...), so a grid
stopped early still has balanced results across algorithms.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import re
import shutil
import subprocess
import sys
import threading
import time
import tomllib
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console

from mam_core.config import ALGOS, AlgoConfig
from services import options
from services.options import RunConfig, write_json

ABLATIONS = {"no-ot": "no_ot", "no-wt": "no_wt"}
MULTI_ACTOR_FLAGS = frozenset({"actors", "workers", "eliminate_at", "compete_every", "eta",
                               "single_env_after_elimination", "no_ot", "no_wt"})
RUN_FLAGS = frozenset({"sync_every", "checkpoint_every", "send_batch", "band", "save_replay", "learner_threads",
                       "bias_every", "bias_rollouts"})
_ALGO_FLAGS = frozenset(f.name for f in dataclasses.fields(AlgoConfig)) - {"algo", "seed"}
FLAG_NAMES = _ALGO_FLAGS | RUN_FLAGS
GRID_KEYS = {"name", "exp_dir", "envs", "algos", "seeds", "steps", "ablations", "etas", "common", "algo"}


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

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "envs": list(self.envs), "algos": list(self.algos), "seeds": list(self.seeds),
                "steps": self.steps, "ablations": list(self.ablations), "etas": list(self.etas),
                "common": _jsonable(self.common), "per_algo": _jsonable(self.per_algo),
                "overrides": _jsonable(self.overrides)}


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
    if not envs:
        raise GridError("no envs: give --envs (comma-separated) or `envs` in the grid file")
    if not algos:
        raise GridError("no algos: give --algos (comma-separated) or `algos` in the grid file")
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
    return Grid(envs=envs, algos=algos, seeds=seeds, steps=int(steps), ablations=ablations, etas=etas,
                common=common, per_algo=per_algo, overrides=overrides, name=name)


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
    return kept, aliases


def plan(grid: Grid) -> list[RunSpec]:
    """Every run of the grid, seed by seed (then env, then variant). Pure: touches no files."""
    kept, _ = variants(grid)
    return [RunSpec(env, name, algo, seed, grid.steps, tuple(sorted(flags.items())))
            for seed in grid.seeds for env in grid.envs for name, algo, flags in kept]


# --- resuming --------------------------------------------------------------------------------


def run_state(spec: RunSpec, exp_dir: Path) -> str:
    """'done' (summary.json exists), 'partial' (a run directory without it) or 'todo'."""
    d = Path(exp_dir) / spec.path
    if (d / "summary.json").is_file():
        return "done"
    return "partial" if d.exists() else "todo"


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


def check_resume(specs: Sequence[RunSpec], exp_dir: Path) -> None:
    """Refuse to mix grids: every finished run must match the grid's configuration."""
    bad = []
    for spec in specs:
        if run_state(spec, exp_dir) == "done":
            problems = config_mismatch(spec, Path(exp_dir) / spec.path)
            if problems:
                bad.append(f"{spec.path}: " + "; ".join(problems[:4]))
    if bad:
        raise GridError(f"{exp_dir} holds finished runs of a different grid (use another --exp-dir, or remove "
                        "them):\n  " + "\n  ".join(bad[:10]))


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
    """Rich progress of the whole grid: runs done / total, env steps, elapsed, ETA, the current run.

    The runs go on in the main thread (the launcher installs signal handlers); a background thread
    reads the current run's learner.jsonl / eval.jsonl once a second.
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
        self.current: RunSpec | None = None
        self.current_dir: Path | None = None
        self.current_steps = 0
        self.lock = threading.Lock()
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(bar_width=28),
                                 TextColumn("{task.fields[info]}"), console=console, refresh_per_second=2,
                                 transient=False)
        self.grid_task = self.progress.add_task("[bold]grid", total=max(self.total_steps, 1),
                                                completed=self.done_steps, info="")
        self.run_task = self.progress.add_task("waiting", total=1, completed=0, info="", visible=False)
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

    def eta(self) -> float | None:
        elapsed = time.monotonic() - self.started
        steps = self.session_steps + self.current_steps
        if steps <= 0 or elapsed <= 0:
            return None
        remaining = self.total_steps - self.done_steps - self.current_steps
        return remaining / (steps / elapsed)

    def grid_info(self) -> str:
        failed = f" · [red]{self.failed} failed[/]" if self.failed else ""
        return (f"{self.done_runs}/{self.total_runs} runs · {self.done_steps + self.current_steps:,}/"
                f"{self.total_steps:,} steps · elapsed {_hms(time.monotonic() - self.started)} · "
                f"ETA {_hms(self.eta())}{failed}")

    def refresh(self) -> None:
        with self.lock:
            self.progress.update(self.grid_task, completed=self.done_steps + self.current_steps,
                                 info=self.grid_info())

    def start_run(self, spec: RunSpec, run_dir: Path, index: int) -> None:
        with self.lock:
            self.current, self.current_dir, self.current_steps = spec, run_dir, 0
            self.progress.update(self.run_task, description=f"run {index}: {spec.label}", total=spec.steps,
                                 completed=0, info="starting", visible=True)
        self.refresh()

    def end_run(self, spec: RunSpec, ok: bool, message: str, count_failure: bool = True) -> None:
        with self.lock:
            self.current, self.current_dir, self.current_steps = None, None, 0
            if ok:
                self.done_runs += 1
                self.done_steps += spec.steps
                self.session_steps += spec.steps
            elif count_failure:
                self.failed += 1
            self.progress.update(self.run_task, visible=False)
        self.progress.console.print(message)
        self.refresh()

    def _poll(self) -> None:
        while not self._stop.wait(1.0):
            with self.lock:
                spec, run_dir = self.current, self.current_dir
            if spec is None or run_dir is None:
                self.refresh()
                continue
            row = _tail_row(run_dir / "learner.jsonl") or {}
            steps = row.get("env_steps") if isinstance(row.get("env_steps"), int) else 0
            updates = row.get("updates") if isinstance(row.get("updates"), int) else 0
            ev = _tail_row(run_dir / "eval.jsonl") or {}
            means = [m for m in (ev.get("mean") or []) if isinstance(m, (int, float))]
            best = f" · best eval {max(means):.1f}" if means else ""
            with self.lock:
                if self.current is not spec:
                    continue
                self.current_steps = min(steps, spec.steps)
                self.progress.update(self.run_task, completed=self.current_steps,
                                     info=f"{steps:,}/{spec.steps:,} steps · upd {updates:,}{best}")
            self.refresh()


# --- running the grid ------------------------------------------------------------------------

Runner = Callable[[RunConfig, Path, Console, bool], dict[str, Any]]


def _default_runner(cfg: RunConfig, run_dir: Path, console: Console, plot: bool) -> dict[str, Any]:
    from services.launcher import run_local

    return run_local(cfg, run_dir, console=console, plot=plot)


def run_name_for(spec: RunSpec, tag: str) -> str:
    env = re.sub(r"[^A-Za-z0-9]+", "", spec.env.split("-")[0]).lower()[:16]
    return options.check_run_name(f"x{tag}-{spec.variant}-{env}-s{spec.seed}"[:128])


@dataclass
class GridResult:
    skipped: list[RunSpec] = field(default_factory=list)
    finished: list[RunSpec] = field(default_factory=list)
    failed: list[RunSpec] = field(default_factory=list)
    interrupted: bool = False


def versions() -> dict[str, str]:
    """Library versions that change results (MuJoCo trajectories differ across releases)."""
    from importlib import metadata

    out = {"python": platform.python_version()}
    for dist in ("mam", "torch", "numpy", "gymnasium", "mujoco", "eclipse-zenoh"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    root = Path(__file__).resolve().parents[1]
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                                timeout=5)
        if commit.returncode == 0 and commit.stdout.strip():
            out["git"] = commit.stdout.strip()
            changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                     capture_output=True, text=True, timeout=10)
            if changed.returncode == 0 and changed.stdout.strip():  # tracked files modified: say so
                out["git"] += "+modified(" + ",".join(line[3:] for line in changed.stdout.splitlines()) + ")"
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def write_manifest(exp_dir: Path, grid: Grid, specs: Sequence[RunSpec], aliases: Mapping[str, str]) -> None:
    path = Path(exp_dir) / "experiment.json"
    old: dict[str, Any] = {}
    try:
        old = json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        pass
    write_json(path, {"name": grid.name, "grid": grid.to_dict(), "aliases": dict(aliases),
                      "runs": [s.to_dict() for s in specs], "versions": versions(),
                      "created": old.get("created") or time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                      "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": sys.argv})


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


def run_grid(specs: Sequence[RunSpec], exp_dir: Path, console: Console, *, plot_runs: bool = True,
             retries: int = 1, fail_fast: bool = False, runner: Runner | None = None,
             tag: str | None = None) -> GridResult:
    """Run every spec not finished yet, one after the other; returns what happened."""
    runner = runner or _default_runner
    exp_dir = Path(exp_dir)
    tag = tag or f"{int(time.time()) % 100000:05d}"
    result = GridResult()
    todo = []
    for spec in specs:
        (result.skipped if run_state(spec, exp_dir) == "done" else todo).append(spec)
    if result.skipped:
        console.print(f"resuming: {len(result.skipped)} of {len(specs)} runs already finished, skipped")
    with GridView(console, specs, result.skipped) as view:
        for i, spec in enumerate(todo, start=len(result.skipped) + 1):
            ok = False
            for attempt in range(1, max(retries, 0) + 2):
                run_dir = exp_dir / spec.path
                if run_dir.exists():  # a partial run (interrupted, or a failed attempt): redo it
                    shutil.rmtree(run_dir)
                run_dir.mkdir(parents=True)
                view.start_run(spec, run_dir, i)
                cfg = spec.run_config(run_name_for(spec, tag))
                started = time.monotonic()
                log_path = run_dir / "launcher.log"
                with open(log_path, "w", encoding="utf-8") as log:
                    run_console = Console(file=log, width=120, force_terminal=False, color_system=None)
                    try:
                        summary = runner(cfg, run_dir, run_console, plot_runs)
                    except KeyboardInterrupt:
                        result.interrupted = True
                        summary = {}
                    except Exception:  # a broken run must not end the grid: it is logged and retried
                        log.write(traceback.format_exc())
                        summary = {}
                if not summary and "interrupted: stopping" in log_path.read_text(errors="replace"):
                    result.interrupted = True  # Ctrl-C / SIGTERM reached the launcher
                if result.interrupted:
                    view.end_run(spec, False, f"[yellow]interrupted[/] {spec.label} (it is redone on resume)",
                                 count_failure=False)
                    return result
                ok = bool(summary) and (run_dir / "summary.json").is_file()
                took = time.monotonic() - started
                if ok:
                    finals = summary.get("final_returns") or []
                    best = max((f for f in finals if isinstance(f, (int, float))), default=None)
                    score = "–" if best is None else f"{best:.2f}"
                    view.end_run(spec, True, f"[green]✓[/] {spec.label}  final {score}  survivor "
                                             f"{summary.get('survivor')}  {summary.get('env_steps', 0):,} steps  "
                                             f"{_hms(took)}")
                    break
                kept = _keep_failure(exp_dir, spec, run_dir, attempt)
                last = attempt > max(retries, 0)
                view.end_run(spec, False, f"[red]✗[/] {spec.label} failed (attempt {attempt}"
                                          f"{'' if last else ', retrying'}); logs: {kept or run_dir}",
                             count_failure=last)
            if ok:
                result.finished.append(spec)
            else:
                result.failed.append(spec)
                if fail_fast:
                    break
    return result


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


def describe_plan(specs: Sequence[RunSpec], aliases: Mapping[str, str], exp_dir: Path, console: Console) -> None:
    from rich.table import Table

    table = Table(title=f"{len(specs)} runs in {exp_dir}")
    for h in ("env", "variant", "seeds", "steps", "options", "finished"):
        table.add_column(h, overflow="fold")
    groups: dict[tuple[str, str], list[RunSpec]] = {}
    for s in specs:
        groups.setdefault((s.env, s.variant), []).append(s)
    for (env, variant), ss in groups.items():
        done = sum(run_state(s, exp_dir) == "done" for s in ss)
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
    precision: options.Precision = None,
    name: Annotated[Optional[str], typer.Option("--name", help="experiment name (default: the grid file's)")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="print the planned runs and exit")] = False,
    retries: Annotated[int, typer.Option("--retries", help="attempts after a failed run")] = 1,
    fail_fast: Annotated[bool, typer.Option("--fail-fast", help="stop at the first run that fails")] = False,
    no_plot: Annotated[bool, typer.Option("--no-plot", help="no per-run PNGs (RUN_DIR/plots)")] = False,
    no_report: Annotated[bool, typer.Option("--no-report", help="skip `mam report` at the end")] = False,
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
                     bias_rollouts=bias_rollouts, precision=precision)
        grid = make_grid(file, envs=envs, algos=algos, seeds=seeds, steps=steps, ablations=ablations, etas=etas,
                         name=name, flags=flags)
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
        check_resume(specs, exp_dir)
    except GridError as e:
        raise typer.BadParameter(str(e)) from e
    describe_plan(specs, aliases, exp_dir, console)
    if dry_run:
        return
    exp_dir.mkdir(parents=True, exist_ok=True)
    write_manifest(exp_dir, grid, specs, aliases)
    try:
        result = run_grid(specs, exp_dir, console, plot_runs=not no_plot, retries=retries, fail_fast=fail_fast)
    except KeyboardInterrupt:
        result = GridResult(interrupted=True)
    console.print(f"[bold]{len(result.skipped) + len(result.finished)}/{len(specs)}[/] runs finished "
                  f"({len(result.finished)} now, {len(result.skipped)} before), {len(result.failed)} failed")
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
