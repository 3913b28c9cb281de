"""An algorithm family: what TD3/DDPG or SAC supplies to the multi-actor mechanism.

The mechanism is written once, for any family: K actors with n critics each in batched
ensembles, Eq. 9's weighted target, Eq. 5's critic regression, the delayed actor phase and the
soft target update (mam_core.agent), the competitions of Eq. 8 and the elimination
(mam_core.obsolescence, mam_core.algorithm1). A family supplies what differs between TD3 and
SAC, and nothing else:

- its `--algo` names, their defaults and their `--help` line;
- the torch-free acting rule of the workers and the reference (`act`), the kind of numpy actor
  it exports to policy.npz (`policy_kind`, mam_core.policy) and `mam eval --noise`'s rule;
- the learner's pieces, batched over K actors: the actors, the next actions and entropy term of
  the Eq. 9 value (`next_actions`), and the actor phase, Eq. 7 with its optimizer steps.

The learner's pieces import torch when called: workers and the referee import a family for its
acting rule and stay without torch. Every random draw of an update goes through
`agent.draw_noise`, and `actor_step` neither syncs with the device nor changes Python state (a
CUDA graph captures it, mam_core.graphs).

`--algo` names a built-in family's name (`ma-td3`, `sac`, ...) or `module.path:Name`, an object
with these attributes in a user's module, imported on every host that runs a role (installed,
on PYTHONPATH, or in the directory the command starts in), as a `module:EnvId` env is.
docs/ARCHITECTURE.md, "Adding an algorithm family", walks through mam_core/td3.py.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    import torch

Policy = Callable[[np.ndarray], np.ndarray]
AlgoConfig = Any  # mam_core.config.AlgoConfig, which names its family: this module sits below it
EnvSpec = Any  # mam_core.policy.EnvSpec
BUILTIN = ("mam_core.td3:TD3", "mam_core.sac:SAC")  # loaded by name: they import this module's types


class Agent(Protocol):
    """What a family's learner pieces use of the learner's agent (mam_core.agent.MultiActorAgent)."""

    cfg: AlgoConfig
    spec: EnvSpec
    actor: Any  # the K actors (the family's `make_actors`)
    actor_target: Any  # their targets, or None (`target_actor`)
    critic: Any  # the n·K critics (mam_core.ensemble.CriticEnsemble)
    live: torch.Tensor  # [K]: 1 for an actor that still trains (0 after its elimination)
    max_action: torch.Tensor  # [A]
    first_critic_members: slice  # the critics Q_k1, k = 0..K-1
    actor_opt: torch.optim.Optimizer
    actor_params_list: list[torch.Tensor]
    log_alpha: torch.Tensor | None  # the family's `temperature`
    alpha_opt: torch.optim.Optimizer | None

    def draw_noise(self, shape: tuple[int, ...]) -> torch.Tensor:
        """N(0, I) from the agent's seeded stream: every random draw of an update."""

    def adam_step(self, opt: torch.optim.Optimizer, loss: torch.Tensor, params: list[torch.Tensor]) -> None:
        """One optimizer step on `loss`'s gradients w.r.t. `params` only."""


class Family(Protocol):
    """What an algorithm family supplies (module docstring); mam_core.td3.TD3 is the model."""

    names: tuple[str, ...]  # the `--algo` names it answers to (a user's family: none, it is `module:Name`)
    help: str  # its line in `mam run --help`'s --algo, naming its algos and where their defaults come from
    policy_kind: str  # its numpy actors and policy.npz layout: a kind of mam_core.policy.POLICY_KINDS
    stochastic: bool  # actors are distributions with a temperature α_k per actor (`agent.log_alpha`)
    target_actor: bool  # Eq. 9's ã_j comes from a target actor, soft-updated with the critics

    def defaults(self, algo: str) -> dict[str, Any]:
        """AlgoConfig fields for `--algo algo` (the rest keep AlgoConfig's defaults)."""

    def problems(self, cfg: AlgoConfig) -> list[str]:
        """What is wrong with `cfg` for this family (empty: nothing)."""

    def act(self, policy: Policy, obs: np.ndarray, noise: np.random.Generator, cfg: AlgoConfig,
            max_action: np.ndarray) -> np.ndarray:
        """Algorithm 1, line 7: a slot's action on one observation, drawing exactly |A| normals
        from `noise`, the slot's stream (a replacement worker fast-forwards it that way:
        mam_core.slot.SlotStreams)."""

    def explorer(self, policy: Any, sigma: float, rng: np.random.Generator) -> Policy:
        """`mam eval --noise`: a batched acting rule with noise around a TrainedPolicy."""

    def make_actors(self, k: int, spec: EnvSpec, hidden: tuple[int, ...], gen: torch.Generator) -> Any:
        """K actors as one ensemble (mam_core.ensemble), initialised from `gen`."""

    def temperature(self, cfg: AlgoConfig, spec: EnvSpec, device: torch.device) -> tuple[Any, Any]:
        """(log α [K], its optimizer or None), or (None, None) for a family without one."""

    def next_actions(self, agent: Agent, next_obs: torch.Tensor) -> tuple[torch.Tensor, Any]:
        """ã_j of Eq. 9 for every actor j on `next_obs` [rows, obs] or [K, rows, obs] -> [K, rows, A],
        and the entropy term α_j·log π_j(ã_j|s') [K, rows] subtracted from Q' (None: none)."""

    def actor_step(self, agent: Agent, obs: torch.Tensor) -> list[torch.Tensor]:
        """Eq. 7 for every live actor and its optimizer step(s); its metrics as 1-D tensors, in the
        order of `actor_metric_names`. The agent then soft-updates the targets (Eq. 4)."""

    def actor_metric_names(self, agent: Agent) -> list[str]:
        """The names of `actor_step`'s values."""


@functools.cache
def builtin_families() -> tuple[Family, ...]:
    """TD3 (with DDPG) and SAC."""
    out = []
    for path in BUILTIN:
        module, _, name = path.partition(":")
        out.append(getattr(importlib.import_module(module), name)())
    return tuple(out)


def builtin_algos() -> tuple[str, ...]:
    """Every built-in `--algo` name, family by family."""
    return tuple(name for family in builtin_families() for name in family.names)


@functools.cache
def family_for(algo: str) -> Family:
    """The family of `--algo algo`: a built-in name, or `module.path:Name` (the module is imported;
    `Name` is a family object, or a class made with no arguments). ValueError when there is none."""
    if ":" not in algo:
        for family in builtin_families():
            if algo in family.names:
                return family
        raise ValueError(f"unknown algo {algo!r}; choose one of {', '.join(builtin_algos())}, or name an "
                         "algorithm family in your module as module.path:Name (mam_core/family.py)")
    from mam_core.envs import import_module_from_cwd  # gymnasium: only for a user's family

    module, _, name = algo.partition(":")
    try:
        found = getattr(import_module_from_cwd(module), name)
    except Exception as e:  # ImportError, AttributeError, or anything the module raises while importing
        raise ValueError(f"algo {algo!r}: no algorithm family {name!r} in module {module!r} ({type(e).__name__}: "
                         f"{e}). The module must import on every host that runs a role") from e
    family = found() if isinstance(found, type) else found
    missing = [a for a in _REQUIRED if not hasattr(family, a)]
    if missing:
        raise ValueError(f"algo {algo!r}: {name} is not an algorithm family (it lacks {', '.join(missing)}; "
                         "mam_core/family.py)")
    return family


_REQUIRED = ("help", "policy_kind", "stochastic", "target_actor", "defaults", "problems", "act", "explorer",
             "make_actors", "temperature", "next_actions", "actor_step", "actor_metric_names")
