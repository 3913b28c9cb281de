"""The SAC family: MA-SAC and SAC (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications").

Squashed-Gaussian actors π_k(·|s) = max_action · tanh(N(μ_k(s), σ_k(s)²)), no target actor, and
a temperature α_k per actor. What the family supplies to the mechanism (mam_core.family):

- acting: a ~ π_k(·|s), ε drawn from the slot's noise stream (no exploration noise of its own);
- Eq. 9 on soft values: ã_j ~ π_j(·|s') from the current actors, with the entropy term
  α_j·log π_j(ã_j|s') subtracted from every Q'_ji (docs/DESIGN-DECISIONS.md, "MA-SAC");
- Eq. 7: actor k minimises E[α_k·log π_k(a|s) − min_i Q_ki(s, a)], then α_k steps towards the
  target entropy −|A| (SAC v2), unless `--alpha` fixes it.

The learner's pieces import torch when called (mam_core.family).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from mam_core.policy import GAUSSIAN_POLICY
from mam_core.td3 import TABLE_3

if TYPE_CHECKING:
    import torch

    from mam_core.config import AlgoConfig
    from mam_core.family import Agent
    from mam_core.policy import EnvSpec, Policy

# SAC v2 (Haarnoja et al. 2018, Table 1): Adam at 3e-4 for actor, critics and α, batch 256, γ 0.99,
# τ 0.005, two hidden layers of 256, one gradient step and one target update per step (d = 1),
# target entropy −|A| with α learned. It fixes no random start phase: the TD3 family's 25,000 keeps
# SAC and MA-SAC on grid b's data protocol. The mechanism (K, M, C, A, η) is Table 3's, as MA-TD3.
SAC_V2 = dict(TABLE_3, target_smoothing=False, policy_delay=1)
DEFAULTS: dict[str, dict[str, Any]] = {
    "ma-sac": dict(SAC_V2, actors=2, workers=3),
    "sac": dict(SAC_V2, actors=1, workers=1, eta=0.0),
}


def soft_actor_loss(q: torch.Tensor, log_prob: torch.Tensor, alpha: torch.Tensor, live: torch.Tensor) -> torch.Tensor:
    """SAC's Eq. 7: actor k minimises E[α_k·log π_k(a|s) − min_i Q_ki(s, a)], a ~ π_k(·|s);
    q [K, n, B] of a, log_prob [K, B], alpha [K] (no gradient), live [K] -> scalar (summed over k)."""
    per_actor = (alpha.unsqueeze(-1) * log_prob - q.min(dim=1).values).mean(dim=-1)
    return (per_actor * live).sum()


def temperature_loss(log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float,
                     live: torch.Tensor) -> torch.Tensor:
    """SAC v2's temperature objective per actor, −log α_k·(log π_k(a|s) + H̄) averaged over the
    batch (log π without gradient, H̄ = −|A|): α_k falls while π_k's entropy is above H̄ and rises
    below it. log_alpha [K], log_prob [K, B], live [K] -> scalar (frozen actors contribute 0)."""
    per_actor = -(log_alpha * (log_prob.detach() + target_entropy).mean(dim=-1))
    return (per_actor * live).sum()


def alpha(agent: Agent) -> torch.Tensor:
    """The temperatures α_k [K] (no gradient)."""
    return agent.log_alpha.detach().exp()


def sampled(agent: Agent, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """a ~ π_k(·|s) for every actor k on `obs` [rows, obs] or [K, rows, obs] (reparameterised, ε from
    the agent's stream) and log π_k(a|s): [K, rows, A], [K, rows]."""
    eps = agent.draw_noise((agent.cfg.actors, obs.shape[-2], agent.spec.act_dim))
    return agent.actor.sample(obs, eps)


class SAC:
    """The SAC family (mam_core.family.Family)."""

    names = tuple(DEFAULTS)
    help = ("sac and ma-sac: SAC v2 (Haarnoja et al. 2018: lr 3e-4, batch 256, 256x256, τ 0.005, d = 1, α tuned "
            "towards entropy −|A|), with MA-TD3's K, M, C, A, η for ma-sac")
    policy_kind = GAUSSIAN_POLICY
    stochastic = True
    target_actor = False

    def defaults(self, algo: str) -> dict[str, Any]:
        return dict(DEFAULTS[algo])

    def problems(self, cfg: AlgoConfig) -> list[str]:
        return []

    # -- acting, numpy ----------------------------------------------------------------------------
    def act(self, policy: Any, obs: np.ndarray, noise: np.random.Generator, cfg: AlgoConfig,
            max_action: np.ndarray) -> np.ndarray:
        """a = max_action · tanh(μ + σ·ε), ε from the slot's noise stream (a SquashedGaussianPolicy)."""
        return policy.sample(obs, noise)

    def explorer(self, policy: Any, sigma: float, rng: np.random.Generator) -> Policy:
        """Actions sampled from π(·|s) (σ is TD3's; unused)."""
        return lambda obs: policy.sample(obs, rng)

    # -- the learner's pieces, torch --------------------------------------------------------------
    def make_actors(self, k: int, spec: EnvSpec, hidden: tuple[int, ...], gen: torch.Generator) -> Any:
        from mam_core.ensemble import GaussianActorEnsemble

        return GaussianActorEnsemble(k, spec.obs_dim, spec.act_dim, hidden, np.array(spec.max_action), gen)

    def temperature(self, cfg: AlgoConfig, spec: EnvSpec, device: torch.device) -> tuple[Any, Any]:
        """log α_k per actor, learned from α = 1 towards the target entropy −|A| (SAC v2), or fixed."""
        import torch

        fixed = cfg.alpha is not None
        log_alpha = torch.full((cfg.actors,), math.log(cfg.alpha) if fixed else 0.0, device=device,
                               requires_grad=not fixed)
        return log_alpha, None if fixed else torch.optim.Adam([log_alpha], lr=cfg.lr, fused=True)

    def next_actions(self, agent: Agent, next_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Eq. 9's ã_j ~ π_j(·|s') from the current actors, and α_j·log π_j(ã_j|s')."""
        action, log_prob = sampled(agent, next_obs)
        return action, alpha(agent).unsqueeze(-1) * log_prob

    def actor_step(self, agent: Agent, obs: torch.Tensor) -> list[torch.Tensor]:
        """Actor k descends the soft Eq. 7 on a ~ π_k(·|s), then log α_k descends the temperature loss
        with the same log π (as SAC v2's code does); eliminated actors and their α_k stay frozen
        (masked). Its metrics: the actor loss, the temperature loss (when α is learned), α_k after."""
        k, n = agent.cfg.actors, agent.cfg.critics_per_actor
        action, log_prob = sampled(agent, obs)
        critic_obs = obs.repeat_interleave(n, dim=0) if obs.dim() == 3 else obs
        q = agent.critic(critic_obs, agent.critic.per_actor_actions(action)).view(k, n, -1)
        loss = soft_actor_loss(q, log_prob, alpha(agent), agent.live)
        agent.adam_step(agent.actor_opt, loss, agent.actor_params_list)  # actor params only
        values = [loss.detach().reshape(1)]
        if agent.alpha_opt is not None:
            loss_alpha = temperature_loss(agent.log_alpha, log_prob, -float(agent.spec.act_dim), agent.live)
            agent.adam_step(agent.alpha_opt, loss_alpha, [agent.log_alpha])
            values.append(loss_alpha.detach().reshape(1))
        return [*values, alpha(agent)]

    def actor_metric_names(self, agent: Agent) -> list[str]:
        k = agent.cfg.actors
        return ["loss/actor", *(["loss/alpha"] if agent.alpha_opt is not None else []),
                *(f"alpha/actor{j}" for j in range(k))]
