"""The TD3 family: MA-TD3, TD3, MA-DDPG and DDPG (Fujimoto et al. 2018; Lillicrap et al. 2016).

Deterministic actors π_k(s) = max_action · tanh(MLP_k(s)) with target actors. What the family
supplies to the mechanism (mam_core.family), phase by phase:

- acting (workers, reference): π_k(s) + N(0, σ)·max_action, clipped (`explore`);
- Eq. 9's ã_j: the target actor's action, smoothed with clipped noise (`smoothed`; DDPG: none);
- Eq. 7: actor k ascends its first critic, Q_k1(s, π_k(s)) (`actor_loss`).

DDPG is this family with n = 1, d = 1 and no smoothing (Table 1's defaults); single-actor TD3
and DDPG are K = 1. The learner's pieces import torch when called (mam_core.family).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from mam_core.policy import DETERMINISTIC

if TYPE_CHECKING:
    import torch

    from mam_core.config import AlgoConfig
    from mam_core.family import Agent
    from mam_core.policy import EnvSpec, Policy

# The paper's Table 3 (TD3 family) and Table 1 (DDPG family); MA-DDPG shows obsolescence alone,
# so its η defaults to 0 (docs/DESIGN-DECISIONS.md).
TABLE_3 = dict(critics_per_actor=2, target_smoothing=True, policy_delay=2, batch_size=256, start_steps=25_000,
               eliminate_at=300_000, compete_every=5_000, eta=0.1)
TABLE_1 = dict(critics_per_actor=1, target_smoothing=False, policy_delay=1, batch_size=100, start_steps=10_000,
               eliminate_at=24_000, compete_every=1_000, eta=0.0)
DEFAULTS: dict[str, dict[str, Any]] = {
    "ma-td3": dict(TABLE_3, actors=2, workers=3),
    "td3": dict(TABLE_3, actors=1, workers=1, eta=0.0),
    "ma-ddpg": dict(TABLE_1, actors=3, workers=5),
    "ddpg": dict(TABLE_1, actors=1, workers=1),
}


def explore(policy: Policy, obs: np.ndarray, noise: np.random.Generator, sigma: float,
            max_action: np.ndarray) -> np.ndarray:
    """π_k(s) + N(0, σ)·max_action, clipped to the action bounds (Algorithm 1, line 7)."""
    action = policy(obs)
    eps = noise.normal(0.0, sigma, action.shape[-1]).astype(np.float32)
    return np.clip(action + eps * max_action, -max_action, max_action)


def actor_loss(q1: torch.Tensor, live: torch.Tensor) -> torch.Tensor:
    """Eq. 7: actor k ascends Q_k1(s, π_k(s)); q1 [K, B], live [K] -> scalar (summed over k)."""
    return (-q1.mean(dim=-1) * live).sum()


def smoothed(agent: Agent, action: torch.Tensor) -> torch.Tensor:
    """Target policy smoothing: ã = clip(π'(s') + clip(N(0, σ̃), ±c), ±max_action)."""
    cfg, max_action = agent.cfg, agent.max_action
    if not cfg.target_smoothing:
        return action
    noise = agent.draw_noise(tuple(action.shape))
    noise = (noise * (cfg.policy_noise * max_action)).clamp(-cfg.noise_clip * max_action, cfg.noise_clip * max_action)
    return (action + noise).minimum(max_action).maximum(-max_action)


class TD3:
    """The TD3 family (mam_core.family.Family)."""

    names = tuple(DEFAULTS)
    help = "the paper's Table 3 (ma-td3, td3) and Table 1 (ma-ddpg, ddpg)"
    policy_kind = DETERMINISTIC
    stochastic = False
    target_actor = True

    def defaults(self, algo: str) -> dict[str, Any]:
        return dict(DEFAULTS[algo])

    def problems(self, cfg: AlgoConfig) -> list[str]:
        return ["alpha is a SAC temperature: only for --algo sac or ma-sac"] if cfg.alpha is not None else []

    # -- acting, numpy ----------------------------------------------------------------------------
    def act(self, policy: Policy, obs: np.ndarray, noise: np.random.Generator, cfg: AlgoConfig,
            max_action: np.ndarray) -> np.ndarray:
        return explore(policy, obs, noise, cfg.explore_noise, max_action)

    def explorer(self, policy: Any, sigma: float, rng: np.random.Generator) -> Policy:
        """a + N(0, σ·max_action) per row, clipped to the bounds."""
        scale = np.float32(sigma) * policy.max_action

        def noisy(obs: np.ndarray) -> np.ndarray:
            a = policy(obs)
            return np.clip(a + rng.normal(size=a.shape).astype(np.float32) * scale, -policy.max_action,
                           policy.max_action)

        return noisy

    # -- the learner's pieces, torch --------------------------------------------------------------
    def make_actors(self, k: int, spec: EnvSpec, hidden: tuple[int, ...], gen: torch.Generator) -> Any:
        from mam_core.ensemble import ActorEnsemble

        return ActorEnsemble(k, spec.obs_dim, spec.act_dim, hidden, np.array(spec.max_action), gen)

    def temperature(self, cfg: AlgoConfig, spec: EnvSpec, device: torch.device) -> tuple[Any, Any]:
        return None, None

    def next_actions(self, agent: Agent, next_obs: torch.Tensor) -> tuple[torch.Tensor, None]:
        """Eq. 9's ã_j: the target actors' smoothed actions; no entropy term."""
        return smoothed(agent, agent.actor_target(next_obs)), None

    def actor_step(self, agent: Agent, obs: torch.Tensor) -> list[torch.Tensor]:
        """Eq. 7 on every live actor's first critic, one Adam step of the actors."""
        pi = agent.actor(obs)
        q1 = agent.critic(obs, pi, members=agent.first_critic_members)
        loss = actor_loss(q1, agent.live)
        agent.adam_step(agent.actor_opt, loss, agent.actor_params_list)  # actor params only
        return [loss.detach().reshape(1), -q1.detach().mean(dim=-1) * agent.live]

    def actor_metric_names(self, agent: Agent) -> list[str]:
        return ["loss/actor", *(f"loss/actor{j}" for j in range(agent.cfg.actors))]
