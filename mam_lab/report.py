"""`mam report PATH`: tables with confidence intervals and figures from an experiment's runs.

PATH is an experiment directory (written by `mam experiment`: one run directory per
(env, variant, seed), `EXP_DIR/<env>/<variant>/seed<k>/`, plus the records of the ledger its
experiment.json names), a ledger directory (the compact records, same layout), or a folder holding
the ledger in `runs/` (`docs/results/<exp>`). Only finished runs (with `summary.json`) count; runs
planned in `experiment.json` but not finished are listed as missing. Nothing is rerun.

The report opens with a **Verdict**: each multi-actor variant against the K=1 baseline of its
family (TD3 / DDPG) in the same env, on the **deployed actor** (mam_lab.scores.deployed_points: the
survivor after the elimination C, before C the actor ranked best at the latest competition, scored
only on evaluation episodes that played no part in selecting it). Per row: the deployed actor's
final return (mean of its last 3 evaluations) and AUC after the random phase per side,
P(variant > baseline) of the final returns with a bootstrap 95% CI (`--verdict-boot`, at least
10,000 resamples), the exact one-sided permutation test's p in each direction, raw and
Holm-adjusted over the rows sharing a baseline, the stability over `--stability-seeds` bootstrap
seeds, and the word (mam_lab.stats.verdict_word): *better* only with the CI above ½ and the Holm
p below 0.05 under every seed, *worse* the mirror image, *too few runs* below 5 runs a side, else
*not separated*; the word the same rules give on the AUC; best-of-K last-10 IQMs as a labelled
secondary column; wall-clock time per run. A planned row with runs missing says how many of its
runs are in the ledger (`--config GRID.toml` plans a grid that has not started). Each run's
record.json names the commit it ran at; rows whose runs differ get a note.
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

from pathlib import Path
from typing import Annotated, Optional

import typer

from mam_lab.analysis import AXES, Report, build_report
from mam_lab.figures import plot_bias, plot_env_allocation, plot_env_curves, plot_env_training, plot_iqm
from mam_lab.stats import N_BOOT, N_BOOT_VERDICT, STABILITY_SEEDS
from mam_lab.tables import print_tables, render_markdown
from services.run import rundir


def write_report(exp_dir: Path, out: Path | None = None, n_boot: int = N_BOOT, seed: int = 0,
                 figures: bool = True, axis: str = "transitions", verdict_boot: int = N_BOOT_VERDICT,
                 stability_seeds: int = STABILITY_SEEDS, grid_file: Path | None = None,
                 ) -> tuple[Report, Path, list[Path]]:
    """Build the report, write the Markdown file and the PNGs; returns (report, markdown, PNGs)."""
    exp_dir = Path(exp_dir)
    out = Path(out) if out is not None else exp_dir / rundir.REPORT
    report = build_report(exp_dir, n_boot=n_boot, seed=seed, axis=axis, verdict_boot=verdict_boot,
                          stability_seeds=stability_seeds, grid_file=grid_file)
    report.meta = {**report.meta, "n_boot": n_boot}
    fig_dir = out.parent / rundir.FIGURES
    written: dict[str, list[Path]] = {}
    if figures:
        for env, vs in report.envs.items():
            name = rundir.env_dirname(env)
            curves = [plot_env_curves(env, vs, fig_dir / f"curves_{name}{'' if a == 'transitions' else '_' + a}.png",
                                      seed=seed, axis=a) for a in report.axes]
            for p in (*curves, plot_env_allocation(env, vs, fig_dir / f"allocation_{name}.png"),
                      plot_env_training(env, vs, fig_dir / f"training_{name}.png")):
                if p is not None:
                    written.setdefault(env, []).append(p)
        for env, bs in report.bias.items():
            p = plot_bias(env, bs, fig_dir / f"bias_{rundir.env_dirname(env)}.png")
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
    verdict_boot: Annotated[int, typer.Option(
        "--verdict-boot", help="bootstrap resamples of P(improvement) behind each verdict (at least 10,000)")
                            ] = N_BOOT_VERDICT,
    stability_seeds: Annotated[int, typer.Option(
        "--stability-seeds", help="bootstrap seeds 0..N-1 the verdict must agree over (else 'not separated')")
                               ] = STABILITY_SEEDS,
    config: Annotated[Optional[Path], typer.Option(
        "--config", help="grid TOML file whose runs count as planned too: a row not finished says how many of "
                         "its runs are in the ledger (EXP_DIR may then not exist yet)")] = None,
) -> None:
    """The verdict of each multi-actor variant against its K=1 baseline (the deployed actor's final
    return and AUC, P(improvement) with its 95% CI, the exact test's p raw and Holm, the stability
    over bootstrap seeds, the word), tables (best-of-K last-10 mean, IQM and P(improvement) with 95%
    CIs, Table 4's max average return, updates, wall time, Eq. 17 bias) and figures (learning curves
    with CI bands, allocation, bias) of an experiment. Rows not finished say how many of their runs
    are in the ledger."""
    from rich.console import Console

    console = Console()
    console.soft_wrap = not console.is_terminal  # piped: tables are Markdown, lines stay whole
    if not Path(exp_dir).is_dir() and config is None:
        raise typer.BadParameter(f"{exp_dir} is not a directory")
    if n_boot < 100:
        raise typer.BadParameter("--n-boot must be at least 100")
    if verdict_boot < N_BOOT_VERDICT:
        raise typer.BadParameter(f"--verdict-boot must be at least {N_BOOT_VERDICT:,}")
    if stability_seeds < 1:
        raise typer.BadParameter("--stability-seeds must be at least 1")
    if x not in AXES:
        raise typer.BadParameter(f"--x must be one of {', '.join(AXES)}")
    try:
        report, md, pngs = write_report(exp_dir, out, n_boot=n_boot, seed=seed, figures=not no_figures, axis=x,
                                        verdict_boot=verdict_boot, stability_seeds=stability_seeds, grid_file=config)
    except ValueError as e:  # a grid file that does not load (GridError)
        raise typer.BadParameter(str(e)) from e
    if not report.envs:
        console.print(f"[yellow]no finished runs under {exp_dir}[/]")
    print_tables(report, console)
    console.print(f"[green]wrote[/] {md}")
    for p in pngs:
        console.print(f"[green]wrote[/] {p}")


if __name__ == "__main__":
    typer.run(report_command)
