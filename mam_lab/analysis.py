"""The statistics of an experiment (`build_report`): per env and variant the last-10 mean, IQM,
max average return, AppleCollect's 50-apple share, wall time; P(X > Y) between variants; the
aggregate over envs; the Eq. 17 bias; and the verdict of each multi-actor variant against the
K=1 baseline of its family. No files written (mam_lab.report writes them), nothing rerun.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mam_lab.runs import BiasStats, RunRecord, bias_stats, collect_runs, common_bias_points, manifest
from mam_lab.scores import (
    MaxAverage,
    aligned_curves,
    auc_after,
    final_return,
    finite_or_none,
    first_reach,
    last_n_mean,
    max_average_return,
)
from mam_lab.stats import (
    N_BOOT,
    N_BOOT_VERDICT,
    STABILITY_SEEDS,
    Interval,
    RankTest,
    VerdictResult,
    decide,
    holm_family,
    iqm_ci,
    mean_ci,
    probability_of_improvement_ci,
    rank_test,
    wilson_interval,
)


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


# Which variant is compared with which (X, Y): P(X > Y).
BASELINES = (("ma-td3", "td3"), ("ma-ddpg", "ddpg"), ("ma-sac", "sac"))


_FAMILY_ORDER = ("ma-td3", "td3", "ma-ddpg", "ddpg", "ma-sac", "sac")


def variant_order(name: str, planned: Sequence[str] = ()) -> tuple:
    """Plan order when known; else MA-TD3, its variants, TD3, MA-DDPG, its variants, DDPG, MA-SAC, its
    variants, SAC, others."""
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
    which counts schedule steps: iterations under --schedule paper, where after C one iteration is
    one transition, so it is the finest spacing on either axis), else the median gap."""
    every = []
    for r in runs:
        e = r.algo_config.get("eval_every")
        if isinstance(e, (int, float)) and e > 0:
            every.append(float(e))
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
    deployed_final: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per run: the headline score
    deployed_auc: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per run: AUC after start-steps
    deployed_curves: tuple[np.ndarray, np.ndarray] | None = None  # (grid, runs × grid) on deployed_axis
    deployed_axis: str = "iterations"  # schedule steps: iterations, or transitions for runs without them

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
        vals = [finite_or_none(r.summary.get("launcher_wall_time_s")) or finite_or_none(r.summary.get("wall_time_s"))
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


SINGLE_ACTOR_BASELINE = {"ma-td3": "td3", "ma-ddpg": "ddpg", "ma-sac": "sac"}


@dataclass(frozen=True)
class Verdict:
    """One multi-actor variant against the single-actor baseline of its family, on one env.

    The verdict rests on the deployed actor's final return (`final`); the same rules applied to
    its AUC after the random phase are in `auc`. Best-of-K (the best live actor's last-10 IQM) is
    a secondary, labelled figure."""

    env: str
    variant: str
    baseline: str
    n_x: int
    n_y: int
    final: VerdictResult  # on the deployed actor's final return (mean of its last FINAL_N evaluations)
    auc: VerdictResult  # on its AUC after the random phase
    final_x: np.ndarray  # per run
    final_y: np.ndarray
    auc_x: np.ndarray
    auc_y: np.ndarray
    iqm_x: Interval  # best-of-K last-10 IQM (secondary)
    iqm_y: Interval
    wall_x: float  # mean wall-clock seconds per run
    wall_y: float
    commits: dict[str, int]  # over the runs of both rows
    planned_x: int | None = None  # runs planned (experiment.json / grid file), where known
    planned_y: int | None = None

    @property
    def p(self) -> Interval:
        return self.final.p

    @property
    def word(self) -> str:
        return self.final.word

    @property
    def mixed(self) -> bool:
        return len(self.commits) > 1

    @property
    def complete(self) -> bool:
        return all(p is None or n >= p for n, p in ((self.n_x, self.planned_x), (self.n_y, self.planned_y)))


@dataclass(frozen=True)
class PendingRow:
    """A planned comparison with runs missing: how many of its runs are in the ledger."""

    env: str
    variant: str
    baseline: str
    have_x: int
    planned_x: int
    have_y: int
    planned_y: int

    @property
    def have(self) -> int:
        return self.have_x + self.have_y

    @property
    def planned(self) -> int:
        return self.planned_x + self.planned_y

    def text(self) -> str:
        return (f"{self.have} of {self.planned} runs in the ledger ({self.variant} {self.have_x}/{self.planned_x}, "
                f"{self.baseline} {self.have_y}/{self.planned_y})")


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


def verdicts(envs: dict[str, list[VariantStats]], n_boot: int = N_BOOT_VERDICT,
             seeds: Sequence[int] | None = None, planned: dict[tuple[str, str], int] | None = None) -> list[Verdict]:
    """Each multi-actor variant against its family's K=1 baseline in the same env: the exact
    one-sided rank tests on the deployed actor's final return and AUC, Holm-adjusted over the rows
    that share a baseline (per env, metric and direction), and P(variant > baseline)'s bootstrap CI
    (`n_boot` resamples) under each of `seeds` (default 0..STABILITY_SEEDS−1)."""
    seeds = list(range(STABILITY_SEEDS)) if seeds is None else list(seeds)
    planned = planned or {}
    pairs: list[tuple[str, VariantStats, VariantStats]] = []
    for env, vs in envs.items():
        for v in vs:
            b = baseline_of(v, vs)
            if b is not None:
                pairs.append((env, v, b))

    def finite(a: np.ndarray) -> np.ndarray:
        return a[np.isfinite(a)]

    tests: dict[tuple[str, str, str], RankTest] = {}  # (metric, env, variant)
    for metric in ("final", "auc"):
        families: dict[tuple[str, str], list[tuple[str, VariantStats, VariantStats]]] = {}
        for env, v, b in pairs:
            families.setdefault((env, b.variant), []).append((env, v, b))
        for fam in families.values():
            raw = [rank_test(finite(getattr(v, f"deployed_{metric}")), finite(getattr(b, f"deployed_{metric}")))
                   for _, v, b in fam]
            for (env, v, _), t in zip(fam, holm_family(raw)):
                tests[(metric, env, v.variant)] = t
    out = []
    for env, v, b in pairs:
        fx, fy = finite(v.deployed_final), finite(b.deployed_final)
        ax, ay = finite(v.deployed_auc), finite(b.deployed_auc)
        commits = dict(v.commits)
        for c, n in b.commits.items():
            commits[c] = commits.get(c, 0) + n
        wx, wy = v.wall_times(), b.wall_times()
        out.append(Verdict(
            env, v.variant, b.variant, fx.size, fy.size,
            decide(fx, fy, tests[("final", env, v.variant)], n_boot, seeds),
            decide(ax, ay, tests[("auc", env, v.variant)], n_boot, seeds),
            fx, fy, ax, ay, v.iqm, b.iqm,
            float(wx.mean()) if wx.size else math.nan, float(wy.mean()) if wy.size else math.nan, commits,
            planned.get((env, v.variant)), planned.get((env, b.variant))))
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
    pending: list[PendingRow] = field(default_factory=list)  # planned comparisons with runs missing
    notes: list[str] = field(default_factory=list)  # e.g. runs of one row at different commits
    axes: tuple[str, ...] = ("transitions",)  # the learning curves drawn


def _mean_of(runs: Sequence[RunRecord], key: str) -> float:
    vals = [finite_or_none(r.summary.get(key)) for r in runs]
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else math.nan


def is_apple_collect(env: str) -> bool:
    return env.lower().startswith("applecollect")


def start_of(run: RunRecord) -> float:
    """The run's random phase (--start-steps, in schedule steps), 0 where the config lacks it."""
    v = finite_or_none(run.algo_config.get("start_steps"))
    return v if v is not None else 0.0


def budget_of(run: RunRecord) -> float | None:
    """The run's budget T in schedule steps (config.json `steps`), None where it lacks it."""
    return finite_or_none(run.config.get("steps"))


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
    sched = (spacings or {}).get("iterations") or (spacings or {}).get("transitions") or spacing
    deployed_final = np.asarray([final_return(r.deployed_xy(), sched) for r in runs], dtype=float)
    deployed_auc = np.asarray([auc_after(r.deployed_xy(), sched, start_of(r), budget_of(r)) for r in runs],
                              dtype=float)
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
        axis=axis, reached=reached, curves_by_axis=by_axis, deployed_final=deployed_final,
        deployed_auc=deployed_auc, deployed_curves=aligned_curves([r.deployed_xy() for r in runs], sched),
        deployed_axis="iterations" if any(r.has_iterations for r in runs) else "transitions")


def comparison_pairs(variants: Sequence[str]) -> list[tuple[str, str]]:
    """(X, Y) pairs for P(X > Y): MA vs single-actor baseline, and the full method vs each of its
    ablation / η variants (named `<base>-...`)."""
    present = set(variants)
    pairs = [(x, y) for x, y in BASELINES if x in present and y in present]
    for base in ("ma-td3", "ma-ddpg"):
        if base in present:
            pairs += [(base, v) for v in variants if v.startswith(base + "-")]
    return pairs


@dataclass(frozen=True)
class PlannedRun:
    """A run of the plan (experiment.json or a grid file): enough to pair a variant with its baseline."""

    path: str
    env: str
    variant: str
    algo: str
    actors: int


def planned_specs(exp_dir: Path, grid_file: Path | None = None) -> list[PlannedRun]:
    """The runs planned for an experiment: experiment.json's (or its ledger's), and with `grid_file`
    those of that grid file (mam_lab.grid.plan), the union in that order."""
    out: list[PlannedRun] = []
    plan_rows = manifest(exp_dir).get("runs")
    for r in plan_rows if isinstance(plan_rows, list) else []:
        if isinstance(r, dict) and isinstance(r.get("path"), str):
            parts = Path(r["path"]).parts
            flags = r.get("flags") if isinstance(r.get("flags"), dict) else {}
            algo = str(r.get("algo") or "")
            out.append(PlannedRun(r["path"], str(r.get("env") or (parts[0] if parts else "?")),
                                  str(r.get("variant") or (parts[1] if len(parts) > 1 else "?")), algo,
                                  int(flags.get("actors") or (2 if algo.startswith("ma-") else 1))))
    if grid_file is not None:
        from mam_lab.grid import load_grid_file, make_grid, plan

        have = {p.path for p in out}
        for spec in plan(make_grid(load_grid_file(Path(grid_file)))):
            if spec.path.as_posix() not in have:
                out.append(PlannedRun(spec.path.as_posix(), spec.env, spec.variant, spec.algo,
                                      spec.run_config("plan").algo.actors))
    return out


def pending_rows(planned: Sequence[PlannedRun], have: dict[tuple[str, str], int]) -> list[PendingRow]:
    """Each planned multi-actor variant with its family's K=1 baseline (the variant named like the
    algorithm first) where either side has fewer runs finished than planned."""
    count: dict[tuple[str, str], int] = {}
    first: dict[tuple[str, str], PlannedRun] = {}
    for p in planned:
        count[(p.env, p.variant)] = count.get((p.env, p.variant), 0) + 1
        first.setdefault((p.env, p.variant), p)
    out = []
    for (env, variant), p in first.items():
        base = SINGLE_ACTOR_BASELINE.get(p.algo)
        if base is None or p.actors <= 1:
            continue
        cands = [q for q in first.values() if q.env == env and q.algo == base and q.actors == 1]
        cands.sort(key=lambda q: q.variant != base)
        if not cands:
            continue
        b = cands[0]
        hx, hy = have.get((env, variant), 0), have.get((env, b.variant), 0)
        px, py = count[(env, variant)], count[(env, b.variant)]
        if hx < px or hy < py:
            out.append(PendingRow(env, variant, b.variant, hx, px, hy, py))
    return out


def build_report(exp_dir: Path, n_boot: int = N_BOOT, seed: int = 0, axis: str = "transitions",
                 verdict_boot: int = N_BOOT_VERDICT, stability_seeds: int = STABILITY_SEEDS,
                 grid_file: Path | None = None) -> Report:
    """All statistics of an experiment directory, a ledger, or a folder holding the ledger in runs/
    (no files written, nothing rerun; a directory that does not exist has no runs). Tables on the
    x-axis `axis` (transitions or iterations). The verdicts use `verdict_boot` bootstrap resamples
    under seeds 0..`stability_seeds`−1; `grid_file` adds that grid's runs to the plan (rows not
    finished say how many of their runs are in the ledger)."""
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}")
    exp_dir = Path(exp_dir)
    runs = collect_runs(exp_dir) if exp_dir.is_dir() else []
    plan_full = planned_specs(exp_dir, grid_file)
    planned = [p.path for p in plan_full]
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
        # Where Q* < 0 the printed form flips the sign: the ÷|Q*| form beside it, labelled
        bias[env] += [b for b in (bias_stats(f"{v.variant} (÷|Q*|)", v.runs, common, absolute=True) for v in vs
                                  if any(r.bias != r.bias_abs for r in v.runs)) if b is not None]
    bias = {env: bs for env, bs in bias.items() if bs}
    meta = manifest(exp_dir)
    return Report(exp_dir, envs, bias, comparisons, aggregate, missing, meta, axis=axis,
                  verdicts=verdicts(envs, verdict_boot, range(stability_seeds), planned_count(plan_full)),
                  notes=notes, axes=axes, pending=pending_rows(plan_full, have_count(runs)))


def planned_count(planned: Sequence[PlannedRun]) -> dict[tuple[str, str], int]:
    out: dict[tuple[str, str], int] = {}
    for p in planned:
        out[(p.env, p.variant)] = out.get((p.env, p.variant), 0) + 1
    return out


def have_count(runs: Sequence[RunRecord]) -> dict[tuple[str, str], int]:
    out: dict[tuple[str, str], int] = {}
    for r in runs:
        out[(r.env, r.variant)] = out.get((r.env, r.variant), 0) + 1
    return out
