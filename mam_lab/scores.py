"""Per-run scores from a run's evaluation and bias rows, pure: the best live actor's score of an
evaluation row, evaluation points on a common grid, the last-10 mean, runs aligned on a grid and
the paper's max average return (Table 4), and the Eq. 17 bias rate per point.

Rows are the dicts of `eval.jsonl` / `bias.jsonl` (services.rundir.read_jsonl); nothing here reads
files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

LAST_N = 10


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


def bias_rate_of(bias: dict[str, Any], absolute: bool = False) -> float | None:
    """Eq. 17 of a bias.jsonl row: (Q̂ − Q*)/Q* as printed, or ÷|Q*| (`absolute`). Rows since
    issue #9 (they carry `horizon`) store the printed form in `bias_rate` and, where Q* < 0,
    the other in `bias_rate_abs`; older rows stored the ÷|Q*| form in `bias_rate`."""
    rate = _finite(bias.get("bias_rate"))
    if rate is None:
        return None
    q_star = _finite(bias.get("q_true"))
    negative = q_star is not None and q_star < 0
    if "horizon" in bias:  # printed form stored
        if absolute and negative:
            return _finite(bias.get("bias_rate_abs", -rate))
        return rate
    return -rate if negative and not absolute else rate  # ÷|Q*| form stored


def bias_points(rows: list[dict[str, Any]], absolute: bool = False) -> list[tuple[float, float]]:
    """(point, bias rate) per measurement of a run: the mean of Eq. 17 (as printed, or ÷|Q*|
    with `absolute`) over the actors live at that point (after the elimination: the survivor's).
    Points with no finite rate are left out, and so are points before the first update (the
    critic is still its random initialisation)."""
    by_point: dict[float, list[float]] = {}
    for r in rows:
        if r.get("updates") == 0:
            continue
        point = _finite(r.get("point", r.get("env_steps")))
        rate = bias_rate_of(r["bias"], absolute) if isinstance(r.get("bias"), dict) else None
        if point is not None and rate is not None:
            by_point.setdefault(point, []).append(rate)
    return [(p, float(np.mean(v))) for p, v in sorted(by_point.items())]
