"""PNG plots of a run directory (`mam plot RUN_DIR`).

Reads the JSONL metrics a run writes (`eval.jsonl`, `allocation.jsonl`, `learner.jsonl`) plus
`config.json` / `summary.json`, and writes into `RUN_DIR/plots/`:

- `learning_curves.png`  mean evaluation return per actor (±1 std over episodes), elimination at C
- `allocation.png`       I_k (slots per actor, stacked) and P_k (Eq. 8) over env steps
- `bias.png`             estimation bias rate (Eq. 17) from `bias.jsonl` (runs with `--bias-every`)
- `learner.png`          critic loss, actor loss per actor, updates per iteration (or per transition
                         under `--schedule equal-data`) from the first update on, mean Q per actor

A run may still be going: the last JSONL line can be half written and is skipped. A plot whose
data is absent is skipped. Figures use the object API (`Figure` + Agg canvas), never pyplot,
so plotting changes no global matplotlib state of the calling process.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mam_core.algorithm1 import elimination_transitions
from services.run import rundir
from services.run.rundir import read_json, read_jsonl

PLOTS_DIR = rundir.PLOTS
DPI = 120


def _num(value: Any) -> float:
    """A metric value as float; None, strings and other junk become NaN (a gap in the line)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _rows_with_steps(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if isinstance(r.get("env_steps"), (int, float))]


# --- run facts ------------------------------------------------------------------------------


def _survivor(summary: dict[str, Any], allocation: list[dict[str, Any]]) -> int | None:
    if isinstance(summary.get("survivor"), int):
        return summary["survivor"]
    for row in reversed(allocation):
        if isinstance(row.get("survivor"), int):
            return row["survivor"]
    return None


def _elimination_step(config: dict[str, Any], allocation: list[dict[str, Any]], last_step: float) -> float | None:
    """Env step of the elimination: the referee's record, else C from the config once reached."""
    for row in allocation:
        if row.get("reason") == "elimination" and isinstance(row.get("env_steps"), (int, float)):
            return float(row["env_steps"])
    c = elimination_transitions(_algo_config(config))
    return None if c is None or c > last_step else float(c)


def _algo_config(config: dict[str, Any]) -> dict[str, Any]:
    """config.json keeps the algorithm's settings under "algo" (older files: "algo_config")."""
    algo = config.get("algo")
    return algo if isinstance(algo, dict) else (config.get("algo_config") or {})


def _title(config: dict[str, Any]) -> str:
    algo = _algo_config(config).get("algo") or (config.get("algo") if isinstance(config.get("algo"), str) else None)
    parts = [str(p) for p in (config.get("run"), algo, config.get("env_id")) if p]
    return " · ".join(parts)


TITLE_WIDTH = 70  # characters per title line at the figures' width


def _set_title(ax: Axes, what: str, title: str) -> None:
    """`what — run · algo · env`, broken between its parts (never inside one, never leaving a
    dangling "·"), so a long run name is never cut at the figure's edge."""
    lines = [what]
    for i, part in enumerate(p for p in title.split(" · ") if p):
        sep = " — " if i == 0 else " · "
        if len(lines[-1]) + len(sep) + len(part) <= TITLE_WIDTH:
            lines[-1] += sep + part
        else:
            lines.append(part if len(part) <= TITLE_WIDTH else "\n".join(textwrap.wrap(part, TITLE_WIDTH)))
    ax.set_title("\n".join(lines), fontsize="medium")


def _last_per_x(xs: list[float], *columns: list[float]) -> tuple[list[float], ...]:
    """One point per x, the last one recorded there (the run's final evaluation comes after the
    last periodic one at the same env step: both drawn gave a vertical zigzag at the last x)."""
    keep: dict[float, int] = {}
    for i, x in enumerate(xs):
        keep[x] = i
    order = sorted(keep.values())
    return tuple([col[i] for i in order] for col in (xs, *columns))


def _actor_label(k: int, survivor: int | None) -> str:
    return f"actor {k} (survivor)" if k == survivor else f"actor {k}"


def _mark_elimination(ax: Axes, step: float | None, label: bool = True) -> None:
    if step is not None:
        ax.axvline(step, color="0.3", linestyle="--", linewidth=1.0,
                   label=f"elimination @ {step:,.0f}" if label else None)


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=DPI)
    return path


def _n_actors(*lists: Sequence[Any]) -> int:
    return max((len(x) for x in lists if isinstance(x, list)), default=0)


# --- plots ----------------------------------------------------------------------------------


X_AXES = {"transitions": "transitions (env steps received by the learner)",
          "iterations": "iterations (Algorithm 1: M transitions before C, one after)"}
TRANSITIONS = X_AXES["transitions"]


def plot_learning_curves(
    evals: list[dict[str, Any]], survivor: int | None, elimination: float | None, title: str, path: Path,
    xlabel: str = TRANSITIONS,
) -> Path | None:
    """Mean evaluation return per actor with a ±1 std band over the evaluation episodes."""
    evals = _rows_with_steps(evals)
    k_actors = max((_n_actors(r.get("mean"), r.get("returns")) for r in evals), default=0)
    if k_actors == 0:
        return None
    fig = Figure(figsize=(8, 4.8), layout="constrained")
    ax = fig.add_subplot()
    for k in range(k_actors):
        xs, mean, std = [], [], []
        for row in evals:
            returns = row.get("returns") or []
            episodes = [_num(v) for v in returns[k]] if k < len(returns) and isinstance(returns[k], list) else []
            episodes = [v for v in episodes if math.isfinite(v)]
            means = row.get("mean") or []
            m = _num(means[k]) if k < len(means) else math.nan
            if not math.isfinite(m) and episodes:
                m = float(np.mean(episodes))
            if not math.isfinite(m):
                continue  # actor not evaluated this round (e.g. eliminated)
            xs.append(float(row["env_steps"]))
            mean.append(m)
            std.append(float(np.std(episodes)) if episodes else 0.0)
        if not xs:
            continue
        xs, mean, std = _last_per_x(xs, mean, std)
        x, m, s = np.asarray(xs), np.asarray(mean), np.asarray(std)
        color = f"C{k % 10}"
        ax.plot(x, m, color=color, marker="o", markersize=3, linewidth=2.2 if k == survivor else 1.5,
                label=_actor_label(k, survivor))
        ax.fill_between(x, m - s, m + s, color=color, alpha=0.18, linewidth=0)
    _mark_elimination(ax, elimination)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("mean evaluation return")
    _set_title(ax, "Learning curves", title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return _save(fig, path)


def plot_allocation(
    allocation: list[dict[str, Any]], last_step: float, survivor: int | None, elimination: float | None,
    title: str, path: Path, xlabel: str = TRANSITIONS,
) -> Path | None:
    """I_k stacked (slots per actor, sums to M) and P_k, both held until the next allocation."""
    rows = [r for r in _rows_with_steps(allocation)
            if isinstance(r.get("counts"), list) or isinstance(r.get("probabilities"), list)]
    if not rows:
        return None
    k_actors = max(_n_actors(r.get("counts"), r.get("probabilities")) for r in rows)
    x = np.asarray([float(r["env_steps"]) for r in rows])
    counts = np.full((k_actors, len(rows)), np.nan)
    probs = np.full((k_actors, len(rows)), np.nan)
    for j, row in enumerate(rows):
        for k, v in enumerate((row.get("counts") or [])[:k_actors]):
            counts[k, j] = _num(v)
        for k, v in enumerate((row.get("probabilities") or [])[:k_actors]):
            probs[k, j] = _num(v)
    # Hold the last allocation until the end of the data so the final step is visible.
    if last_step > x[-1]:
        x = np.append(x, last_step)
        counts = np.concatenate([counts, counts[:, -1:]], axis=1)
        probs = np.concatenate([probs, probs[:, -1:]], axis=1)

    fig = Figure(figsize=(9, 6), layout="constrained")
    ax_i, ax_p = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    colors = [f"C{k % 10}" for k in range(k_actors)]
    labels = [_actor_label(k, survivor) for k in range(k_actors)]
    ax_i.stackplot(x, np.nan_to_num(counts), labels=labels, colors=colors, step="post", alpha=0.8)
    ax_i.set_ylabel("slots $I_k$")
    m_total = np.nanmax(np.nansum(counts, axis=0)) if np.isfinite(counts).any() else 0
    if m_total > 0:
        ax_i.set_ylim(0, m_total)
        ax_i.set_yticks(range(int(m_total) + 1))
    _set_title(ax_i, "Allocation", title)
    ax_i.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    _mark_elimination(ax_i, elimination, label=False)
    for k in range(k_actors):
        ax_p.step(x, probs[k], where="post", color=colors[k], linewidth=1.6, label=f"$P_{{{k}}}$")
    _mark_elimination(ax_p, elimination)
    ax_p.set_ylim(-0.02, 1.02)
    ax_p.set_ylabel("probability $P_k$ (Eq. 8)")
    ax_p.set_xlabel(xlabel)
    ax_p.grid(alpha=0.3)
    ax_p.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    return _save(fig, path)


def plot_bias(evals: list[dict[str, Any]], title: str, path: Path, xlabel: str = TRANSITIONS) -> Path | None:
    """Estimation bias rate (Eq. 17) and the two Q values it compares."""
    rows = [r for r in _rows_with_steps(evals) if isinstance(r.get("bias"), dict)]
    if not rows:
        return None
    fig = Figure(figsize=(8, 6), layout="constrained")
    ax_rate, ax_q = fig.subplots(2, 1, sharex=True)
    actors = sorted({int(r["bias"].get("actor", 0)) for r in rows if isinstance(r["bias"].get("actor", 0), int)})
    for k in actors:
        sel = [r for r in rows if r["bias"].get("actor", 0) == k]
        x = [float(r["env_steps"]) for r in sel]
        color = f"C{k % 10}"
        ax_rate.plot(x, [_num(r["bias"].get("bias_rate")) for r in sel], color=color, marker="o", markersize=3,
                     label=f"actor {k}")
        ax_q.plot(x, [_num(r["bias"].get("q_estimate")) for r in sel], color=color, marker="o", markersize=3,
                  label=f"actor {k}: critic $\\hat Q$")
        ax_q.plot(x, [_num(r["bias"].get("q_true")) for r in sel], color=color, linestyle="--",
                  label=f"actor {k}: Monte-Carlo $Q^*$")
    ax_rate.axhline(0.0, color="0.3", linewidth=0.8)
    ax_rate.set_ylabel("bias rate $(\\hat Q - Q^*)/|Q^*|$")
    _set_title(ax_rate, "Estimation bias (Eq. 17)", title)
    ax_rate.grid(alpha=0.3)
    ax_rate.legend(loc="best", fontsize="small")
    ax_q.set_ylabel("Q at start states")
    ax_q.set_xlabel(xlabel)
    ax_q.grid(alpha=0.3)
    ax_q.legend(loc="best", fontsize="small")
    return _save(fig, path)


def _eliminated(row: dict[str, Any], k: int) -> bool:
    live = row.get("live")
    return isinstance(live, list) and k < len(live) and live[k] is False


def plot_learner(learner: list[dict[str, Any]], target_utd: float | None, title: str, path: Path,
                 xlabel: str = TRANSITIONS, utd_unit: str = "transition") -> Path | None:
    """Critic loss, actor loss, updates per schedule step (`utd_unit`: iteration under the paper's
    schedule, transition under equal-data) and mean Q per actor over env steps."""
    rows = _rows_with_steps(learner)
    if not rows:
        return None
    x = np.asarray([float(r["env_steps"]) for r in rows])
    critic = np.asarray([_num(r.get("loss/critic")) for r in rows])
    # updates per schedule step from the first update on (before it the ratio only ramps up from 0)
    utd = np.asarray([_num(r.get("utd")) if not _num(r.get("updates")) <= 0 else math.nan for r in rows])
    actor_keys = sorted({k for r in rows for k in r if k.startswith("loss/actor") and k[10:].isdigit()},
                        key=lambda s: int(s[10:]))
    q_keys = sorted({k for r in rows for k in r if k.startswith("q/actor")}, key=lambda s: (len(s), s))

    fig = Figure(figsize=(8, 8 if q_keys else 6.5), layout="constrained")
    axes = fig.subplots(4 if q_keys else 3, 1, sharex=True)
    ax_c, ax_a, ax_u = axes[:3]
    ax_c.plot(x, critic, color="C0", linewidth=1.2)
    if np.isfinite(critic).any() and np.nanmin(critic) > 0:
        ax_c.set_yscale("log")
    ax_c.set_ylabel("critic loss")
    _set_title(ax_c, "Learner", title)
    if actor_keys:  # Eq. 7 per actor: -Q_k1(s, pi_k(s)); an eliminated actor's line ends at C
        for key in actor_keys:
            k = int(key[10:])
            ys = [math.nan if _eliminated(r, k) else _num(r.get(key)) for r in rows]
            ax_a.plot(x, ys, color=f"C{k % 10}", linewidth=1.2, label=f"actor {k}")
    else:  # runs from before the per-actor losses: the sum over the actors
        ax_a.plot(x, [_num(r.get("loss/actor")) for r in rows], color="C1", linewidth=1.2,
                  label="sum over the actors")
    ax_a.legend(loc="best", fontsize="small")
    ax_a.set_ylabel("actor loss")
    ax_u.plot(x, utd, color="C2", linewidth=1.2, label="measured")
    if target_utd is not None:
        ax_u.axhline(target_utd, color="0.3", linestyle="--", linewidth=1.0, label=f"target {target_utd:g}")
        ax_u.legend(loc="best", fontsize="small")
    ax_u.set_ylabel(f"updates / {utd_unit}")
    if q_keys:
        for key in q_keys:
            k = key.removeprefix("q/actor")
            color = f"C{int(k) % 10}" if k.isdigit() else None
            axes[3].plot(x, [_num(r.get(key)) for r in rows], color=color, linewidth=1.2, label=f"actor {k}")
        axes[3].set_ylabel("mean Q")
        axes[3].legend(loc="best", fontsize="small")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel(xlabel)
    return _save(fig, path)


# --- entry points ---------------------------------------------------------------------------


def on_axis(rows: list[dict[str, Any]], x: str) -> list[dict[str, Any]]:
    """Rows with `env_steps` holding the x-axis value: transitions as recorded, or the row's
    `iterations` (rows without it, from runs before the schedules, keep their transitions)."""
    if x == "transitions":
        return rows
    return [{**r, "env_steps": r["iterations"]} if isinstance(r.get("iterations"), (int, float)) else r
            for r in rows]


def plot_run(run_dir: Path, x: str = "transitions") -> list[Path]:
    """Write every plot whose data is present into `run_dir/plots/`; return the files written.

    `x`: "transitions" (env steps received by the learner) or "iterations" (schedule steps);
    iteration plots get an `_iterations` suffix."""
    if x not in X_AXES:
        raise ValueError(f"x must be one of {', '.join(X_AXES)}, not {x!r}")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"run directory not found: {run_dir}")
    xlabel = X_AXES[x]
    config = read_json(run_dir / rundir.CONFIG)
    summary = on_axis([read_json(run_dir / rundir.SUMMARY)], x)[0]
    evals = on_axis(read_jsonl(run_dir / rundir.EVAL), x)
    allocation = on_axis(read_jsonl(run_dir / rundir.ALLOCATION), x)
    learner = on_axis(read_jsonl(run_dir / rundir.LEARNER_LOG), x)
    suffix = "" if x == "transitions" else "_iterations"

    steps = [float(r["env_steps"]) for r in _rows_with_steps(evals + allocation + learner)]
    if isinstance(summary.get("env_steps"), (int, float)):
        steps.append(float(summary["env_steps"]))
    last_step = max(steps, default=0.0)
    survivor = _survivor(summary, allocation)
    elimination = _elimination_step(config, allocation, last_step)
    title = _title(config)
    utd = _num(_algo_config(config).get("utd"))
    target_utd = utd if math.isfinite(utd) else None
    # learner.jsonl's utd counts updates per schedule step: per iteration under the paper's schedule
    # (runs from before the schedules have no `schedule` and counted transitions)
    utd_unit = "iteration" if _algo_config(config).get("schedule") == "paper" else "transition"

    out = run_dir / PLOTS_DIR
    out.mkdir(exist_ok=True)
    written = [
        plot_learning_curves(evals, survivor, elimination, title, out / f"learning_curves{suffix}.png", xlabel),
        plot_allocation(allocation, last_step, survivor, elimination, title, out / f"allocation{suffix}.png",
                        xlabel),
        plot_bias(evals + on_axis(read_jsonl(run_dir / rundir.BIAS), x), title, out / f"bias{suffix}.png", xlabel),
        plot_learner(learner, target_utd, title, out / f"learner{suffix}.png", xlabel, utd_unit),
    ]
    return [p for p in written if p is not None]


def main(run_dir: Path | str, x: str = "transitions") -> list[Path]:
    """Plot a run directory; the files written."""
    return plot_run(Path(run_dir), x)


def plot_command(run_dir: Path, x: str = "transitions") -> None:
    """Write PNG curves (learning curves, allocation, bias rate, learner) into RUN_DIR/plots."""
    from rich.console import Console

    console = Console()
    files = main(run_dir, x)
    if not files:
        console.print(f"[yellow]no metrics to plot in {run_dir}[/yellow]")
        return
    for path in files:
        console.print(f"[green]wrote[/green] {path}")
