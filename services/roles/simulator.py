"""A worker's simulator, guarded: a step that raises or returns something non-finite is an
`EnvFault` (counted by kind), a reset that keeps failing makes the env anew, and one that never
works ends the process (its supervisor restarts it). services/roles/worker.py retries the
faulty step of an iteration on a reset env, so every iteration keeps its one transition."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from mam_core.envs import make_env

log = logging.getLogger("mam.worker")

ENV_RETRIES = 10  # consecutive failed resets before the env is made anew; as many again: the worker exits
FAULTS = ("step_exception", "reset_exception", "nonfinite_obs", "nonfinite_reward")


class EnvFault(Exception):
    """The simulator raised or returned something unusable (counted by kind)."""

    def __init__(self, kind: str, detail: str = "") -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


class GuardedSimulator:
    """The env methods of a worker (a mixin: it holds `env`, `spec`, `cfg`, `faults`, `env_remade`)."""

    env: Any
    spec: Any
    cfg: Any
    faults: dict[str, int]
    env_remade: int

    def env_step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        """env.step, or EnvFault if it raises or returns a non-finite observation or reward."""
        try:
            next_obs, reward, terminated, truncated, _ = self.env.step(action)
            next_obs = np.asarray(next_obs, np.float32)
            reward = float(reward)
        except Exception as e:  # anything the simulator throws: this episode is lost, not the worker
            raise EnvFault("step_exception", f"{type(e).__name__}: {e}") from e
        if next_obs.shape != (self.spec.obs_dim,) or not np.isfinite(next_obs).all():
            raise EnvFault("nonfinite_obs", f"shape {next_obs.shape}")
        if not math.isfinite(reward):
            raise EnvFault("nonfinite_reward", repr(reward))
        return next_obs, reward, bool(terminated), bool(truncated)

    def reset_env(self, seed: int | None = None) -> np.ndarray:
        """A finite first observation: retries a failing reset, then makes the env anew,
        and gives up (the worker exits, its supervisor restarts it) if that fails too."""
        for attempt in range(2 * ENV_RETRIES):
            if attempt == ENV_RETRIES:
                log.warning("env reset failed %d times in a row: making %s anew", ENV_RETRIES, self.cfg.env_id)
                try:
                    self.env.close()
                except Exception:
                    pass
                self.env = make_env(self.cfg.env_id, self.cfg.env_kwargs)
                self.env_remade += 1
            try:
                obs, _ = self.env.reset(seed=seed) if seed is not None and attempt == 0 else self.env.reset()
                obs = np.asarray(obs, np.float32)
            except Exception as e:
                self.count_fault(EnvFault("reset_exception", f"{type(e).__name__}: {e}"))
                continue
            if obs.shape != (self.spec.obs_dim,) or not np.isfinite(obs).all():
                self.count_fault(EnvFault("nonfinite_obs", "after reset"))
                continue
            return obs
        raise RuntimeError(f"{self.cfg.env_id}: no usable reset in {2 * ENV_RETRIES} tries")

    def count_fault(self, fault: EnvFault) -> None:
        self.faults[fault.kind] += 1
        if self.faults[fault.kind] <= 3 or self.faults[fault.kind] % 100 == 0:
            log.warning("env fault %s (%d so far): %s", fault.kind, self.faults[fault.kind], fault.detail[:300])
