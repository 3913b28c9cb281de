"""Issue 38, the pieces a recovery reads back: the actor versions and referee snapshots a
checkpoint keeps (pickle-free, checked against the run's shapes) and the referee's state on disk
before it reports an evaluation done (fsync)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_core.replay import ReplayBuffer
from services.roles import referee as referee_role
from services.roles.checkpoint import load_checkpoint, save_checkpoint
from services.roles.learner_files import kept_weights_from, kept_weights_state
from services.run.config import RunConfig

ENV = "AppleCollect-v1"


def test_the_checkpoint_keeps_older_actor_versions_and_reads_them_back_checked(tmp_path: Path) -> None:
    algo = resolve("ma-ddpg", actors=2, hidden=(8, 8))
    cfg, spec = RunConfig(run="kept", env_id=ENV, steps=1000, algo=algo), EnvSpec.from_env_id(ENV)
    agent = MultiActorAgent(algo, spec)
    rng = np.random.default_rng(0)
    kept = [(v, k, v, {n: rng.normal(size=s).astype(np.float32) for n, s in agent.actor_shapes().items()})
            for v in (6, 7) for k in range(2)]
    save_checkpoint(tmp_path, agent, ReplayBuffer(10, spec.obs_dim, spec.act_dim), {"env_steps": 0}, cfg,
                    extra={"kept_weights": kept_weights_state(kept)})
    state = load_checkpoint(tmp_path)  # torch.load(weights_only=True): no pickle
    back = kept_weights_from(state["kept_weights"], agent.actor_shapes(), algo.actors)
    assert [row[:3] for row in back] == [row[:3] for row in kept]
    assert all(np.array_equal(a[3][n], b[3][n]) for a, b in zip(back, kept) for n in a[3])
    with pytest.raises(ValueError, match="not of this run's shapes"):  # another run's nets
        kept_weights_from(state["kept_weights"], {"w0": (3, 3)}, algo.actors)
    with pytest.raises(ValueError, match="not of this run's shapes"):  # an actor the run does not have
        kept_weights_from(state["kept_weights"], agent.actor_shapes(), 1)
    with pytest.raises(ValueError, match="not \\[version"):
        kept_weights_from([[1, 2, "x", {}]], agent.actor_shapes(), algo.actors)
    assert kept_weights_from([], agent.actor_shapes(), algo.actors) == []
    wrong = [[6, 0, 6, {n: torch.zeros(s) for n, s in agent.actor_shapes().items()} | {"w9": torch.zeros(1)}]]
    with pytest.raises(ValueError):
        kept_weights_from(wrong, agent.actor_shapes(), algo.actors)


def test_the_referee_state_is_fsynced_with_its_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = RunConfig(run="state", env_id=ENV, steps=300, algo=resolve("ma-ddpg", actors=2, hidden=(8, 8)))
    referee = referee_role.Referee(cfg, None, tmp_path)
    synced: list[str] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    referee._save_state()
    state = tmp_path / referee_role.STATE_FILE
    assert state.is_file() and not state.with_suffix(".json.tmp").exists()
    # the file before the rename, then its directory
    assert synced == [str(state.with_suffix(".json.tmp")), str(tmp_path)]
    assert referee_role.Referee(cfg, None, tmp_path).resumed  # a successor reads it back
