"""Configuration: paper defaults per algorithm, TOML file, flags on top, clear errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer

from mam_core.config import defaults_for, resolve
from services.run.config import RunConfig
from services.run.options import build_run_config


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
    ({"env": "AppleCollect-v0", "steps": 10, "algo": "ppo"}, "--algo"),
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

    from services.run.options import OPTION

    command = get_command(app)
    if name is not None:
        command = command.commands[name]
    return {p.name: (tuple(p.opts) + tuple(p.secondary_opts), p.help) for p in command.params if p.name in OPTION}


def test_the_option_table_drives_mam_run_and_mam_learner():
    from services.cli import app as cli
    from services.roles import learner
    from services.run.options import cli_options

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
    from services.run.options import ALGO, OPTION, RUN, RUN_OPTIONS

    algo_fields = {f.name for f in dataclasses.fields(AlgoConfig)}
    run_fields = {f.name for f in dataclasses.fields(RunConfig)}
    assert {o.name for o in RUN_OPTIONS if o.target == ALGO} == algo_fields
    assert {o.name for o in RUN_OPTIONS if o.target == RUN} <= run_fields | {"env"}
    assert len(OPTION) == len(RUN_OPTIONS)  # one entry per name


def test_toml_reads_table_options_and_refuses_unknown_keys(tmp_path: Path):
    f = tmp_path / "run.toml"
    f.write_text('env_id = "AppleCollect-v0"\nsteps = 500\ngamma = 0.9\nsend-batch = 16\n'
                 '[service]\ncheckpoint-rows = 7000\n[algorithm]\nlag = 2\n[env_kwargs]\napple_radius = 0.3\n')
    cfg = build_run_config({}, f)
    assert cfg.env_id == "AppleCollect-v0" and cfg.algo.gamma == 0.9 and cfg.send_batch == 16
    assert cfg.checkpoint_rows == 7000 and cfg.algo.lag == 2 and cfg.env_kwargs == {"apple_radius": 0.3}
    f.write_text('env = "AppleCollect-v0"\nsteps = 500\n[service]\nsync-every = 7\n')
    with pytest.raises(typer.BadParameter, match="'sync-every' was removed with the asynchronous collection"):
        build_run_config({}, f)
    f.write_text('env = "AppleCollect-v0"\nsteps = 500\n[obsolescence]\ncompete-evry = 10\n')
    with pytest.raises(typer.BadParameter, match="unknown option 'compete-evry'"):
        build_run_config({}, f)
    with pytest.raises(typer.BadParameter, match="unknown option 'endpoint'"):
        build_run_config({"env": "AppleCollect-v0", "steps": 10, "endpoint": "tcp/1.2.3.4:1"}, None)


def _help_panels(text: str) -> dict[str, str]:
    """`--help` output split into rich panels: title -> the panel's text."""
    import re

    panels: dict[str, list[str]] = {}
    current = None
    for line in text.splitlines():
        title = re.match(r"^╭─ (.+?) ─+╮$", line)
        if title:
            current = title.group(1)
            panels[current] = []
        elif line.startswith("╰"):
            current = None
        elif current is not None:
            panels[current].append(line.strip("│").rstrip())
    return {name: "\n".join(lines) for name, lines in panels.items()}


def _option_blocks(panel: str) -> dict[str, str]:
    """Flag -> its rows (help text joined) in one panel."""
    blocks: dict[str, list[str]] = {}
    flag = None
    for line in panel.splitlines():
        if line.startswith(" --"):  # an option's row; its help wraps onto indented rows
            flag = line.split()[0]
            blocks[flag] = []
        if flag is not None:
            blocks[flag].append(line)
    return {f: " ".join(" ".join(rows).split()) for f, rows in blocks.items()}


def test_help_snapshot_every_option_in_a_panel_with_its_default_at_80_columns():
    """`mam run --help` at 80 columns: every run option sits in one of the named panels, whole (no
    name cut with …), with its default (per --algo where they differ), and no `<bool>` tag."""
    import os
    import subprocess
    import sys

    from services.run.options import HELP_PANELS, cli_options, default_text

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, COLUMNS="80", TERM="dumb", NO_COLOR="1")
    text = subprocess.run([sys.executable, "-m", "services.cli", "run", "--help"], cwd=root, env=env,
                          capture_output=True, text=True, timeout=120).stdout
    assert "<bool>" not in text and max(len(line) for line in text.splitlines()) <= 80
    panels = _help_panels(text)
    assert set(panels) <= set(HELP_PANELS) | {"Options"}  # Options: typer's own --help only
    blocks = {name: _option_blocks(body) for name, body in panels.items()}
    assert set(blocks.get("Options", {})) <= {"--help"}
    for option in cli_options():
        flag = option.decls[0].split("/")[0]
        where = [name for name, b in blocks.items() if flag in b]
        assert where == [option.help_panel], (flag, where)
        block = blocks[option.help_panel][flag]
        default = default_text(option)
        if default:
            assert f"[default: {default}]" in block, (flag, block)
    for flag in ("--config", "--run-dir", "--max-restarts", "--restart-window", "--no-plot"):
        assert any(flag in b for b in blocks.values()), flag
    assert "…" not in " ".join(f for b in blocks.values() for f in b)  # no flag cut short
    algorithm = blocks["Algorithm (the paper's symbols)"]
    assert "[default: ma-td3, ma-sac: 2; td3, ddpg, sac: 1; ma-ddpg: 3]" in algorithm["--actors"]
    assert algorithm["--eliminate-at"].startswith("--eliminate-at <int> [C] ")


def test_steps_error_speaks_the_schedule_s_units():
    with pytest.raises(typer.BadParameter, match=r"--steps \[T\] must be a positive number of iterations "
                                                 r"\(under --schedule paper\), not -5"):
        build_run_config({"env": "AppleCollect-v0", "steps": -5}, None)
    with pytest.raises(typer.BadParameter, match="transitions"):
        build_run_config({"env": "AppleCollect-v0", "steps": 0, "schedule": "equal-data"}, None)


def test_a_toml_typo_gets_did_you_mean_and_points_to_help(tmp_path: Path):
    f = tmp_path / "run.toml"
    f.write_text('env = "AppleCollect-v0"\nsteps = 500\neliminate-att = 300\n')
    with pytest.raises(typer.BadParameter) as e:
        build_run_config({}, f)
    message = str(e.value)
    assert "unknown option 'eliminate-att'; did you mean 'eliminate-at'?" in message
    assert "mam run --help" in message and "services/run/options.py" not in message


def test_help_names_what_is_true_today():
    """The help items of issue 40: MA-SAC named, bf16's layers, --env and --steps required, the
    --arithmetic default shown, and no generated run name offered to a process that joins a run."""
    import typer

    from mam_lab.experiment import experiment_command
    from services.cli.app import app
    from services.roles import monitor, referee, worker
    from services.run import options

    assert "MA-SAC" in (app.info.help or "")
    assert "ma-sac" in (experiment_command.__doc__ or "")
    assert "every layer but the head" in options.OPTION["precision"].help_text
    for name in ("env", "steps"):
        assert "required" in options.OPTION[name].help_text
    assert "[default: portable" in options.OPTION["arithmetic"].help_text
    for role in (worker, referee, monitor):
        run = next(p for p in typer.main.get_command(role.app).params if p.name == "run")
        assert "ALGO-ENV" not in (run.help or "") and not run.default, role.__name__
