"""The report's figures (matplotlib object API with the Agg canvas, never pyplot; matplotlib is
imported only when a figure is drawn): learning curves with bootstrap CI bands, the allocation to
the eventual survivor, training-episode returns beside the evaluations, the Eq. 17 bias rate (Fig. 3)
and the IQMs with their CIs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mam_core.algorithm1 import elimination_transitions
from mam_lab.analysis import SUCCESS_RETURN, Report, VariantStats, is_apple_collect
from mam_lab.runs import BiasStats, RunRecord
from mam_lab.scores import aligned_curves, finite_or_none
from mam_lab.stats import curve_band

DPI = 120


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
    ax.set_xlabel("transitions (env steps received by the learner)" if axis == "transitions"
                  else "iterations (env transitions where a run does not record them)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")


def deployed_curve(v: VariantStats, axis: str, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The deployed actor's returns (runs × grid) on `axis`: as analysed (schedule steps), or moved
    to the transitions axis through each run's evaluation rows (iteration -> env steps)."""
    if v.deployed_curves is None or not v.deployed_curves[0].size:
        return None
    if v.deployed_axis == axis:
        return v.deployed_curves
    if axis != "transitions" or grid.size < 2:
        return None
    runs = []
    for run in v.runs:
        steps_at = {it: step for step, it, _ in run.evals if it is not None}
        runs.append([(steps_at[d.x], d.score) for d in run.deployed if d.x in steps_at])
    return aligned_curves(runs, float(np.median(np.diff(grid))))


def plot_env_curves(env: str, vs: Sequence[VariantStats], path: Path, n_boot: int = 1000, seed: int = 0,
                    axis: str = "transitions") -> Path | None:
    """Mean best-live-actor (best-of-K) return over seeds per variant on `axis`, with a bootstrap 95%
    CI band, and for multi-actor variants the deployed actor's mean return (dashed, on the
    schedule-step axis); the legend gives each variant's mean wall-clock time per run."""
    curves = [(v, *v.curves_by_axis.get(axis, (v.grid, v.curves))) for v in vs]
    if not any(grid.size for _, grid, _ in curves):
        return None
    fig = _figure(figsize=(8.5, 5))
    ax = fig.add_subplot()
    dashed = False
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
        multi = (v.runs[0].algo_config.get("actors") or 1) > 1
        deployed = deployed_curve(v, axis, grid) if multi else None
        if deployed is not None and deployed[0].size:
            d_grid, d_matrix = deployed
            seen = np.isfinite(d_matrix).sum(axis=0)
            d_mean = np.where(seen > 0, np.nansum(d_matrix, axis=0) / np.maximum(seen, 1), np.nan)
            # above the solid line (after C the two coincide), dark-edged so it shows on it
            ax.plot(d_grid, d_mean, color="0.1", linewidth=2.6, linestyle=(0, (3, 2)), zorder=4)
            ax.plot(d_grid, d_mean, color=color, linewidth=1.6, linestyle=(0, (3, 2)), zorder=5,
                    label=f"{v.variant}: deployed actor")
            dashed = True
        algo = v.runs[0].algo_config
        at = elimination_transitions(algo)  # None: no elimination
        c = at if axis == "transitions" else algo.get("eliminate_at")  # else in schedule steps, as C is given
        if at is not None and 0 < c <= grid[-1]:
            ax.axvline(c, color=color, linestyle=":", linewidth=1.0)
    if is_apple_collect(env):
        ax.axhline(SUCCESS_RETURN, color="0.5", linestyle="--", linewidth=0.8, label=f"return {SUCCESS_RETURN:.2f}")
    styles = "solid: best live actor, best-of-K" + ("; dashed: deployed actor" if dashed else "") + \
        "; dotted: elimination C"
    _label_steps_axes(ax, "evaluation return", f"{env}: mean over seeds, 95% bootstrap CI\n({styles})", axis)
    return _save(fig, path)


def allocation_share(run: RunRecord, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Share of the slots I_k/ΣI and probability P_k of the run's eventual best actor over `steps`
    (held from each allocation row to the next; NaN before the first)."""
    best = run.eventual_best
    share = np.full(steps.size, np.nan)
    prob = share.copy()
    rows = [r for r in run.allocation if finite_or_none(r.get("env_steps")) is not None]
    if best is None or not rows:
        return share, prob
    xs = np.asarray([float(r["env_steps"]) for r in rows])
    s_vals, p_vals = [], []
    for r in rows:
        counts = r.get("counts") if isinstance(r.get("counts"), list) else []
        total = sum(c for c in counts if isinstance(c, (int, float)))
        s_vals.append(counts[best] / total if total and best < len(counts) else np.nan)
        probs = r.get("probabilities") if isinstance(r.get("probabilities"), list) else []
        p = finite_or_none(probs[best]) if best < len(probs) else None
        p_vals.append(np.nan if p is None else p)
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
        axes[1, col].set_xlabel("transitions")
    axes[0, 0].legend(loc="lower right", fontsize="small")
    fig.suptitle(f"{env}: allocation to the eventual survivor (thin: seeds)")
    return _save(fig, path)


def plot_env_training(env: str, vs: Sequence[VariantStats], path: Path) -> Path | None:
    """Per variant with training returns recorded: each run's mean training-episode return (line: what
    the behaviour policy did) and its deployed actor's evaluations (dots, the same colour), on the
    schedule-step axis (iterations). Shows whether a fall in the evaluations is in training too."""
    drawn = [v for v in vs if any(r.train for r in v.runs)]
    if not drawn:
        return None
    fig = _figure(figsize=(max(7.5, 4.2 * len(drawn) + 1), 4.5))
    axes = fig.subplots(1, len(drawn), sharey=True, squeeze=False)[0]
    for ax, v in zip(axes, drawn):
        for i, run in enumerate(r for r in v.runs if r.train):
            colour = f"C{i % 10}"
            xs, ys = zip(*run.train)
            ax.plot(xs, ys, color=colour, linewidth=0.9, label=f"seed {run.seed}")
            if run.deployed:
                dx, dy = zip(*run.deployed_xy())
                ax.plot(dx, dy, "o", color=colour, markersize=3)
        n_train = sum(1 for r in v.runs if r.train)
        ax.set_title(f"{v.variant} ({n_train} of {v.n} runs recorded)", fontsize="medium")
        ax.set_xlabel("iterations (env transitions where a run does not record them)")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    axes[0].set_ylabel("return")
    fig.suptitle(f"{env}: training episodes (lines) and the deployed actor's evaluations (dots)")
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
    _label_steps_axes(ax, "bias rate $(\\hat Q - Q^*)/Q^*$ (Eq. 17; rows marked ÷|Q*|: $/|Q^*|$)",
                      f"{env}: estimation bias, mean over seeds ± 1 std")
    return _save(fig, path)


def plot_iqm(report: Report, path: Path) -> Path | None:
    """IQM of the best-of-K last-10 scores with 95% CIs, one panel per env (+ the normalised aggregate)."""
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
    fig.suptitle("IQM of the best-of-K last-10 scores (secondary), 95% bootstrap CI")
    return _save(fig, path)
