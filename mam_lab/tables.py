"""The report's tables: Markdown (report.md) and rich (the terminal), from a `Report`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mam_lab.analysis import SUCCESS_RETURN, Comparison, Report, VariantStats, Verdict
from mam_lab.runs import BiasStats
from mam_lab.stats import N_BOOT, Interval


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
                     f"{v.successes}/{v.n} ({_fmt(100 * s.value, 0)}%) "
                     f"[{_fmt(100 * s.lo, 0)}%, {_fmt(100 * s.hi, 0)}%]",
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


def render_markdown(report: Report, figures: dict[str, list[Path]], out: Path) -> str:
    """The report as Markdown; `figures` maps env (or "all") to PNG paths, linked relative to `out`."""
    lines = [f"# Experiment report: {report.meta.get('name') or report.exp_dir.name}", ""]
    n_runs = sum(v.n for vs in report.envs.values() for v in vs)
    lines.append(f"Experiment directory `{report.exp_dir}`: {n_runs} finished runs.")
    grid = report.meta.get("grid") or {}
    if grid:
        lines.append(f"Grid: envs {grid.get('envs')}, algos {grid.get('algos')}, seeds {grid.get('seeds')}, "
                     f"budget T = {_fmt(grid.get('steps') or math.nan, 0)} schedule steps per run: iterations "
                     f"under --schedule paper (M transitions and one update each before C, one of each after), "
                     f"transitions under equal-data (see each row's env steps and updates).")
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
