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

AppleCollect-v1 reads the open choices so that the premise of the paper's Fig. 1 holds (a
uniform random policy rarely finds a 50 apple, so a single actor can settle for a 10 apple):
the move is bounded as a radius (|move| <= 0.2), apples have radius 0.04, and leaving the
square ends the episode with the step costs it forfeits (the return is -1.0, as for wandering
until the time limit). docs/APPLECOLLECT.md has the measured hit rates of both versions.

`render_mode="rgb_array"` draws a frame with numpy alone (no GL): the square, the apples (50:
red, 10: green), the path walked this episode and the agent, 256×256 pixels by default.
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


MOVE_BOUNDS = ("axis", "radius")
EPISODE_STEPS = 100


class AppleCollectEnv(gym.Env[np.ndarray, np.ndarray]):
    """Move from the centre to an apple; every step costs 0.01, an apple ends the episode.

    v0: `move_bound="axis"`, `apple_radius=0.1`, `leave_ends=False` (the defaults).
    v1: `move_bound="radius"`, `apple_radius=0.04`, `leave_ends=True`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, move_bound: str = "axis", apple_radius: float = APPLE_RADIUS,
                 leave_ends: bool = False, render_size: int = 256) -> None:
        if move_bound not in MOVE_BOUNDS:
            raise ValueError(f"move_bound must be one of {MOVE_BOUNDS}, not {move_bound!r}")
        if not 0.0 < apple_radius < 0.5:
            raise ValueError(f"apple_radius must be in (0, 0.5), got {apple_radius}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, not {render_mode!r}")
        self.render_mode = render_mode
        self.move_bound = move_bound
        self.apple_radius = float(apple_radius)
        self.leave_ends = bool(leave_ends)
        self.render_size = int(render_size)
        self._trail: list[np.ndarray] = [np.zeros(2)]
        self._canvas: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._path: np.ndarray | None = None  # pixels of the path drawn so far (render)
        self._path_points = 1  # trail points already in _path
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.action_space = gym.spaces.Box(-MAX_MOVE, MAX_MOVE, shape=(2,), dtype=np.float32)
        self._position = np.zeros(2)
        self._steps = 0

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self._position = np.zeros(2)
        self._steps = 0
        self._trail = [self._position]
        self._path = None
        return self._position.astype(np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        move = np.clip(np.asarray(action, dtype=np.float64).reshape(2), -MAX_MOVE, MAX_MOVE)
        if not np.all(np.isfinite(move)):
            raise ValueError(f"AppleCollect action must be finite, got {action}")
        if self.move_bound == "radius":
            length = float(np.hypot(*move))
            if length > MAX_MOVE:
                move = move * (MAX_MOVE / length)
        self._steps += 1
        start = self._position
        unclipped = start + move
        left = self.leave_ends and bool(np.any(np.abs(unclipped) > 1.0))
        end = np.clip(unclipped, -1.0, 1.0)
        self._position = end
        self._trail.append(end)
        apple = _apple_on_segment(start, end, self.apple_radius)
        reward = STEP_REWARD
        if apple is not None:
            reward += float(APPLE_VALUES[apple])
        elif left:  # the episode ends here: charge the steps it forfeits, so leaving never pays
            reward = STEP_REWARD * max(EPISODE_STEPS - self._steps + 1, 1)
        info = {"apple": 0.0 if apple is None else float(APPLE_VALUES[apple]), "left": left and apple is None}
        return end.astype(np.float32), reward, apple is not None or left, False, info

    # -- rendering (numpy only) -----------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """An RGB frame [size, size, 3] uint8 of the current state (None without render_mode)."""
        if self.render_mode != "rgb_array":
            return None
        wx, wy, frame = self._background()
        frame = frame.copy()
        px = 2.0 / (self.render_size - 1)  # world units per pixel (about)
        if self._path is None:
            self._path, self._path_points = np.zeros(wx.shape, bool), 1
        for a, b in zip(self._trail[self._path_points - 1:-1], self._trail[self._path_points:]):
            self._path |= _distance_to_segment(wx, wy, a, b) <= 1.5 * px  # only the new segments
        self._path_points = len(self._trail)
        frame[self._path] = (90, 120, 235)
        agent = (wx - self._position[0]) ** 2 + (wy - self._position[1]) ** 2
        frame[agent <= (0.05 + px) ** 2] = (20, 30, 120)
        frame[agent <= 0.04**2] = (40, 80, 230)
        return frame

    def _background(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World coordinates of every pixel and the static picture (square, apples), cached."""
        if self._canvas is None:
            n = self.render_size
            # pixel centres to world: x right, y up, the square [-1, 1]^2 fills the frame with a border
            margin = 1.06
            grid = (np.arange(n) + 0.5) / n * 2 * margin - margin
            wx, wy = np.meshgrid(grid, grid[::-1])
            frame = np.full((n, n, 3), 200, np.uint8)
            inside = (np.abs(wx) <= 1.0) & (np.abs(wy) <= 1.0)
            frame[inside] = (246, 244, 236)
            edge = inside & ((np.abs(wx) >= 1.0 - 2.5 / n) | (np.abs(wy) >= 1.0 - 2.5 / n))
            frame[edge] = (60, 60, 60)
            for (ax, ay), value in zip(APPLE_POSITIONS, APPLE_VALUES):
                disk = (wx - ax) ** 2 + (wy - ay) ** 2 <= max(self.apple_radius, 0.05) ** 2  # visible at 256 px
                frame[disk] = (215, 35, 35) if value >= 50 else (50, 165, 60)
            self._canvas = (wx, wy, frame)
        return self._canvas


def _distance_to_segment(x: np.ndarray, y: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of every point (x, y) to the segment a-b."""
    d = b - a
    length2 = float(d @ d)
    if length2 == 0.0:
        return np.hypot(x - a[0], y - a[1])
    t = np.clip(((x - a[0]) * d[0] + (y - a[1]) * d[1]) / length2, 0.0, 1.0)
    return np.hypot(x - (a[0] + t * d[0]), y - (a[1] + t * d[1]))


def _apple_on_segment(start: np.ndarray, end: np.ndarray, radius: float = APPLE_RADIUS) -> int | None:
    """Index of the first apple the move start -> end passes within `radius` of, else None."""
    d = end - start
    length2 = float(d @ d)
    to_apples = APPLE_POSITIONS - start  # (4, 2)
    t = np.clip(to_apples @ d / length2, 0.0, 1.0) if length2 > 0 else np.zeros(len(APPLE_POSITIONS))
    closest = start + t[:, None] * d
    hit = np.sum((APPLE_POSITIONS - closest) ** 2, axis=1) <= radius**2
    if not hit.any():
        return None
    candidates = np.flatnonzero(hit)
    return int(candidates[np.argmin(t[candidates])])


def random_hit_rates(env_id: str, episodes: int = 2000, seed: int = 0) -> dict[float, float]:
    """Share of episodes of a uniform random policy that collect a 50 apple and a 10 apple
    (episode i reset with seed + i, actions from the action space seeded with `seed`)."""
    env = gym.make(env_id)
    env.action_space.seed(seed)
    hits = {50.0: 0, 10.0: 0}
    try:
        for i in range(episodes):
            env.reset(seed=seed + i)
            while True:
                _, _, terminated, truncated, info = env.step(env.action_space.sample())
                if info["apple"]:
                    hits[info["apple"]] += 1
                if terminated or truncated:
                    break
    finally:
        env.close()
    return {value: n / episodes for value, n in hits.items()}


if __name__ == "__main__":  # python -m mam_core.envs.apple_collect [EPISODES]: the table of docs/APPLECOLLECT.md
    import sys

    import mam_core.envs  # noqa: F401  (registers the versions)

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 20_000
    print(f"uniform random policy, {n:,} episodes, seed 0")
    for version in ("AppleCollect-v0", "AppleCollect-v1"):
        rates = random_hit_rates(version, n)
        print(f"{version}: 50 apple {rates[50.0]:.2%}, 10 apple {rates[10.0]:.2%}")


def best_apple_return(env_id: str, env_kwargs: dict[str, Any]) -> float | None:
    """The return of the straight line to the (0.8, 0.8) apple on an AppleCollect env (49.94 on v1,
    49.96 on v0: the optimum, docs/APPLECOLLECT.md); None for other envs."""
    try:
        import gymnasium as gym

        from mam_core.envs import make_env  # registers the ids

        if "apple_collect" not in str(gym.spec(env_id).entry_point):
            return None
        env = make_env(env_id, env_kwargs)
    except Exception:  # not AppleCollect, or an id gym.spec cannot resolve here
        return None
    try:
        env.reset(seed=0)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.high.copy())
            total, done = total + float(reward), terminated or truncated
        return total
    finally:
        env.close()
