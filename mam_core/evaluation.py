"""Deterministic evaluation (R_k for Eq. 8) and the estimation bias rate (Eq. 17).

A policy is a batched deterministic callable `policy(obs[N, obs_dim] float32) -> act[N, act_dim]`;
a Q-function is `q(obs[N, obs_dim], act[N, act_dim]) -> [N]`. Episodes run side by side in a
small batch of envs so the policy is called once per step for all unfinished episodes.
Episode i is always reset with seed + i, whatever the batch width, so results are
reproducible and independent of how many envs run at once.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mam_core.envs import make_env  # registers AppleCollect-v0; imports `module:EnvId` modules

Policy = Callable[[np.ndarray], np.ndarray]
QFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]

MAX_ENVS = 32  # episodes that run side by side; more only costs memory


@dataclass(frozen=True)
class Rollouts:
    """What a batch of deterministic episodes produced."""

    initial_obs: np.ndarray  # [episodes, obs_dim] float32
    initial_actions: np.ndarray  # [episodes, act_dim] float32, π(s0) as applied
    returns: np.ndarray  # [episodes] undiscounted sum of rewards
    discounted_returns: np.ndarray  # [episodes] sum_t γ^t r_t
    lengths: np.ndarray  # [episodes] steps until terminated or truncated


def rollout(
    policy: Policy,
    env_id: str,
    episodes: int,
    seed: int,
    gamma: float = 1.0,
    env_kwargs: dict[str, Any] | None = None,
    max_envs: int = MAX_ENVS,
) -> Rollouts:
    """Run exactly `episodes` episodes of `policy` (episode i reset with seed + i).

    An episode ends at terminated or truncated (the registered time limit); nothing is
    bootstrapped past the end. Actions are clipped to the action space, as a worker does.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    width = max(1, min(max_envs, episodes))
    envs = [make_env(env_id, env_kwargs) for _ in range(width)]
    try:
        space = envs[0].action_space
        low, high = np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)
        act_dim = int(np.prod(space.shape))
        initial_obs, initial_actions = [], []
        returns = np.zeros(episodes)
        discounted = np.zeros(episodes)
        lengths = np.zeros(episodes, np.int64)
        for first in range(0, episodes, width):
            ids = list(range(first, min(first + width, episodes)))
            obs = [np.asarray(envs[j].reset(seed=seed + i)[0], np.float32).reshape(-1) for j, i in enumerate(ids)]
            active = list(range(len(ids)))  # positions into ids/envs still running
            discount = np.ones(len(ids))
            step = 0
            while active:
                batch = np.stack([obs[j] for j in active])
                actions = np.asarray(policy(batch), dtype=np.float32).reshape(len(active), act_dim)
                actions = np.clip(actions, low.reshape(-1), high.reshape(-1))
                if step == 0:
                    initial_obs.append(batch)
                    initial_actions.append(actions)
                still = []
                for row, j in enumerate(active):
                    next_obs, reward, terminated, truncated, _ = envs[j].step(actions[row].reshape(space.shape))
                    i = ids[j]
                    returns[i] += float(reward)
                    discounted[i] += discount[j] * float(reward)
                    discount[j] *= gamma
                    lengths[i] += 1
                    obs[j] = np.asarray(next_obs, np.float32).reshape(-1)
                    if not (terminated or truncated):
                        still.append(j)
                active = still
                step += 1
    finally:
        for env in envs:
            env.close()
    return Rollouts(
        initial_obs=np.concatenate(initial_obs),
        initial_actions=np.concatenate(initial_actions),
        returns=returns,
        discounted_returns=discounted,
        lengths=lengths,
    )


def eval_seed(run_seed: int, env_steps: int) -> int:
    """Seed of the referee's evaluation at `env_steps` (episode i is reset with this + i)."""
    return run_seed + 1_000_003 + env_steps


def evaluate_policy(
    policy: Policy,
    env_id: str,
    episodes: int,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
    max_envs: int = MAX_ENVS,
) -> np.ndarray:
    """Undiscounted returns of exactly `episodes` deterministic episodes (R_k is their mean)."""
    return rollout(policy, env_id, episodes, seed, 1.0, env_kwargs, max_envs).returns


def monte_carlo_q(
    policy: Policy,
    env_id: str,
    episodes: int,
    gamma: float,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
    max_envs: int = MAX_ENVS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Q*(s0, π(s0)) by rolling the current policy out from initial states (paper: 20 rollouts).

    Returns (initial obs [episodes, obs_dim], initial actions [episodes, act_dim],
    discounted returns sum_t γ^t r_t [episodes]). Episodes cut by the time limit are not
    bootstrapped, as in the paper's measure.
    """
    r = rollout(policy, env_id, episodes, seed, gamma, env_kwargs, max_envs)
    return r.initial_obs, r.initial_actions, r.discounted_returns


def bias_rate(q_estimate: float | np.ndarray, q_true: float | np.ndarray, atol: float = 1e-8) -> float:
    """Eq. 17: (mean Q̂ - mean Q*) / |mean Q*|.

    Dividing by |Q*| (the paper prints Q*) keeps the sign meaning for negative returns:
    > 0 is over-estimation, < 0 under-estimation. Means are taken first (a ratio of means,
    stable when single Q* values are near zero). When |mean Q*| <= atol the rate is
    undefined and NaN is returned; the absolute bias is still reported by `estimation_bias`.
    """
    q_hat = float(np.mean(q_estimate))
    q_star = float(np.mean(q_true))
    if not np.isfinite(q_hat) or not np.isfinite(q_star) or abs(q_star) <= atol:
        return float("nan")
    return (q_hat - q_star) / abs(q_star)


def estimation_bias(
    policy: Policy,
    q: QFunction,
    env_id: str,
    episodes: int,
    gamma: float,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
) -> dict[str, float]:
    """The critic's Q̂(s0, π(s0)) against the Monte-Carlo Q* of the same policy (Eq. 17)."""
    obs, actions, discounted = monte_carlo_q(policy, env_id, episodes, gamma, seed, env_kwargs)
    q_hat = np.asarray(q(obs, actions), dtype=np.float64).reshape(-1)
    if q_hat.shape != (episodes,):
        raise ValueError(f"q returned {q_hat.shape[0]} values for {episodes} states")
    q_estimate = float(q_hat.mean())
    q_true = float(discounted.mean())
    return {
        "q_estimate": q_estimate,
        "q_true": q_true,
        "bias": q_estimate - q_true,
        "bias_rate": bias_rate(q_estimate, q_true),
    }
