"""A small custom env that mam does not register: importing this module registers it.

Used as `--env tests.envs.tiny:Tiny-v0` (gymnasium's `module:EnvId` form). A point on a line
moves towards a goal: obs (position, goal), action a move in [-scale, scale], reward minus the
distance after the move; 20 steps. `goal` and `scale` are constructor kwargs (`--env-kwargs`).
Also registers two envs mam must refuse: a discrete action space and unbounded actions.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class TinyEnv(gym.Env[np.ndarray, np.ndarray]):
    metadata = {"render_modes": []}

    def __init__(self, goal: float = 0.5, scale: float = 0.25) -> None:
        self.goal = float(goal)
        self.scale = float(scale)
        self.observation_space = gym.spaces.Box(-2.0, 2.0, shape=(2,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-self.scale, self.scale, shape=(1,), dtype=np.float32)
        self._x = 0.0

    def _obs(self) -> np.ndarray:
        return np.array([self._x, self.goal], np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._x = float(self.np_random.uniform(-1.0, 1.0))
        return self._obs(), {}

    def step(self, action: np.ndarray):
        move = float(np.clip(np.asarray(action, np.float64).reshape(-1)[0], -self.scale, self.scale))
        self._x = float(np.clip(self._x + move, -2.0, 2.0))
        return self._obs(), -abs(self._x - self.goal), False, False, {}


class TinyDiscreteEnv(TinyEnv):
    def __init__(self) -> None:
        super().__init__()
        self.action_space = gym.spaces.Discrete(3)


class TinyUnboundedEnv(TinyEnv):
    def __init__(self) -> None:
        super().__init__()
        self.action_space = gym.spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32)


for _id, _cls in (("Tiny-v0", "TinyEnv"), ("TinyDiscrete-v0", "TinyDiscreteEnv"),
                  ("TinyUnbounded-v0", "TinyUnboundedEnv")):
    if _id not in gym.registry:
        gym.register(id=_id, entry_point=f"{__name__}:{_cls}", max_episode_steps=20)
