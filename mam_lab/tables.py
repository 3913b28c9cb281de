"""The report's tables: Markdown (report.md) and rich (the terminal), from a `Report`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mam_lab.analysis import SUCCESS_RETURN, Comparison, PendingRow, Report, VariantStats, Verdict
from mam_lab.runs import BiasStats
from mam_lab.stats import N_BOOT, Interval, VerdictResult


def _fmt(x: float, digits: int | None = None) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    if digits is None:
        digits = 0 if abs(x) >= 1000 else 1 if abs(x) >= 100 else 2
    return f"{x:,.{digits}f}"


def _ci(i: Interval, digits: int | None = None) -> str:
    return f"[{_fmt(i.lo, digits)}, {_fmt(i.hi, digits)}]"


TABLE_HEADER = ("variant", "setting", "runs", "deployed final return ± std", "deployed AUC ± std",
                "best-of-K last-10 mean ± std", "95% CI", "best-of-K IQM [95% CI]",
                "best-of-K max avg return ± std (@ step)", "updates", "transitions", "wall s (run)",
                "wall s (launcher)")


def env_rows(vs: Sequence[VariantStats]) -> tuple[list[str], list[list[str]]]:
    header = list(TABLE_HEADER)
    apple = any(v.success is not None for v in vs)
    if apple:
        header.append(f"final ≥ {SUCCESS_RETURN:.2f} (50 apple) [95% CI]")
    rows = []
    for v in vs:
        row = [v.variant, v.setting(), str(v.n), _mean_std(v.deployed_final), _mean_std(v.deployed_auc),
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


def _p(x: float) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.3f}" if x >= 0.001 else f"{x:.1e}"


# What every `±` of the report is (the paper's ± is a std over seeds too, without saying which).
SPREAD_TEXT = ("Every ± is the standard deviation over seeds with divisor n (numpy's default), not the sample "
               "deviation (divisor n − 1), which is √(n/(n − 1)) times larger: 12% for 5 seeds, 5% for 10.")


def _mean_std(a: np.ndarray) -> str:
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    if not a.size:
        return "–"
    return f"{_fmt(float(a.mean()))} ± {_fmt(float(a.std()))}"


def _runs_cell(v: Verdict) -> str:
    text = f"{v.n_x} / {v.n_y}"
    if not v.complete:
        have = v.n_x + v.n_y
        planned = (v.planned_x or v.n_x) + (v.planned_y or v.n_y)
        text += f" ({have} of {planned} runs in the ledger)"
    return text


def _verdict_cells(r: VerdictResult) -> list[str]:
    t = r.test
    return [f"{_fmt(r.p.value, 2)} {_ci(r.p, 2)}", f"{_p(t.p_greater)} / {_p(t.p_greater_holm)}",
            f"{_p(t.p_less)} / {_p(t.p_less_holm)}", r.stability_text(), f"*{r.word}*"]


VERDICT_HEADER = ("env", "variant", "vs", "runs", "final return variant / baseline (mean ± std)",
                  "AUC variant / baseline (mean ± std)", "P(variant > baseline) [95% CI]",
                  "exact p variant > baseline (raw / Holm)", "exact p variant < baseline (raw / Holm)",
                  "stability over bootstrap seeds", "verdict", "verdict on AUC",
                  "best-of-K last-10 IQM variant / baseline (secondary)", "wall s/run variant / baseline", "commit")
TERMINAL_COLUMNS = 11  # the terminal shows the first columns (to the verdict word); report.md has them all


def verdict_rows(vd: Sequence[Verdict], pending: Sequence[PendingRow] = ()) -> tuple[list[str], list[list[str]]]:
    """The verdict table: per row the deployed actor's final return and AUC per side, P(variant >
    baseline) on the final return with its CI, the exact one-sided p (raw and Holm) in both
    directions, the stability over bootstrap seeds, the verdict word (and the word the same rules
    give on the AUC), then best-of-K as a labelled secondary column. `pending`: planned rows with
    no verdict yet, each saying how many of its runs are in the ledger."""
    header = list(VERDICT_HEADER)
    rows = []
    for v in vd:
        commit = (next(iter(v.commits)) if not v.mixed else
                  "**different commits**: " + ", ".join(f"{c} ({n})" for c, n in sorted(v.commits.items())))
        ratio = v.wall_x / v.wall_y if math.isfinite(v.wall_x) and math.isfinite(v.wall_y) and v.wall_y > 0 else None
        p, pg, pl, stab, word = _verdict_cells(v.final)
        rows.append([v.env, v.variant, v.baseline, _runs_cell(v),
                     f"{_mean_std(v.final_x)} / {_mean_std(v.final_y)}", f"{_mean_std(v.auc_x)} / {_mean_std(v.auc_y)}",
                     p, pg, pl, stab, word, f"*{v.auc.word}*", f"{_fmt(v.iqm_x.value)} / {_fmt(v.iqm_y.value)}",
                     f"{_wall(v.wall_x)} / {_wall(v.wall_y)}" + (f" (×{ratio:.2f})" if ratio else ""), commit])
    have = {(v.env, v.variant) for v in vd}
    for r in pending:
        if (r.env, r.variant) not in have:
            word = "*not yet run*" if not r.have else "*too few runs*"
            rows.append([r.env, r.variant, r.baseline, r.text()] + ["–"] * 6 + [word] + ["–"] * 4)
    return header, rows


def per_run_rows(vs: Sequence[VariantStats]) -> tuple[list[str], list[list[str]]]:
    """Per variant, each run's deployed final return and AUC (seed: value)."""
    header = ["variant", "deployed final return per run", "deployed AUC per run"]

    def cells(values: np.ndarray, v: VariantStats) -> str:
        return ", ".join(f"{r.seed}: {_fmt(float(x))}" for r, x in zip(v.runs, values))

    return header, [[v.variant, cells(v.deployed_final, v), cells(v.deployed_auc, v)] for v in vs]


def auc_verdict_rows(vd: Sequence[Verdict]) -> tuple[list[str], list[list[str]]]:
    """The verdict rules applied to the deployed actor's AUC (the word is also in the main table)."""
    header = ["env", "variant", "vs", "runs", "AUC variant / baseline (mean ± std)", "P(variant > baseline) [95% CI]",
              "exact p variant > baseline (raw / Holm)", "exact p variant < baseline (raw / Holm)",
              "stability over bootstrap seeds", "verdict on AUC"]
    rows = [[v.env, v.variant, v.baseline, _runs_cell(v), f"{_mean_std(v.auc_x)} / {_mean_std(v.auc_y)}",
             *_verdict_cells(v.auc)] for v in vd]
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


VERDICT_TEXT = (
    "Each multi-actor variant against the K=1 baseline of its family in the same grid (TD3 for MA-TD3, DDPG for "
    "MA-DDPG, SAC for MA-SAC), on the **deployed actor**: the survivor after the elimination C and, before C, "
    "the actor ranked best at the latest competition, scored only on evaluation episodes that played no part in "
    "selecting it (rows of a competition's own evaluation score the actor chosen by the competition before it). *Final "
    "return*: per run the mean of the deployed actor's last {final_n} evaluations; *AUC*: the area under its "
    "curve from the end of the random phase (--start-steps) to the budget, divided by that span (a mean return). "
    "P(variant > baseline) of the final returns with a bootstrap 95% CI ({verdict_boot:,} resamples, seed 0); "
    "the exact one-sided permutation (Mann-Whitney) p in each direction, raw and Holm-adjusted over the rows "
    "that share a baseline. *better* only where the CI's lower bound is above 0.5 **and** the Holm-adjusted p "
    "(variant > baseline) is below 0.05, *worse* the mirror image, under each of {seeds} bootstrap seeds "
    "(where the seeds disagree: *not separated*); *too few runs* below {min_runs} runs a side. Best-of-K "
    "(the best live actor's last-10 score, a max over K before C) is a secondary column only.")


def verdict_params(report: Report) -> dict[str, Any]:
    from mam_lab.scores import FINAL_N
    from mam_lab.stats import MIN_RUNS

    n_boot = next((v.final.n_boot for v in report.verdicts), report.meta.get("verdict_boot") or 10_000)
    seeds = next((len(v.final.words) for v in report.verdicts), report.meta.get("stability_seeds") or 20)
    return {"final_n": FINAL_N, "verdict_boot": n_boot, "seeds": seeds, "min_runs": MIN_RUNS}


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
                     f"budget T = {_fmt(grid.get('steps') or math.nan, 0)} per run: iterations "
                     f"under --schedule paper (M transitions and one update each before C, one of each after), "
                     f"transitions under equal-data (see each row's transitions and updates).")
    versions = report.meta.get("versions") or {}
    if versions:
        lines.append("Versions: " + ", ".join(f"{k} {v}" for k, v in sorted(versions.items())) + ".")
    if report.missing:
        lines += ["", f"**Incomplete: {len(report.missing)} planned run(s) not finished** "
                      f"(resume with the same `mam experiment` command): "
                      + ", ".join(f"`{m}`" for m in report.missing[:20])
                      + (" …" if len(report.missing) > 20 else "")]
    if report.verdicts or report.pending:
        header, rows = verdict_rows(report.verdicts, report.pending)
        lines += ["", "## Verdict", "", VERDICT_TEXT.format(**verdict_params(report)), "", _md_table(header, rows)]
        if report.verdicts:
            lines += ["", "The same rules on the deployed actor's AUC after the random phase:", "",
                      _md_table(*auc_verdict_rows(report.verdicts))]
    if report.notes:
        lines += ["", "**Notes:**", ""] + [f"- {n}" for n in report.notes]
    lines += ["", f"Tables on the x-axis: **{AXIS_TEXT.get(report.axis, report.axis)}**; learning curves on "
              + " and on ".join(report.axes) + ".",
              "", SPREAD_TEXT,
              "", "*Deployed final return* and *deployed AUC*: the verdict's scores (above), mean ± std over "
              "seeds. The *best-of-K* columns (secondary: before C they take a max over the K actors, on the "
              "episodes that selected them) score an evaluation as the mean return of the best live actor (the "
              "survivor after the elimination). *last-10 mean*: per run the mean of its last 10 evaluations, then "
              "mean ± std over "
              "seeds and a bootstrap 95% CI; *IQM*: interquartile mean of the per-run last-10 scores "
              f"(bootstrap 95% CI, {N_BOOT if not report.meta.get('n_boot') else report.meta['n_boot']} "
              "resamples); *max avg return*: the paper's Table 4 statistic, max over evaluation points of the "
              "mean over seeds, ± std over seeds at that point."]
    for env, vs in report.envs.items():
        header, rows = env_rows(vs)
        unit = report.axis
        lines += ["", f"## {env}", "", f"Evaluation grid spacing: {_fmt(vs[0].spacing, 0)} {unit} (x-axis: "
                  f"{report.axis}); wall s: mean wall-clock seconds per run (the referee's, and the launcher's from "
                  "start to end).", "", _md_table(header, rows)]
        header, rows = per_run_rows(vs)
        lines += ["", "Per run (seed: value), the deployed actor's final return and AUC:", "", _md_table(header, rows)]
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
                  "Secondary (best-of-K scores). P(X > Y): the chance that a run of X has a higher best-of-K last-10 "
                  "score than a run of Y (ties count ½), "
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


def print_table(console: Any, title: str, header: Sequence[str], rows: Sequence[Sequence[str]],
                fold: bool = False) -> None:
    """A table on a terminal as a rich table; elsewhere (a pipe, a file) as a Markdown table under
    its title, one line per row, never wrapped to the console's width."""
    if console.is_terminal:
        console.print(_rich_table(title, header, rows, fold=fold))
        return
    console.print(f"{title}\n\n{_md_table(header, rows)}\n", markup=False, highlight=False, soft_wrap=True)


def print_tables(report: Report, console: Any) -> None:
    """The report's tables on the console: rich tables on a terminal, Markdown otherwise (print_table)."""
    if report.verdicts or report.pending:
        header, rows = verdict_rows(report.verdicts, report.pending)
        console.print(SPREAD_TEXT, highlight=False)
        print_table(console, "Verdict (the deployed actor's final return; rules and more columns in report.md)",
                    header[:TERMINAL_COLUMNS], [r[:TERMINAL_COLUMNS] for r in rows], fold=True)
    for r in report.pending:
        console.print(f"[yellow]unfinished[/]: {r.env} {r.variant} vs {r.baseline}: {r.text()}")
    for note in report.notes:
        console.print(f"[yellow]note[/]: {note}")
    for env, vs in report.envs.items():
        print_table(console, f"{env} (x-axis {report.axis})", *env_rows(vs), fold=True)
        if any(v.success is not None for v in vs):
            print_table(console, f"{env}: 50 apple", *reach_rows(vs), fold=True)
    for env, bs in report.bias.items():
        print_table(console, f"Estimation bias (Eq. 17), {env}", *bias_rows(bs))
    if report.comparisons:
        print_table(console, "Probability of improvement on another score: the best live actor's last-10 mean "
                    "(best-of-K, secondary; the verdict's P scores the deployed actor's final return)",
                    *comparison_rows(report.comparisons))
    if report.aggregate:
        rows = [[name, str(n), _fmt(i.value, 3), _ci(i, 3)] for name, n, i in report.aggregate]
        print_table(console, "Aggregate over envs: IQM of range-normalised scores",
                    ("variant", "envs", "normalised IQM", "95% CI"), rows)
    if report.missing:
        console.print(f"[yellow]{len(report.missing)} planned run(s) not finished[/]")
