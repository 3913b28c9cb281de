"""The replay buffer on disk: append-only chunks, exactly the rows a checkpoint counts, no pickle."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from mam_core.replay import PERSISTED, ReplayBuffer, ReplayLog


def rows(first: int, n: int, obs_dim: int = 3, act_dim: int = 2) -> dict[str, np.ndarray]:
    """Rows whose values encode their insertion index (row i has obs[:, 0] == i)."""
    i = np.arange(first, first + n, dtype=np.float32)
    return {"obs": np.repeat(i[:, None], obs_dim, 1), "action": np.repeat(-i[:, None], act_dim, 1) / 1e6,
            "reward": i * 0.5, "next_obs": np.repeat(i[:, None] + 0.25, obs_dim, 1), "terminated": (i % 7) == 0}


def insert(buf: ReplayBuffer, first: int, n: int) -> None:
    r = rows(first, n, buf.obs.shape[1], buf.action.shape[1])
    buf.add_batch(r["obs"], r["action"], r["reward"], r["next_obs"], r["terminated"], actor=first % 3,
                  version=first)


def held(buf: ReplayBuffer) -> list[int]:
    """Insertion indices of the rows in the buffer, sorted (obs[:, 0] is the index)."""
    return sorted(int(x) for x in buf.obs[: buf.size, 0])


def test_checkpoints_write_only_new_rows_and_restore_exactly(tmp_path: Path) -> None:
    buf = ReplayBuffer(100, 3, 2, seed=4)
    log = ReplayLog(tmp_path)
    insert(buf, 0, 30)
    m1 = log.append(buf)
    insert(buf, 30, 25)
    m2 = log.append(buf)
    assert m1 == [[0, 30]] and m2 == [[0, 30], [30, 25]]
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["chunk-000000000000-30.npz", "chunk-000000000030-25.npz"]
    # Plain arrays only: every member of the zip is a .npy that loads without pickle.
    with zipfile.ZipFile(tmp_path / files[1]) as z:
        assert sorted(z.namelist()) == sorted(f"{name}.npy" for name in PERSISTED)
    buf.rng.integers(0, 10, 5)  # the sampling stream moved on; the checkpoint keeps its state
    state = buf.rng.bit_generator.state
    again = ReplayBuffer(100, 3, 2)
    assert ReplayLog(tmp_path).restore(again, m2, 55, state) == 55
    for name in PERSISTED:
        np.testing.assert_array_equal(getattr(again, name)[:55], getattr(buf, name)[:55])
    assert (again.pos, again.size, again.inserted) == (buf.pos, buf.size, buf.inserted)
    np.testing.assert_array_equal(again.sample_indices(64), buf.sample_indices(64))


def test_rows_after_the_checkpoint_are_not_restored_and_stale_chunks_are_ignored(tmp_path: Path) -> None:
    buf = ReplayBuffer(100, 3, 2)
    log = ReplayLog(tmp_path)
    insert(buf, 0, 40)
    manifest = log.append(buf)  # the checkpoint counts 40 rows
    insert(buf, 40, 10)
    log.append(buf)  # a chunk written by a checkpoint that never completed (learner killed)
    again = ReplayBuffer(100, 3, 2)
    resumed = ReplayLog(tmp_path)
    resumed.restore(again, manifest, 40)
    assert held(again) == list(range(40))
    # The resumed learner gets other rows 40.. and its next checkpoint replaces the stale chunk.
    insert(again, 40, 15)
    assert resumed.append(again) == [[0, 40], [40, 15]]
    assert resumed.prune() == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chunk-000000000000-40.npz", "chunk-000000000040-15.npz"]


def test_a_wrapped_ring_keeps_the_newest_capacity_rows_and_prunes_old_chunks(tmp_path: Path) -> None:
    buf = ReplayBuffer(50, 3, 2)
    log = ReplayLog(tmp_path)
    first = 0
    for n in (20, 20, 20, 20):  # 80 rows into 50 slots
        insert(buf, first, n)
        first += n
        log.append(buf)
        log.prune()
    assert log.manifest == [[20, 20], [40, 20], [60, 20]]  # rows 0..19 are overwritten: chunk gone
    assert len(list(tmp_path.iterdir())) == 3
    insert(buf, 80, 130)  # more than the whole ring between two checkpoints
    assert log.append(buf) == [[160, 50]]  # only what the buffer still holds can be written
    log.prune()
    again = ReplayBuffer(50, 3, 2)
    ReplayLog(tmp_path).restore(again, log.manifest, 210)
    assert held(again) == list(range(160, 210)) == held(buf)
    np.testing.assert_array_equal(again.obs, buf.obs)  # the same ring positions
    # A resumed learner with a smaller buffer takes the newest rows it can hold.
    small = ReplayBuffer(30, 3, 2)
    ReplayLog(tmp_path).restore(small, log.manifest, 210)
    assert held(small) == list(range(180, 210))


def test_missing_or_malformed_chunks_fail_loudly(tmp_path: Path) -> None:
    buf = ReplayBuffer(100, 3, 2)
    log = ReplayLog(tmp_path)
    insert(buf, 0, 10)
    log.append(buf)
    insert(buf, 10, 10)
    manifest = log.append(buf)
    with pytest.raises(ValueError, match="cover"):
        ReplayLog(tmp_path).restore(ReplayBuffer(100, 3, 2), manifest[1:], 20)
    with pytest.raises(ValueError, match="checkpoint counts 25"):
        ReplayLog(tmp_path).restore(ReplayBuffer(100, 3, 2), manifest, 25)
    with pytest.raises(ValueError, match="want float32"):  # a buffer of another env's shapes
        ReplayLog(tmp_path).restore(ReplayBuffer(100, 4, 2), manifest, 20)
    (tmp_path / "chunk-000000000010-10.npz").unlink()
    with pytest.raises(ValueError, match="missing"):
        ReplayLog(tmp_path).restore(ReplayBuffer(100, 3, 2), manifest, 20)
    # An object array (which would need pickle) is refused by np.load(allow_pickle=False).
    bad = {name: np.zeros(10, dtype=object) for name in PERSISTED}
    with open(tmp_path / "chunk-000000000010-10.npz", "wb") as f:
        np.savez(f, **bad)
    with pytest.raises(ValueError, match="pickle"):
        ReplayLog(tmp_path).restore(ReplayBuffer(100, 3, 2), manifest, 20)
