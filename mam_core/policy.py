"""Acting without torch: the env spec and the actors as numpy functions.

Workers and the referee only run policies forward, one observation (or a few) at a time.
For that, torch's per-op dispatch costs more than the arithmetic (docs/PERFORMANCE.md), and
importing it costs seconds of start-up and a few hundred MB per process. This module holds
what acting needs, with numpy alone; the learner's `ActorEnsemble` shares the parameter layout
(`member_shapes`), and `tests/test_policy.py` checks that both compute the same function.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class EnvSpec:
    """What the networks need to know about an environment."""

    obs_dim: int
    act_dim: int
    max_action: tuple[float, ...]  # per action dimension, symmetric bounds ±max_action

    @classmethod
    def from_env(cls, env: Any) -> "EnvSpec":
        space = env.action_space
        if not np.allclose(space.low, -space.high):
            raise ValueError("only symmetric action bounds (low == -high) are supported")
        return cls(int(np.prod(env.observation_space.shape)), int(space.shape[0]),
                   tuple(float(h) for h in space.high))

    @classmethod
    def from_env_id(cls, env_id: str) -> "EnvSpec":
        import gymnasium as gym

        import mam_core.envs  # noqa: F401  (registers AppleCollect-v0)

        env = gym.make(env_id)
        try:
            return cls.from_env(env)
        finally:
            env.close()

    def to_dict(self) -> dict[str, Any]:
        return {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "max_action": list(self.max_action)}


def member_shapes(in_dim: int, hidden: Sequence[int], out_dim: int) -> dict[str, tuple[int, ...]]:
    """One member's parameters as they travel on the weights topic: w{i} [fan_in, fan_out], b{i} [1, fan_out]."""
    sizes = [in_dim, *hidden, out_dim]
    shapes: dict[str, tuple[int, ...]] = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        shapes[f"w{i}"] = (fan_in, fan_out)
        shapes[f"b{i}"] = (1, fan_out)
    return shapes


def mlp_policy(layers: Sequence[tuple[np.ndarray, np.ndarray]], max_action: np.ndarray) -> Policy:
    """obs [obs_dim] or [B, obs_dim] -> max_action · tanh(Linear-ReLU-...-Linear(obs)).

    `layers` are (w [in, out], b [out]) float32 arrays, read at every call: arrays updated in
    place are seen at once.
    """
    last = len(layers) - 1

    def policy(obs: np.ndarray) -> np.ndarray:
        h = np.asarray(obs, np.float32)
        for i, (w, b) in enumerate(layers):
            h = h @ w + b
            if i < last:
                np.maximum(h, 0.0, out=h)
        return max_action * np.tanh(h)

    return policy


class NumpyActors:
    """K actors' parameters as float32 arrays, for acting only (no gradients, no torch).

    Zero until `load_member` fills them from the weights topic: callers act with actor k
    only once its weights have arrived (workers and the referee track versions for that).
    """

    def __init__(self, n_actors: int, spec: EnvSpec, hidden: Sequence[int]) -> None:
        self.n_actors = n_actors
        self.shapes = member_shapes(spec.obs_dim, hidden, spec.act_dim)
        self.max_action = np.asarray(spec.max_action, np.float32)
        self.params = [{name: np.zeros(shape, np.float32) for name, shape in self.shapes.items()}
                       for _ in range(n_actors)]
        n_layers = len(self.shapes) // 2
        # b{i}[0]: a [out] view of the [1, out] wire layout, so one observation gives one action
        self._policies = [mlp_policy([(p[f"w{i}"], p[f"b{i}"][0]) for i in range(n_layers)], self.max_action)
                          for p in self.params]

    def load_member(self, k: int, params: Mapping[str, np.ndarray]) -> None:
        """Copy actor k's parameters in place (policies handed out earlier see them)."""
        for name, shape in self.shapes.items():
            value = np.asarray(params[name], np.float32)
            if value.shape != shape:
                raise ValueError(f"{name}: shape {value.shape}, expected {shape}")
            self.params[k][name][...] = value

    def policy(self, k: int) -> Policy:
        return self._policies[k]
