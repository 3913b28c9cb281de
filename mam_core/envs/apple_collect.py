"""AppleCollect (paper Sec. 3.1.2): a 2-D task with two far, large rewards and two near, small ones.

The paper fixes: square [-1, 1]^2 (side 2), start (0, 0), max move 0.2 per step, apples worth
50 at (0.8, 0.8) and (-0.8, -0.8), worth 10 at (0.5, -0.5) and (-0.5, 0.5), reward -0.01
every step, 100 steps per episode. The 10 apples are local optima near the start; a policy
that explores enough finds a 50 apple.

Choices the paper leaves open (also in docs/APPLECOLLECT.md):
- Action: Box(-0.2, 0.2, (2,), float32), the move (dx, dy). Each axis is clipped to +-0.2,
  so the largest step is 0.2 per axis (0.28 diagonally).
- Border: the new position is clipped into the square; pushing into a wall slides along it.
- Apple radius 0.1. An apple is collected when the straight move of this step passes within
  the radius of it (segment-to-point distance), not only when the step ends inside it, so a
  0.28-long diagonal step cannot jump over a 0.2-wide apple.
- Collecting an apple ends the episode: terminated=True, reward = apple value - 0.01.
  Hence the optimum is a 50 apple reached in 4 steps (return 49.96).
- Observation: the position (x, y) as float32, nothing else.
- Episode length 100 comes from gymnasium's TimeLimit (`max_episode_steps=100` at
  registration), which sets truncated=True; the class itself has no step limit.
- Deterministic: no randomness in start or dynamics; `reset(seed=)` is accepted for the API.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

MAX_MOVE = 0.2
STEP_REWARD = -0.01
APPLE_RADIUS = 0.1
APPLE_POSITIONS = np.array([[0.8, 0.8], [-0.8, -0.8], [0.5, -0.5], [-0.5, 0.5]])
APPLE_VALUES = np.array([50.0, 50.0, 10.0, 10.0])


class AppleCollectEnv(gym.Env[np.ndarray, np.ndarray]):
    """Move from the centre to an apple; every step costs 0.01, an apple ends the episode."""

    metadata = {"render_modes": []}

    def __init__(self, render_mode: str | None = None) -> None:
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-MAX_MOVE, MAX_MOVE, shape=(2,), dtype=np.float32)
        self._position = np.zeros(2)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._position = np.zeros(2)
        return self._position.astype(np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        move = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -MAX_MOVE, MAX_MOVE)
        if not np.all(np.isfinite(move)):
            raise ValueError(f"AppleCollect action must be finite, got {action}")
        start = self._position
        end = np.clip(start + move, -1.0, 1.0)
        self._position = end
        apple = _apple_on_segment(start, end)
        reward = STEP_REWARD
        if apple is not None:
            reward += float(APPLE_VALUES[apple])
        info = {"apple": 0.0 if apple is None else float(APPLE_VALUES[apple])}
        return end.astype(np.float32), reward, apple is not None, False, info


def _apple_on_segment(start: np.ndarray, end: np.ndarray) -> int | None:
    """Index of the first apple the move start -> end passes within APPLE_RADIUS of, else None."""
    d = end - start
    length2 = float(d @ d)
    to_apples = APPLE_POSITIONS - start  # (4, 2)
    t = np.clip(to_apples @ d / length2, 0.0, 1.0) if length2 > 0 else np.zeros(len(APPLE_POSITIONS))
    closest = start + t[:, None] * d
    hit = np.sum((APPLE_POSITIONS - closest) ** 2, axis=1) <= APPLE_RADIUS**2
    if not hit.any():
        return None
    candidates = np.flatnonzero(hit)
    return int(candidates[np.argmin(t[candidates])])
