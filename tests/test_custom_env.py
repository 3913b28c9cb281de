"""Any gymnasium Box env: registered ids, `module.path:EnvId`, `--env-kwargs`, and clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer

from mam_core.envs import EnvError, make_env
from mam_core.evaluation import evaluate_policy
from mam_core.policy import EnvSpec
from services.messaging.codec import decode, encode
from services.run.config import RunConfig
from services.run.options import build_run_config, default_run_name

TINY = "tests.envs.tiny:Tiny-v0"


def test_module_env_id_and_kwargs_reach_the_env():
    env = make_env(TINY, {"goal": -0.75, "scale": 0.5})
    obs, _ = env.reset(seed=1)
    assert obs[1] == np.float32(-0.75) and env.action_space.high.tolist() == [0.5]
    assert env.spec.max_episode_steps == 20
    assert EnvSpec.from_env_id(TINY, {"scale": 0.5}) == EnvSpec(2, 1, (0.5,))
    # evaluation rollouts make the env with the same kwargs: the goal moves the returns
    stay = lambda obs: np.zeros((len(obs), 1), np.float32)  # noqa: E731
    near = evaluate_policy(stay, TINY, 4, seed=3, env_kwargs={"goal": 0.0})
    far = evaluate_policy(stay, TINY, 4, seed=3, env_kwargs={"goal": 1.9})
    assert far.mean() < near.mean() - 10


def test_run_config_carries_env_kwargs_from_flags_toml_and_the_wire(tmp_path: Path):
    cfg = build_run_config({"env": TINY, "env_kwargs": '{"goal": -0.5}', "steps": 100, "algo": "td3"}, None)
    assert cfg.env_id == TINY and cfg.env_kwargs == {"goal": -0.5}
    assert default_run_name(TINY, "td3").startswith("td3-tiny-")
    # the config topic (msgpack) and config.json (JSON) keep them
    wire = decode(encode("config", {"config": cfg.to_dict()}, sender="t", seq=1))
    assert RunConfig.from_dict(wire["config"]) == cfg
    assert RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    f = tmp_path / "run.toml"
    f.write_text(f'env = "{TINY}"\nsteps = 100\nalgo = "td3"\n[env_kwargs]\ngoal = 0.25\nscale = 0.1\n')
    assert build_run_config({}, f).env_kwargs == {"goal": 0.25, "scale": 0.1}
    assert build_run_config({"env_kwargs": '{"goal": 1}'}, f).env_kwargs == {"goal": 1}  # the flag wins
    # a run config from before env_kwargs existed still loads
    old = cfg.to_dict()
    del old["env_kwargs"]
    assert RunConfig.from_dict(old).env_kwargs == {}


@pytest.mark.parametrize("cli, message", [
    ({"env": "tests.envs.tiny:TinyDiscrete-v0"}, "must be a gymnasium Box"),
    ({"env": "tests.envs.tiny:TinyUnbounded-v0"}, "must be finite"),
    ({"env": "tests.envs.no_such_module:Tiny-v0"}, "'tests.envs.no_such_module' does not import"),
    ({"env": "tests.envs.broken:Broken-v0"}, "does not import .RuntimeError: this env module is broken"),
    ({"env": "tests.envs.tiny:Nope-v0"}, "Nope"),
    ({"env": TINY, "env_kwargs": "{goal: 1}"}, "not valid JSON"),
    ({"env": TINY, "env_kwargs": "[1, 2]"}, "JSON object"),
    ({"env": TINY, "env_kwargs": '{"nope": 1}'}, "nope"),
    ({"env": "Blackjack-v1"}, "must be a gymnasium Box"),  # a registered env mam cannot train on
])
def test_envs_mam_cannot_use_are_clear_errors_before_anything_starts(cli, message):
    with pytest.raises(typer.BadParameter, match=message):
        build_run_config({"steps": 10, **cli}, None)


def test_make_env_errors_are_env_errors():
    with pytest.raises(EnvError, match="does not import"):
        make_env("tests.envs.no_such_module:Tiny-v0")
    with pytest.raises(EnvError, match="kwargs"):
        make_env(TINY, {"nope": 1})
