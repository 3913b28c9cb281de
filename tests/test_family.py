"""Algorithm families as plug-ins: a family defined here, named `tests.test_family:TOY`, runs as the
built-in ones do, exactly, in the reference and under `mam run` (mam_core/family.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import typer

from mam_core.config import AlgoConfig, defaults_for, resolve
from mam_core.family import family_for
from mam_core.td3 import TABLE_3, TD3, actor_loss

ALGO = "tests.test_family:TOY"


class MeanCritics(TD3):
    """A toy family: TD3 whose actor k ascends the mean of its n critics, mean_i Q_ki(s, π_k(s)),
    instead of its first critic (Eq. 7). Everything else is TD3's: the acting rule, Eq. 9's
    smoothed target actions, the export."""

    names = ()
    help = "TD3 with Eq. 7 on the mean of an actor's critics"

    def defaults(self, algo: str) -> dict[str, Any]:
        return dict(TABLE_3, actors=2, workers=3, eta=0.2)

    def actor_step(self, agent: Any, obs: Any) -> list[Any]:
        k, n = agent.cfg.actors, agent.cfg.critics_per_actor
        pi = agent.actor(obs)
        critic_obs = obs.repeat_interleave(n, dim=0) if obs.dim() == 3 else obs
        q = agent.critic(critic_obs, agent.critic.per_actor_actions(pi)).view(k, n, -1).mean(dim=1)
        loss = actor_loss(q, agent.live)
        agent.adam_step(agent.actor_opt, loss, agent.actor_params_list)
        return [loss.detach().reshape(1), -q.detach().mean(dim=-1) * agent.live]


TOY = MeanCritics()
NOT_A_FAMILY = object()

# Pendulum: returns that differ between actors and seeds, so equal returns mean something.
SMALL = dict(hidden=(16, 16), batch_size=16, start_steps=60, compete_every=60, eliminate_at=180, workers=3,
             actors=2, eval_episodes=2, eval_every=60)
STEPS = 240


def test_a_family_in_a_users_module_is_named_module_colon_name():
    assert family_for(ALGO) is TOY
    cfg = resolve(ALGO, seed=3)
    assert cfg.family is TOY and cfg.algo == ALGO and not cfg.stochastic
    assert (cfg.actors, cfg.workers, cfg.eta, cfg.critics_per_actor) == (2, 3, 0.2, 2)  # the toy's defaults
    assert defaults_for(ALGO).policy_delay == 2
    assert AlgoConfig.from_dict(cfg.to_dict()) == cfg  # the config travels (the wire, config.json)
    assert family_for("ma-td3").names == ("ma-td3", "td3", "ma-ddpg", "ddpg")
    assert family_for("sac").stochastic and not family_for("ddpg").stochastic


@pytest.mark.parametrize("algo, message", [
    ("tests.no_such_module:Fam", "no algorithm family 'Fam' in module 'tests.no_such_module'"),
    ("tests.test_family:Missing", "no algorithm family 'Missing'"),
    ("tests.test_family:NOT_A_FAMILY", "is not an algorithm family"),
    ("ma-td4", "unknown algo 'ma-td4'; choose one of ma-td3, td3, ma-ddpg, ddpg, ma-sac, sac, or name"),
])
def test_an_algo_without_a_family_is_a_clear_error(algo: str, message: str):
    with pytest.raises(ValueError, match="invalid configuration") as e:
        AlgoConfig.from_dict(AlgoConfig(algo=algo).to_dict())
    assert message in str(e.value)
    from services.run.options import build_run_config

    with pytest.raises(typer.BadParameter, match="--algo"):
        build_run_config({"env": "Pendulum-v1", "steps": 10, "algo": algo}, None)


def test_mam_run_takes_the_family_from_the_command_line():
    from services.run.options import build_run_config

    cfg = build_run_config({"env": "Pendulum-v1", "steps": 10, "algo": ALGO, "seed": 5}, None)
    assert cfg.algo.family is TOY and cfg.algo.eta == 0.2 and cfg.run.startswith("toy-pendulum-")


def test_the_toys_actor_phase_is_its_own():
    """The reference run with the toy family differs from MA-TD3's only by Eq. 7, and reruns."""
    from mam_core.reference import run_reference

    toy = run_reference("Pendulum-v1", resolve(ALGO, seed=3, **SMALL), STEPS)
    td3 = run_reference("Pendulum-v1", resolve("ma-td3", seed=3, eta=0.2, **SMALL), STEPS)
    assert not _same_params(toy.policy, td3.policy)
    assert toy.evaluations[0] == td3.evaluations[0]  # before any actor update: the same actors
    again = run_reference("Pendulum-v1", resolve(ALGO, seed=3, **SMALL), STEPS)
    assert _same_params(again.policy, toy.policy)


def _same_params(a: list[dict[str, np.ndarray]], b: list[dict[str, np.ndarray]]) -> bool:
    return len(a) == len(b) and all(set(x) == set(y) and all(np.array_equal(x[n], y[n]) for n in x)
                                    for x, y in zip(a, b))


@pytest.mark.slow
def test_mam_run_with_a_users_family_equals_the_reference(tmp_path: Path):
    import torch

    from mam_core.policy import read_policy_file
    from mam_core.reference import run_reference
    from services.run.rundir import read_jsonl
    from tests.e2e import mam, unique_run

    torch.set_num_threads(1)  # the learner's default: the same float sums
    run_dir = tmp_path / "toy"
    mam("run", "--env", "Pendulum-v1", "--algo", ALGO, "--steps", str(STEPS), "--workers", "3", "--actors", "2",
        "--start-steps", "60", "--compete-every", "60", "--eliminate-at", "180", "--eval-episodes", "2",
        "--eval-every", "60", "--hidden", "16,16", "--batch-size", "16", "--seed", "3",
        "--run", unique_run("toy"), "--run-dir", str(run_dir), "--no-plot", timeout=240)
    ref = run_reference("Pendulum-v1", resolve(ALGO, seed=3, **SMALL), STEPS)
    meta, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exact"] is True and meta["algo"] == ALGO and "policy" not in meta
    evals = [(e["iterations"], e["purpose"], e["returns"]) for e in read_jsonl(run_dir / "eval.jsonl")]
    assert evals == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert summary["survivor"] == ref.survivor
    assert _same_params(params, ref.policy)  # np.array_equal, every actor, every layer
