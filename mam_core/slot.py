"""One environment slot's acting rule, shared by the worker process and the reference driver.

Both must produce the same transitions from the same seed, so both call these functions: the
slot's random streams (mam_core.seeding, per slot and purpose), the acting rule (`act`: the
algorithm family's), and the conversions of what the env returns.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mam_core.config import AlgoConfig
from mam_core.seeding import episode_seed, stream, stream_seed

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass
class SlotStreams:
    """Slot `slot`'s streams: the start phase's uniform actions (they seed `env.action_space`),
    the exploration noise, and a reset seed per episode (`seeding.episode_seed`, from the
    iteration of the episode's first step). Each iteration of the slot draws a fixed amount:
    one action-space sample in the start phase, `act_dim` normals after it (`act`), so
    `fast_forward` can put both streams where they stand at any iteration."""

    seed: int
    slot: int
    action_seed: int
    noise: np.random.Generator

    @classmethod
    def for_slot(cls, seed: int, slot: int, generation: int = 0) -> SlotStreams:
        return cls(seed, slot, stream_seed(seed, "random-actions", slot, generation),
                   stream(seed, "noise", slot, generation))

    def episode_seed(self, iteration: int) -> int:
        """The reset seed of the episode whose first step is iteration `iteration`."""
        return episode_seed(self.seed, self.slot, iteration)

    def reset(self, env: Any, iteration: int) -> np.ndarray:
        """Reset `env` for the episode that starts at `iteration`; its first observation."""
        return np.asarray(env.reset(seed=self.episode_seed(iteration))[0], np.float32)

    def seed_env(self, env: Any) -> np.ndarray:
        """Seed the env's action space and reset it for the slot's first episode (iteration 1)."""
        env.action_space.seed(self.action_seed)
        return self.reset(env, 1)

    def fast_forward(self, env: Any, random_steps: int, policy_steps: int, chunk: int = 1 << 16) -> None:
        """Draw what `random_steps` start-phase and `policy_steps` later iterations drew (the
        slot's iterations before some point: `Algorithm1.slot_steps`) from a freshly seeded slot."""
        env.action_space.seed(self.action_seed)
        for _ in range(random_steps):
            env.action_space.sample()
        act_dim = int(np.prod(env.action_space.shape))
        while policy_steps > 0:  # numpy fills arrays element by element: one call per chunk draws the same
            n = min(policy_steps, chunk)
            self.noise.standard_normal(n * act_dim)
            policy_steps -= n


@dataclass
class Replayed:
    """The outcome of `replay_episode`: where the slot stands, or at which step it diverged."""

    obs: np.ndarray  # the observation the slot acts on next
    episode_return: float  # the reward summed so far in the current episode
    fresh: bool = False  # `obs` comes from a reset: the next step is an episode's first
    mismatch: str = ""  # empty, or what differed (the env is then not deterministic)


def replay_episode(env: Any, streams: SlotStreams, start: int, next_iteration: int, obs: np.ndarray,
                   actions: np.ndarray, next_obs: np.ndarray) -> Replayed:
    """Rebuild slot `streams.slot`'s env at `next_iteration` from its current episode: reset
    with the episode's seed (`start`), step the recorded actions, and check every observation
    (float32, as the replay holds them) bit for bit. An episode that ended at its last step
    is followed by the next episode's reset, as the worker does."""
    current = streams.reset(env, start)
    total = 0.0
    for j in range(len(actions)):
        where = f"iteration {start + j} (step {j} of the episode that starts at {start})"
        if not np.array_equal(current, obs[j]):
            return Replayed(current, total, mismatch=f"the observation before {where} differs")
        got, reward, terminated, truncated, _ = env.step(actions[j])
        current = np.asarray(got, np.float32)
        total += float(reward)
        if not np.array_equal(current, next_obs[j]):
            return Replayed(current, total, mismatch=f"the observation after {where} differs")
        if (terminated or truncated) and j < len(actions) - 1:
            return Replayed(current, total, mismatch=f"the episode ended early, at {where}")
        if terminated or truncated:
            return Replayed(streams.reset(env, next_iteration), 0.0, fresh=True)
    return Replayed(current, total, fresh=len(actions) == 0)  # no actions: the episode starts at next_iteration


def act(policy: Policy, obs: np.ndarray, noise: np.random.Generator, algo: AlgoConfig,
        max_action: np.ndarray) -> np.ndarray:
    """Algorithm 1, line 7: the family's acting rule (mam_core.family). TD3 and DDPG explore around
    π_k(s) (mam_core.td3.explore); SAC samples a = max_action · tanh(μ + σ·ε) from π_k(·|s) with the
    slot's noise stream drawing ε, so it has no exploration noise of its own (mam_core.sac)."""
    return algo.family.act(policy, obs, noise, algo, max_action)


def uniform(env: Any) -> np.ndarray:
    """A start-phase action: uniform over the action space (its seeded generator)."""
    return env.action_space.sample().astype(np.float32)
