"""`mam`: the umbrella command (run, watch, plot, and the role commands)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import typer

from services.run import cpu, options
from services.run.config import curve_points, no_updates

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Multi-actor mechanism (MA-TD3, MA-DDPG, MA-SAC) over Zenoh: run, watch and plot training "
                       "runs, on one box or across machines.")


@app.command(cls=options.PlainFlags, epilog=options.FILE_ONLY_EPILOG)
@options.run_options()
def run(
    run_opts: dict[str, Any], config: options.ConfigFile = None, run_dir: options.RunDir = None,
    max_restarts: int = typer.Option(5, help="a child that dies more often than this within --restart-window "
                                             "stops the run", rich_help_panel=options.SUPERVISION_PANEL),
    restart_window: float = typer.Option(300.0, help="seconds over which --max-restarts counts",
                                         rich_help_panel=options.SUPERVISION_PANEL),
    no_plot: bool = typer.Option(False, "--no-plot", help="skip the PNG plots at the end",
                                 show_default=False, rich_help_panel=options.RUN_PANEL),
    resume: Optional[Path] = typer.Option(None, "--resume", metavar="RUN_DIR",
                                          help="continue the stopped run in RUN_DIR (Ctrl-C, a killed `mam run`, "
                                               "a reboot) to its budget, with the options it started with",
                                          rich_help_panel=options.RUN_PANEL),
    allow_no_updates: bool = typer.Option(False, "--allow-no-updates", show_default=False,
                                          help="run a budget that ends within the random start phase (no update: "
                                               "the policy stays random); refused without it",
                                          rich_help_panel=options.SCHEDULE_PANEL),
    allow_other_code: bool = typer.Option(False, "--allow-other-code", show_default=False,
                                          help="with --resume: continue a run that ran another commit or other "
                                               "library versions (it is then no longer exact)",
                                          rich_help_panel=options.RUN_PANEL),
) -> None:
    """Train on this box: learner + referee + M workers over an embedded loopback Zenoh."""
    from services.run.cluster import RestartPolicy
    from services.run.launcher import run_local

    logging.basicConfig(level=logging.WARNING)
    from mam_lab.provenance import run_code
    from services.run import preflight

    code = run_code()  # what RUN_DIR/code.json records (a resume compares it)
    if resume is not None:
        if run_dir is not None and run_dir.resolve() != resume.resolve():
            raise typer.BadParameter(f"--run-dir {run_dir} contradicts --resume {resume}")
        (cfg, forced), run_dir = options.resume_config(resume, run_opts, config, code, allow_other_code), resume
    else:
        forced = []
        cfg = options.build_run_config(run_opts, config)
    cpu.check_precision(cfg)
    run_dir = run_dir or Path("runs") / cfg.run
    made = not run_dir.exists()
    try:  # a configuration error stops here, before any process starts (services/run/preflight.py)
        preflight.check_device(cfg.algo.device)
        preflight.check_run_dir(run_dir)
    except preflight.ConfigError as e:
        raise typer.BadParameter(str(e)) from None
    if resume is None and no_updates(cfg) and not allow_no_updates:  # a random policy's return, said as a result
        if made:
            run_dir.rmdir()  # the check above made it; nothing else is there
        raise typer.BadParameter(f"{no_updates(cfg)}, or pass --allow-no-updates to run it anyway")
    if resume is None and curve_points(cfg):
        typer.echo(f"note: {curve_points(cfg)}", err=True)
    outcome: dict[str, Any] = {}
    try:  # a new run refuses a directory holding another run's checkpoint (checked under the run lock)
        summary = run_local(cfg, run_dir, plot=not no_plot, outcome=outcome,
                            policy=RestartPolicy(max_restarts=max_restarts, window_s=restart_window), code=code,
                            forced_code=forced, new_run=resume is None)
    except preflight.ConfigError as e:
        raise typer.BadParameter(str(e)) from None
    if not summary:  # 130 / 143 when SIGINT / SIGTERM stopped it (128 + the signal), else 1
        raise typer.Exit(128 + int(outcome["signal"]) if outcome.get("signal") else 1)


@app.command(cls=options.PlainFlags)
def watch(
    run_name: options.Run = None, connect: options.Connect = None, zenoh_config: options.ZenohConfig = None,
    run_dir: Optional[Path] = typer.Option(None, "--run-dir", help="the run's directory (its config.json says "
                                           "where it listens); default: the local runs `mam run` registers, "
                                           "then runs/NAME"),
    timeout: float = typer.Option(60.0, "--timeout", help="seconds to wait for the run to appear (and for its "
                                  "first message)"),
    keep: bool = typer.Option(False, "--keep", help="keep watching after the run is done"),
    plain: Optional[bool] = typer.Option(None, "--plain/--live", show_default=False,
                                         help="one line per update, or the live view (default: plain when the "
                                         "output is not a terminal)"),
) -> None:
    """Live view of a run (only subscribes). Without --connect it finds a local `mam run` by its name."""
    from services.roles.monitor import watch_command

    watch_command(run_name, connect, zenoh_config, run_dir, timeout, keep, plain)


@app.command(cls=options.PlainFlags)
def plot(run_dir: Path = typer.Argument(..., help="a run directory written by `mam run`"),
         x: str = typer.Option("transitions", "--x", help="x-axis: transitions or iterations "
                                                           "(iteration plots get an _iterations suffix)")) -> None:
    """Learning curves per actor, allocation over time, bias rate and learner curves as PNG."""
    from services.run.plot import X_AXES, plot_command

    if not run_dir.is_dir():
        raise typer.BadParameter(f"{run_dir} is not a directory")
    if not any((run_dir / name).is_file() for name in ("config.json", "eval.jsonl", "learner.jsonl")):
        raise typer.BadParameter(f"{run_dir} is not a run directory (no config.json, eval.jsonl or learner.jsonl; "
                                 "`mam run` writes them into runs/NAME)")
    if x not in X_AXES:
        raise typer.BadParameter(f"--x must be one of {', '.join(X_AXES)}")
    plot_command(run_dir, x)


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True, "help_option_names": []})
def bench(ctx: typer.Context) -> None:
    """Performance ratios: learner vs single TD3, end to end, transport, scaling (see --help)."""
    from mam_lab.bench import app as bench_app

    bench_app(ctx.args, prog_name="mam bench", standalone_mode=True)


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True, "help_option_names": []})
def chaos(ctx: typer.Context) -> None:
    """A `mam run` while random children are killed with SIGKILL; checks it still finishes (see --help)."""
    from services.run.chaos import app as chaos_app

    chaos_app(ctx.args, prog_name="mam chaos", standalone_mode=True)


_PASSTHROUGH = {"allow_extra_args": True, "ignore_unknown_options": True, "help_option_names": []}


def _register_lab() -> None:
    """`mam experiment` and `mam report`, imported only when they run (their modules import
    matplotlib and torch, which the role commands must not load)."""
    lab = {"experiment": ("mam_lab.experiment", "experiment_command",
                          "Run a grid of algorithms × seeds × envs through the distributed system; resumable "
                          "(see --help)."),
           "report": ("mam_lab.report", "report_command",
                      "Tables (last-10 mean, IQM, P(improvement)) and figures of an experiment (see --help).")}

    def lazy(name: str, module: str, function: str, doc: str) -> None:
        def command(ctx: typer.Context) -> None:
            import importlib

            sub = typer.Typer(add_completion=False)
            sub.command(cls=options.PlainFlags)(getattr(importlib.import_module(module), function))
            sub(ctx.args, prog_name=f"mam {name}", standalone_mode=True)

        command.__doc__ = doc
        app.command(name, context_settings=_PASSTHROUGH)(command)

    for name, (module, function, doc) in lab.items():
        lazy(name, module, function, doc)


_register_lab()


def _register_eval() -> None:
    """`mam eval RUN_DIR`: a trained actor's returns and video, numpy only (services/cli/eval_command.py)."""
    from services.cli.eval_command import eval_command

    app.command("eval", cls=options.PlainFlags)(eval_command)


_register_eval()


def _role(name: str):
    def command(ctx: typer.Context) -> None:
        import importlib

        module = importlib.import_module(f"services.roles.{name}")
        module.app(ctx.args, prog_name=f"mam {name}", standalone_mode=True)

    command.__doc__ = ("A Zenoh router (star hub) for multi-host runs." if name == "router"
                       else f"Same as `mam-{name}` (pass its flags after the name).")
    return command


for _name in ("learner", "worker", "referee", "router"):
    app.command(_name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True,
                                         "help_option_names": []})(_role(_name))


def main() -> None:
    app()


if __name__ == "__main__":
    main()
