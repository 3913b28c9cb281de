"""Batched ensembles of MLPs: K actors or n·K critics run in one matmul per layer.

Parameters of every member are stacked along a leading "member" axis, so a forward pass
over the whole ensemble is one `baddbmm` per layer instead of a Python loop over networks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn


class EnsembleMLP(nn.Module):
    """`members` independent MLPs `in_dim -> hidden... -> out_dim` with ReLU between layers.

    Initialised like `nn.Linear` (uniform ±1/sqrt(fan_in) for weights and biases), member by
    member, so an ensemble of one is distributed exactly like the reference TD3 networks.
    """

    def __init__(self, members: int, in_dim: int, hidden: Sequence[int], out_dim: int,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.members = members
        self.sizes = [in_dim, *hidden, out_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(self.sizes[:-1], self.sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)
            w = torch.empty(members, fan_in, fan_out).uniform_(-bound, bound, generator=generator)
            b = torch.empty(members, 1, fan_out).uniform_(-bound, bound, generator=generator)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))

    def forward(self, x: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
        """x: [E, B, in] (one input per member) -> [E, B, out].

        `members` (index tensor) runs only those members; x's leading axis must match it.
        """
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            if members is not None:
                w, b = w.index_select(0, members), b.index_select(0, members)
            x = torch.baddbmm(b, x, w)
            if i < last:
                x = torch.relu(x)
        return x

    def member_state(self, k: int) -> dict[str, np.ndarray]:
        """Member k's parameters as float32 numpy arrays (`w0, b0, w1, ...`), for the wire."""
        out: dict[str, np.ndarray] = {}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            out[f"w{i}"] = w[k].detach().to("cpu", torch.float32).numpy().copy()
            out[f"b{i}"] = b[k].detach().to("cpu", torch.float32).numpy().copy()
        return out

    def member_shapes(self) -> dict[str, tuple[int, ...]]:
        shapes: dict[str, tuple[int, ...]] = {}
        for i, (fan_in, fan_out) in enumerate(zip(self.sizes[:-1], self.sizes[1:])):
            shapes[f"w{i}"] = (fan_in, fan_out)
            shapes[f"b{i}"] = (1, fan_out)
        return shapes

    @torch.no_grad()
    def load_member(self, k: int, params: dict[str, np.ndarray]) -> None:
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            # np.array copies: decoded wire arrays are read-only views.
            w[k].copy_(torch.from_numpy(np.array(params[f"w{i}"], dtype=np.float32)))
            b[k].copy_(torch.from_numpy(np.array(params[f"b{i}"], dtype=np.float32)))


class ActorEnsemble(nn.Module):
    """K deterministic policies π_k(s) = max_action · tanh(MLP_k(s))."""

    def __init__(self, n_actors: int, obs_dim: int, act_dim: int, hidden: Sequence[int],
                 max_action: np.ndarray | float, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.net = EnsembleMLP(n_actors, obs_dim, hidden, act_dim, generator)
        max_action = torch.as_tensor(np.broadcast_to(max_action, (act_dim,)).copy(), dtype=torch.float32)
        self.register_buffer("max_action", max_action)

    def forward(self, obs: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
        """obs: [B, obs_dim] shared by all members, or [E, B, obs_dim] -> actions [E, B, act_dim]."""
        e = self.net.members if members is None else members.numel()
        if obs.dim() == 2:
            obs = obs.unsqueeze(0).expand(e, -1, -1)
        return self.max_action * torch.tanh(self.net(obs, members))


class CriticEnsemble(nn.Module):
    """n·K Q-functions Q_ki(s, a); member index k·n + i (actor-major, Eq. 5 numbering)."""

    def __init__(self, n_actors: int, critics_per_actor: int, obs_dim: int, act_dim: int,
                 hidden: Sequence[int], generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.n_actors = n_actors
        self.per_actor = critics_per_actor
        self.net = EnsembleMLP(n_actors * critics_per_actor, obs_dim + act_dim, hidden, 1, generator)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor,
                members: torch.Tensor | None = None) -> torch.Tensor:
        """obs [B, obs_dim] shared; actions [E, B, act_dim], one per member -> Q [E, B]."""
        e = actions.shape[0]
        x = torch.cat((obs.unsqueeze(0).expand(e, -1, -1), actions), dim=-1)
        return self.net(x, members).squeeze(-1)

    def per_actor_actions(self, actions: torch.Tensor) -> torch.Tensor:
        """[K, B, A] actions of the K actors -> [n·K, B, A], critic (k, i) gets actor k's action."""
        return actions.repeat_interleave(self.per_actor, dim=0)


@torch.no_grad()
def soft_update(target: nn.Module, online: nn.Module, tau: torch.Tensor | float) -> None:
    """Eq. 4: θ' ← τθ + (1−τ)θ', in place. `tau` may be per member ([E, 1, 1]) to freeze some."""
    tgt = [p for p in target.parameters()]
    src = [p for p in online.parameters()]
    if isinstance(tau, torch.Tensor):
        for t, s in zip(tgt, src):
            t.lerp_(s, tau)
    else:
        torch._foreach_lerp_(tgt, src, tau)
