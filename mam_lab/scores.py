"""Per-run scores from a run's evaluation and bias rows, pure: the best live actor's score of an
evaluation row, evaluation points on a common grid, the last-10 mean, runs aligned on a grid and
the paper's max average return (Table 4), and the Eq. 17 bias rate per point.

Rows are the dicts of `eval.jsonl` / `bias.jsonl` (services.run.rundir.read_jsonl); nothing here reads
files.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

LAST_N = 10


def finite_or_none(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def best_live_score(row: dict[str, Any]) -> float | None:
    """Score of one evaluation row: the best mean return over the actors evaluated (live) at that
    point; None when no actor was evaluated."""
    means = row.get("mean")
    values: list[float] = []
    if isinstance(means, list):
        values = [v for v in (finite_or_none(m) for m in means) if v is not None]
    if not values and isinstance(row.get("returns"), list):  # older rows: only the episode returns
        for episodes in row["returns"]:
            if isinstance(episodes, list):
                eps = [v for v in (finite_or_none(e) for e in episodes) if v is not None]
                if eps:
                    values.append(float(np.mean(eps)))
    return max(values) if values else None


def eval_points(rows: list[dict[str, Any]]) -> list[tuple[float, float]]:
    """(env_steps, best live score) of every evaluation row with a score, in file order."""
    out = []
    for row in rows:
        step, score = finite_or_none(row.get("env_steps")), best_live_score(row)
        if step is not None and score is not None:
            out.append((step, score))
    return out


def eval_triples(rows: list[dict[str, Any]]) -> list[tuple[float, float | None, float]]:
    """(env_steps, iterations or None, best live score) of every evaluation row with a score."""
    out = []
    for row in rows:
        step, score = finite_or_none(row.get("env_steps")), best_live_score(row)
        if step is not None and score is not None:
            out.append((step, finite_or_none(row.get("iterations")), score))
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
    rate = finite_or_none(bias.get("bias_rate"))
    if rate is None:
        return None
    q_star = finite_or_none(bias.get("q_true"))
    negative = q_star is not None and q_star < 0
    if "horizon" in bias:  # printed form stored
        if absolute and negative:
            return finite_or_none(bias.get("bias_rate_abs", -rate))
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
        point = finite_or_none(r.get("point", r.get("env_steps")))
        rate = bias_rate_of(r["bias"], absolute) if isinstance(r.get("bias"), dict) else None
        if point is not None and rate is not None:
            by_point.setdefault(point, []).append(rate)
    return [(p, float(np.mean(v))) for p, v in sorted(by_point.items())]


# --- the deployed actor ----------------------------------------------------------------------


SELECTION_PURPOSES = frozenset({"round", "elimination"})  # evaluations that selected an actor
FINAL_N = 3  # the final return: mean of the deployed actor's last 3 evaluations


def _x_of(row: dict[str, Any], axis: str) -> float | None:
    """A row's place on `axis`: iterations (env transitions in rows without them) or env transitions
    (allocation rows of old records carry `decided_at` too)."""
    if axis == "iterations":
        it = finite_or_none(row.get("iterations"))
        if it is not None:
            return it
    step = finite_or_none(row.get("env_steps"))
    return step if step is not None else finite_or_none(row.get("decided_at"))


def _actor_return(row: dict[str, Any], k: int) -> float | None:
    """Actor k's mean return in an evaluation row (None where it was not evaluated)."""
    means = row.get("mean")
    if isinstance(means, list) and k < len(means):
        value = finite_or_none(means[k])
        if value is not None:
            return value
    returns = row.get("returns")
    if isinstance(returns, list) and k < len(returns) and isinstance(returns[k], list):
        eps = [v for v in (finite_or_none(e) for e in returns[k]) if v is not None]
        if eps:
            return float(np.mean(eps))
    return None


@dataclass(frozen=True)
class Competition:
    """A competition of the allocation log: where it happened and the actor it ranked best."""

    x: float
    best: int
    reason: str  # "round" or "elimination"


def competition_winner(row: dict[str, Any]) -> int | None:
    """The actor a competition row ranks best: the survivor at the elimination; at a round the
    actor with the highest return, a tie (the row's `tie`, or equal returns) going to the lowest
    index. None without returns."""
    if row.get("reason") == "elimination" and isinstance(row.get("survivor"), int):
        return int(row["survivor"])
    returns = row.get("returns")
    if not isinstance(returns, list):
        return None
    vals = [(finite_or_none(r), k) for k, r in enumerate(returns)]
    vals = [(v, k) for v, k in vals if v is not None]
    if not vals:
        return None
    tie = row.get("tie")
    if isinstance(tie, list) and tie and all(isinstance(t, int) for t in tie):
        return min(tie)
    best = max(v for v, _ in vals)
    return min(k for v, k in vals if v == best)


def competitions(allocation: list[dict[str, Any]], axis: str = "iterations") -> list[Competition]:
    """The competitions of a run (allocation rows with reason "round" or "elimination" that carry
    `returns`), in file order."""
    out = []
    for row in allocation:
        if row.get("reason") not in SELECTION_PURPOSES:
            continue
        x, best = _x_of(row, axis), competition_winner(row)
        if x is not None and best is not None:
            out.append(Competition(x, best, str(row["reason"])))
    return out


def initial_actor(allocation: list[dict[str, Any]]) -> int:
    """The deployed actor before any competition: the actor the run's initial allocation prefers
    (its "initial" row, else the first row that is not a competition: the largest P_k, the lowest
    index on a tie; P is uniform at the start, so actor 0), else actor 0."""
    rows = [r for r in allocation if r.get("reason") == "initial"]
    rows += [r for r in allocation if r.get("reason") not in SELECTION_PURPOSES]
    for row in rows[:1]:
        probs = row.get("probabilities")
        if isinstance(probs, list) and probs:
            vals = [finite_or_none(p) for p in probs]
            if all(v is not None for v in vals):
                return vals.index(max(vals))
    return 0


@dataclass(frozen=True)
class DeployedPoint:
    """The deployed actor's score at one evaluation row."""

    x: float  # on the axis asked for
    actor: int
    score: float
    purpose: str | None  # the row's purpose (None in records older than it)


def deployed_points(evals: list[dict[str, Any]], allocation: list[dict[str, Any]],
                    axis: str = "iterations") -> list[DeployedPoint]:
    """The deployed actor's return at each evaluation row that played no part in selecting it.

    The deployed actor is the survivor after the elimination C and, before C, the actor ranked best
    at the latest competition (competition_winner); before the first competition, initial_actor
    (actor 0). A single-actor run has one actor, 0.

    - Rows with a `purpose` (records since exact mode): "round" and "elimination" rows are the
      competitions' own selection evaluations and are never scored; "curve" and "final" rows (on
      episodes disjoint from the competitions') score the actor chosen by the latest competition
      at or before them.
    - Rows without `purpose` (older records): an evaluation at a competition's iteration *is* that
      competition's selection evaluation, so it scores the actor chosen by the latest competition
      strictly before it — the actor that was deployed while those episodes were played.

    A row where the deployed actor has no return is left out."""
    comps = sorted(competitions(allocation, axis), key=lambda c: c.x)
    first = initial_actor(allocation)
    out = []
    for row in evals:
        purpose = row.get("purpose")
        purpose = purpose if isinstance(purpose, str) else None
        if purpose in SELECTION_PURPOSES:
            continue
        x = _x_of(row, axis)
        if x is None:
            continue
        if purpose is None:
            before = [c for c in comps if c.x < x]
        else:
            before = [c for c in comps if c.x <= x]
        actor = before[-1].best if before else first
        score = _actor_return(row, actor)
        if score is not None:
            out.append(DeployedPoint(x, actor, score, purpose))
    return out


def final_return(points: Sequence[tuple[float, float]], spacing: float, n: int = FINAL_N) -> float:
    """Mean of the last `n` grid points (see bucket_points) of a run's (x, score) points; NaN without any."""
    return last_n_mean(points, spacing, n)


def auc_after(points: Sequence[tuple[float, float]], spacing: float, start: float, end: float | None = None,
              ) -> float:
    """Area under the learning curve after the random phase, per unit of x: the trapezoid integral of
    the grid points (bucket_points) with x ≥ `start` (and ≤ `end`), divided by the x range they
    span, i.e. the mean return over the learning phase in return units. NaN with fewer than 2
    points (one point: its score)."""
    cells = [(x, s) for x, s in bucket_points(points, spacing).items()
             if x >= start - 1e-9 and (end is None or x <= end + 1e-9)]
    if not cells:
        return math.nan
    if len(cells) == 1:
        return float(cells[0][1])
    xs = np.asarray([c[0] for c in cells], dtype=float)
    ys = np.asarray([c[1] for c in cells], dtype=float)
    area = float(np.sum((xs[1:] - xs[:-1]) * (ys[1:] + ys[:-1]) / 2))
    return area / float(xs[-1] - xs[0])
