"""A test-only environment with randomness outside the seed: `tests.hidden_env:HiddenNoise-v0`.

AppleCollect-v1 whose observations carry a little noise from a generator seeded by the operating
system, so two processes never see the same episode even from the same reset seed. A worker
that takes a slot over cannot rebuild it: it must say so, and the run must finish anyway.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from mam_core.envs import make_env


class HiddenNoise(gym.ObservationWrapper):
    def __init__(self) -> None:
        super().__init__(make_env("AppleCollect-v1"))
        self.hidden = np.random.default_rng()  # not from any seed: the point of this env

    def observation(self, observation: np.ndarray) -> np.ndarray:
        noise = self.hidden.normal(0.0, 1e-3, np.shape(observation))
        return np.clip(np.asarray(observation) + noise, self.observation_space.low,
                       self.observation_space.high).astype(self.observation_space.dtype)


if "HiddenNoise-v0" not in gym.registry:
    gym.register(id="HiddenNoise-v0", entry_point=HiddenNoise, max_episode_steps=None)
