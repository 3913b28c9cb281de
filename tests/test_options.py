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
