"""`mam report PATH`: tables with confidence intervals and figures from an experiment's runs.

PATH is an experiment directory (written by `mam experiment`: one run directory per
(env, variant, seed), `EXP_DIR/<env>/<variant>/seed<k>/`, plus the records of the ledger its
experiment.json names), a ledger directory (the compact records, same layout), or a folder holding
the ledger in `runs/` (`docs/results/<exp>`). Only finished runs (with `summary.json`) count; runs
planned in `experiment.json` but not finished are listed as missing. Nothing is rerun.

The report opens with a **Verdict**: each multi-actor variant against the K=1 baseline of its
family (TD3 / DDPG) in the same env: P(variant > baseline) with its 95% CI, both IQMs with CIs,
wall-clock time per run, and *better* (CI lower bound > 0.5), *worse* (upper bound < 0.5) or *not
separated*. Each run's record.json names the commit it ran at; rows whose runs differ get a note.
Tables are on one x-axis (`--x transitions` (default) or `iterations`, which rows of older runs
lack: their env transitions stand in) and say which; learning curves are drawn on both.

Per run, the score of an evaluation point is the mean return of the **best live actor** at that
point (after the elimination only the survivor is evaluated, so it is the survivor's return; a
single-actor run has one actor). Evaluation points are put on a common grid of the env's
evaluation spacing (the largest `eval_every` of its runs): an evaluation at env step s belongs to
grid point floor(s / spacing)·spacing, the last one in a grid cell wins (the multi-actor runs also
evaluate at every allocation round A, which would otherwise give them more points).

Per env and variant the report gives:

- **last-10 mean** (primary): per run, the mean score of its last 10 grid points; then the mean
  over seeds with a bootstrap 95% CI (seeds resampled) and the std over seeds;
- **IQM** of the per-run last-10 scores with a bootstrap 95% CI;
- **max average return** (the paper's Table 4): the maximum over grid points of the mean over seeds
  (runs held at their last value between evaluations), ± the std over seeds at that point;
- probability of improvement P(X > Y) (MA-TD3 vs TD3, MA-DDPG vs DDPG, the full method vs each
  ablation / η variant) with a stratified-bootstrap 95% CI, per env and over all envs;
- updates, env steps and wall time per algorithm; for AppleCollect the share of runs whose final
  policy reaches a 50 apple (final return ≥ 49) with a Wilson 95% interval, and the env step (and
  iteration) at which each run's evaluation first reached one;
- for runs with `--bias-every` (the learner's `bias.jsonl`): the Eq. 17 bias rate per point
  (mean over the live actors; points before the first update left out), per run its mean, mean
  absolute value and last value, then mean ± std over seeds, and the Fig. 3 curve (mean ± 1 std).

Across envs (when there are several), scores are range-normalised per env — (x − min)/(max − min)
over every finished run of that env — and the IQM uses a stratified bootstrap: seeds are resampled
within each env. Statistics (IQM, bootstrap, probability of improvement) are written with numpy
only, after Agarwal et al. 2021 ("Deep RL at the edge of the statistical precipice", rliable).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Optional

import numpy as np
import typer

from services.plot import _read_json, read_jsonl  # one reader of run files for plots and reports

LAST_N = 10


def _success_return() -> float:
    """AppleCollect: the least return of an episode that collects a 50 apple within the episode's
    step limit (50 − 0.01·100 = 49); a 10 apple gives at most 9.99, so a score at or above it means
    the policy reaches a 50 apple (in every evaluation episode: the env is deterministic)."""
    try:
        import gymnasium as gym

        import mam_core.envs  # noqa: F401
        from mam_core.envs.apple_collect import APPLE_VALUES, STEP_REWARD

        limit = gym.spec("AppleCollect-v0").max_episode_steps or 100
        return float(APPLE_VALUES.max() + STEP_REWARD * limit) - 1e-6  # float sums of −0.01
    except Exception:  # noqa: BLE001 - the report must work without the env package
        return 49.0 - 1e-6


SUCCESS_RETURN = _success_return()
AXES = ("transitions", "iterations")
CONFIDENCE = 0.95
N_BOOT = 2000
DPI = 120

# Which variant is compared with which (X, Y): P(X > Y).
BASELINES = (("ma-td3", "td3"), ("ma-ddpg", "ddpg"))
_FAMILY_ORDER = ("ma-td3", "td3", "ma-ddpg", "ddpg")


# --- statistics (pure numpy) -----------------------------------------------------------------


def _iqm_weights(n: int) -> np.ndarray:
    """Weights of the sorted observations for the mean of the middle 50%.

    Observation i covers [i, i+1) of [0, n); the middle half is [n/4, 3n/4), so when n is not a
    multiple of 4 the two boundary observations count fractionally (for n = 4m this is the
    25%-trimmed mean, as `scipy.stats.trim_mean(x, 0.25)` and rliable compute it).
    """
    if n < 1:
        raise ValueError("IQM of an empty sample")
    i = np.arange(n, dtype=float)
    w = np.clip(np.minimum(i + 1, 0.75 * n) - np.maximum(i, 0.25 * n), 0.0, 1.0)
    return w / w.sum()


def iqm(scores: Any, axis: int = -1) -> np.ndarray | float:
    """Interquartile mean: the mean of the middle 50% of `scores` along `axis`."""
    x = np.moveaxis(np.sort(np.asarray(scores, dtype=float), axis=axis), axis, -1)
    out = (x * _iqm_weights(x.shape[-1])).sum(axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def stratified_bootstrap(
    groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray], n_boot: int = N_BOOT, seed: int = 0,
) -> np.ndarray:
    """Bootstrap replicates of `statistic`, resampling within each stratum.

    `groups` is one or more lists of strata (one 1-D sample per env, e.g. the per-seed scores of
    one algorithm on each env). Every stratum of every group is resampled with replacement,
    independently and keeping its size. `statistic(*groups)` gets, per group, a list of arrays
    of shape (B, n_stratum) and must return shape (B,). Returns the `n_boot` replicates.
    """
    rng = np.random.default_rng(seed)
    resampled = []
    for strata in groups:
        arrays = [np.asarray(s, dtype=float) for s in strata]
        if not arrays or any(a.ndim != 1 or a.size == 0 for a in arrays):
            raise ValueError("every stratum must be a non-empty 1-D sample")
        resampled.append([a[rng.integers(0, a.size, size=(n_boot, a.size))] for a in arrays])
    return np.asarray(statistic(*resampled), dtype=float)


@dataclass(frozen=True)
class Interval:
    """A point estimate with a (lo, hi) confidence interval."""

    value: float
    lo: float
    hi: float

    def contains(self, x: float) -> bool:
        return self.lo <= x <= self.hi


def _point(groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray]) -> float:
    return float(np.asarray(statistic(*[[np.asarray(s, dtype=float)[None, :] for s in strata]
                                         for strata in groups]))[0])


def bootstrap_ci(
    groups: Sequence[Sequence[Any]], statistic: Callable[..., np.ndarray], n_boot: int = N_BOOT,
    confidence: float = CONFIDENCE, seed: int = 0,
) -> Interval:
    """Point estimate and percentile stratified-bootstrap CI of `statistic` (see stratified_bootstrap)."""
    reps = stratified_bootstrap(groups, statistic, n_boot, seed)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(reps, [alpha, 1.0 - alpha])
    return Interval(_point(groups, statistic), float(lo), float(hi))


def _pooled_iqm(strata: list[np.ndarray]) -> np.ndarray:
    return iqm(np.concatenate(strata, axis=-1), axis=-1)


def _pooled_mean(strata: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(strata, axis=-1).mean(axis=-1)


def iqm_ci(strata: Sequence[Any], n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0) -> Interval:
    """IQM of the scores of all strata pooled, with a stratified-bootstrap CI (one stratum per env)."""
    return bootstrap_ci([strata], _pooled_iqm, n_boot, confidence, seed)


def mean_ci(scores: Any, n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0) -> Interval:
    """Mean over seeds with a bootstrap CI (seeds resampled)."""
    return bootstrap_ci([[scores]], _pooled_mean, n_boot, confidence, seed)


def _poi_per_stratum(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of one env: mean over all pairs of 1[x > y] + ½·1[x = y]; shapes (B, n), (B, m)."""
    xx, yy = x[..., :, None], y[..., None, :]
    return ((xx > yy) + 0.5 * (xx == yy)).mean(axis=(-2, -1))


def probability_of_improvement(x_strata: Sequence[Any], y_strata: Sequence[Any]) -> float:
    """P(X > Y): per env, the chance a random run of X scores above a random run of Y (ties ½),
    averaged over envs. Strata are matched by position (one per env)."""
    return _point([x_strata, y_strata], _poi_stat)


def _poi_stat(xs: list[np.ndarray], ys: list[np.ndarray]) -> np.ndarray:
    if len(xs) != len(ys):
        raise ValueError("X and Y need the same envs")
    return np.mean([_poi_per_stratum(x, y) for x, y in zip(xs, ys)], axis=0)


def probability_of_improvement_ci(
    x_strata: Sequence[Any], y_strata: Sequence[Any], n_boot: int = N_BOOT, confidence: float = CONFIDENCE,
    seed: int = 0,
) -> Interval:
    """P(X > Y) with a stratified-bootstrap CI: the runs of X and of Y are resampled independently
    within each env."""
    return bootstrap_ci([x_strata, y_strata], _poi_stat, n_boot, confidence, seed)


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> Interval:
    """A share k/n with its Wilson score interval (sound for small n and k = 0 or n)."""
    if n <= 0:
        return Interval(math.nan, math.nan, math.nan)
    z = {0.95: 1.959963984540054, 0.9: 1.6448536269514722, 0.99: 2.5758293035489004}.get(round(confidence, 4))
    if z is None:
        from statistics import NormalDist

        z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return Interval(p, lo, hi)


# --- per-run scores --------------------------------------------------------------------------


def _finite(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def best_live_score(row: dict[str, Any]) -> float | None:
    """Score of one evaluation row: the best mean return over the actors evaluated (live) at that
    point; None when no actor was evaluated."""
    means = row.get("mean")
    values: list[float] = []
    if isinstance(means, list):
        values = [v for v in (_finite(m) for m in means) if v is not None]
    if not values and isinstance(row.get("returns"), list):  # older rows: only the episode returns
        for episodes in row["returns"]:
            if isinstance(episodes, list):
                eps = [v for v in (_finite(e) for e in episodes) if v is not None]
                if eps:
                    values.append(float(np.mean(eps)))
    return max(values) if values else None


def eval_points(rows: list[dict[str, Any]]) -> list[tuple[float, float]]:
    """(env_steps, best live score) of every evaluation row with a score, in file order."""
    out = []
    for row in rows:
        step, score = _finite(row.get("env_steps")), best_live_score(row)
        if step is not None and score is not None:
            out.append((step, score))
    return out


def eval_triples(rows: list[dict[str, Any]]) -> list[tuple[float, float | None, float]]:
    """(env_steps, iterations or None, best live score) of every evaluation row with a score."""
    out = []
    for row in rows:
        step, score = _finite(row.get("env_steps")), best_live_score(row)
        if step is not None and score is not None:
            out.append((step, _finite(row.get("iterations")), score))
    return out


def first_reach(triples: Sequence[tuple[float, float | None, float]], threshold: float,
                ) -> tuple[float, float | None] | None:
    """(env steps, iterations) of the first evaluation scoring >= threshold (None: never)."""
    for step, it, score in triples:
        if score >= threshold:
            return step, it
    return None


def bucket_points(points: Sequence[tuple[float, float]], spacing: float) -> dict[int, float]:
    """Evaluation points on the grid of `spacing`: step s goes to floor(s / spacing)·spacing,
    the last point of a grid cell (in file order) wins. Returns {grid step: score}, sorted."""
    if spacing <= 0:
        raise ValueError("spacing must be > 0")
    cells: dict[int, float] = {}
    for step, score in points:
        cells[int(round(math.floor(step / spacing) * spacing))] = score
    return dict(sorted(cells.items()))


def last_n_mean(points: Sequence[tuple[float, float]], spacing: float, n: int = LAST_N) -> float:
    """Mean score of the last `n` grid points of one run (NaN when it has none)."""
    cells = bucket_points(points, spacing)
    if not cells:
        return math.nan
    return float(np.mean(list(cells.values())[-n:]))


def aligned_curves(runs: Sequence[Sequence[tuple[float, float]]], spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Runs on a common grid: (grid steps, matrix runs × grid). A run holds its last value between
    its evaluations; NaN before its first and after its last grid point."""
    cells = [bucket_points(points, spacing) for points in runs]
    grid = np.asarray(sorted({s for c in cells for s in c}), dtype=float)
    matrix = np.full((len(runs), grid.size), np.nan)
    for r, c in enumerate(cells):
        if not c:
            continue
        first, last = min(c), max(c)
        value = math.nan
        for j, step in enumerate(grid):
            if step in c:
                value = c[int(step)]
            if first <= step <= last:
                matrix[r, j] = value
    return grid, matrix


@dataclass(frozen=True)
class MaxAverage:
    """The paper's 'max average return': max over grid points of the mean over seeds."""

    value: float
    std: float  # std over seeds at that point (the paper's ±)
    step: float


def max_average_return(grid: np.ndarray, matrix: np.ndarray) -> MaxAverage:
    """Over the grid points where every run has a value: the largest mean over runs."""
    if matrix.size == 0:
        return MaxAverage(math.nan, math.nan, math.nan)
    full = np.all(np.isfinite(matrix), axis=0)
    if not full.any():
        return MaxAverage(math.nan, math.nan, math.nan)
    means = matrix[:, full].mean(axis=0)
    j = int(np.argmax(means))
    column = matrix[:, full][:, j]
    return MaxAverage(float(means[j]), float(np.std(column)), float(grid[full][j]))


# --- run directories -------------------------------------------------------------------------


@dataclass
class RunRecord:
    """One finished run of an experiment."""

    env: str
    variant: str
    seed: int
    path: Path
    config: dict[str, Any]
    summary: dict[str, Any]
    points: list[tuple[float, float]]
    allocation: list[dict[str, Any]] = field(default_factory=list)
    bias: list[tuple[float, float]] = field(default_factory=list)  # (point, Eq. 17 rate) from bias.jsonl
    evals: list[tuple[float, float | None, float]] = field(default_factory=list)  # (env steps, iterations, score)
    record: dict[str, Any] = field(default_factory=dict)  # record.json (the commit it ran at), if any

    @property
    def key(self) -> str:
        """<env>/<variant>/seed<k>: the run's place in the grid (and in the ledger)."""
        return f"{_slug(self.env)}/{self.variant}/seed{self.seed}"

    @property
    def has_iterations(self) -> bool:
        return any(it is not None for _, it, _ in self.evals)

    def axis_points(self, axis: str = "transitions") -> list[tuple[float, float]]:
        """(x, score) on the x-axis `axis`: env transitions, or iterations (env transitions in
        the rows that carry no `iterations`, i.e. runs older than it)."""
        if axis == "transitions" or not self.evals:
            return self.points
        return [(step if it is None else it, score) for step, it, score in self.evals]

    def iterations_per_transition(self) -> float:
        """From the last evaluation row with both counts (1 without iterations)."""
        for step, it, _ in reversed(self.evals):
            if it is not None and step > 0:
                return it / step
        return 1.0

    @property
    def commit(self) -> str:
        from services.experiment import commit_label

        return commit_label(self.record)

    @property
    def algo_config(self) -> dict[str, Any]:
        algo = self.config.get("algo")
        return algo if isinstance(algo, dict) else {}

    @property
    def final_score(self) -> float | None:
        """Best live actor's return in the final evaluation (summary.json), else the last point."""
        finals = self.summary.get("final_returns")
        score = best_live_score({"mean": finals}) if isinstance(finals, list) else None
        if score is None and self.points:
            score = self.points[-1][1]
        return score

    @property
    def eventual_best(self) -> int | None:
        """The survivor, else the actor with the best final return (e.g. `--no-ot`)."""
        if isinstance(self.summary.get("survivor"), int):
            return self.summary["survivor"]
        finals = self.summary.get("final_returns")
        if isinstance(finals, list):
            vals = [(v, k) for k, v in enumerate(_finite(f) for f in finals) if v is not None]
            if vals:
                return max(vals)[1]
        return None


def load_run(path: Path, env: str | None = None, variant: str | None = None) -> RunRecord | None:
    """A finished run directory (None without summary.json)."""
    summary = _read_json(path / "summary.json")
    if not summary:
        return None
    config = _read_json(path / "config.json")
    algo = config.get("algo") if isinstance(config.get("algo"), dict) else {}
    seed = algo.get("seed")
    if not isinstance(seed, int):
        m = re.fullmatch(r"seed(\d+)", path.name)
        seed = int(m.group(1)) if m else 0
    rows = read_jsonl(path / "eval.jsonl")
    return RunRecord(
        env=env or str(config.get("env_id") or summary.get("env_id") or "?"),
        variant=variant or str(algo.get("algo") or summary.get("algo") or "?"),
        seed=seed, path=path, config=config, summary=summary,
        points=eval_points(rows), evals=eval_triples(rows),
        allocation=read_jsonl(path / "allocation.jsonl"),
        bias=bias_points(read_jsonl(path / "bias.jsonl")),
        record=_read_json(path / "record.json"))


def bias_points(rows: list[dict[str, Any]]) -> list[tuple[float, float]]:
    """(point, bias rate) per measurement of a run: the mean of Eq. 17 over the actors live at
    that point (after the elimination: the survivor's). Points with no finite rate are left out,
    and so are points before the first update (the critic is still its random initialisation)."""
    by_point: dict[float, list[float]] = {}
    for r in rows:
        if r.get("updates") == 0:
            continue
        point = _finite(r.get("point", r.get("env_steps")))
        rate = _finite(r["bias"].get("bias_rate")) if isinstance(r.get("bias"), dict) else None
        if point is not None and rate is not None:
            by_point.setdefault(point, []).append(rate)
    return [(p, float(np.mean(v))) for p, v in sorted(by_point.items())]


@dataclass
class BiasStats:
    """Eq. 17 bias rate of one variant over its runs (rows: runs, columns: bias points)."""

    variant: str
    points: np.ndarray
    rates: np.ndarray  # runs × points, NaN where a run has no measurement

    @property
    def n(self) -> int:
        return self.rates.shape[0]

    def per_run(self, reduce: Callable[[np.ndarray], float]) -> np.ndarray:
        return np.asarray([reduce(row[np.isfinite(row)]) if np.isfinite(row).any() else np.nan
                           for row in self.rates])


def bias_stats(variant: str, runs: Sequence[RunRecord], points: Sequence[float] | None = None) -> BiasStats | None:
    """`points`: only these (e.g. the points every run of the env measured), else every point."""
    measured = [r for r in runs if r.bias]
    if not measured:
        return None
    if points is None:
        points = sorted({p for r in measured for p, _ in r.bias})
    points = np.asarray(sorted(points), dtype=float)
    if not points.size:
        return None
    rates = np.full((len(measured), points.size), np.nan)
    for i, r in enumerate(measured):
        for p, rate in r.bias:
            j = np.searchsorted(points, p)
            if j < points.size and points[j] == p:
                rates[i, j] = rate
    return BiasStats(variant, points, rates)


def common_bias_points(runs: Sequence[RunRecord]) -> list[float]:
    """The bias points every measured run of an env has: the table compares like with like."""
    sets = [{p for p, _ in r.bias} for r in runs if r.bias]
    return sorted(set.intersection(*sets)) if sets else []


def load_runs(exp_dir: Path) -> list[RunRecord]:
    """Every finished run under a directory: <env>/<variant>/seed<k>/ directories with a summary.json,
    at any depth (EXP_DIR/<env>/..., a ledger DIR/<env>/..., docs/results/<exp>/runs/<env>/...);
    other layouts: any dir with a summary.json, env and algo read from its config. Hidden
    directories (a ledger record being written) and EXP_DIR/failures are left out."""
    exp_dir = Path(exp_dir)
    runs = []
    for summary in sorted(exp_dir.rglob("summary.json")):
        path = summary.parent
        rel = path.relative_to(exp_dir).parts
        if any(p.startswith(".") for p in rel) or (rel and rel[0] == "failures"):
            continue
        layout = len(rel) >= 3 and re.fullmatch(r"seed\d+", rel[-1]) is not None
        run = load_run(path, env=None, variant=rel[-2] if layout else None)
        if run is not None:
            runs.append(run)
    return runs


def manifest(root: Path) -> dict[str, Any]:
    """experiment.json of an experiment directory or ledger (ROOT, else ROOT/runs)."""
    root = Path(root)
    for path in (root / "experiment.json", root / "runs" / "experiment.json"):
        data = _read_json(path)
        if data:
            return data
    return {}


def collect_runs(root: Path) -> list[RunRecord]:
    """The finished runs of an experiment: those under ROOT and, when ROOT's experiment.json names a
    ledger, the ledger's records of runs ROOT does not have (the run directory wins when both do)."""
    runs = load_runs(root)
    ledger = manifest(root).get("ledger")
    if isinstance(ledger, str) and Path(ledger).is_dir() and Path(ledger).resolve() != Path(root).resolve():
        have = {r.key for r in runs}
        runs += [r for r in load_runs(Path(ledger)) if r.key not in have]
    return runs


def planned_runs(exp_dir: Path) -> list[str]:
    """Relative run paths that experiment.json planned (empty without it)."""
    plan = manifest(exp_dir).get("runs")
    return [r["path"] for r in plan if isinstance(r, dict) and isinstance(r.get("path"), str)] if isinstance(
        plan, list) else []


# --- the report ------------------------------------------------------------------------------


def variant_order(name: str, planned: Sequence[str] = ()) -> tuple:
    """Plan order when known; else MA-TD3, its variants, TD3, MA-DDPG, its variants, DDPG, others."""
    if name in planned:
        return (0, planned.index(name), name)
    for i, base in enumerate(_FAMILY_ORDER):
        if name == base:
            return (1, 2 * i, name)
        if name.startswith(base + "-"):
            return (1, 2 * i + 1, name)
    return (2, 0, name)


def env_spacing(runs: Sequence[RunRecord], axis: str = "transitions") -> float:
    """Grid spacing of one env on `axis`: the largest evaluation spacing of its runs (eval_every,
    in iterations: × the run's iterations per transition), else the median gap."""
    every = []
    for r in runs:
        e = r.algo_config.get("eval_every")
        if isinstance(e, (int, float)) and e > 0:
            every.append(float(e) * (r.iterations_per_transition() if axis == "iterations" else 1.0))
    if every:
        return max(every)
    pts = [r.axis_points(axis) for r in runs]
    gaps = [b[0] - a[0] for p in pts for a, b in zip(p, p[1:]) if b[0] > a[0]]
    return float(np.median(gaps)) if gaps else 1.0


@dataclass
class VariantStats:
    env: str
    variant: str
    runs: list[RunRecord]
    spacing: float
    last10: np.ndarray  # per run
    last10_mean: Interval
    last10_std: float
    iqm: Interval
    max_avg: MaxAverage
    grid: np.ndarray
    curves: np.ndarray  # runs × grid
    final: np.ndarray  # per run: best live actor's final return
    success: Interval | None  # AppleCollect: share of final returns >= SUCCESS_RETURN
    successes: int
    updates: float
    env_steps: float
    wall_time_s: float
    launcher_wall_time_s: float
    axis: str = "transitions"
    reached: list[tuple[float, float | None] | None] = field(default_factory=list)  # AppleCollect, per run
    curves_by_axis: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # axis -> (grid, curves)

    @property
    def n(self) -> int:
        return len(self.runs)

    @property
    def commits(self) -> dict[str, int]:
        """Commit label -> number of runs (record.json; "unknown" without one)."""
        out: dict[str, int] = {}
        for r in self.runs:
            out[r.commit] = out.get(r.commit, 0) + 1
        return out

    def wall_times(self) -> np.ndarray:
        """Per run: the launcher's wall time (start to end of the run), else the referee's."""
        vals = [_finite(r.summary.get("launcher_wall_time_s")) or _finite(r.summary.get("wall_time_s"))
                for r in self.runs]
        return np.asarray([v for v in vals if v is not None], dtype=float)

    def setting(self) -> str:
        a = self.runs[0].algo_config
        k, m = a.get("actors"), a.get("workers")
        eta = 0.0 if a.get("no_wt") or k == 1 else a.get("eta")
        text = f"K={k} M={m}"
        if k and k > 1:
            text += f" η={eta:g}" if isinstance(eta, (int, float)) else ""
            text += " no-OT" if a.get("no_ot") else ""
        return text


@dataclass(frozen=True)
class Comparison:
    x: str
    y: str
    env: str  # an env id, or "all envs"
    n_x: int
    n_y: int
    p: Interval


BETTER, WORSE, NOT_SEPARATED = "better", "worse", "not separated"
SINGLE_ACTOR_BASELINE = {"ma-td3": "td3", "ma-ddpg": "ddpg"}


def verdict_word(p: Interval) -> str:
    """*better* only where the 95% CI of P(MA > baseline) lies above ½, *worse* where it lies
    below, else *not separated* (also without a finite interval)."""
    if math.isfinite(p.lo) and p.lo > 0.5:
        return BETTER
    if math.isfinite(p.hi) and p.hi < 0.5:
        return WORSE
    return NOT_SEPARATED


@dataclass(frozen=True)
class Verdict:
    """One multi-actor variant against the single-actor baseline of its family, on one env."""

    env: str
    variant: str
    baseline: str
    n_x: int
    n_y: int
    p: Interval  # P(variant > baseline), last-10 scores
    iqm_x: Interval
    iqm_y: Interval
    wall_x: float  # mean wall-clock seconds per run
    wall_y: float
    commits: dict[str, int]  # over the runs of both rows

    @property
    def word(self) -> str:
        return verdict_word(self.p)

    @property
    def mixed(self) -> bool:
        return len(self.commits) > 1


def baseline_of(v: VariantStats, vs: Sequence[VariantStats]) -> VariantStats | None:
    """The K=1 run of the variant's family in the same env: TD3 for MA-TD3 variants, DDPG for
    MA-DDPG ones; the variant named like the algorithm first."""
    algo = v.runs[0].algo_config.get("algo")
    base = SINGLE_ACTOR_BASELINE.get(algo) if isinstance(algo, str) else None
    if base is None or (v.runs[0].algo_config.get("actors") or 1) <= 1:
        return None
    cands = [w for w in vs if w.runs[0].algo_config.get("algo") == base
             and (w.runs[0].algo_config.get("actors") or 1) == 1]
    cands.sort(key=lambda w: w.variant != base)
    return cands[0] if cands else None


def verdicts(envs: dict[str, list[VariantStats]], n_boot: int = N_BOOT, seed: int = 0) -> list[Verdict]:
    out = []
    for env, vs in envs.items():
        for v in vs:
            b = baseline_of(v, vs)
            if b is None:
                continue
            x, y = v.last10[np.isfinite(v.last10)], b.last10[np.isfinite(b.last10)]
            if not x.size or not y.size:
                continue
            commits = dict(v.commits)
            for c, n in b.commits.items():
                commits[c] = commits.get(c, 0) + n
            wx, wy = v.wall_times(), b.wall_times()
            out.append(Verdict(env, v.variant, b.variant, x.size, y.size,
                               probability_of_improvement_ci([x], [y], n_boot, seed=seed), v.iqm, b.iqm,
                               float(wx.mean()) if wx.size else math.nan, float(wy.mean()) if wy.size else math.nan,
                               commits))
    return out


@dataclass
class Report:
    exp_dir: Path
    envs: dict[str, list[VariantStats]]
    bias: dict[str, list[BiasStats]]
    comparisons: list[Comparison]
    aggregate: list[tuple[str, int, Interval]]  # variant, n envs, normalised IQM
    missing: list[str]
    meta: dict[str, Any]
    axis: str = "transitions"
    verdicts: list[Verdict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # e.g. runs of one row at different commits
    axes: tuple[str, ...] = ("transitions",)  # the learning curves drawn


def _mean_of(runs: Sequence[RunRecord], key: str) -> float:
    vals = [_finite(r.summary.get(key)) for r in runs]
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else math.nan


def is_apple_collect(env: str) -> bool:
    return env.lower().startswith("applecollect")


def variant_stats(env: str, variant: str, runs: list[RunRecord], spacing: float, n_boot: int = N_BOOT,
                  seed: int = 0, axis: str = "transitions",
                  spacings: dict[str, float] | None = None) -> VariantStats:
    """Statistics of one variant on `axis` (its grid `spacing`); `spacings` (axis -> spacing) adds
    the learning curves on those axes too."""
    runs = sorted(runs, key=lambda r: r.seed)
    points = [r.axis_points(axis) for r in runs]
    last10 = np.asarray([last_n_mean(p, spacing) for p in points])
    scored = last10[np.isfinite(last10)]
    grid, curves = aligned_curves(points, spacing)
    by_axis = {axis: (grid, curves)}
    for other, sp in (spacings or {}).items():
        if other not in by_axis:
            by_axis[other] = aligned_curves([r.axis_points(other) for r in runs], sp)
    final = np.asarray([np.nan if r.final_score is None else r.final_score for r in runs])
    successes, success = 0, None
    reached: list[tuple[float, float | None] | None] = []
    if is_apple_collect(env):
        successes = int(np.sum(final >= SUCCESS_RETURN))
        success = wilson_interval(successes, len(runs))
        reached = [first_reach(r.evals, SUCCESS_RETURN) for r in runs]
    nan = Interval(math.nan, math.nan, math.nan)
    return VariantStats(
        env=env, variant=variant, runs=runs, spacing=spacing, last10=last10,
        last10_mean=mean_ci(scored, n_boot, seed=seed) if scored.size else nan,
        last10_std=float(np.std(scored)) if scored.size else math.nan,
        iqm=iqm_ci([scored], n_boot, seed=seed) if scored.size else nan,
        max_avg=max_average_return(grid, curves), grid=grid, curves=curves, final=final,
        success=success, successes=successes,
        updates=_mean_of(runs, "updates"), env_steps=_mean_of(runs, "env_steps"),
        wall_time_s=_mean_of(runs, "wall_time_s"), launcher_wall_time_s=_mean_of(runs, "launcher_wall_time_s"),
        axis=axis, reached=reached, curves_by_axis=by_axis)


def comparison_pairs(variants: Sequence[str]) -> list[tuple[str, str]]:
    """(X, Y) pairs for P(X > Y): MA vs single-actor baseline, and the full method vs each of its
    ablation / η variants (named `<base>-...`)."""
    present = set(variants)
    pairs = [(x, y) for x, y in BASELINES if x in present and y in present]
    for base in ("ma-td3", "ma-ddpg"):
        if base in present:
            pairs += [(base, v) for v in variants if v.startswith(base + "-")]
    return pairs


def build_report(exp_dir: Path, n_boot: int = N_BOOT, seed: int = 0, axis: str = "transitions") -> Report:
    """All statistics of an experiment directory, a ledger, or a folder holding the ledger in runs/
    (no files written, nothing rerun). Tables on the x-axis `axis` (transitions or iterations)."""
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}")
    exp_dir = Path(exp_dir)
    runs = collect_runs(exp_dir)
    planned = planned_runs(exp_dir)
    plan_variants: list[str] = []
    for p in planned:
        parts = Path(p).parts
        if len(parts) == 3 and parts[1] not in plan_variants:
            plan_variants.append(parts[1])
    done = {r.key for r in runs}
    missing = [p for p in planned if p not in done]
    axes = AXES if any(r.has_iterations for r in runs) else ("transitions",)
    if axis not in axes:
        axes = (*axes, axis)

    by_env: dict[str, dict[str, list[RunRecord]]] = {}
    for r in runs:
        by_env.setdefault(r.env, {}).setdefault(r.variant, []).append(r)
    envs: dict[str, list[VariantStats]] = {}
    notes: list[str] = []
    for env in sorted(by_env):
        env_runs = [r for rs in by_env[env].values() for r in rs]
        spacings = {a: env_spacing(env_runs, a) for a in axes}
        names = sorted(by_env[env], key=lambda v: variant_order(v, plan_variants))
        envs[env] = [variant_stats(env, v, by_env[env][v], spacings[axis], n_boot, seed, axis, spacings)
                     for v in names]
        for v in envs[env]:
            if len(v.commits) > 1:
                notes.append(f"{env} / {v.variant}: runs at different commits: "
                             + ", ".join(f"{c} ({n})" for c, n in sorted(v.commits.items())))
        if axis == "iterations":
            old = sum(not r.has_iterations for r in env_runs)
            if old:
                notes.append(f"{env}: {old} run(s) without `iterations` in eval.jsonl (older code): their env "
                             "transitions stand in for iterations")

    comparisons: list[Comparison] = []
    all_variants = sorted({v.variant for vs in envs.values() for v in vs},
                          key=lambda v: variant_order(v, plan_variants))
    for x, y in comparison_pairs(all_variants):
        strata_x, strata_y = [], []
        for env, vs in envs.items():
            sx = {v.variant: v.last10[np.isfinite(v.last10)] for v in vs}
            if sx.get(x) is not None and sx.get(y) is not None and sx[x].size and sx[y].size:
                p = probability_of_improvement_ci([sx[x]], [sx[y]], n_boot, seed=seed)
                comparisons.append(Comparison(x, y, env, sx[x].size, sx[y].size, p))
                strata_x.append(sx[x])
                strata_y.append(sx[y])
        if len(strata_x) > 1:
            p = probability_of_improvement_ci(strata_x, strata_y, n_boot, seed=seed)
            comparisons.append(Comparison(x, y, f"all {len(strata_x)} envs", sum(map(len, strata_x)),
                                          sum(map(len, strata_y)), p))

    aggregate: list[tuple[str, int, Interval]] = []
    if len(envs) > 1:
        ranges = {}
        for env, vs in envs.items():
            allv = np.concatenate([v.last10[np.isfinite(v.last10)] for v in vs])
            if allv.size and allv.max() > allv.min():
                ranges[env] = (float(allv.min()), float(allv.max()))
        for name in all_variants:
            strata = []
            for env, (lo, hi) in ranges.items():
                v = next((v for v in envs[env] if v.variant == name), None)
                if v is not None and np.isfinite(v.last10).any():
                    strata.append((v.last10[np.isfinite(v.last10)] - lo) / (hi - lo))
            if len(strata) > 1:
                aggregate.append((name, len(strata), iqm_ci(strata, n_boot, seed=seed)))
    bias = {}
    for env, vs in envs.items():
        common = common_bias_points([r for v in vs for r in v.runs])
        bias[env] = [b for b in (bias_stats(v.variant, v.runs, common) for v in vs) if b is not None]
    bias = {env: bs for env, bs in bias.items() if bs}
    meta = manifest(exp_dir)
    return Report(exp_dir, envs, bias, comparisons, aggregate, missing, meta, axis=axis,
                  verdicts=verdicts(envs, n_boot, seed), notes=notes, axes=axes)


# --- rendering -------------------------------------------------------------------------------


def _fmt(x: float, digits: int | None = None) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    if digits is None:
        digits = 0 if abs(x) >= 1000 else 1 if abs(x) >= 100 else 2
    return f"{x:,.{digits}f}"


def _ci(i: Interval, digits: int | None = None) -> str:
    return f"[{_fmt(i.lo, digits)}, {_fmt(i.hi, digits)}]"


TABLE_HEADER = ("variant", "setting", "runs", "last-10 mean ± std", "95% CI", "IQM [95% CI]",
                "max avg return ± std (@ step)", "updates", "env steps", "wall s (run)", "wall s (launcher)")


def env_rows(vs: Sequence[VariantStats]) -> tuple[list[str], list[list[str]]]:
    header = list(TABLE_HEADER)
    apple = any(v.success is not None for v in vs)
    if apple:
        header.append(f"final ≥ {SUCCESS_RETURN:.2f} (50 apple) [95% CI]")
    rows = []
    for v in vs:
        row = [v.variant, v.setting(), str(v.n),
               f"{_fmt(v.last10_mean.value)} ± {_fmt(v.last10_std)}", _ci(v.last10_mean),
               f"{_fmt(v.iqm.value)} {_ci(v.iqm)}",
               f"{_fmt(v.max_avg.value)} ± {_fmt(v.max_avg.std)} (@ {_fmt(v.max_avg.step, 0)})",
               _fmt(v.updates, 0), _fmt(v.env_steps, 0), _fmt(v.wall_time_s, 0), _fmt(v.launcher_wall_time_s, 0)]
        if apple:
            s = v.success
            row.append(f"{v.successes}/{v.n} ({_fmt(100 * s.value, 0)}%) "
                       f"[{_fmt(100 * s.lo, 0)}%, {_fmt(100 * s.hi, 0)}%]" if s else "–")
        rows.append(row)
    return header, rows


AXIS_TEXT = {"transitions": "env transitions (received by the learner, all slots together)",
             "iterations": "iterations (Algorithm 1's loop count; env transitions for runs without it)"}


def _wall(v: float) -> str:
    return "–" if not math.isfinite(v) else f"{v:,.0f}"


def verdict_rows(vd: Sequence[Verdict]) -> tuple[list[str], list[list[str]]]:
    header = ["env", "variant", "vs", "runs", "P(variant > baseline) [95% CI]", "IQM variant [95% CI]",
              "IQM baseline [95% CI]", "wall s/run variant / baseline", "verdict", "commit"]
    rows = []
    for v in vd:
        commit = (next(iter(v.commits)) if not v.mixed else
                  "**different commits**: " + ", ".join(f"{c} ({n})" for c, n in sorted(v.commits.items())))
        ratio = v.wall_x / v.wall_y if math.isfinite(v.wall_x) and math.isfinite(v.wall_y) and v.wall_y > 0 else None
        rows.append([v.env, v.variant, v.baseline, f"{v.n_x} / {v.n_y}", f"{_fmt(v.p.value, 2)} {_ci(v.p, 2)}",
                     f"{_fmt(v.iqm_x.value)} {_ci(v.iqm_x)}", f"{_fmt(v.iqm_y.value)} {_ci(v.iqm_y)}",
                     f"{_wall(v.wall_x)} / {_wall(v.wall_y)}" + (f" (×{ratio:.2f})" if ratio else ""),
                     f"*{v.word}*", commit])
    return header, rows


def _steps_text(values: Sequence[float]) -> str:
    return ", ".join(_fmt(x, 0) for x in values)


def reach_rows(vs: Sequence[VariantStats]) -> tuple[list[str], list[list[str]]]:
    """AppleCollect: share of runs whose final policy reaches a 50 apple, and when each run's
    evaluation first reached one (env transitions, iterations)."""
    header = ["variant", "final policy reaches a 50 apple [Wilson 95% CI]", "runs whose evaluation reached it",
              "first reached at env transitions (median; per run)", "first reached at iterations (median)"]
    rows = []
    for v in vs:
        if v.success is None:
            continue
        s = v.success
        hit = [r for r in v.reached if r is not None]
        steps = sorted(r[0] for r in hit)
        its = sorted(r[1] for r in hit if r[1] is not None)
        rows.append([v.variant,
                     f"{v.successes}/{v.n} ({_fmt(100 * s.value, 0)}%) [{_fmt(100 * s.lo, 0)}%, {_fmt(100 * s.hi, 0)}%]",
                     f"{len(hit)}/{v.n}",
                     f"{_fmt(float(np.median(steps)), 0)}; {_steps_text(steps)}" if steps else "–",
                     _fmt(float(np.median(its)), 0) if its else "–"])
    return header, rows


def bias_rows(bs: Sequence[BiasStats]) -> tuple[list[str], list[list[str]]]:
    header = ["variant", "runs", "points", "mean bias rate ± std", "mean |bias rate| ± std", "final bias rate ± std"]
    rows = []
    for b in bs:
        cells = [b.per_run(np.mean), b.per_run(lambda x: np.mean(np.abs(x))), b.per_run(lambda x: x[-1])]
        text = [f"{_fmt(float(np.nanmean(c)), 3)} ± {_fmt(float(np.nanstd(c)), 3)}" for c in cells]
        rows.append([b.variant, str(b.n), str(b.points.size), *text])
    return header, rows


def comparison_rows(comparisons: Sequence[Comparison]) -> tuple[list[str], list[list[str]]]:
    header = ["P(X > Y)", "env", "runs X / Y", "estimate", "95% CI"]
    rows = [[f"P({c.x} > {c.y})", c.env, f"{c.n_x} / {c.n_y}", _fmt(c.p.value, 2), _ci(c.p, 2)]
            for c in comparisons]
    return header, rows


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    esc = lambda s: str(s).replace("|", "\\|")  # noqa: E731
    lines = ["| " + " | ".join(esc(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text)


def render_markdown(report: Report, figures: dict[str, list[Path]], out: Path) -> str:
    """The report as Markdown; `figures` maps env (or "all") to PNG paths, linked relative to `out`."""
    lines = [f"# Experiment report: {report.meta.get('name') or report.exp_dir.name}", ""]
    n_runs = sum(v.n for vs in report.envs.values() for v in vs)
    lines.append(f"Experiment directory `{report.exp_dir}`: {n_runs} finished runs.")
    grid = report.meta.get("grid") or {}
    if grid:
        lines.append(f"Grid: envs {grid.get('envs')}, algos {grid.get('algos')}, seeds {grid.get('seeds')}, "
                     f"budget {_fmt(grid.get('steps') or math.nan, 0)} env transitions per run "
                     f"(all slots together, the same for every algorithm).")
    versions = report.meta.get("versions") or {}
    if versions:
        lines.append("Versions: " + ", ".join(f"{k} {v}" for k, v in sorted(versions.items())) + ".")
    if report.missing:
        lines += ["", f"**Incomplete: {len(report.missing)} planned run(s) not finished** "
                      f"(resume with the same `mam experiment` command): "
                      + ", ".join(f"`{m}`" for m in report.missing[:20])
                      + (" …" if len(report.missing) > 20 else "")]
    if report.verdicts:
        header, rows = verdict_rows(report.verdicts)
        lines += ["", "## Verdict", "",
                  "Each multi-actor variant against the K=1 baseline of its family in the same grid (TD3 for "
                  "MA-TD3, DDPG for MA-DDPG): P(variant > baseline) of the per-run last-10 scores with a bootstrap "
                  "95% CI, the IQM of those scores with 95% CIs, and the mean wall-clock time per run. *better* only "
                  "where the CI's lower bound is above 0.5, *worse* where its upper bound is below 0.5, else *not "
                  f"separated*. Last-10 scores on the {report.axis} axis.", "", _md_table(header, rows)]
    if report.notes:
        lines += ["", "**Notes:**", ""] + [f"- {n}" for n in report.notes]
    lines += ["", f"Tables on the x-axis: **{AXIS_TEXT.get(report.axis, report.axis)}**; learning curves on "
              + " and on ".join(report.axes) + ".",
              "", "Score of an evaluation = mean return of the best live actor (the survivor after the "
              "elimination). *last-10 mean*: per run the mean of its last 10 evaluations, then mean ± std over "
              "seeds and a bootstrap 95% CI; *IQM*: interquartile mean of the per-run last-10 scores "
              f"(bootstrap 95% CI, {N_BOOT if not report.meta.get('n_boot') else report.meta['n_boot']} "
              "resamples); *max avg return*: the paper's Table 4 statistic, max over evaluation points of the "
              "mean over seeds, ± std over seeds at that point."]
    for env, vs in report.envs.items():
        header, rows = env_rows(vs)
        unit = "env steps" if report.axis == "transitions" else report.axis
        lines += ["", f"## {env}", "", f"Evaluation grid spacing: {_fmt(vs[0].spacing, 0)} {unit} (x-axis: "
                  f"{report.axis}); wall s: mean wall-clock seconds per run (the referee's, and the launcher's from "
                  "start to end).", "", _md_table(header, rows)]
        if any(v.success is not None for v in vs):
            header, rows = reach_rows(vs)
            lines += ["", f"A final return ≥ {SUCCESS_RETURN:.2f} means the final policy reaches a 50 apple (a 50 "
                      "apple within the 100-step limit returns at least 50 − 0.01·100 = 49; a 10 apple at most "
                      "9.99).", "", _md_table(header, rows)]
        for path in figures.get(env, []):
            lines += ["", f"![{path.stem}]({_rel(path, out)})"]
        if report.bias.get(env):
            header, rows = bias_rows(report.bias[env])
            lines += ["", f"### Estimation bias (Eq. 17), {env}", "",
                      "Bias rate (Q̂ − Q*)/|Q*| of the critic at the start states against the Monte-Carlo discounted "
                      "return of the current policy, measured by the learner every `--bias-every` transitions (mean "
                      "over the live actors), at the points every run of the env measured (before the first update "
                      "left out); per run the mean (and mean absolute value) over those points and its last one, then "
                      "mean ± std over seeds. > 0: over-estimation.", "", _md_table(header, rows)]
            for path in figures.get(f"bias:{env}", []):
                lines += ["", f"![{path.stem}]({_rel(path, out)})"]
    if report.comparisons:
        header, rows = comparison_rows(report.comparisons)
        lines += ["", "## Probability of improvement", "",
                  "P(X > Y): the chance that a run of X has a higher last-10 score than a run of Y (ties count ½), "
                  "averaged over envs; 95% CI from a stratified bootstrap (runs of X and Y resampled "
                  "independently within each env).", "", _md_table(header, rows)]
    if report.aggregate:
        rows = [[name, str(n), _fmt(i.value, 3), _ci(i, 3)] for name, n, i in report.aggregate]
        lines += ["", "## Aggregate over envs", "",
                  "IQM of range-normalised last-10 scores ((x − min)/(max − min) over all finished runs of each "
                  "env), 95% CI from a stratified bootstrap (seeds resampled within each env).", "",
                  _md_table(["variant", "envs", "normalised IQM", "95% CI"], rows)]
    for path in figures.get("all", []):
        lines += ["", f"![{path.stem}]({_rel(path, out)})"]
    return "\n".join(lines) + "\n"


def _rel(path: Path, out: Path) -> str:
    try:
        return str(path.resolve().relative_to(out.resolve().parent))
    except ValueError:
        return str(path)


def _rich_table(title: str, header: Sequence[str], rows: Sequence[Sequence[str]], fold: bool = False) -> Any:
    from rich.table import Table

    table = Table(title=title)
    for h in header:
        table.add_column(h, overflow="fold" if fold else "ellipsis")
    for row in rows:
        table.add_row(*row)
    return table


def print_tables(report: Report, console: Any) -> None:
    if report.verdicts:
        console.print(_rich_table(f"Verdict (last-10 scores, x-axis {report.axis})", *verdict_rows(report.verdicts),
                                  fold=True))
    for note in report.notes:
        console.print(f"[yellow]note[/]: {note}")
    for env, vs in report.envs.items():
        console.print(_rich_table(f"{env} (x-axis {report.axis})", *env_rows(vs), fold=True))
        if any(v.success is not None for v in vs):
            console.print(_rich_table(f"{env}: 50 apple", *reach_rows(vs), fold=True))
    for env, bs in report.bias.items():
        console.print(_rich_table(f"Estimation bias (Eq. 17), {env}", *bias_rows(bs)))
    if report.comparisons:
        console.print(_rich_table("Probability of improvement (last-10 scores)", *comparison_rows(report.comparisons)))
    if report.aggregate:
        rows = [[name, str(n), _fmt(i.value, 3), _ci(i, 3)] for name, n, i in report.aggregate]
        console.print(_rich_table("Aggregate over envs: IQM of range-normalised scores",
                                  ("variant", "envs", "normalised IQM", "95% CI"), rows))
    if report.missing:
        console.print(f"[yellow]{len(report.missing)} planned run(s) not finished[/]")


# --- figures (matplotlib object API, Agg) ----------------------------------------------------


def _figure(**kw: Any):
    from matplotlib.figure import Figure

    return Figure(layout="constrained", **kw)


def _save(fig: Any, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path


def _label_steps_axes(ax: Any, ylabel: str, title: str, axis: str = "transitions") -> None:
    """Labels, grid and legend of a plot over env steps (or iterations)."""
    ax.set_xlabel("env steps (transitions received by the learner)" if axis == "transitions"
                  else "iterations (env transitions where a run does not record them)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def curve_band(curves: np.ndarray, n_boot: int = N_BOOT, confidence: float = CONFIDENCE, seed: int = 0,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over runs at each grid point and a bootstrap CI band (runs resampled; NaN where a run
    has no value is skipped)."""
    mean = np.full(curves.shape[1], np.nan)
    lo, hi = mean.copy(), mean.copy()
    rng = np.random.default_rng(seed)
    alpha = (1 - confidence) / 2
    for j in range(curves.shape[1]):
        col = curves[:, j][np.isfinite(curves[:, j])]
        if col.size == 0:
            continue
        mean[j] = col.mean()
        reps = col[rng.integers(0, col.size, size=(n_boot, col.size))].mean(axis=1)
        lo[j], hi[j] = np.quantile(reps, [alpha, 1 - alpha])
    return mean, lo, hi


def plot_env_curves(env: str, vs: Sequence[VariantStats], path: Path, n_boot: int = 1000, seed: int = 0,
                    axis: str = "transitions") -> Path | None:
    """Mean best-live-actor return over seeds per variant on `axis`, with a bootstrap 95% CI band;
    the legend gives each variant's mean wall-clock time per run."""
    curves = [(v, *v.curves_by_axis.get(axis, (v.grid, v.curves))) for v in vs]
    if not any(grid.size for _, grid, _ in curves):
        return None
    fig = _figure(figsize=(8.5, 5))
    ax = fig.add_subplot()
    for i, (v, grid, matrix) in enumerate(curves):
        if not grid.size:
            continue
        mean, lo, hi = curve_band(matrix, n_boot, seed=seed)
        color = f"C{i % 10}"
        wall = v.wall_times()
        wall_text = f", {wall.mean():,.0f} s/run" if wall.size else ""
        ax.plot(grid, mean, color=color, linewidth=1.8, marker="o", markersize=2.5,
                label=f"{v.variant} (n={v.n}{wall_text})")
        ax.fill_between(grid, lo, hi, color=color, alpha=0.18, linewidth=0)
        c = v.runs[0].algo_config.get("eliminate_at")
        k = v.runs[0].algo_config.get("actors") or 1
        if isinstance(c, (int, float)) and axis == "iterations":
            c = c * v.runs[0].iterations_per_transition()
        if k > 1 and not v.runs[0].algo_config.get("no_ot") and isinstance(c, (int, float)) and 0 < c <= grid[-1]:
            ax.axvline(c, color=color, linestyle=":", linewidth=1.0)
    if is_apple_collect(env):
        ax.axhline(SUCCESS_RETURN, color="0.5", linestyle="--", linewidth=0.8, label=f"return {SUCCESS_RETURN:.2f}")
    _label_steps_axes(ax, "evaluation return (best live actor)",
                      f"{env}: mean over seeds, 95% bootstrap CI (dotted: elimination C)", axis)
    return _save(fig, path)


def allocation_share(run: RunRecord, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Share of the slots I_k/ΣI and probability P_k of the run's eventual best actor over `steps`
    (held from each allocation row to the next; NaN before the first)."""
    best = run.eventual_best
    share = np.full(steps.size, np.nan)
    prob = share.copy()
    rows = [r for r in run.allocation if _finite(r.get("env_steps")) is not None]
    if best is None or not rows:
        return share, prob
    xs = np.asarray([float(r["env_steps"]) for r in rows])
    s_vals, p_vals = [], []
    for r in rows:
        counts = r.get("counts") if isinstance(r.get("counts"), list) else []
        total = sum(c for c in counts if isinstance(c, (int, float)))
        s_vals.append(counts[best] / total if total and best < len(counts) else np.nan)
        probs = r.get("probabilities") if isinstance(r.get("probabilities"), list) else []
        p_vals.append(_finite(probs[best]) if best < len(probs) and _finite(probs[best]) is not None else np.nan)
    idx = np.searchsorted(xs, steps, side="right") - 1
    ok = idx >= 0
    share[ok] = np.asarray(s_vals)[idx[ok]]
    prob[ok] = np.asarray(p_vals)[idx[ok]]
    return share, prob


def plot_env_allocation(env: str, vs: Sequence[VariantStats], path: Path) -> Path | None:
    """Per multi-actor variant: the share of slots and P of the eventual survivor over env steps
    (thin lines: seeds, thick: mean)."""
    multi = [v for v in vs if (v.runs[0].algo_config.get("actors") or 1) > 1 and any(r.allocation for r in v.runs)]
    if not multi:
        return None
    fig = _figure(figsize=(max(7.5, 4.2 * len(multi) + 1), 6))
    axes = fig.subplots(2, len(multi), sharex=True, sharey="row", squeeze=False)
    for col, v in enumerate(multi):
        last = max(max((float(r.get("env_steps") or 0) for r in run.allocation), default=0.0) for run in v.runs)
        last = max(last, v.env_steps if math.isfinite(v.env_steps) else 0.0)
        steps = np.linspace(0, last, 300)
        shares, probs = zip(*(allocation_share(r, steps) for r in v.runs))
        for ax, data, label in ((axes[0, col], np.asarray(shares), "slot share of the survivor $I_s/M$"),
                                (axes[1, col], np.asarray(probs), "$P_s$ of the survivor (Eq. 8)")):
            for row in data:
                ax.step(steps, row, where="post", color="0.6", linewidth=0.6, alpha=0.7)
            seen = np.isfinite(data).sum(axis=0)
            mean = np.where(seen > 0, np.nansum(data, axis=0) / np.maximum(seen, 1), np.nan)
            ax.step(steps, mean, where="post", color=f"C{col % 10}", linewidth=2.0, label="mean over seeds")
            k = v.runs[0].algo_config.get("actors") or 1
            ax.axhline(1.0 / k, color="0.3", linestyle=":", linewidth=0.8, label="uniform 1/K")
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
            if col == 0:
                ax.set_ylabel(label)
        axes[0, col].set_title(f"{v.variant} ({v.setting()}, n={v.n})", fontsize="medium")
        axes[1, col].set_xlabel("env steps")
    axes[0, 0].legend(loc="lower right", fontsize="small")
    fig.suptitle(f"{env}: allocation to the eventual survivor (thin: seeds)")
    return _save(fig, path)


def plot_bias(env: str, bs: Sequence[BiasStats], path: Path) -> Path | None:
    """Fig. 3: the Eq. 17 bias rate over env steps per variant, mean over seeds ± one std."""
    if not bs:
        return None
    fig = _figure(figsize=(8.5, 5))
    ax = fig.add_subplot()
    for i, b in enumerate(bs):
        seen = np.isfinite(b.rates).sum(axis=0)
        ok = seen > 0
        filled = np.where(np.isfinite(b.rates), b.rates, 0.0)
        mean = filled.sum(axis=0)[ok] / seen[ok]
        std = np.sqrt(np.maximum((filled ** 2).sum(axis=0)[ok] / seen[ok] - mean ** 2, 0.0))
        color = f"C{i % 10}"
        ax.plot(b.points[ok], mean, color=color, linewidth=1.8, marker="o", markersize=2.5,
                label=f"{b.variant} (n={b.n})")
        ax.fill_between(b.points[ok], mean - std, mean + std, color=color, alpha=0.18, linewidth=0)
    ax.axhline(0.0, color="0.3", linewidth=0.8)
    _label_steps_axes(ax, "bias rate $(\\hat Q - Q^*)/|Q^*|$ (Eq. 17)", f"{env}: estimation bias, mean over seeds ± 1 std")
    return _save(fig, path)


def plot_iqm(report: Report, path: Path) -> Path | None:
    """IQM of the last-10 scores with 95% CIs, one panel per env (+ the normalised aggregate)."""
    panels = [(env, [(v.variant, v.iqm) for v in vs]) for env, vs in report.envs.items()]
    if report.aggregate:
        panels.append(("all envs (normalised)", [(n, i) for n, _, i in report.aggregate]))
    panels = [(t, [(n, i) for n, i in items if math.isfinite(i.value)]) for t, items in panels]
    panels = [p for p in panels if p[1]]
    if not panels:
        return None
    cols = min(len(panels), 4)
    rows = math.ceil(len(panels) / cols)
    height = max(2.0, 0.4 * max(len(items) for _, items in panels) + 1.2)
    fig = _figure(figsize=(max(7.0, 4.2 * cols), height * rows + 0.4))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax, (title, items) in zip(axes.flat, panels):
        y = np.arange(len(items))[::-1]
        for yy, (name, i) in zip(y, items):
            ax.errorbar(i.value, yy, xerr=[[i.value - i.lo], [i.hi - i.value]], fmt="o", capsize=3)
        ax.set_yticks(y, [n for n, _ in items])
        ax.set_title(title, fontsize="medium")
        ax.grid(alpha=0.3, axis="x")
    fig.suptitle("IQM of the last-10 scores, 95% bootstrap CI")
    return _save(fig, path)


def write_report(exp_dir: Path, out: Path | None = None, n_boot: int = N_BOOT, seed: int = 0,
                 figures: bool = True, axis: str = "transitions") -> tuple[Report, Path, list[Path]]:
    """Build the report, write the Markdown file and the PNGs; returns (report, markdown, PNGs)."""
    exp_dir = Path(exp_dir)
    out = Path(out) if out is not None else exp_dir / "report.md"
    report = build_report(exp_dir, n_boot=n_boot, seed=seed, axis=axis)
    report.meta = {**report.meta, "n_boot": n_boot}
    fig_dir = out.parent / "figures"
    written: dict[str, list[Path]] = {}
    if figures:
        for env, vs in report.envs.items():
            curves = [plot_env_curves(env, vs, fig_dir / f"curves_{_slug(env)}{'' if a == 'transitions' else '_' + a}"
                                                         f".png", seed=seed, axis=a) for a in report.axes]
            for p in (*curves, plot_env_allocation(env, vs, fig_dir / f"allocation_{_slug(env)}.png")):
                if p is not None:
                    written.setdefault(env, []).append(p)
        for env, bs in report.bias.items():
            p = plot_bias(env, bs, fig_dir / f"bias_{_slug(env)}.png")
            if p is not None:
                written.setdefault(f"bias:{env}", []).append(p)
        p = plot_iqm(report, fig_dir / "iqm.png")
        if p is not None:
            written.setdefault("all", []).append(p)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(render_markdown(report, written, out), encoding="utf-8")
    tmp.replace(out)
    return report, out, [p for ps in written.values() for p in ps]


# --- command ---------------------------------------------------------------------------------


def report_command(
    exp_dir: Annotated[Path, typer.Argument(
        help="experiment directory written by `mam experiment` (its ledger's records count too), a ledger "
             "directory, or a folder with the ledger in runs/ (docs/results/<exp>)")],
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="Markdown file to write (default EXP_DIR/report.md); PNGs go to its folder's figures/")] = None,
    n_boot: Annotated[int, typer.Option("--n-boot", help="bootstrap resamples for the 95% CIs")] = N_BOOT,
    seed: Annotated[int, typer.Option("--seed", help="seed of the bootstrap")] = 0,
    no_figures: Annotated[bool, typer.Option("--no-figures", help="tables only, no PNGs")] = False,
    x: Annotated[str, typer.Option("--x", help="x-axis of the tables: transitions (env transitions) or "
                                              "iterations (Algorithm 1's count; transitions for older runs)")
                 ] = "transitions",
) -> None:
    """Tables (last-10 mean, IQM and P(improvement) with 95% CIs, Table 4's max average return,
    updates, wall time, Eq. 17 bias) and figures (learning curves with CI bands, allocation, bias) of an experiment."""
    from rich.console import Console

    console = Console()
    if not Path(exp_dir).is_dir():
        raise typer.BadParameter(f"{exp_dir} is not a directory")
    if n_boot < 100:
        raise typer.BadParameter("--n-boot must be at least 100")
    if x not in AXES:
        raise typer.BadParameter(f"--x must be one of {', '.join(AXES)}")
    report, md, pngs = write_report(exp_dir, out, n_boot=n_boot, seed=seed, figures=not no_figures, axis=x)
    if not report.envs:
        console.print(f"[yellow]no finished runs under {exp_dir}[/]")
    print_tables(report, console)
    console.print(f"[green]wrote[/] {md}")
    for p in pngs:
        console.print(f"[green]wrote[/] {p}")


if __name__ == "__main__":
    typer.run(report_command)
