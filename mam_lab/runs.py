"""The finished runs of an experiment, read from its directories: a run directory
(`EXP_DIR/<env>/<variant>/seed<k>/`), an experiment directory and the ledger its experiment.json
names, a ledger, or a folder holding the ledger in `runs/` (`docs/results/<exp>`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mam_lab.provenance import commit_label
from mam_lab.scores import (
    DeployedPoint,
    best_live_score,
    bias_points,
    deployed_points,
    eval_points,
    eval_triples,
    finite_or_none,
)
from services.run import rundir
from services.run.rundir import read_json, read_jsonl


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
    bias: list[tuple[float, float]] = field(default_factory=list)  # (point, Eq. 17 rate as printed) from bias.jsonl
    bias_abs: list[tuple[float, float]] = field(default_factory=list)  # the same, ÷|Q*|
    evals: list[tuple[float, float | None, float]] = field(default_factory=list)  # (env steps, iterations, score)
    record: dict[str, Any] = field(default_factory=dict)  # record.json (the commit it ran at), if any
    deployed: list[DeployedPoint] = field(default_factory=list)  # the deployed actor's scores, schedule-step axis
    train: list[tuple[float, float]] = field(default_factory=list)  # (schedule step, mean training-episode return)

    def deployed_xy(self) -> list[tuple[float, float]]:
        """(schedule step, deployed actor's return): iterations, env transitions in rows without them."""
        return [(d.x, d.score) for d in self.deployed]

    @property
    def key(self) -> str:
        """<env>/<variant>/seed<k>: the run's place in the grid (and in the ledger)."""
        return f"{rundir.env_dirname(self.env)}/{self.variant}/seed{self.seed}"

    @property
    def has_iterations(self) -> bool:
        return any(it is not None for _, it, _ in self.evals)

    def axis_points(self, axis: str = "transitions") -> list[tuple[float, float]]:
        """(x, score) on the x-axis `axis`: env transitions, or iterations (env transitions in
        the rows that carry no `iterations`, i.e. runs older than it)."""
        if axis == "transitions" or not self.evals:
            return self.points
        return [(step if it is None else it, score) for step, it, score in self.evals]

    @property
    def commit(self) -> str:
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
            vals = [(v, k) for k, v in enumerate(finite_or_none(f) for f in finals) if v is not None]
            if vals:
                return max(vals)[1]
        return None


def load_run(path: Path, env: str | None = None, variant: str | None = None) -> RunRecord | None:
    """A finished run directory (None without summary.json)."""
    summary = read_json(path / rundir.SUMMARY)
    if not summary:
        return None
    config = read_json(path / rundir.CONFIG)
    algo = config.get("algo") if isinstance(config.get("algo"), dict) else {}
    seed = algo.get("seed")
    if not isinstance(seed, int):
        m = re.fullmatch(r"seed(\d+)", path.name)
        seed = int(m.group(1)) if m else 0
    rows = read_jsonl(path / rundir.EVAL)
    allocation = read_jsonl(path / rundir.ALLOCATION)
    return RunRecord(
        env=env or str(config.get("env_id") or summary.get("env_id") or "?"),
        variant=variant or str(algo.get("algo") or summary.get("algo") or "?"),
        seed=seed, path=path, config=config, summary=summary,
        points=eval_points(rows), evals=eval_triples(rows),
        allocation=allocation, deployed=deployed_points(rows, allocation, "iterations"),
        bias=bias_points(read_jsonl(path / rundir.BIAS)),
        bias_abs=bias_points(read_jsonl(path / rundir.BIAS), absolute=True),
        record=read_json(path / rundir.RECORD), train=train_points(path))


def train_points(path: Path) -> list[tuple[float, float]]:
    """(iterations, or env transitions in rows without them; the mean return of the training episodes
    that ended since the row before) from a ledger record's train_returns.jsonl, else from a run
    directory's whole learner.jsonl. A ledger record made before train_returns.jsonl has only a thinned
    learner.jsonl, whose few training returns would draw a false curve: none then."""
    rows = read_jsonl(path / rundir.TRAIN_RETURNS)
    if not rows:
        thinned = read_json(path / rundir.RECORD).get("learner_rows")
        if isinstance(thinned, dict) and thinned.get("kept") != thinned.get("of"):
            return []
        rows = read_jsonl(path / rundir.LEARNER_LOG)
    points = []
    for row in rows:
        x = row.get("iterations", row.get("env_steps"))
        y = row.get("train_return")
        if isinstance(x, (int, float)) and isinstance(y, (int, float)) and np.isfinite(y):
            points.append((float(x), float(y)))
    return points


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


def bias_stats(variant: str, runs: Sequence[RunRecord], points: Sequence[float] | None = None,
               absolute: bool = False) -> BiasStats | None:
    """`points`: only these (e.g. the points every run of the env measured), else every point.
    `absolute`: the ÷|Q*| form (labelled so in `variant`)."""
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
        for p, rate in (r.bias_abs if absolute else r.bias):
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
    for summary in sorted(exp_dir.rglob(rundir.SUMMARY)):
        path = summary.parent
        rel = path.relative_to(exp_dir).parts
        if any(p.startswith(".") for p in rel) or (rel and rel[0] == rundir.FAILURES):
            continue
        layout = len(rel) >= 3 and re.fullmatch(r"seed\d+", rel[-1]) is not None
        run = load_run(path, env=None, variant=rel[-2] if layout else None)
        if run is not None:
            runs.append(run)
    return runs


def manifest(root: Path) -> dict[str, Any]:
    """experiment.json of an experiment directory or ledger (ROOT, else ROOT/runs)."""
    root = Path(root)
    for path in (root / rundir.EXPERIMENT, root / "runs" / rundir.EXPERIMENT):
        data = read_json(path)
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
