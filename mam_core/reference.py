"""A synchronous, single-process driver of Algorithm 1: the yardstick for tests and benchmarks.

It drives `mam_core.algorithm1.Algorithm1` (the one owner of the control flow) with the same
pieces the distributed roles use: the slots' acting rule and random streams (mam_core.slot,
mam_core.seeding), numpy copies of the actors for acting and evaluation (mam_core.policy,
what workers and the referee load from the weights topic), the agent's update phases, and
the obsolescence state (mam_core.obsolescence). A distributed run in exact mode computes the
same run bit for bit on one machine (services/, docs/DESIGN-DECISIONS.md "Exact Algorithm 1").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from mam_core.agent import EnvSpec, MultiActorAgent, pick_device
from mam_core.algorithm1 import Algorithm1, Iteration, Purpose
from mam_core.config import AlgoConfig
from mam_core.envs import make_env  # registers AppleCollect; imports `module:EnvId` modules
from mam_core.evaluation import evaluate_policy
from mam_core.obsolescence import competition_returns, obsolescence_for
from mam_core.policy import NumpyActors
from mam_core.replay import Replay, ReplayBuffer
from mam_core.seeding import evaluation_seed, stream
from mam_core.slot import SlotStreams, act, uniform


@dataclass
class ReferenceResult:
    evaluations: list[dict[str, Any]] = field(default_factory=list)
    allocations: list[dict[str, Any]] = field(default_factory=list)
    env_steps: int = 0
    iterations: int = 0
    updates: int = 0
    survivor: int | None = None
    wall_time_s: float = 0.0
    policy: list[dict[str, np.ndarray]] = field(default_factory=list)  # the final actors' parameters

    def final_mean(self) -> float:
        """Mean return of the best live actor at the last evaluation."""
        last = self.evaluations[-1]
        return max(m for m in last["mean"] if m is not None)


def run_reference(env_id: str, cfg: AlgoConfig, steps: int, env_kwargs: dict[str, Any] | None = None,
                  log: Callable[[str, dict[str, Any]], None] | None = None) -> ReferenceResult:
    """Train for `steps` schedule steps (iterations under `paper`, transitions under `equal-data`)."""
    started = time.perf_counter()
    device = pick_device(cfg.device)
    plan = Algorithm1.for_run(cfg, steps)
    envs = [make_env(env_id, env_kwargs) for _ in range(cfg.workers)]
    spec = EnvSpec.from_env(envs[0])
    torch.manual_seed(cfg.seed)
    agent = MultiActorAgent(cfg, spec, device)
    buffer = ReplayBuffer(plan.replay_capacity(cfg.buffer_size), spec.obs_dim, spec.act_dim, device, cfg.seed)
    sample = agent.sampler(buffer, cfg.batch_size)  # on a GPU: indices staged for the CUDA graphs
    state = obsolescence_for(cfg, steps)
    rng = stream(cfg.seed, "allocation")
    actors = NumpyActors(cfg.actors, spec, cfg.hidden, cfg.family.policy_kind)  # the newest: what the referee judges
    for k in range(cfg.actors):
        actors.load_member(k, agent.actor_params(k))
    # What the slots act with: the actors after iteration t-1-B (B = cfg.lag), by version.
    acting = NumpyActors(cfg.actors, spec, cfg.hidden, cfg.family.policy_kind)
    history: dict[int, list[dict[str, np.ndarray] | None]] = {0: [agent.actor_params(k) for k in range(cfg.actors)]}
    max_action = np.asarray(spec.max_action, np.float32)
    streams = [SlotStreams.for_slot(cfg.seed, i) for i in range(cfg.workers)]
    obs = [s.seed_env(env) for s, env in zip(streams, envs)]
    result = ReferenceResult()
    decisions = {0: list(state.allocation(cfg.workers, rng))}  # iteration that decided -> slot -> actor
    result.allocations.append({"env_steps": 0, "iterations": 0, "slots": decisions[0],
                               "probabilities": state.probabilities.tolist()})
    acting_version = -1

    def evaluate(it: Iteration, purpose: Purpose) -> list[float | None]:
        seed = evaluation_seed(cfg.seed, purpose, it.evaluation_index(purpose))
        means: list[float | None] = []
        returns: list[list[float]] = []
        for k in range(cfg.actors):
            if not state.live[k]:
                means.append(None)
                returns.append([])
                continue
            r = evaluate_policy(actors.policy(k), env_id, cfg.eval_episodes, seed=seed, env_kwargs=env_kwargs)
            means.append(float(r.mean()))
            returns.append(r.tolist())
        row = {"env_steps": it.transitions[1], "iterations": it.units[1], "updates": agent.updates,
               "purpose": purpose.value, "seed": seed, "mean": means, "returns": returns}
        result.evaluations.append(row)
        if log:
            log("eval", row)
        return means

    def compete(it: Iteration) -> None:
        """Eq. 8 from the actors after the previous iteration (lines 15-17), or the elimination
        (18-20); the allocation drawn applies from iteration it.index + 1 + B on."""
        means = evaluate(it, Purpose.ELIMINATION if it.eliminate else Purpose.ROUND)
        state.record_evaluation(it.units[1], competition_returns(means), rng=rng)
        decisions[it.index] = list(state.allocation(cfg.workers, rng))[:plan.slot_width(it.index)]
        result.allocations.append({"env_steps": it.transitions[1], "iterations": it.units[1],
                                   "slots": decisions[it.index], "probabilities": state.probabilities.tolist(),
                                   "survivor": state.survivor})
        if log:
            log("allocation", result.allocations[-1])

    def log_update(metrics: dict[str, float]) -> None:
        if log and agent.updates % 1000 == 0:
            log("learner", {"env_steps": it.transitions[1], "updates": agent.updates, **metrics})

    for index in range(1, plan.iterations + 1):
        it = plan.iteration(index)
        # Lines 5-10: every slot of the iteration steps once, in slot order, with the allocation and
        # the actors of B iterations before (B = 0: the latest decision, the actors after i-1).
        allocation = decisions[plan.decision_for(index)]
        if not it.random and plan.version_for(index) != acting_version:
            acting_version = plan.version_for(index)
            for k, params in enumerate(history[acting_version]):
                if params is not None:
                    acting.load_member(k, params)
        rows = []
        for i in it.slots:
            k = allocation[i]
            action = uniform(envs[i]) if it.random else \
                act(acting.policy(k), obs[i], streams[i].noise, cfg, max_action)
            next_obs, reward, terminated, truncated, _ = envs[i].step(action)
            next_obs = np.asarray(next_obs, np.float32)
            rows.append((obs[i], action, float(reward), next_obs, bool(terminated), k,
                         -1 if it.random else min(acting_version, agent.versions[k])))
            obs[i] = streams[i].reset(envs[i], index + 1) if terminated or truncated else next_obs
        add_rows(buffer, rows)
        # Lines 11-24: the updates, with the round and the elimination between critic and actor phases.
        if it.competes:
            compete(it)
        plan.run_updates(it, agent, sample,
                         lambda: agent.eliminate(state.survivor), log_update if log else None)
        if it.eliminate:
            result.survivor = state.survivor
        if plan.weights_change(index):
            version = plan.version_after(index)
            history[version] = [agent.actor_params(k) if state.live[k] else None for k in range(cfg.actors)]
            for k in range(cfg.actors):
                if state.live[k]:
                    actors.load_member(k, agent.actor_params(k))
            for old in [v for v in history if v < plan.version_for(min(index + 1, plan.iterations))]:
                del history[old]
        if it.curve is not None:
            evaluate(it, Purpose.CURVE)
        elif it.last:
            evaluate(it, Purpose.FINAL)

    for env in envs:
        env.close()
    last = plan.iteration(plan.iterations)
    result.env_steps, result.iterations, result.updates = last.transitions[1], last.units[1], agent.updates
    result.policy = [agent.actor_params(k) for k in range(cfg.actors)]
    result.wall_time_s = time.perf_counter() - started
    return result


def add_rows(buffer: Replay, rows: list[tuple]) -> None:
    """An iteration's transitions (obs, action, reward, next_obs, terminated, actor, version),
    in slot order, as one insert (what the learner does with the rows the workers sent)."""
    if not rows:
        return
    obs, action, reward, next_obs, term, actor, version = zip(*rows)
    buffer.add_batch(np.stack(obs), np.stack(action), np.asarray(reward, np.float32), np.stack(next_obs),
                     np.asarray(term, np.bool_), actor=np.asarray(actor, np.int64),
                     version=np.asarray(version, np.int64))
