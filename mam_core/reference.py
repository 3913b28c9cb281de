"""A synchronous, single-process driver of Algorithm 1: the yardstick for tests and benchmarks.

M environment slots step in lock-step, each with the actor the allocation gives it; after each
sweep the agent makes the updates the schedule allows (mam_core.schedule: `paper` is one update
per iteration of M transitions, `equal-data` `utd` per transition). Every A schedule steps the
live actors are evaluated and P_k recomputed (Eq. 8); at C all but the best actor are
eliminated, and under `paper` the survivor runs one slot. The distributed system in `services/`
does the same work spread over processes; this driver shares every piece of math.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch

import mam_core.envs  # noqa: F401  (registers AppleCollect-v0)
from mam_core.agent import EnvSpec, MultiActorAgent, pick_device
from mam_core.config import AlgoConfig
from mam_core.evaluation import evaluate_policy
from mam_core.obsolescence import obsolescence_for
from mam_core.replay import ReplayBuffer
from mam_core.schedule import Schedule


@dataclass
class ReferenceResult:
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    allocations: list[dict[str, Any]] = field(default_factory=list)
    env_steps: int = 0
    iterations: int = 0
    updates: int = 0
    survivor: int | None = None
    wall_time_s: float = 0.0

    def final_mean(self) -> float:
        """Mean return of the best live actor at the last evaluation."""
        last = self.evaluations[-1]
        return max(m for m in last["mean"] if m is not None)


def run_reference(env_id: str, cfg: AlgoConfig, steps: int,
                  log: Callable[[str, dict[str, Any]], None] | None = None) -> ReferenceResult:
    """Train for `steps` schedule steps (iterations under `paper`, transitions under `equal-data`)."""
    started = time.perf_counter()
    device = pick_device(cfg.device)
    envs = [gym.make(env_id) for _ in range(cfg.workers)]
    spec = EnvSpec.from_env(envs[0])
    agent = MultiActorAgent(cfg, spec, device)
    clock = Schedule.for_run(cfg, steps)
    budget = clock.budget
    capacity = min(cfg.buffer_size, max(budget, cfg.batch_size))
    buffer = ReplayBuffer(capacity, spec.obs_dim, spec.act_dim, device, cfg.seed)
    schedule = obsolescence_for(cfg)
    rng = np.random.default_rng(cfg.seed)
    result = ReferenceResult()
    max_action = np.asarray(spec.max_action, np.float32)
    obs = np.stack([env.reset(seed=cfg.seed + 1000 * i)[0] for i, env in enumerate(envs)]).astype(np.float32)
    for i, env in enumerate(envs):
        env.action_space.seed(cfg.seed + 1000 * i)
    allocation = schedule.allocation(cfg.workers, rng)
    result.allocations.append({"env_steps": 0, "slots": list(allocation),
                               "probabilities": schedule.probabilities.tolist()})
    next_curve_eval = cfg.eval_every

    def evaluate(env_steps: int) -> list[float | None]:
        means: list[float | None] = []
        returns: list[list[float]] = []
        for k in range(cfg.actors):
            if not agent.live_actors[k]:
                means.append(None)
                returns.append([])
                continue
            r = evaluate_policy(lambda o, k=k: agent.act(o, k), env_id, cfg.eval_episodes,
                                seed=cfg.seed + 10_000 + env_steps)
            means.append(float(r.mean()))
            returns.append(r.tolist())
        row = {"env_steps": env_steps, "iterations": clock.units_at(env_steps), "updates": agent.updates,
               "mean": means, "returns": returns}
        result.evaluations.append(row)
        if log:
            log("eval", row)
        return means

    t = 0
    while t < budget:
        active = [0] if (cfg.single_env and schedule.survivor is not None) else range(cfg.workers)
        if t < clock.random_until:
            actions = np.stack([envs[i].action_space.sample() for i in range(cfg.workers)]).astype(np.float32)
        else:
            with torch.no_grad():
                all_actions = agent.actor(torch.as_tensor(obs, device=device)).cpu().numpy()  # [K, M, A]
            actions = all_actions[allocation, np.arange(cfg.workers)]
            actions += rng.normal(0.0, cfg.explore_noise, actions.shape).astype(np.float32) * max_action
            actions = np.clip(actions, -max_action, max_action)
        for i in active:
            if t >= budget:
                break
            next_obs, reward, terminated, truncated, _ = envs[i].step(actions[i])
            buffer.add_batch(obs[i:i + 1], actions[i:i + 1], np.array([reward], np.float32),
                             np.asarray(next_obs, np.float32)[None], np.array([terminated]),
                             actor=int(allocation[i]), version=agent.versions[allocation[i]])
            obs[i] = envs[i].reset()[0] if terminated or truncated else next_obs
            t += 1
        # Updates keep pace with collection, as the schedule allows once the start phase is over.
        due = clock.updates_allowed(t) if len(buffer) >= cfg.batch_size else 0
        while agent.updates < due:
            metrics = agent.update(buffer.sample(cfg.batch_size, agent.batch_groups))
            if log and agent.updates % 1000 == 0:
                log("learner", {"env_steps": t, "updates": agent.updates, **metrics})

        # Obsolescence (Eq. 8) every A schedule steps; elimination at C.
        units = clock.units_at(t)
        if schedule.due_elimination(units) or schedule.due_round(units):
            means = evaluate(t)
            returns = [m if m is not None else -np.inf for m in means]
            was = schedule.survivor
            schedule.record_evaluation(units, np.where(np.isfinite(returns), returns, 0.0), rng=rng)
            if schedule.survivor is not None and was is None:
                agent.eliminate(schedule.survivor)
                result.survivor = schedule.survivor
            allocation = schedule.allocation(cfg.workers, rng)
            result.allocations.append({"env_steps": t, "slots": list(allocation),
                                       "probabilities": schedule.probabilities.tolist()})
            if log:
                log("allocation", result.allocations[-1])
            next_curve_eval = (units // cfg.eval_every + 1) * cfg.eval_every
        elif units >= next_curve_eval:
            evaluate(t)
            next_curve_eval = (units // cfg.eval_every + 1) * cfg.eval_every

    if not result.evaluations or result.evaluations[-1]["env_steps"] != t:
        evaluate(t)
    for env in envs:
        env.close()
    result.env_steps, result.iterations, result.updates = t, clock.units_at(t), agent.updates
    result.wall_time_s = time.perf_counter() - started
    return result
