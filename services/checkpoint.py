"""The learner's checkpoint: agent, counters and config in one pickle-free torch file, and the
replay buffer as append-only chunks beside it (RUN_DIR/checkpoints/)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from mam_core.agent import MultiActorAgent
from mam_core.policy import EnvSpec
from mam_core.replay import ReplayBuffer, ReplayLog
from services import rundir
from services.options import RunConfig

CHECKPOINT_FILE = rundir.LEARNER_CHECKPOINT
REPLAY_DIR = rundir.REPLAY  # RUN_DIR/checkpoints/replay/chunk-<first>-<rows>.npz


def replay_dir(run_dir: Path) -> Path:
    return run_dir / rundir.CHECKPOINTS / REPLAY_DIR


def save_checkpoint(run_dir: Path, agent: MultiActorAgent, buffer: ReplayBuffer, counters: dict[str, Any],
                    cfg: RunConfig, replay_log: ReplayLog | None = None) -> Path:
    """Atomic, pickle-free checkpoint (tensors and plain containers; load with weights_only=True).

    With a `replay_log` the rows inserted since the previous checkpoint are appended as one
    chunk file first; the checkpoint then names the chunks that hold every row it counts
    (`replay_log`: inserted, manifest, sampling rng). Chunks no checkpoint names any more are
    deleted only once this checkpoint is in place.
    """
    path = run_dir / rundir.CHECKPOINTS / CHECKPOINT_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"agent": agent.state_dict(), "counters": counters, "config": json.dumps(cfg.to_dict())}
    if replay_log is not None:
        manifest = replay_log.append(buffer)
        state["replay_log"] = {"inserted": buffer.inserted, "manifest": manifest,
                               "rng": json.dumps(buffer.rng.bit_generator.state)}
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    if replay_log is not None:
        replay_log.prune()
    return path


def load_replay(run_dir: Path, capacity: int | None = None, state: dict[str, Any] | None = None) -> ReplayBuffer:
    """The replay buffer a checkpoint counts (for tests and tools): every row, in a new buffer."""
    state = state if state is not None else load_checkpoint(run_dir)
    meta = state["replay_log"]
    cfg = RunConfig.from_dict(json.loads(state["config"]))
    spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
    inserted = int(meta["inserted"])
    buffer = ReplayBuffer(capacity or max(inserted, 1), spec.obs_dim, spec.act_dim)
    ReplayLog(replay_dir(run_dir)).restore(buffer, meta["manifest"], inserted, json.loads(meta["rng"]))
    return buffer


def load_checkpoint(run_dir: Path) -> dict[str, Any]:
    path = run_dir / rundir.CHECKPOINTS / CHECKPOINT_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return torch.load(path, weights_only=True, map_location="cpu")
