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
    final_obs: np.ndarray  # [episodes, obs_dim] s_T, the observation the episode ended on
    truncated: np.ndarray  # [episodes] bool: ended by the time limit, not by termination
    final_discount: np.ndarray  # [episodes] γ^T, T the episode's length


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
        final_obs = np.zeros((episodes, int(np.prod(envs[0].observation_space.shape))), np.float32)
        truncated_at_end = np.zeros(episodes, bool)
        final_discount = np.ones(episodes)
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
                    else:
                        final_obs[i], truncated_at_end[i], final_discount[i] = obs[j], truncated and not terminated, \
                            discount[j]
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
        final_obs=final_obs,
        truncated=truncated_at_end,
        final_discount=final_discount,
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


def bias_rate(q_estimate: float | np.ndarray, q_true: float | np.ndarray, atol: float = 1e-8,
              absolute: bool = False) -> float:
    """Eq. 17 as printed: (mean Q̂ - mean Q*) / mean Q*; `absolute=True` divides by |mean Q*|.

    The two differ only where Q* < 0 (e.g. Reacher): there the printed rate is > 0 for an
    under-estimate, and the |Q*| form keeps "> 0 is over-estimation". Means are taken first
    (a ratio of means, stable when single Q* values are near zero). When |mean Q*| <= atol the
    rate is undefined and NaN is returned; the absolute bias is still reported by `estimation_bias`.
    """
    q_hat = float(np.mean(q_estimate))
    q_star = float(np.mean(q_true))
    if not np.isfinite(q_hat) or not np.isfinite(q_star) or abs(q_star) <= atol:
        return float("nan")
    return (q_hat - q_star) / (abs(q_star) if absolute else q_star)


def estimation_bias(
    policy: Policy,
    q: QFunction,
    env_id: str,
    episodes: int,
    gamma: float,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
    horizon: str = "critic",
) -> dict[str, Any]:
    """The critic's Q̂(s0, π(s0)) against the Monte-Carlo Q* of the same policy (Eq. 17).

    `horizon="critic"` (default): an episode cut by the time limit gets the bootstrap tail
    γ^T·Q̂(s_T, π(s_T)), because the critic bootstraps through truncation and so estimates
    an infinite-horizon value; without the tail Q* is a T-step value and the rate measures
    the horizon mismatch as under-estimation. `horizon="episode"`: the return is cut at the
    time limit (terminated episodes get no tail in either case). The tail uses the critic
    itself, so at a time limit Q* is the critic's own n-step target, not an independent truth;
    with γ^T small (long episodes) it hardly matters.
    """
    if horizon not in ("critic", "episode"):
        raise ValueError(f"horizon must be critic or episode, not {horizon!r}")
    r = rollout(policy, env_id, episodes, seed, gamma, env_kwargs)
    q_hat = np.asarray(q(r.initial_obs, r.initial_actions), dtype=np.float64).reshape(-1)
    if q_hat.shape != (episodes,):
        raise ValueError(f"q returned {q_hat.shape[0]} values for {episodes} states")
    discounted = r.discounted_returns.copy()
    tail = 0.0
    if horizon == "critic" and r.truncated.any():
        cut = np.flatnonzero(r.truncated)
        final_obs = r.final_obs[cut]
        tails = np.asarray(q(final_obs, np.asarray(policy(final_obs), np.float32)), np.float64).reshape(-1)
        discounted[cut] += r.final_discount[cut] * tails
        tail = float((r.final_discount[cut] * tails).sum() / episodes)
    q_estimate = float(q_hat.mean())
    q_true = float(discounted.mean())
    out = {
        "q_estimate": q_estimate,
        "q_true": q_true,
        "bias": q_estimate - q_true,
        "bias_rate": bias_rate(q_estimate, q_true),  # Eq. 17 as printed: ÷ Q*
        "tail": tail,  # mean bootstrap tail included in q_true (0 for horizon="episode")
        "horizon": horizon,
    }
    if q_true < 0:  # the two forms differ: keep the sign-preserving one, labelled
        out["bias_rate_abs"] = bias_rate(q_estimate, q_true, absolute=True)
    return out
