"""`mam`: the umbrella command (run, watch, plot, and the role commands)."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from services import bus, options

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Multi-actor mechanism (MA-TD3, MA-DDPG) over Zenoh: run, watch and plot training runs.")


@app.command()
def run(
    env: options.Env = None, algo: options.Algo = None, steps: options.Steps = None,
    env_kwargs: options.EnvKwargs = None,
    actors: options.Actors = None, workers: options.Workers = None, eliminate_at: options.EliminateAt = None,
    compete_every: options.CompeteEvery = None, eta: options.Eta = None, eval_episodes: options.EvalEpisodes = None,
    eval_every: options.EvalEvery = None, start_steps: options.StartSteps = None, batch_size: options.BatchSize = None,
    utd: options.Utd = None, no_ot: options.NoOt = None, no_wt: options.NoWt = None, seed: options.Seed = None,
    device: options.Device = None, hidden: options.Hidden = None, config: options.ConfigFile = None,
    single_env_after_elimination: options.SingleEnv = None,
    bias_every: options.BiasEvery = None, bias_rollouts: options.BiasRollouts = None,
    precision: options.Precision = None, schedule: options.Schedule = None, shared_batch: options.SharedBatch = None,
    after_elimination: options.AfterElimination = None, skip_random_rounds: options.SkipRandomRounds = None,
    bias_horizon: options.BiasHorizon = None,
    run_name: options.Run = None, run_dir: options.RunDir = None,
    sync_every: int = typer.Option(None, help="publish actor weights every N updates (default 100)"),
    save_replay: bool = typer.Option(None, "--save-replay/--no-save-replay",
                                     help="persist the replay buffer beside the checkpoint (default: on)"),
    checkpoint_every: int = typer.Option(None, help="checkpoint every N updates (default 50000) ..."),
    checkpoint_rows: int = typer.Option(None, help="... or N transitions (default 20000) ..."),
    checkpoint_seconds: float = typer.Option(None, help="... or N seconds (default 60)"),
    max_restarts: int = typer.Option(5, help="a child that dies more often than this within --restart-window "
                                             "stops the run"),
    restart_window: float = typer.Option(300.0, help="seconds over which --max-restarts counts"),
    no_plot: bool = typer.Option(False, "--no-plot", help="skip the PNG plots at the end"),
) -> None:
    """Train on this box: learner + referee + M workers over an embedded loopback Zenoh."""
    from services.launcher import RestartPolicy, run_local

    logging.basicConfig(level=logging.WARNING)
    cfg = options.build_run_config(dict(
        env=env, algo=algo, steps=steps, actors=actors, workers=workers, eliminate_at=eliminate_at,
        env_kwargs=env_kwargs,
        compete_every=compete_every, eta=eta, eval_episodes=eval_episodes, eval_every=eval_every,
        start_steps=start_steps, batch_size=batch_size, utd=utd, no_ot=no_ot, no_wt=no_wt, seed=seed,
        device=device, hidden=hidden, single_env_after_elimination=single_env_after_elimination,
        run=run_name, sync_every=sync_every, save_replay=save_replay, bias_every=bias_every,
        bias_rollouts=bias_rollouts, precision=precision, schedule=schedule, shared_batch=shared_batch,
        after_elimination=after_elimination, skip_random_rounds=skip_random_rounds, bias_horizon=bias_horizon,
        checkpoint_every=checkpoint_every, checkpoint_rows=checkpoint_rows, checkpoint_seconds=checkpoint_seconds),
        config)
    options.check_precision(cfg)
    summary = run_local(cfg, run_dir or Path("runs") / cfg.run, plot=not no_plot,
                        policy=RestartPolicy(max_restarts=max_restarts, window_s=restart_window))
    if not summary:
        raise typer.Exit(1)


@app.command()
def watch(
    run_name: options.Run = None, connect: options.Connect = None, zenoh_config: options.ZenohConfig = None,
    keep: bool = typer.Option(False, help="keep watching after the run is done"),
) -> None:
    """Live view of a run from anywhere on the network (only subscribes)."""
    from services.monitor import watch as watch_run

    if not run_name:
        raise typer.BadParameter("--run NAME is required (printed by `mam run`, in RUN_DIR/config.json)")
    options.check_run_name(run_name)
    conf = bus.make_config(connect=connect or ([] if zenoh_config else ["tcp/127.0.0.1:7447"]), config_file=zenoh_config)
    watch_run(run_name, conf, until_done=not keep)


@app.command()
def plot(run_dir: Path = typer.Argument(..., help="a run directory written by `mam run`"),
         x: str = typer.Option("transitions", "--x", help="x-axis: transitions or iterations "
                                                           "(iteration plots get an _iterations suffix)")) -> None:
    """Learning curves per actor, allocation over time, bias rate and learner curves as PNG."""
    from services.plot import X_AXES, plot_command

    if not run_dir.is_dir():
        raise typer.BadParameter(f"{run_dir} is not a directory")
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
    from services.chaos import app as chaos_app

    chaos_app(ctx.args, prog_name="mam chaos", standalone_mode=True)


def _register_harness() -> None:
    """`mam experiment` and `mam report` (their modules import matplotlib)."""
    from mam_lab.experiment import experiment_command
    from mam_lab.report import report_command

    app.command("experiment")(experiment_command)
    app.command("report")(report_command)


_register_harness()


def _register_eval() -> None:
    """`mam eval RUN_DIR`: a trained actor's returns and video, numpy only (services/eval_command.py)."""
    from services.eval_command import eval_command

    app.command("eval")(eval_command)


_register_eval()


def _role(name: str):
    def command(ctx: typer.Context) -> None:
        import importlib

        module = importlib.import_module(f"services.{name}")
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
