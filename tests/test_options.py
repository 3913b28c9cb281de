"""Configuration: paper defaults per algorithm, TOML file, flags on top, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer

from mam_core.config import defaults_for, resolve
from services.options import RunConfig, build_run_config


def test_paper_defaults_per_algorithm():
    ma_td3 = defaults_for("ma-td3")  # Table 3
    assert (ma_td3.actors, ma_td3.workers, ma_td3.eliminate_at, ma_td3.compete_every) == (2, 3, 300_000, 5_000)
    assert (ma_td3.eta, ma_td3.batch_size, ma_td3.start_steps, ma_td3.policy_delay) == (0.1, 256, 25_000, 2)
    assert ma_td3.critics_per_actor == 2 and ma_td3.target_smoothing
    ma_ddpg = defaults_for("ma-ddpg")  # Table 1
    assert (ma_ddpg.actors, ma_ddpg.workers, ma_ddpg.eliminate_at, ma_ddpg.compete_every) == (3, 5, 24_000, 1_000)
    assert (ma_ddpg.batch_size, ma_ddpg.start_steps, ma_ddpg.critics_per_actor, ma_ddpg.eta) == (100, 10_000, 1, 0.0)
    assert defaults_for("td3").actors == 1 and defaults_for("ddpg").critics_per_actor == 1
    assert resolve("ma-td3", no_wt=True).effective_eta == 0.0


def test_toml_file_then_flags(tmp_path: Path):
    f = tmp_path / "run.toml"
    f.write_text('env = "AppleCollect-v0"\nalgo = "ma-ddpg"\nsteps = 5000\neliminate-at = 15000\nseed = 3\n'
                 '[obsolescence]\ncompete-every = 700\n')
    cfg = build_run_config({"seed": 9, "actors": None}, f)
    assert cfg.env_id == "AppleCollect-v0" and cfg.steps == 5000
    assert cfg.algo.eliminate_at == 15000 and cfg.algo.compete_every == 700
    assert cfg.algo.seed == 9  # the flag wins over the file
    assert cfg.algo.actors == 3  # untouched: Table 1
    assert RunConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize("cli, message", [
    ({"env": "Nope-v0", "steps": 10}, "Nope"),
    ({"env": "AppleCollect-v0"}, "--steps"),
    ({"env": "AppleCollect-v0", "steps": 10, "algo": "sac"}, "--algo"),
    ({"env": "AppleCollect-v0", "steps": 10, "eta": 1.5}, "eta"),
    ({"env": "AppleCollect-v0", "steps": 10, "run": "a/b"}, "run name"),
    ({"steps": 10}, "--env"),
])
def test_bad_input_is_a_clear_error(cli, message):
    with pytest.raises(typer.BadParameter, match=message):
        build_run_config(cli, None)


def _run_option_flags(app, name: str | None = None) -> dict[str, tuple[tuple[str, ...], str]]:
    """The run-option parameters of a typer command: name -> (flags, help)."""
    from typer.main import get_command

    from services.options import OPTION

    command = get_command(app)
    if name is not None:
        command = command.commands[name]
    return {p.name: (tuple(p.opts) + tuple(p.secondary_opts), p.help) for p in command.params if p.name in OPTION}


def test_the_option_table_drives_mam_run_and_mam_learner():
    from services import cli, learner
    from services.options import cli_options

    table = {o.name: (tuple(o.decls[0].split("/")), o.annotation.__metadata__[0].help) for o in cli_options()}
    assert len(table) >= 30 and "eliminate_at" in table and "save_replay" in table
    assert table["save_replay"][0] == ("--save-replay", "--no-save-replay")
    assert table["eliminate_at"][1].startswith("[C] ")
    assert _run_option_flags(cli.app, "run") == table
    assert _run_option_flags(learner.app) == table
    # `mam experiment`: the same options, less the grid's own dimensions (env, algo, steps, seed, run)
    import typer as _typer

    from mam_lab.experiment import experiment_command
    from mam_lab.grid import FLAG_NAMES, GRID_DIMENSIONS

    lab = _typer.Typer()
    lab.command()(experiment_command)
    grid_table = {k: v for k, v in table.items() if k not in GRID_DIMENSIONS}
    assert {k: v for k, v in _run_option_flags(lab).items() if k not in GRID_DIMENSIONS} == grid_table
    assert set(grid_table) <= FLAG_NAMES  # and a grid file takes every one of them


def test_the_table_knows_every_algorithm_field():
    import dataclasses

    from mam_core.config import AlgoConfig
    from services.options import ALGO, OPTION, RUN, RUN_OPTIONS

    algo_fields = {f.name for f in dataclasses.fields(AlgoConfig)}
    run_fields = {f.name for f in dataclasses.fields(RunConfig)}
    assert {o.name for o in RUN_OPTIONS if o.target == ALGO} == algo_fields
    assert {o.name for o in RUN_OPTIONS if o.target == RUN} <= run_fields | {"env"}
    assert len(OPTION) == len(RUN_OPTIONS)  # one entry per name


def test_toml_reads_table_options_and_refuses_unknown_keys(tmp_path: Path):
    f = tmp_path / "run.toml"
    f.write_text('env_id = "AppleCollect-v0"\nsteps = 500\ngamma = 0.9\nsend-batch = 16\n'
                 '[service]\nsync-every = 7\n[env_kwargs]\napple_radius = 0.3\n')
    cfg = build_run_config({}, f)
    assert cfg.env_id == "AppleCollect-v0" and cfg.algo.gamma == 0.9 and cfg.send_batch == 16
    assert cfg.sync_every == 7 and cfg.env_kwargs == {"apple_radius": 0.3}
    f.write_text('env = "AppleCollect-v0"\nsteps = 500\n[obsolescence]\ncompete-evry = 10\n')
    with pytest.raises(typer.BadParameter, match="unknown option 'compete-evry'"):
        build_run_config({}, f)
    with pytest.raises(typer.BadParameter, match="unknown option 'endpoint'"):
        build_run_config({"env": "AppleCollect-v0", "steps": 10, "endpoint": "tcp/1.2.3.4:1"}, None)
