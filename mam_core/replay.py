"""Replay buffer: float32 numpy ring with batched O(1) insert and uniform sampling.

Each row carries the id of the actor that produced it and that actor's policy version, so
off-policy lag and the share of experience per actor can be measured.

On a CUDA learner the rows are also kept in GPU memory (`resident`, the default there): a
mini-batch is then gathered on the GPU with one index_select per field, instead of being
gathered on the host and copied over every update. The numpy arrays stay the source of
truth (checkpoints, statistics); sampling draws the same indices either way.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


class ReplayBuffer:
    FIELDS = ("obs", "action", "reward", "next_obs", "not_done")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
                 seed: int = 0, resident: bool | None = None) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = capacity
        self.device = torch.device(device)
        # A copy of the sampled fields on `device` (default: on CUDA only).
        self.resident = self.device.type == "cuda" if resident is None else resident
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.action = np.zeros((capacity, act_dim), np.float32)
        self.reward = np.zeros(capacity, np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.not_done = np.zeros(capacity, np.float32)
        self.actor = np.zeros(capacity, np.int16)
        self.version = np.zeros(capacity, np.int32)
        self.rng = np.random.default_rng(seed)
        self.pos = 0
        self.size = 0
        self.inserted = 0  # rows ever inserted (the learner's transition count)
        self._mirror: dict[str, torch.Tensor] = {}
        if self.resident:
            self._mirror = {name: torch.zeros(getattr(self, name).shape, dtype=torch.float32, device=self.device)
                            for name in self.FIELDS}

    def __len__(self) -> int:
        return self.size

    def add_batch(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                  terminated: np.ndarray, actor: int | np.ndarray = 0, version: int | np.ndarray = 0) -> None:
        """Insert N rows at once (at most two slice copies, wrapping around the ring).

        `terminated` is the environment's terminal flag only: a time-limit truncation must be
        passed as False so the target still bootstraps.
        """
        n = len(reward)
        if n == 0:
            return
        if n > self.capacity:  # only the newest `capacity` rows survive anyway
            cut = n - self.capacity
            obs, action, reward, next_obs, terminated = (a[cut:] for a in (obs, action, reward, next_obs, terminated))
            actor = actor[cut:] if isinstance(actor, np.ndarray) else actor
            version = version[cut:] if isinstance(version, np.ndarray) else version
            self.inserted += cut
            n = self.capacity
        first = min(n, self.capacity - self.pos)
        for dst, src in ((slice(self.pos, self.pos + first), slice(0, first)),
                         (slice(0, n - first), slice(first, n))):
            if src.stop == src.start:
                continue
            self.obs[dst] = obs[src]
            self.action[dst] = action[src]
            self.reward[dst] = reward[src]
            self.next_obs[dst] = next_obs[src]
            self.not_done[dst] = 1.0 - np.asarray(terminated[src], np.float32)
            self.actor[dst] = actor[src] if isinstance(actor, np.ndarray) else actor
            self.version[dst] = version[src] if isinstance(version, np.ndarray) else version
            self._mirror_rows(dst)
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.size + n, self.capacity)
        self.inserted += n

    def sample_indices(self, batch_size: int) -> np.ndarray:
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        return self.rng.integers(0, self.size, size=batch_size)

    def _mirror_rows(self, rows: slice) -> None:
        if not self._mirror or rows.stop == rows.start:
            return
        for name, dst in self._mirror.items():
            dst[rows].copy_(torch.from_numpy(getattr(self, name)[rows]))

    def sample(self, batch_size: int, groups: int | None = None) -> dict[str, torch.Tensor]:
        """Uniform mini-batch as float32 tensors on the buffer's device.

        `groups=K` draws K independent mini-batches at once (Algorithm 1, line 11: every actor
        samples its own): every field gets a leading axis of K, e.g. obs [K, B, obs_dim].
        """
        shape = (batch_size,) if groups is None else (groups, batch_size)
        idx = self.sample_indices(batch_size) if groups is None else self.sample_indices(groups * batch_size)
        if self._mirror:
            # Indices to the device (2 KB), then the gather happens there.
            i = torch.from_numpy(idx).to(self.device, non_blocking=self.device.type == "cuda")
            return {name: t.index_select(0, i).reshape(*shape, *t.shape[1:]) for name, t in self._mirror.items()}
        idx = idx.reshape(shape)
        pin = self.device.type == "cuda"
        out = {}
        for name in self.FIELDS:
            t = torch.from_numpy(getattr(self, name)[idx])
            if pin:  # page-locked staging: the copy to the GPU runs asynchronously
                t = t.pin_memory().to(self.device, non_blocking=True)
            out[name] = t
        return out

    def actor_share(self) -> np.ndarray:
        """Fraction of stored rows produced by each actor id (up to the largest id seen)."""
        if self.size == 0:
            return np.zeros(0)
        counts = np.bincount(self.actor[: self.size].astype(np.int64))
        return counts / counts.sum()

    # -- checkpoints: arrays and ints only -----------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        n = self.size
        return {
            "obs": torch.from_numpy(self.obs[:n].copy()), "action": torch.from_numpy(self.action[:n].copy()),
            "reward": torch.from_numpy(self.reward[:n].copy()), "next_obs": torch.from_numpy(self.next_obs[:n].copy()),
            "not_done": torch.from_numpy(self.not_done[:n].copy()), "actor": torch.from_numpy(self.actor[:n].copy()),
            "version": torch.from_numpy(self.version[:n].copy()),
            "pos": self.pos, "size": self.size, "inserted": self.inserted,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = int(state["size"])
        if n > self.capacity:
            raise ValueError(f"checkpoint holds {n} rows, buffer capacity is {self.capacity}")
        for name in ("obs", "action", "reward", "next_obs", "not_done", "actor", "version"):
            getattr(self, name)[:n] = state[name].numpy()
        self.pos, self.size, self.inserted = int(state["pos"]), n, int(state["inserted"])
        self.rng.bit_generator.state = state["rng"]
        self._mirror_rows(slice(0, n))
