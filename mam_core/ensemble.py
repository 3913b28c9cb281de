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

from mam_core import arithmetic, gemm
from mam_core.policy import LOG_STD_MAX, LOG_STD_MIN, member_shapes

Members = slice | torch.Tensor | None


FEATURE_MAJOR_MIN_ROWS = 32


def _products(x: torch.Tensor) -> tuple:
    """(baddbmm, addmm, relu_) for float32 layers on x's device: on a CPU under portable arithmetic
    the pinned kernels of `mam_core.gemm` (the same bits on every CPU) and its ReLU, whose backward
    minds their layouts; else torch's."""
    if x.device.type == "cpu" and x.dtype == torch.float32 and arithmetic.portable_gemm():
        return gemm.baddbmm, gemm.addmm, gemm.relu_
    return torch.baddbmm, torch.addmm, torch.relu_


def run_layers(x: torch.Tensor, layers: Sequence[tuple[torch.Tensor, torch.Tensor]],
               low: torch.dtype | None = None) -> torch.Tensor:
    """x [E, B, in] through Linear-ReLU-...-Linear with stacked (w [E, in, out], b [E, 1, out]).

    `low` (e.g. torch.bfloat16): every layer but the head runs its GEMM in that dtype, mixed
    precision: parameters, their gradients and the optimizer stay float32, and so does the head
    (Q values and actions keep float32 precision; its GEMMs are narrow and cheap).

    Two layouts, the same numbers (docs/PERFORMANCE.md has the measurements). Training
    batches (B >= FEATURE_MAJOR_MIN_ROWS) keep the activations feature-major,
    hᵀ = Wᵀ·xᵀ + bᵀ ([E, out, B]), so every batched GEMM of the forward pass and of the
    input gradients has the batch as its wide output side. Row-major, the narrow heads
    (Q of width 1, actions of width 6 to 17) make batched GEMMs of output width 1 to 17,
    which the CPU kernels run up to ~6x slower. A few rows stay row-major.
    """
    last = len(layers) - 1
    baddbmm, _, relu_ = _products(x)
    if x.shape[-2] >= FEATURE_MAJOR_MIN_ROWS:
        h = x.mT
        for i, (w, b) in enumerate(layers):
            if low is not None and i < last:
                h = torch.relu_(torch.baddbmm(b.mT.to(low), w.mT.to(low), h.to(low)))
            elif i < last:  # in place: baddbmm keeps its inputs for backward, not its output
                h = relu_(baddbmm(b.mT, w.mT, h.to(w.dtype)))
            else:
                h = baddbmm(b.mT, w.mT, h.to(w.dtype))
        return h.mT
    for i, (w, b) in enumerate(layers):
        if low is not None and i < last:
            x = torch.relu_(torch.baddbmm(b.to(low), x.to(low), w.to(low)))
        elif i < last:
            x = relu_(baddbmm(b, x.to(w.dtype), w))
        else:
            x = baddbmm(b, x.to(w.dtype), w)
    return x


def run_member(x: torch.Tensor, weights: Sequence[torch.Tensor], biases: Sequence[torch.Tensor],
               k: int, low: torch.dtype | None = None) -> torch.Tensor:
    """One member k on x [B, in] or [1, B, in] -> [1, B, out] with plain 2-D GEMMs: a worker's or the referee's
    policy, a K=1 actor. CPU BLAS runs these several times faster than a batched GEMM of one."""
    if x.dim() == 3:
        if x.shape[0] != 1:
            raise ValueError(f"one member selected, but inputs for {x.shape[0]} members given")
        x = x[0]
    h = x
    last = len(weights) - 1
    _, addmm, relu_ = _products(x)
    for i, (w, b) in enumerate(zip(weights, biases)):
        if low is not None and i < last:  # mixed precision as in run_layers
            h = torch.relu_(torch.addmm(b[k].to(low), h.to(low), w[k].to(low)))
        elif i < last:  # in place: addmm keeps its inputs for backward, not its output
            h = relu_(addmm(b[k], h.to(w.dtype), w[k]))
        else:
            h = addmm(b[k], h.to(w.dtype), w[k])
    return h.unsqueeze(0)


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
        self.low_precision: torch.dtype | None = None  # see run_layers; one-member paths stay float32
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(self.sizes[:-1], self.sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)
            w = torch.empty(members, fan_in, fan_out).uniform_(-bound, bound, generator=generator)
            b = torch.empty(members, 1, fan_out).uniform_(-bound, bound, generator=generator)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))

    def layers(self, members: Members = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(weight, bias) of every layer, restricted to `members`: a slice is a view (no copy)."""
        if members is None:
            return list(zip(self.weights, self.biases))
        if isinstance(members, slice):
            return [(w[members], b[members]) for w, b in zip(self.weights, self.biases)]
        return [(w.index_select(0, members), b.index_select(0, members)) for w, b in zip(self.weights, self.biases)]

    def forward(self, x: torch.Tensor, members: Members = None) -> torch.Tensor:
        """x: [E, B, in] (one input per member) or [B, in] (shared by all) -> [E, B, out].

        `members` (slice or index tensor) runs only those members; x's leading axis must match.
        """
        k = self.single_member(members)
        if k is not None:
            return run_member(x, self.weights, self.biases, k, self.low_precision)
        layers = self.layers(members)
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(layers[0][0].shape[0], -1, -1)
        return run_layers(x, layers, self.low_precision)

    def single_member(self, members: Members) -> int | None:
        """The member's index when `members` names exactly one (without a device sync), else None."""
        if self.members == 1 and members is None:
            return 0
        if isinstance(members, slice):
            picked = range(self.members)[members]
            return picked[0] if len(picked) == 1 else None
        if isinstance(members, torch.Tensor) and members.numel() == 1 and members.device.type == "cpu":
            return int(members)
        return None

    def member_state(self, k: int) -> dict[str, np.ndarray]:
        """Member k's parameters as float32 numpy arrays (`w0, b0, w1, ...`), for the wire."""
        out: dict[str, np.ndarray] = {}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            out[f"w{i}"] = w[k].detach().to("cpu", torch.float32).numpy().copy()
            out[f"b{i}"] = b[k].detach().to("cpu", torch.float32).numpy().copy()
        return out

    def member_shapes(self) -> dict[str, tuple[int, ...]]:
        return member_shapes(self.sizes[0], self.sizes[1:-1], self.sizes[-1])

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

    def forward(self, obs: torch.Tensor, members: Members = None) -> torch.Tensor:
        """obs: [B, obs_dim] shared by all members, or [E, B, obs_dim] -> actions [E, B, act_dim]."""
        return self.max_action * torch.tanh(self.net(obs, members))


def squashed_gaussian_log_prob(u: torch.Tensor, eps: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """log π(a|s) of a = tanh(u), u = μ + σ·ε ~ N(μ, σ²), summed over the action axis: [..., A] -> [...].

    log N(u; μ, σ) = −ε²/2 − log σ − log(2π)/2 per dimension, minus the change of variables
    log(1 − tanh²u) = 2·(log 2 − u − softplus(−2u)), exact and finite where tanh saturates in float32
    (|u| ≳ 9; the SAC paper's Appendix C, Haarnoja et al. 2018a; this form is Spinning Up's). It is
    the density of the action in the unit box: the max_action scale is a constant left out, as in
    softlearning and Stable-Baselines3, so the target entropy −|A| does not depend on the bounds.
    """
    gaussian = -0.5 * eps.pow(2) - log_std - 0.5 * math.log(2.0 * math.pi)
    squash = 2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))
    return (gaussian - squash).sum(dim=-1)


class GaussianActorEnsemble(nn.Module):
    """K squashed-Gaussian policies (SAC): one MLP per actor whose last layer holds the μ and
    log σ heads ([..., :A] and [..., A:], log σ clamped to [LOG_STD_MIN, LOG_STD_MAX]);
    π_k(·|s) = max_action · tanh(N(μ_k(s), σ_k(s)²)). `forward` is the mean action
    max_action · tanh(μ_k(s)) (evaluation); `sample` the reparameterised draw with its log π.
    The numpy twin for workers and the referee is `mam_core.policy.SquashedGaussianPolicy`."""

    def __init__(self, n_actors: int, obs_dim: int, act_dim: int, hidden: Sequence[int],
                 max_action: np.ndarray | float, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.act_dim = act_dim
        self.net = EnsembleMLP(n_actors, obs_dim, hidden, 2 * act_dim, generator)
        max_action = torch.as_tensor(np.broadcast_to(max_action, (act_dim,)).copy(), dtype=torch.float32)
        self.register_buffer("max_action", max_action)

    def heads(self, obs: torch.Tensor, members: Members = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(μ, log σ), each [E, B, act_dim]."""
        out = self.net(obs, members)
        return out[..., :self.act_dim], out[..., self.act_dim:].clamp(LOG_STD_MIN, LOG_STD_MAX)

    def forward(self, obs: torch.Tensor, members: Members = None) -> torch.Tensor:
        """The mean action: obs [B, obs_dim] or [E, B, obs_dim] -> [E, B, act_dim]."""
        return self.max_action * torch.tanh(self.heads(obs, members)[0])

    def sample(self, obs: torch.Tensor, eps: torch.Tensor,
               members: Members = None) -> tuple[torch.Tensor, torch.Tensor]:
        """a = max_action · tanh(μ + σ·ε) for the given ε [E, B, act_dim], differentiable in the
        actors' parameters (the reparameterisation trick), and log π(a|s) [E, B]."""
        mu, log_std = self.heads(obs, members)
        u = mu + log_std.exp() * eps
        return self.max_action * torch.tanh(u), squashed_gaussian_log_prob(u, eps, log_std)


class CriticEnsemble(nn.Module):
    """n·K Q-functions Q_ki(s, a); member index k·n + i (actor-major, Eq. 5 numbering)."""

    def __init__(self, n_actors: int, critics_per_actor: int, obs_dim: int, act_dim: int,
                 hidden: Sequence[int], generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.n_actors = n_actors
        self.per_actor = critics_per_actor
        self.net = EnsembleMLP(n_actors * critics_per_actor, obs_dim + act_dim, hidden, 1, generator)

    def forward(self, obs: torch.Tensor, actions: torch.Tensor, members: Members = None) -> torch.Tensor:
        """obs [B, obs_dim] shared, or [E, B, obs_dim] one per member (per-actor mini-batches);
        actions [E, B, act_dim] one per member, or [B, act_dim] shared by all members (the
        critic regression step on a shared batch) -> Q [E, B].

        One concatenated first layer: measured faster than splitting its weights into an obs
        part (one GEMM shared by all members) and an action part (docs/PERFORMANCE.md).
        """
        if actions.dim() == 2 or obs.dim() == 3:
            x = torch.cat((obs, actions), dim=-1)
        else:
            x = torch.cat((obs.unsqueeze(0).expand(actions.shape[0], -1, -1), actions), dim=-1)
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
