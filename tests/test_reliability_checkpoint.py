"""Verified checkpoint generations: a damaged newest one falls back to the previous one; a full
disk leaves the previous one intact and no temp file; a damaged chunk's error names the file."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_core.policy import load_policy
from mam_core.replay import ReplayBuffer, ReplayLog
from services.roles.checkpoint import (
    CheckpointCorrupt,
    CheckpointError,
    generations,
    load_checkpoint,
    load_replay,
    replay_dir,
    save_checkpoint,
)
from services.run.config import RunConfig

ENV = "AppleCollect-v0"


def make(tmp: Path, rows_per_gen: int = 50):
    algo = resolve("ma-ddpg", actors=2, hidden=(8, 8))
    cfg = RunConfig(run="ck", env_id=ENV, steps=1000, algo=algo)
    spec = EnvSpec.from_env_id(ENV)
    agent = MultiActorAgent(algo, spec)
    buf = ReplayBuffer(10_000, spec.obs_dim, spec.act_dim)
    return cfg, spec, agent, buf, ReplayLog(replay_dir(tmp))


def add(buf: ReplayBuffer, spec: EnvSpec, n: int) -> None:
    rng = np.random.default_rng(buf.inserted)
    buf.add_batch(rng.normal(size=(n, spec.obs_dim)).astype(np.float32),
                  rng.uniform(-1, 1, (n, spec.act_dim)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, spec.obs_dim)).astype(np.float32), np.zeros(n, bool))


def two_generations(tmp: Path):
    cfg, spec, agent, buf, rlog = make(tmp)
    for _ in range(2):
        add(buf, spec, 50)
        save_checkpoint(tmp, agent, buf, {"env_steps": buf.inserted}, cfg, rlog)
    assert generations(tmp) == [2, 1]
    return cfg, spec, agent, buf, rlog


def flip(path: Path, offset: int | None = None) -> None:
    data = bytearray(path.read_bytes())
    i = len(data) // 2 if offset is None else offset
    data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def test_generations_are_kept_two_with_manifests_and_links(tmp_path: Path) -> None:
    cfg, spec, agent, buf, rlog = two_generations(tmp_path)
    add(buf, spec, 50)
    save_checkpoint(tmp_path, agent, buf, {"env_steps": buf.inserted}, cfg, rlog)
    ck = tmp_path / "checkpoints"
    assert generations(tmp_path) == [3, 2]
    assert sorted(p.name for p in ck.iterdir() if p.is_file()) == [
        "learner-000002.pt", "learner-000003.pt", "learner.pt", "manifest-000002.json", "manifest-000003.json",
        "policy-000002.npz", "policy-000003.npz", "policy.npz"]
    assert os.path.samefile(ck / "learner.pt", ck / "learner-000003.pt")
    assert load_policy(tmp_path, actor=1).env_id == ENV
    state = load_checkpoint(tmp_path)
    assert state["checkpoint"] == {"generation": 3, "skipped": []}
    assert len(load_replay(tmp_path, state=state)) == 150
    assert not list(ck.rglob("*.tmp"))


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "policy", "manifest"])
def test_a_damaged_newest_generation_falls_back_to_the_previous_one(tmp_path: Path, damage: str, caplog) -> None:
    two_generations(tmp_path)
    ck = tmp_path / "checkpoints"
    if damage == "flipped byte":  # 64 bytes into the middle of learner.pt, as in the issue
        path = ck / "learner.pt"
        data = bytearray(path.read_bytes())
        data[len(data) // 2:len(data) // 2 + 64] = os.urandom(64)
        with open(path, "r+b") as f:  # in place: learner.pt is the newest generation's file
            f.write(bytes(data))
    elif damage == "truncated":
        path = ck / "learner-000002.pt"
        os.truncate(path, path.stat().st_size // 3)
    elif damage == "policy":
        flip(ck / "policy-000002.npz")
    else:
        (ck / "manifest-000002.json").write_text("{not json")
    with caplog.at_level(logging.WARNING, logger="mam.checkpoint"):
        state = load_checkpoint(tmp_path)
    assert state["checkpoint"]["generation"] == 1 and len(state["checkpoint"]["skipped"]) == 1
    assert int(state["counters"]["env_steps"]) == 50
    assert "generation 2 is not usable" in caplog.text and "resuming from checkpoint generation 1" in caplog.text
    assert len(load_replay(tmp_path, state=state)) == 50


def test_a_damaged_newest_replay_chunk_falls_back_and_names_the_file(tmp_path: Path) -> None:
    two_generations(tmp_path)
    chunk = replay_dir(tmp_path) / "chunk-000000000050-50.npz"
    flip(chunk, 100)
    state = load_checkpoint(tmp_path)
    assert state["checkpoint"]["generation"] == 1
    assert str(chunk) in state["checkpoint"]["skipped"][0]
    # Read directly (bypassing the manifest), a damaged chunk is a ValueError naming it, never a bare BadZipFile.
    spec = EnvSpec.from_env_id(ENV)
    buf = ReplayBuffer(1000, spec.obs_dim, spec.act_dim)
    chunk.write_bytes(chunk.read_bytes()[:200])
    with pytest.raises(ValueError, match=str(chunk)):
        ReplayLog(replay_dir(tmp_path)).restore(buf, [[0, 50], [50, 50]], 100)


def test_no_generation_verifies_is_a_clear_error(tmp_path: Path) -> None:
    two_generations(tmp_path)
    flip(replay_dir(tmp_path) / "chunk-000000000000-50.npz")  # both generations need it
    with pytest.raises(CheckpointCorrupt, match="no checkpoint generation .* verifies"):
        load_checkpoint(tmp_path)


def test_a_new_generation_after_a_fallback_drops_the_damaged_one(tmp_path: Path) -> None:
    cfg, spec, agent, buf, _ = two_generations(tmp_path)
    flip(tmp_path / "checkpoints" / "learner-000002.pt")
    state = load_checkpoint(tmp_path)
    buf = ReplayBuffer(10_000, spec.obs_dim, spec.act_dim)
    rlog = ReplayLog(replay_dir(tmp_path))
    meta = state["replay_log"]
    rlog.restore(buf, meta["manifest"], int(meta["inserted"]))
    add(buf, spec, 10)
    save_checkpoint(tmp_path, agent, buf, {"env_steps": buf.inserted}, cfg, rlog)
    assert generations(tmp_path) == [3, 1]  # the damaged 2 is gone, 1 kept to fall back to
    assert load_checkpoint(tmp_path)["checkpoint"]["generation"] == 3
    assert len(load_replay(tmp_path)) == 60


def fill(directory: Path, leave: int = 0) -> Path:
    """Fill the file system of `directory` (leaving about `leave` bytes)."""
    ballast = directory / "ballast"
    free = shutil.disk_usage(directory).free - leave
    with open(ballast, "wb") as f:
        try:
            while free > 0:
                n = min(free, 1 << 20)
                f.write(b"\0" * n)
                free -= n
            f.flush()
        except OSError:
            pass
    return ballast


def test_disk_full_keeps_the_previous_generation_and_leaves_no_temp_file(tmpfs: Path) -> None:
    run_dir = tmpfs / "run"
    cfg, spec, agent, buf, rlog = two_generations(run_dir)
    fill(tmpfs)
    add(buf, spec, 2000)
    with pytest.raises(CheckpointError) as info:
        save_checkpoint(run_dir, agent, buf, {"env_steps": buf.inserted}, cfg, rlog)
    text = str(info.value)
    assert "No space left on device" in text and str(run_dir / "checkpoints") in text and "free" in text, text
    assert "the previous checkpoint (generation 2) is intact" in text
    ck = run_dir / "checkpoints"
    assert not [p for p in ck.rglob("*") if p.name.endswith(".tmp")]
    assert sorted(p.name for p in replay_dir(run_dir).iterdir()) == ["chunk-000000000000-50.npz",
                                                                      "chunk-000000000050-50.npz"]
    assert generations(run_dir) == [2, 1]
    assert load_checkpoint(run_dir)["checkpoint"] == {"generation": 2, "skipped": []}
    # Space again: the next checkpoint goes on from where the failed one left off.
    (tmpfs / "ballast").unlink()
    save_checkpoint(run_dir, agent, buf, {"env_steps": buf.inserted}, cfg, rlog)
    assert len(load_replay(run_dir)) == 2100
