"""`mam experiment`: a grid of algorithms × seeds × envs through the distributed system.

The command only wires the pieces together: `mam_lab.grid` (which runs, with which flags, and the
budget in schedule steps), `mam_lab.scheduler` (P runs at once, each its own process, Ctrl-C and
resuming), `mam_lab.ledger` (the compact records of finished runs, which a fresh clone resumes
from) and `mam_lab.view` (the progress view); their docstrings say how each works.

EXP_DIR is runs/experiments/<name> unless `--exp-dir` or the grid file's `exp-dir` says otherwise
(runs/ is ignored by git: a user's grid writes nothing into the source tree); a ledger is kept only
where `--ledger` or the grid file's `ledger` names one (the project's evidence grids:
docs/results/<name>/runs). The grid file's format: deploy/experiments/README.md.

    EXP_DIR/experiment.json             the grid, the planned runs, versions, the ledger
    EXP_DIR/<env>/<variant>/seed<k>/    a run directory (config.json, eval.jsonl, summary.json, ...)
    EXP_DIR/<env>/<variant>/seed<k>/launcher.log   what `mam run` would have printed
    EXP_DIR/<env>/<variant>/seed<k>/record.json    which code ran it (commit), with what, how long
    EXP_DIR/failures/...                logs of failed attempts
    EXP_DIR/report.md, EXP_DIR/figures/ `mam report EXP_DIR` (run at the end unless --no-report)

Runs are ordered seed by seed (all envs and variants of seed 0, then seed 1, ...), so a grid
stopped early still has balanced results across algorithms (a grid file's `order = "env"` runs env
by env instead, and `[env-seeds]` gives an env its own seeds). `--stop-by TIME` starts no run that
its estimated wall time would carry past TIME (see mam_lab.scheduler); runs in flight at TIME are
allowed to finish and are recorded when they do.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.console import Console

from mam_core.config import ALGOS
from mam_lab.grid import GRID_DIMENSIONS, GridError, load_grid_file, make_grid, plan, seeds_text, variants
from mam_lab.ledger import check_resume, wall_estimates, write_manifest
from mam_lab.provenance import ROOT, code_version, commit_label
from mam_lab.scheduler import GridResult, core_slots, default_parallel, parse_stop_by, run_grid
from mam_lab.view import describe_plan, hms

# --- command ---------------------------------------------------------------------------------
from services.run import cpu, options, preflight, runlock


@options.run_options(exclude=tuple(GRID_DIMENSIONS))
def experiment_command(
    run_opts: dict[str, Any],
    config: Annotated[Optional[Path], typer.Option(
        "--config", help="grid TOML file (its format: deploy/experiments/README.md); flags given here win over "
                   "it")] = None,
    exp_dir: Annotated[Optional[Path], typer.Option(
        "--exp-dir", help="experiment directory (default: the grid file's exp-dir, else runs/experiments/<name>, "
                          "<name> being --name, the grid file's name, or 'experiment'); run again with the same "
                          "directory to resume")] = None,
    envs: Annotated[Optional[str], typer.Option("--envs", help="comma-separated env ids, e.g. "
                                                                "HalfCheetah-v5,Hopper-v5")] = None,
    algos: Annotated[Optional[str], typer.Option("--algos", help=f"comma-separated, of {', '.join(ALGOS)}")] = None,
    seeds: Annotated[Optional[str], typer.Option("--seeds", help="N (seeds 0..N-1), A-B, or a list 0,3,7")] = None,
    steps: Annotated[Optional[int], typer.Option(
        "--steps", help="[T] budget of every run in schedule steps: iterations (--schedule paper) or "
                        "transitions (equal-data)")] = None,
    ablations: Annotated[Optional[str], typer.Option(
        "--ablations", help="extra variants of each multi-actor algo: no-ot, no-wt (comma-separated)")] = None,
    etas: Annotated[Optional[str], typer.Option(
        "--etas", help="η sweep: one variant per value for each multi-actor algo, e.g. 0.05,0.1,0.2")] = None,
    name: Annotated[Optional[str], typer.Option("--name", help="experiment name (default: the grid file's)")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="print the planned runs and exit")] = False,
    retries: Annotated[int, typer.Option("--retries", help="attempts after a failed run")] = 1,
    fail_fast: Annotated[bool, typer.Option("--fail-fast", help="stop at the first run that fails")] = False,
    no_plot: Annotated[bool, typer.Option("--no-plot", help="no per-run PNGs (RUN_DIR/plots)")] = False,
    no_report: Annotated[bool, typer.Option("--no-report", help="skip `mam report` at the end")] = False,
    parallel: Annotated[Optional[int], typer.Option(
        "--parallel", help="runs at once, each its own process pinned to its own cores (default: cores ÷ "
                           "--cores-per-run, at least 1)")] = None,
    cores_per_run: Annotated[int, typer.Option("--cores-per-run", help="cores per run for the default --parallel")] = 1,
    pin: Annotated[bool, typer.Option(
        "--pin/--no-pin", help="CPU affinity of each run's learner (cores ÷ P each)")] = True,
    ledger: Annotated[Optional[Path], typer.Option(
        "--ledger", help="directory of the compact records of finished runs, to commit (default: the grid file's "
                         "ledger, else none: the experiment directory alone holds the runs); relative to the "
                         "current directory; a run recorded there is finished")] = None,
    no_ledger: Annotated[bool, typer.Option("--no-ledger", help="keep no ledger")] = False,
    variants_opt: Annotated[Optional[str], typer.Option(
        "--variants", help="run only these variants of the grid (comma-separated names)")] = None,
    stop_by: Annotated[Optional[str], typer.Option(
        "--stop-by", help="deadline, HH:MM (local time, the next time the clock shows it) or an ISO datetime: "
                          "start no run whose estimated "
                          "wall time (median of the finished runs of its env and variant, here and in the ledger; "
                          "for a stopped run that goes on from its checkpoint, the share still to do) "
                          "would end after it; a run with no estimate yet starts while the deadline is ahead. Runs "
                          "still in flight at the deadline are allowed to finish and are recorded when they do "
                          "(Ctrl-C: not recorded, continued from its checkpoint on resume); the runs not started "
                          "wait for the next invocation")] = None,
) -> None:
    """Run a grid of algorithms × seeds × envs through the distributed system; resumable.

    Every run option of `mam run` but the grid's own dimensions (env, algo, steps, seed, run name)
    is a flag here too. The multi-actor flags (--actors, --workers, --eliminate-at, --compete-every,
    --eta, --after-elimination, ...) apply to ma-td3, ma-ddpg and ma-sac only; the others to every run.
    """
    import logging

    logging.basicConfig(level=logging.WARNING)
    console = Console()
    console.soft_wrap = not console.is_terminal  # piped into a file: long lines stay whole
    try:
        file = load_grid_file(config) if config is not None else {}
        flags = run_opts  # every run option of the table but the grid's own dimensions
        grid = make_grid(file, envs=envs, algos=algos, seeds=seeds, steps=steps, ablations=ablations, etas=etas,
                         name=name, flags=flags, variants=variants_opt)
        specs = plan(grid)
        for spec in specs:  # before anything starts: bf16 where it would only be slower
            if dict(spec.flags).get("precision") == "bf16":
                cpu.check_precision(spec.run_config("check"))
        for device in sorted({str(dict(s.flags).get("device") or "auto") for s in specs}):
            try:  # a device torch does not see fails every run: say so once, before the first
                preflight.check_device(device)
            except preflight.ConfigError as e:
                raise GridError(str(e)) from None
        _, aliases = variants(grid)
        if exp_dir is None:  # runs/ is ignored by git: nothing lands in the source tree
            exp_dir = Path(str(file["exp_dir"])) if file.get("exp_dir") else Path("runs") / "experiments" / grid.name
        if no_ledger:
            ledger = None
        elif ledger is None and file.get("ledger"):  # the project's evidence grids: docs/results/<name>/runs
            ledger = Path(str(file["ledger"]))
        if parallel is not None and parallel < 1:
            raise GridError("--parallel must be >= 1")
        if cores_per_run < 1:
            raise GridError("--cores-per-run must be >= 1")
        parallel = parallel or default_parallel(cores_per_run)
        check_resume(specs, exp_dir, ledger)
        deadline = parse_stop_by(stop_by) if stop_by is not None else None
    except (GridError, ValueError) as e:
        raise typer.BadParameter(str(e)) from e
    estimates = wall_estimates(specs, exp_dir, ledger)
    describe_plan(specs, aliases, exp_dir, console, ledger, estimates)
    if deadline is not None:
        console.print(f"stop by {deadline.isoformat(timespec='minutes')}: no run starts that its estimate says "
                      "would end later; runs in flight then are allowed to finish")
    slots = core_slots(parallel) if pin else [()] * parallel
    code = code_version(ROOT)
    console.print(f"{parallel} run(s) at once" + (", cores " + "; ".join(seeds_text(c) for c in slots) if pin else
                                                  ", not pinned")
                  + (f"; ledger {ledger}" if ledger is not None else "; no ledger")
                  + f"; code {ROOT} at {commit_label(code)}")
    if dry_run:
        return
    try:  # one grid per directory: a second would take this one's runs in flight for stopped ones
        lock = runlock.lock_experiment(exp_dir, grid.name)
    except runlock.RunInUse as e:
        console.print(f"[red]error[/]: {e}", highlight=False)
        raise typer.Exit(runlock.EXIT_REFUSED) from None
    with lock:
        write_manifest(exp_dir, grid, specs, aliases, ledger, parallel=parallel)
        try:
            result = run_grid(specs, exp_dir, console, plot_runs=not no_plot, retries=retries, fail_fast=fail_fast,
                              parallel=parallel, cores=slots, ledger=ledger, experiment=grid.name,
                              stop_by=deadline.timestamp() if deadline is not None else None, estimates=estimates)
        except KeyboardInterrupt:
            result = GridResult(interrupted=True)
    console.print(f"[bold]{len(result.skipped) + len(result.finished)}/{len(specs)}[/] runs finished "
                  f"({len(result.finished)} now, {len(result.skipped)} before), {len(result.failed)} failed "
                  f"in {hms(result.elapsed_s)}")
    if result.deferred:
        console.print(f"[yellow]{len(result.deferred)} run(s) not started[/]: they would end after --stop-by "
                      f"{stop_by}; run the same command again to continue")
    if not no_report and (result.finished or result.skipped):
        from mam_lab.report import write_report
        from mam_lab.tables import print_tables

        report, md, pngs = write_report(exp_dir)
        print_tables(report, console)
        console.print(f"[green]report[/] {md} ({len(pngs)} figures)")
    if result.interrupted:
        console.print(f"[yellow]interrupted[/]: run the same command again to resume ({exp_dir})")
        raise typer.Exit(130)
    if result.in_use:
        console.print(f"[red]{len(result.in_use)} run(s) not started[/]: another process holds their run "
                      "directories (above); stop it, then run the same command again")
    if result.failed or result.in_use:
        raise typer.Exit(1)


def main() -> None:
    typer.run(experiment_command)


if __name__ == "__main__":
    main()
