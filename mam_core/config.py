"""Hyperparameters of MA-TD3 / MA-DDPG / MA-SAC / TD3 / DDPG / SAC with the paper's defaults.

One flat, frozen dataclass (paper symbols in the help text). `defaults_for(algo)` gives the
defaults of `algo`'s family (mam_core.family): Table 3 (TD3 family) and Table 1 (DDPG family) in
mam_core.td3, SAC v2's hyperparameters with Table 3's mechanism in mam_core.sac, or a user's
family's; `resolve(algo, **overrides)` applies user flags on top and checks them.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Any

from mam_core.family import Family, builtin_algos, family_for

ALGOS = builtin_algos()  # the built-in `--algo` names; `module.path:Name` names a user's family
PRECISIONS = ("fp32", "bf16")
SCHEDULES = ("paper", "equal-data")  # mam_core.schedule
AFTER_ELIMINATION = ("frozen", "train-critics", "no-weighting")


@dataclass(frozen=True)
class AlgoConfig:
    algo: str = "ma-td3"  # a built-in name (ALGOS) or module.path:Name (mam_core.family)
    actors: int = 2  # K: number of actors
    critics_per_actor: int = 2  # n: 2 for the TD3 family (clipped double Q), 1 for DDPG
    workers: int = 3  # M: environment slots
    eliminate_at: int = 300_000  # C: env step at which all but the best actor are eliminated
    compete_every: int = 5_000  # A: env steps between evaluation / allocation rounds
    eta: float = 0.1  # η: weight of the other actors' Q-values in the target (Eq. 9)
    batch_size: int = 256
    lr: float = 3e-4  # actor and critic learning rate (Adam)
    tau: float = 0.005  # τ: soft target update rate (Eq. 4)
    gamma: float = 0.99  # discount
    explore_noise: float = 0.1  # σ of Gaussian exploration noise, times max_action
    policy_noise: float = 0.2  # σ̃ of target policy smoothing, times max_action (TD3 family)
    noise_clip: float = 0.5  # c: clip of the smoothing noise, times max_action
    target_smoothing: bool = True  # TD3's target policy smoothing; off for DDPG
    policy_delay: int = 2  # d: actor and target updates every d critic updates
    alpha: float | None = None  # α: a fixed SAC temperature; None: α_k tuned per actor towards entropy −|A|
    start_steps: int = 25_000  # transitions collected with uniform random actions first
    hidden: tuple[int, ...] = (256, 256)
    buffer_size: int = 1_000_000
    eval_episodes: int = 20  # episodes per actor in each evaluation round (paper: 20)
    eval_every: int = 5_000  # schedule steps between learning-curve evaluations (iterations or transitions)
    utd: float = 1.0  # gradient updates per received transition
    no_ot: bool = False  # ablation "w/o OT": uniform fixed allocation, no elimination
    no_wt: bool = False  # ablation "w/o WT": η = 0
    single_env_after_elimination: bool = False  # survivor runs one slot only (implied by schedule "paper")
    # Algorithm 1's open choices (docs/DESIGN-DECISIONS.md, "Algorithm 1 as options"):
    schedule: str = "paper"  # paper: options count iterations (M transitions, one update); equal-data: transitions
    shared_batch: bool = False  # one mini-batch for all actors (Algorithm 1 samples one per actor)
    after_elimination: str = "frozen"  # frozen | train-critics | no-weighting: the Eq. 9 target after C
    skip_random_rounds: bool = False  # no allocation round during the random start phase
    seed: int = 0
    device: str = "auto"  # auto | cpu | cuda
    precision: str = "fp32"  # fp32 | bf16: the learner's hidden-to-hidden GEMMs in bfloat16 (mixed precision)
    lag: int = 0  # B: iteration t acts with the actors after iteration t-1-B (mam_core.algorithm1); 0 = Algorithm 1

    @property
    def single_env(self) -> bool:
        """After the elimination the survivor runs one environment slot (I_e = 1)."""
        return self.single_env_after_elimination or self.schedule == "paper"

    @property
    def family(self) -> Family:
        """The algorithm family of `algo`: its acting rule, its actors and actor phase (mam_core.family)."""
        return family_for(self.algo)

    @property
    def stochastic(self) -> bool:
        """The family's actors are distributions with a temperature α_k (SAC)."""
        return self.family.stochastic

    @property
    def effective_eta(self) -> float:
        """η used in Eq. 9: zero for `--no-wt` and for a single actor."""
        return 0.0 if self.no_wt or self.actors == 1 else self.eta

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "AlgoConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config keys: {sorted(unknown)}")
        d = dict(d)
        if "hidden" in d:
            d["hidden"] = tuple(int(h) for h in d["hidden"])
        return validate(cls(**d))


def defaults_for(algo: str) -> AlgoConfig:
    """`algo`'s defaults (its family's); ValueError for an algo no family answers to."""
    return AlgoConfig(algo=algo, **family_for(algo).defaults(algo))


def resolve(algo: str, **overrides: Any) -> AlgoConfig:
    """Paper defaults for `algo` with the non-None `overrides` applied, validated."""
    base = defaults_for(algo)
    known = {f.name for f in dataclasses.fields(AlgoConfig)}
    unknown = set(overrides) - known
    if unknown:
        raise ValueError(f"unknown option(s): {sorted(unknown)}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    if "hidden" in changes:
        changes["hidden"] = tuple(int(h) for h in changes["hidden"])
    return validate(dataclasses.replace(base, **changes))


def validate(cfg: AlgoConfig) -> AlgoConfig:
    problems = []
    try:
        problems += family_for(cfg.algo).problems(cfg)
    except ValueError as e:
        problems.append(str(e))
    if cfg.actors < 1:
        problems.append("actors (K) must be >= 1")
    if cfg.critics_per_actor < 1:
        problems.append("critics_per_actor (n) must be >= 1")
    if cfg.workers < 1:
        problems.append("workers (M) must be >= 1")
    if not 0.0 <= cfg.eta < 1.0:
        problems.append("eta must be in [0, 1)")
    if cfg.compete_every < 1:
        problems.append("compete_every (A) must be >= 1")
    if cfg.eliminate_at < 0:
        problems.append("eliminate_at (C) must be >= 0")
    if cfg.batch_size < 1 or cfg.buffer_size < cfg.batch_size:
        problems.append("need 1 <= batch_size <= buffer_size")
    if not 0.0 < cfg.tau <= 1.0:
        problems.append("tau must be in (0, 1]")
    if not 0.0 <= cfg.gamma <= 1.0:
        problems.append("gamma must be in [0, 1]")
    if cfg.policy_delay < 1:
        problems.append("policy_delay (d) must be >= 1")
    if cfg.alpha is not None and not cfg.alpha > 0.0:
        problems.append("alpha (a fixed SAC temperature) must be > 0")
    if cfg.utd <= 0:
        problems.append("utd must be > 0")
    if cfg.start_steps < 0 or cfg.eval_episodes < 1 or cfg.eval_every < 1:
        problems.append("start_steps >= 0, eval_episodes >= 1 and eval_every >= 1 required")
    if not cfg.hidden or any(h < 1 for h in cfg.hidden):
        problems.append("hidden sizes must be positive")
    if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", cfg.device):
        problems.append("device must be auto, cpu, cuda or cuda:N")
    if cfg.schedule not in SCHEDULES:
        problems.append(f"schedule must be one of {', '.join(SCHEDULES)}")
    if cfg.after_elimination not in AFTER_ELIMINATION:
        problems.append(f"after_elimination must be one of {', '.join(AFTER_ELIMINATION)}")
    if cfg.lag < 0:
        problems.append("lag (B) must be >= 0")
    elif cfg.lag and cfg.actors > 1 and not cfg.no_ot and \
            (cfg.lag + 1) * (1 if cfg.schedule == "paper" else cfg.workers) > cfg.compete_every:
        problems.append("lag (B) must be shorter than the iterations between two competitions (A): a decision "
                        "applies B+1 iterations after it is drawn, before the next one")
    if cfg.precision not in PRECISIONS:
        problems.append(f"precision must be one of {', '.join(PRECISIONS)}")
    if problems:
        raise ValueError("invalid configuration: " + "; ".join(problems))
    return cfg
