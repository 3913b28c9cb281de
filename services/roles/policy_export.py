"""RUN_DIR/checkpoints/policy.npz: the actors' weights for `mam eval` and `load_policy`.

The learner writes it next to every checkpoint (`write_policy`), numpy only and pickle-free,
so using a trained policy needs neither torch nor Zenoh. `export_from_checkpoint` rebuilds it
from `learner.pt` with torch (`weights_only=True`) for run directories that predate the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mam_core.policy import DETERMINISTIC, POLICY_FILE, EnvSpec, save_policy_file
from services.run import rundir
from services.run.config import RunConfig


def policy_meta(cfg: RunConfig, spec: EnvSpec, *, env_steps: int, updates: int, versions: list[int],
                live: list[bool], survivor: int | None) -> dict[str, Any]:
    """What `load_policy` and `mam eval` need besides the weights (JSON)."""
    algo = cfg.algo
    kind = algo.family.policy_kind  # SAC: mean and log σ heads (load_policy)
    kind = {"policy": kind} if kind != DETERMINISTIC else {}
    return {**kind, "run": cfg.run, "env_id": cfg.env_id, "env_kwargs": dict(cfg.env_kwargs), "algo": algo.algo,
            "seed": algo.seed, "explore_noise": algo.explore_noise, "eval_episodes": algo.eval_episodes,
            "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "max_action": list(spec.max_action),
            "hidden": list(algo.hidden), "env_steps": int(env_steps), "updates": int(updates),
            "versions": [int(v) for v in versions], "live": [bool(x) for x in live],
            "survivor": None if survivor is None else int(survivor)}


def write_policy(run_dir: Path, cfg: RunConfig, agent: Any, env_steps: int, survivor: int | None) -> Path:
    """The learner's current actors (a `MultiActorAgent`) to RUN_DIR/checkpoints/policy.npz."""
    params = [agent.actor_params(k) for k in range(cfg.algo.actors)]
    meta = policy_meta(cfg, agent.spec, env_steps=env_steps, updates=agent.updates, versions=agent.versions,
                       live=agent.live_actors, survivor=survivor)
    return save_policy_file(run_dir / rundir.CHECKPOINTS / POLICY_FILE, params, meta)


def export_from_checkpoint(run_dir: Path) -> Path:
    """Write policy.npz from checkpoints/learner.pt (needs torch; for older run directories)."""
    import torch

    from mam_core.agent import MultiActorAgent

    path = run_dir / rundir.CHECKPOINTS / rundir.LEARNER_CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    state = torch.load(path, weights_only=True, map_location="cpu")
    cfg = RunConfig.from_dict(json.loads(state["config"]))
    spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
    agent = MultiActorAgent(cfg.algo, spec, torch.device("cpu"))
    agent.load_state_dict(state["agent"])
    live = agent.live_actors
    survivor = live.index(True) if sum(live) == 1 and cfg.algo.actors > 1 else None
    return write_policy(run_dir, cfg, agent, int(state["counters"]["env_steps"]), survivor)
