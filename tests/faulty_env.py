"""Test-only environments that inject simulator faults into a real MuJoCo env.

Use them as `tests.faulty_env:<ID>` (gymnasium imports this module, which registers them), in
this process or in `mam` child processes started from the repository root.

- `FaultyPendulum-v0`: InvertedPendulum-v5 with a fault in four of every five episodes, in
  turn: an exception in `step`, a NaN observation, an infinite reward, and an exception in the
  `reset` that would start the episode. `FaultyPendulumWorkers-v0` does the same only in
  `services.roles.worker` processes (the referee's evaluation and the learner's shape probe see a
  healthy env).
- `BrokenResetWorkers-v0`: every `reset` raises, in worker processes only (a worker that can
  never run: it exits and `mam run` restarts it until its restart limit).
"""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np

KINDS = ("step_exception", "nonfinite_obs", "nonfinite_reward", "reset_exception")


class SimulatorError(RuntimeError):
    """What a crashing simulator raises."""


def in_worker() -> bool:
    return sys.argv[0].replace("\\", "/").endswith("services/roles/worker.py")


class FaultInjector(gym.Wrapper):
    """Faults on a fixed schedule; `injected` counts them by kind, `steps_ok` the good steps."""

    def __init__(self, env: gym.Env, period: int = 5, at_step: int = 3, active: bool = True,
                 always_fail_reset: bool = False) -> None:
        super().__init__(env)
        self.period, self.at_step, self.active = period, at_step, active
        self.always_fail_reset = always_fail_reset
        self.injected = {k: 0 for k in KINDS}
        self.episode = -1  # episodes started (successful resets)
        self.resets = 0
        self.failed_for = -1
        self.t = 0
        self.steps_ok = 0

    def _kind(self) -> str | None:
        phase = self.episode % self.period
        return KINDS[phase - 1] if self.active and 1 <= phase <= len(KINDS) - 1 else None

    def reset(self, **kwargs):
        self.resets += 1
        due = (self.episode + 1) % self.period == len(KINDS) and self.failed_for != self.episode + 1
        if self.active and (self.always_fail_reset or due):
            self.injected["reset_exception"] += 1
            self.failed_for = self.episode + 1  # the next try starts the episode
            raise SimulatorError("injected: reset failed")
        self.episode += 1
        self.t = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        self.t += 1
        obs, reward, terminated, truncated, info = self.env.step(action)
        kind = self._kind() if self.t == self.at_step else None
        if kind == "step_exception":
            self.injected[kind] += 1
            raise SimulatorError("injected: mj_step went unstable")
        if kind == "nonfinite_obs":
            self.injected[kind] += 1
            obs = np.array(obs, copy=True)
            obs[0] = np.nan
        elif kind == "nonfinite_reward":
            self.injected[kind] += 1
            reward = float("inf")
        else:
            self.steps_ok += 1
        return obs, reward, terminated, truncated, info


def _faulty(active: str = "always", **kwargs) -> gym.Env:
    on = active == "always" or (active == "workers" and in_worker())
    return FaultInjector(gym.make("InvertedPendulum-v5"), active=on, **kwargs)


gym.register("FaultyPendulum-v0", entry_point=_faulty, kwargs={"active": "always"})
gym.register("FaultyPendulumWorkers-v0", entry_point=_faulty, kwargs={"active": "workers"})
gym.register("BrokenResetWorkers-v0", entry_point=_faulty, kwargs={"active": "workers", "always_fail_reset": True})
