"""The multi-actor update step, written once for every algorithm family (mam_core.family).

K actors and n·K critics live in batched ensembles. One `update()` is one critic step for
every live actor's critics (Eq. 5 with the Eq. 9 target) and, every d steps, one actor step
(Eq. 7) followed by the soft target update (Eq. 4). What differs between families is theirs:
the actors, Eq. 9's next actions and entropy term, and the actor phase (mam_core.td3: MA-TD3,
MA-DDPG, TD3 = K 1, n 2, DDPG = K 1, n 1; mam_core.sac: MA-SAC and SAC, Eq. 9 on soft values
Q'_ji(s', ã_j) − α_j·log π_j(ã_j|s'), docs/DESIGN-DECISIONS.md "MA-SAC").
"""

from __future__ import annotations

import copy
import ctypes
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from mam_core import optim_start
from mam_core.accel import for_device
from mam_core.config import AlgoConfig
from mam_core.ensemble import CriticEnsemble, soft_update
from mam_core.policy import EnvSpec  # noqa: F401  (re-exported: EnvSpec lives with the torch-free code)


def weighted_target(q_next: torch.Tensor, eta: float) -> torch.Tensor:
    """Eq. 9 without reward and discount: q_next [K, n, B] of Q'_ji(s', ã_j) -> [K, B].

    (1−η)·min_i Q'_ki + η/(n(K−1))·Σ_{j≠k} Σ_i Q'_ji. With K=1 or η=0 this is TD3's clipped
    double-Q target (n=2) or DDPG's target (n=1).
    """
    k, n, _ = q_next.shape
    own = q_next.min(dim=1).values
    if k == 1 or eta == 0.0:
        return own
    per_actor = q_next.sum(dim=1)  # [K, B]
    others = per_actor.sum(dim=0, keepdim=True) - per_actor
    return (1.0 - eta) * own + (eta / (n * (k - 1))) * others


def weighted_target_per_batch(q_next: torch.Tensor, eta: float, owners: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 9 when every actor has its own mini-batch: q_next [K, n, L, B] holds Q'_ji(s'_l, ã_j)
    (critic j, i on batch l, with actor j's target action there) -> [L, B], row l for the actor
    that owns batch l (`owners[l]`; by default batch k is actor k's, L = K):
    (1−η)·min_i Q'_ki(s'_l, ã_k) + η/(n(K−1))·Σ_{j≠k} Σ_i Q'_ji(s'_l, ã_j), k = owners[l].
    Equal to `weighted_target` when all K batches are the same."""
    k, n, batches, _ = q_next.shape
    owners = torch.arange(batches, device=q_next.device) if owners is None else owners
    cols = torch.arange(batches, device=q_next.device)
    own = q_next.min(dim=1).values[owners, cols]  # [L, B]
    if k == 1 or eta == 0.0:
        return own
    per_actor = q_next.sum(dim=1)  # [K(j), L, B]
    others = per_actor.sum(dim=0) - per_actor[owners, cols]
    return (1.0 - eta) * own + (eta / (n * (k - 1))) * others


def soft_values(q_next: torch.Tensor, entropy: torch.Tensor | None) -> torch.Tensor:
    """SAC's soft values for Eq. 9: Q'_ji(s', ã_j) − α_j·log π_j(ã_j|s') for every critic i of actor
    j; q_next [K, n, ...], entropy (α_j·log π_j) [K, ...] or None (TD3/DDPG: q_next as it is).
    Subtracting before the weighting makes each term of Eq. 9 the soft value of its own actor:
    min_i (Q'_ki − α_k·log π_k) = min_i Q'_ki − α_k·log π_k (docs/DESIGN-DECISIONS.md, "MA-SAC")."""
    return q_next if entropy is None else q_next - entropy.unsqueeze(1)


def critic_target(reward: torch.Tensor, not_done: torch.Tensor, q_next: torch.Tensor,
                  gamma: float, eta: float) -> torch.Tensor:
    """y_k = r + γ(1−d)·weighted_target: reward/not_done [B] (or [K, B], one batch per actor),
    q_next [K, n, B] (or [K, n, K, B], see `weighted_target_per_batch`) -> [K, B]."""
    weighted = weighted_target(q_next, eta) if q_next.dim() == 3 else weighted_target_per_batch(q_next, eta)
    return reward + gamma * not_done * weighted


def critic_loss(q: torch.Tensor, y: torch.Tensor, live: torch.Tensor) -> torch.Tensor:
    """Eq. 5 summed over members: q [K, n, B], y [K, B], live [K] (0/1) -> scalar.

    Each critic gets its own MSE; eliminated actors' critics contribute nothing (frozen).
    """
    per_member = (q - y.unsqueeze(1)).pow(2).mean(dim=-1)  # [K, n]
    return (per_member.sum(dim=1) * live).sum()


def adam_step(opt: torch.optim.Optimizer, loss: torch.Tensor, params: list[torch.Tensor]) -> None:
    """One optimizer step on `loss`'s gradients w.r.t. `params` only; the gradients are dropped
    after the step, so nothing stale is kept between steps.

    The gradients are laid out like their parameters first: the feature-major layers produce
    transposed weight gradients, and torch's fused CPU Adam (2.13) reads a strided gradient as
    if it were contiguous, i.e. it applies another element's gradient (measured: a [2, 8, 4]
    parameter with a transposed gradient moved 0.2 away from plain Adam after one step at
    lr 0.1). `tests/test_agent.py` checks 300 updates against the reference TD3.
    """
    grads = torch.autograd.grad(loss, params)
    for p, g in zip(params, grads):
        p.grad = g if g.stride() == p.stride() else g.contiguous()
    optim_start.step(opt)  # what opt.step() computes, without importing torch._dynamo
    for p in params:
        p.grad = None


def pick_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise RuntimeError(f"--device {device} asked for, but torch sees no CUDA device")
    return torch.device(device)


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters
_allocator_tuned = False


def retain_freed_memory(mmap_threshold: int = 64 << 20, trim_threshold: int = 512 << 20) -> bool:
    """Let glibc keep freed blocks of up to `mmap_threshold` bytes for reuse (once per process).

    torch's CPU allocator is plain malloc. An update step allocates and frees dozens of
    activation and gradient buffers of ~1 MB (K·n members × batch × hidden); by default
    glibc hands such blocks back to the kernel, so every step page-faults them in again
    (measured: ~500 faults and ~1.4 ms of system time per MA-TD3 K=2 update, ~8% of it).
    Raising the mmap and trim thresholds keeps them in the heap. Process-wide and harmless
    for correctness; a no-op off glibc. Returns True when applied.
    """
    global _allocator_tuned
    if _allocator_tuned:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, mmap_threshold) == 1
        ok = libc.mallopt(_M_TRIM_THRESHOLD, trim_threshold) == 1 and ok
    except (OSError, AttributeError):
        return False
    _allocator_tuned = ok
    return ok


class MultiActorAgent:
    """Networks, targets, optimizers and the update step of Algorithm 1.

    Usage: `agent.update(batch)` with batch tensors `obs, action, reward, next_obs, not_done`
    on `agent.device`, either one mini-batch for all actors (obs [B, obs_dim]) or one per actor
    (obs [K, B, obs_dim]: `ReplayBuffer.sample(B, groups=K)`, Algorithm 1's default,
    `agent.batch_groups`); `agent.eliminate(survivor)` at step C; `agent.actor_params(k)` for
    the workers; `state_dict()` / `load_state_dict()` for pickle-free checkpoints.
    """

    def __init__(self, cfg: AlgoConfig, spec: EnvSpec, device: str | torch.device = "cpu") -> None:
        self.cfg = cfg
        self.spec = spec
        self.device = torch.device(device) if not isinstance(device, torch.device) else device
        self.accel = for_device(self.device)  # what only CUDA (or only the CPU) does: mam_core/accel.py
        if self.accel.host_allocator_tuning:
            retain_freed_memory()
        self.eta = cfg.effective_eta
        k, n = cfg.actors, cfg.critics_per_actor
        gen = torch.Generator().manual_seed(cfg.seed)
        self.family = cfg.family  # TD3/DDPG, SAC or a user's: what differs between them (mam_core.family)
        self.stochastic = self.family.stochastic  # a temperature log α_k per actor is part of the step's state
        self.actor = self.family.make_actors(k, spec, cfg.hidden, gen)
        self.critic = CriticEnsemble(k, n, spec.obs_dim, spec.act_dim, cfg.hidden, gen)
        self.actor.to(self.device)
        self.critic.to(self.device)
        if cfg.precision == "bf16":  # mixed precision; the targets (deep copies) inherit it
            self.actor.net.low_precision = self.critic.net.low_precision = torch.bfloat16
        # SAC has no target actor: ã_j is sampled from the current π_j (Eq. 9 on soft values).
        self.actor_target = copy.deepcopy(self.actor).requires_grad_(False) if self.family.target_actor else None
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_params_list = list(self.actor.parameters())
        self.critic_params_list = list(self.critic.parameters())
        # Fused Adam: one kernel per step for all parameters (measured faster than foreach on CPU).
        adam = dict(lr=cfg.lr, fused=True)
        self.actor_opt = torch.optim.Adam(self.actor_params_list, **adam)
        self.critic_opt = torch.optim.Adam(self.critic_params_list, **adam)
        self.noise_gen = torch.Generator(device=self.device).manual_seed(cfg.seed + 1)
        # SAC: log α_k per actor, and its optimizer where α is learned; None and None for TD3.
        self.log_alpha, self.alpha_opt = self.family.temperature(cfg, spec, self.device)
        self.max_action = self.actor.max_action
        self.first_critics = torch.arange(k, device=self.device) * n
        self.first_critic_members = slice(0, k * n, n)  # the same members as a view: no weight copy
        self.live = torch.ones(k, device=self.device)  # actors that act and train (Eq. 7)
        self.critic_live = torch.ones(k, device=self.device)  # actors whose critics train (Eq. 5)
        self._live_flags = [True] * k
        self._training_index = torch.arange(k, device=self.device)  # actors whose critics train (critic_live)
        # Algorithm 1 samples a mini-batch per actor; K = 1 is the same draw either way.
        self.batch_groups = k if k > 1 and not cfg.shared_batch else None
        self._tau_actor = torch.full((k, 1, 1), cfg.tau, device=self.device)
        self._tau_critic = torch.full((k * n, 1, 1), cfg.tau, device=self.device)
        self.updates = 0
        self.actor_updates = 0
        self.versions = [0] * k  # bumped on every actor step of a live actor
        self.update_s = 0.0  # seconds in update_critics / update_actors (on a GPU: issuing the work)
        # CUDA graphs of the two phases (mam_core/graphs.py), made by `sampler` where the device
        # takes them; `structure` counts the changes that invalidate a captured graph.
        self.graphs: Any = None
        self.structure = 0
        self._sampler: tuple[tuple[int, int], Callable[[], Any]] | None = None  # `sampler`'s last (key, function)

    def sampler(self, buffer: Any, batch_size: int | None = None) -> Callable[[], Any]:
        """What Algorithm 1 calls for each update's mini-batch(es) from `buffer` (a ReplayBuffer):
        `buffer.sample(B, batch_groups)`, or on a device that takes CUDA graphs (mam_core/accel.py)
        the same indices staged for the graphed update, which gathers the rows itself. Made once
        per buffer and batch size, then the same function."""
        batch_size = batch_size or self.cfg.batch_size
        key = (id(buffer), batch_size)
        if self._sampler is not None and self._sampler[0] == key:
            return self._sampler[1]
        from mam_core import graphs

        if graphs.usable(self, buffer):
            self.graphs = graphs.UpdateGraphs(self, buffer, batch_size)
            sample = self.graphs.stage
        else:
            sample = lambda: buffer.sample(batch_size, self.batch_groups)  # noqa: E731
        self._sampler = (key, sample)
        return sample

    # -- the update step -------------------------------------------------------------------
    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One update: the critic phase (Eq. 5 on the Eq. 9 targets), then, every d updates,
        the delayed actor phase (Eq. 7) and the soft target update (Eq. 4)."""
        metrics = self.update_critics(batch)
        if self.actor_phase_due:
            metrics.update(self.update_actors(batch))
        return metrics

    @property
    def actor_phase_due(self) -> bool:
        """The update just made is the d-th since the last actor phase (TD3's rule)."""
        return self.updates % self.cfg.policy_delay == 0

    def update_critics(self, batch: Any) -> dict[str, float]:
        """Algorithm 1, lines 11-13: every live actor's critics regress on its Eq. 9 targets.
        Between this and `update_actors` Algorithm 1 places the round and the elimination.
        `batch` is a dict of tensors, or a `graphs.Staged` mini-batch (`sampler`)."""
        started = time.perf_counter()
        if self.graphs is not None and self.graphs.staged(batch):
            metrics: Any = self.graphs.metrics(self.critic_metric_names(), self.graphs.critics())
        else:
            metrics = dict(zip(self.critic_metric_names(), self.critic_step(batch).tolist()))
        self.updates += 1
        self.update_s += time.perf_counter() - started
        return metrics

    def critic_metric_names(self) -> list[str]:
        """The names of `critic_step`'s values, in order."""
        return ["loss/critic", *(f"q/actor{j}" for j in range(self.cfg.actors))]

    def critic_step(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The critic phase's tensor work (no host sync, no Python state: a CUDA graph captures it):
        the Eq. 9 targets, Eq. 5 and the critics' Adam step; its metrics as one tensor."""
        k, n = self.cfg.actors, self.cfg.critics_per_actor
        obs, action, reward = batch["obs"], batch["action"], batch["reward"]
        next_obs, not_done = batch["next_obs"], batch["not_done"]

        per_actor = obs.dim() == 3  # [K, B, obs_dim]: actor k's own mini-batch (Algorithm 1, line 11)
        with torch.no_grad():
            y = self._targets(next_obs, reward, not_done, per_actor)

        # Eq. 5: critic regression for every live actor's n critics.
        if per_actor:  # critic (k, i) regresses on actor k's batch
            q = self.critic(obs.repeat_interleave(n, dim=0), action.repeat_interleave(n, dim=0)).view(k, n, -1)
        else:
            q = self.critic(obs, action).view(k, n, -1)  # the batch's action is shared by all n·K critics
        loss_q = critic_loss(q, y, self.critic_live)
        adam_step(self.critic_opt, loss_q, self.critic_params_list)
        return torch.cat([loss_q.detach().reshape(1), q.detach().mean(dim=(1, 2))])

    def update_actors(self, batch: Any) -> dict[str, float]:
        """Algorithm 1, lines 21-24: the family's Eq. 7 (TD3: actor k follows its first critic
        Q_k1; SAC: min_i Q_ki with its entropy bonus, then α_k steps), then the soft target update
        (Eq. 4); eliminated members and their targets stay frozen."""
        started = time.perf_counter()
        if self.graphs is not None and self.graphs.staged(batch):
            metrics = self.graphs.metrics(self.actor_metric_names(), self.graphs.actors())
        else:
            metrics = dict(zip(self.actor_metric_names(), self.actor_step(batch).tolist()))
        self.actor_updates += 1
        for j, alive in enumerate(self._live_flags):  # a Python list: no device sync
            if alive:
                self.versions[j] += 1
        self.update_s += time.perf_counter() - started
        return metrics

    def actor_metric_names(self) -> list[str]:
        """The names of `actor_step`'s values, in order (the family's)."""
        return self.family.actor_metric_names(self)

    def actor_step(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The actor phase's tensor work (capturable, like `critic_step`): the family's Eq. 7 and
        optimizer step(s), then the soft target update (Eq. 4); its metrics as one tensor."""
        values = torch.cat(self.family.actor_step(self, batch["obs"]))
        if self.actor_target is not None:
            soft_update(self.actor_target, self.actor, self._tau_actor)
        soft_update(self.critic_target, self.critic, self._tau_critic)
        return values

    def adam_step(self, opt: torch.optim.Optimizer, loss: torch.Tensor, params: list[torch.Tensor]) -> None:
        """`adam_step` for a family's actor phase (it needs no torch import of its own)."""
        adam_step(opt, loss, params)

    def draw_noise(self, shape: tuple[int, ...]) -> torch.Tensor:
        """N(0, I) of `shape` from the agent's seeded stream (`noise_gen`): every random draw of an
        update goes through here (a CUDA graph draws them before its replay, in the same order)."""
        if self.graphs is not None and self.graphs.capturing:
            return self.graphs.noise(shape)
        return torch.randn(shape, generator=self.noise_gen, device=self.device)

    def _targets(self, next_obs: torch.Tensor, reward: torch.Tensor, not_done: torch.Tensor,
                 per_actor: bool) -> torch.Tensor:
        """Eq. 9 targets y [K, B], one per actor (on its own batch when `per_actor`)."""
        cfg, k, n = self.cfg, self.cfg.actors, self.cfg.critics_per_actor
        if not per_actor:
            next_action, entropy = self.family.next_actions(self, next_obs)  # [K, B, A]
            q_next = self.critic_target(next_obs, self.critic.per_actor_actions(next_action))
            return critic_target(reward, not_done, soft_values(q_next.view(k, n, -1), entropy), cfg.gamma, self.eta)
        b = next_obs.shape[1]
        if self.eta == 0.0:  # each actor's own critics on its own batch only
            next_action, entropy = self.family.next_actions(self, next_obs)  # actor k on batch k: [K, B, A]
            q_next = self.critic_target(next_obs.repeat_interleave(n, dim=0),
                                        self.critic.per_actor_actions(next_action))
            return critic_target(reward, not_done, soft_values(q_next.view(k, n, -1), entropy), cfg.gamma, 0.0)
        # Eq. 9 needs every critic j on actor k's next states with actor j's target action there:
        # K·n critics on K·B rows. Only the batches of actors whose critics still train count
        # (after the elimination, usually the survivor's alone): the others' targets stay 0,
        # masked out of the loss (critic_loss), so their rows are not computed.
        index = self._training_index
        owners = len(index)
        rows = next_obs if owners == k else next_obs.index_select(0, index)
        flat = rows.reshape(owners * b, -1)
        next_action, entropy = self.family.next_actions(self, flat)  # actor j on the L batches: [K, L·B, A]
        q_next = self.critic_target(flat, self.critic.per_actor_actions(next_action))  # [K·n, L·B]
        q_next = soft_values(q_next.view(k, n, owners, b), None if entropy is None else entropy.view(k, owners, b))
        weighted = weighted_target_per_batch(q_next, self.eta, index)
        if owners == k:
            return reward + cfg.gamma * not_done * weighted
        y = torch.zeros_like(reward)
        y[index] = reward[index] + cfg.gamma * not_done[index] * weighted
        return y

    @property
    def _training_critics(self) -> list[int]:
        """The actors whose critics still train, as a list (tests; the update uses the tensor)."""
        return self._training_index.tolist()

    @_training_critics.setter
    def _training_critics(self, actors: list[int]) -> None:
        self._training_index = torch.tensor(actors, device=self.device)

    # -- obsolescence ----------------------------------------------------------------------
    def eliminate(self, survivor: int) -> None:
        """Freeze every actor but `survivor` with its target (Sec. 3.1.1); what happens to the
        eliminated actors' critics and to Eq. 9 is `cfg.after_elimination`:

        - `frozen` (the paper's literal reading): their critics and target critics freeze too
          and keep serving the Eq. 9 sum with their values from step C.
        - `train-critics`: their critics keep training on the shared buffer with their own Eq. 9
          targets (their frozen target actors pick ã), so the survivor's weighting term tracks
          the data.
        - `no-weighting`: their critics freeze and the survivor's target becomes plain TD3/DDPG
          (η = 0).

        Frozen members' Adam moments are zeroed: with zero gradients from the masked losses,
        Adam then moves them by exactly zero.
        """
        k, n = self.cfg.actors, self.cfg.critics_per_actor
        if not 0 <= survivor < k:
            raise ValueError(f"survivor {survivor} out of range for K={k}")
        self.structure += 1  # other index tensors, maybe η = 0: a captured graph is stale
        self.live.zero_()
        self.live[survivor] = 1.0
        self._live_flags = [j == survivor for j in range(k)]
        if self.cfg.after_elimination != "train-critics":
            self.critic_live.copy_(self.live)
            self._training_index = torch.tensor([survivor], device=self.device)
        if self.cfg.after_elimination == "no-weighting":
            self.eta = 0.0
        self._tau_actor.copy_(self.live.view(k, 1, 1) * self.cfg.tau)
        self._tau_critic.copy_(self.critic_live.repeat_interleave(n).view(k * n, 1, 1) * self.cfg.tau)
        frozen_actor = self.live == 0
        frozen_critic = (self.critic_live == 0).repeat_interleave(n)
        optimizers = [(self.actor_opt, frozen_actor), (self.critic_opt, frozen_critic)]
        if self.alpha_opt is not None:  # an eliminated actor's temperature freezes with it
            optimizers.append((self.alpha_opt, frozen_actor))
        for opt, mask in optimizers:
            for group in opt.param_groups:
                for p in group["params"]:
                    state = opt.state.get(p, {})
                    for key in ("exp_avg", "exp_avg_sq"):
                        if key in state:
                            state[key][mask] = 0.0

    @property
    def live_actors(self) -> list[bool]:
        return [bool(v) for v in self.live.tolist()]

    # -- weights for workers and the referee ---------------------------------------------------
    def actor_params(self, k: int) -> dict[str, np.ndarray]:
        return self.actor.net.member_state(k)

    def actor_shapes(self) -> dict[str, tuple[int, ...]]:
        return self.actor.net.member_shapes()

    @torch.no_grad()
    def act(self, obs: np.ndarray, k: int) -> np.ndarray:
        """Deterministic action of actor k for a batch of observations (evaluation)."""
        o = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
        members = torch.tensor([k], device=self.device)
        return self.actor(o.reshape(-1, self.spec.obs_dim), members)[0].cpu().numpy()

    @torch.no_grad()
    def q_value(self, obs: np.ndarray, action: np.ndarray, k: int) -> np.ndarray:
        """Q_k1(s, a) of the current critic (Eq. 17's estimate)."""
        o = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device).reshape(-1, self.spec.obs_dim)
        a = torch.as_tensor(np.asarray(action, dtype=np.float32), device=self.device).reshape(1, -1, self.spec.act_dim)
        members = self.first_critics[k:k + 1]
        return self.critic(o, a, members=members)[0].cpu().numpy()

    # -- checkpoints (tensors and plain containers only: loadable with weights_only=True) ----
    def state_dict(self) -> dict[str, Any]:
        state = {
            "actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
            "noise_gen": self.noise_gen.get_state(),
            "live": self.live.clone(), "updates": self.updates, "actor_updates": self.actor_updates,
            "versions": list(self.versions),
        }
        if self.actor_target is not None:
            state["actor_target"] = self.actor_target.state_dict()
        if self.log_alpha is not None:
            state["log_alpha"] = self.log_alpha.detach().clone()
        if self.alpha_opt is not None:
            state["alpha_opt"] = self.alpha_opt.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.structure += 1  # the optimizers' state tensors are new ones: a captured graph is stale
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        if self.actor_target is not None:
            self.actor_target.load_state_dict(state["actor_target"])
        self.critic_target.load_state_dict(state["critic_target"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        if self.log_alpha is not None:
            with torch.no_grad():
                self.log_alpha.copy_(state["log_alpha"])
        if self.alpha_opt is not None:
            self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.noise_gen.set_state(state["noise_gen"])
        live = state["live"].to(self.device)
        self.updates = int(state["updates"])
        self.actor_updates = int(state["actor_updates"])
        self.versions = [int(v) for v in state["versions"]]
        if float(live.sum()) < self.cfg.actors:
            self.eliminate(int(torch.argmax(live)))
