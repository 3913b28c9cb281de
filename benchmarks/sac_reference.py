"""A plain single-actor SAC (v2: learned temperature, two critics, no value network), written
the way the common reference code writes it.

Separate `nn.Sequential` trunk with `nn.Linear` mean and log-std heads, two critics, torch's
own Adam, one `train()` step. It is the yardstick of `mam bench` (update rate) and of
`tests/test_sac.py` (weight for weight), not part of the product. The Gaussian noise comes from
the `generator` it is given, so a test can hand it the same draws as mam's agent.
"""

from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F
from torch import nn
from torch.distributions import Normal

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


class GaussianActor(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, max_action: float, hidden: int = 256) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())
        self.mean = nn.Linear(hidden, act_dim)
        self.log_std = nn.Linear(hidden, act_dim)
        self.max_action = max_action

    def forward(self, s: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(max_action · tanh(u), log π) with u = μ + σ·eps; log π [B, 1] in the unit box."""
        h = self.trunk(s)
        mu = self.mean(h)
        std = self.log_std(h).clamp(LOG_STD_MIN, LOG_STD_MAX).exp()
        u = mu + std * eps
        log_prob = Normal(mu, std).log_prob(u) - 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))
        return self.max_action * torch.tanh(u), log_prob.sum(dim=1, keepdim=True)


class Critic(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 256) -> None:
        super().__init__()
        self.q1 = nn.Sequential(nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                nn.Linear(hidden, 1))
        self.q2 = nn.Sequential(nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                nn.Linear(hidden, 1))

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sa = torch.cat([s, a], 1)
        return self.q1(sa), self.q2(sa)


class SAC:
    def __init__(self, obs_dim: int, act_dim: int, max_action: float, discount: float = 0.99, tau: float = 0.005,
                 lr: float = 3e-4, hidden: int = 256, alpha: float | None = None,
                 generator: torch.Generator | None = None) -> None:
        self.actor = GaussianActor(obs_dim, act_dim, max_action, hidden)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=lr)
        self.critic = Critic(obs_dim, act_dim, hidden)
        self.critic_target = copy.deepcopy(self.critic)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=lr)
        self.log_alpha = torch.tensor([0.0 if alpha is None else math.log(alpha)], requires_grad=alpha is None)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=lr) if alpha is None else None
        self.target_entropy = -float(act_dim)
        self.act_dim, self.discount, self.tau = act_dim, discount, tau
        self.generator = generator

    def noise(self, rows: int) -> torch.Tensor:
        return torch.randn((rows, self.act_dim), generator=self.generator)

    def train(self, s, a, r, s2, not_done) -> float:
        alpha = self.log_alpha.detach().exp()
        with torch.no_grad():
            a2, log_prob2 = self.actor(s2, self.noise(s2.shape[0]))
            q1t, q2t = self.critic_target(s2, a2)
            y = r + not_done * self.discount * (torch.min(q1t, q2t) - alpha * log_prob2)
        q1, q2 = self.critic(s, a)
        critic_loss = F.mse_loss(q1, y) + F.mse_loss(q2, y)
        self.critic_optimizer.zero_grad()
        critic_loss.backward()
        self.critic_optimizer.step()

        pi, log_prob = self.actor(s, self.noise(s.shape[0]))
        q1_pi, q2_pi = self.critic(s, pi)
        actor_loss = (alpha * log_prob - torch.min(q1_pi, q2_pi)).mean()
        self.actor_optimizer.zero_grad()
        actor_loss.backward()
        self.actor_optimizer.step()
        if self.alpha_optimizer is not None:
            alpha_loss = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()
            self.alpha_optimizer.zero_grad()
            alpha_loss.backward()
            self.alpha_optimizer.step()
        with torch.no_grad():
            for p, tp in zip(self.critic.parameters(), self.critic_target.parameters()):
                tp.copy_(self.tau * p + (1 - self.tau) * tp)
        return float(critic_loss)
