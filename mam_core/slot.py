"""One environment slot's acting rule, shared by the worker process and the reference driver.

Both must produce the same transitions from the same seed, so both call these functions: the
slot's random streams (mam_core.seeding, per slot and purpose), the acting rule (`act`: the
exploratory action, or SAC's sampled one), and the conversions of what the env returns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mam_core.config import AlgoConfig
from mam_core.seeding import stream, stream_seed

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass
class SlotStreams:
    """Slot `slot`'s three streams: the first reset's seed, the start phase's uniform actions
    (seeds `env.action_space`), and the exploration noise."""

    reset_seed: int
    action_seed: int
    noise: np.random.Generator

    @classmethod
    def for_slot(cls, seed: int, slot: int, generation: int = 0) -> SlotStreams:
        return cls(stream_seed(seed, "env", slot, generation), stream_seed(seed, "random-actions", slot, generation),
                   stream(seed, "noise", slot, generation))

    def seed_env(self, env: Any) -> np.ndarray:
        """Seed the env's action space and make its first reset; the first observation."""
        env.action_space.seed(self.action_seed)
        return np.asarray(env.reset(seed=self.reset_seed)[0], np.float32)


def explore(policy: Policy, obs: np.ndarray, noise: np.random.Generator, sigma: float,
            max_action: np.ndarray) -> np.ndarray:
    """π_k(s) + N(0, σ)·max_action, clipped to the action bounds (Algorithm 1, line 7)."""
    action = policy(obs)
    eps = noise.normal(0.0, sigma, action.shape[-1]).astype(np.float32)
    return np.clip(action + eps * max_action, -max_action, max_action)


def act(policy: Policy, obs: np.ndarray, noise: np.random.Generator, algo: AlgoConfig,
        max_action: np.ndarray) -> np.ndarray:
    """Algorithm 1, line 7 for every algorithm: TD3 and DDPG explore around π_k(s) (`explore`);
    SAC samples a = max_action · tanh(μ + σ·ε) from π_k(·|s) with the slot's noise stream drawing
    ε (a `SquashedGaussianPolicy`), so it has no exploration noise of its own."""
    if algo.stochastic:
        return policy.sample(obs, noise)
    return explore(policy, obs, noise, algo.explore_noise, max_action)


def uniform(env: Any) -> np.ndarray:
    """A start-phase action: uniform over the action space (its seeded generator)."""
    return env.action_space.sample().astype(np.float32)
