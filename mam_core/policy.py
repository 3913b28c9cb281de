"""Acting without torch: the env spec, the actors as numpy functions, trained policies on disk.

Workers and the referee only run policies forward, one observation (or a few) at a time.
For that, torch's per-op dispatch costs more than the arithmetic (docs/PERFORMANCE.md), and
importing it costs seconds of start-up and a few hundred MB per process. This module holds
what acting needs, with numpy alone; the learner's `ActorEnsemble` shares the parameter layout
(`member_shapes`), and `tests/test_policy.py` checks that both compute the same function.

A trained policy in a few lines, numpy only (no torch, no Zenoh):

    from mam_core.policy import load_policy
    pi = load_policy("runs/NAME")        # the survivor; load_policy("runs/NAME", actor=1) for actor 1
    action = pi(obs)                     # obs [obs_dim] -> [act_dim], or [B, obs_dim] -> [B, act_dim]
    env = pi.make_env()                  # the env it was trained on (gymnasium; AppleCollect registered)

It reads RUN_DIR/checkpoints/policy.npz, which the learner writes next to every checkpoint
(`save_policy_file`; format in docs/DESIGN-DECISIONS.md, "Trained policies on disk").
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mam_core import arithmetic

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class EnvSpec:
    """What the networks need to know about an environment."""

    obs_dim: int
    act_dim: int
    max_action: tuple[float, ...]  # per action dimension, symmetric bounds ±max_action

    @classmethod
    def from_env(cls, env: Any) -> "EnvSpec":
        """The spec of a made env; `EnvError` for an env mam cannot train on.

        mam needs a 1-D Box observation space and a 1-D Box action space with finite, symmetric
        bounds (actors end in max_action · tanh).
        """
        from gymnasium import spaces

        from mam_core.envs import EnvError

        name = getattr(getattr(env, "spec", None), "id", None) or type(env).__name__
        space, obs_space = env.action_space, env.observation_space
        if not isinstance(space, spaces.Box):
            raise EnvError(f"env {name!r}: the action space must be a gymnasium Box (continuous actions), "
                           f"not {space}")
        if len(space.shape) != 1:
            raise EnvError(f"env {name!r}: the action space must be 1-D, not of shape {space.shape}")
        if not (np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))):
            raise EnvError(f"env {name!r}: the action bounds must be finite (got low={space.low}, "
                           f"high={space.high}); give the action space finite bounds")
        if not np.allclose(space.low, -space.high) or np.any(space.high <= 0):
            raise EnvError(f"env {name!r}: only symmetric action bounds (low == -high) are supported (got "
                           f"low={space.low}, high={space.high}); wrap the env in gymnasium.wrappers.RescaleAction")
        if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
            raise EnvError(f"env {name!r}: the observation space must be a 1-D gymnasium Box, not {obs_space}; "
                           "wrap the env in gymnasium.wrappers.FlattenObservation")
        return cls(int(obs_space.shape[0]), int(space.shape[0]), tuple(float(h) for h in space.high))

    @classmethod
    def from_env_id(cls, env_id: str, env_kwargs: Mapping[str, Any] | None = None) -> "EnvSpec":
        from mam_core.envs import make_env  # registers AppleCollect-v0, imports `module:EnvId` modules

        env = make_env(env_id, env_kwargs)
        try:
            return cls.from_env(env)
        finally:
            env.close()

    def to_dict(self) -> dict[str, Any]:
        return {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "max_action": list(self.max_action)}


def member_shapes(in_dim: int, hidden: Sequence[int], out_dim: int) -> dict[str, tuple[int, ...]]:
    """One member's parameters as they travel on the weights topic: w{i} [fan_in, fan_out], b{i} [1, fan_out]."""
    sizes = [in_dim, *hidden, out_dim]
    shapes: dict[str, tuple[int, ...]] = {}
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        shapes[f"w{i}"] = (fan_in, fan_out)
        shapes[f"b{i}"] = (1, fan_out)
    return shapes


def dense(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x [in] or [B, in] @ w [in, out] + b [out] in float32, with the same bits on every CPU.

    Each output is the sum over the inputs i = 0, 1, ... in that order, every product and every
    sum rounded to float32 (no fused multiply-add), then + b: `np.einsum`'s own loop, which calls
    no BLAS and no CPU-dispatched kernel (`x @ w` takes a BLAS kernel chosen per CPU model:
    mam_core/arithmetic.py). tests/test_arithmetic.py checks it against that sum written out. A
    row gets the same bits alone as in a batch. `w` must be C-contiguous (the actors' arrays are).
    """
    return np.einsum("...i,io->...o", x, w) + b


def blas_dense(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`dense` through BLAS: ~2x faster, with the bits of this CPU's kernel (`--arithmetic native`)."""
    return x @ w + b


def mlp_policy(layers: Sequence[tuple[np.ndarray, np.ndarray]], max_action: np.ndarray,
               head: Callable[[np.ndarray], Any] | None = None) -> Policy:
    """obs [obs_dim] or [B, obs_dim] -> max_action · tanh(Linear-ReLU-...-Linear(obs)).

    `layers` are (w [in, out], b [out]) float32 arrays, read at every call: arrays updated in
    place are seen at once. `head` replaces the final max_action · tanh(h) (SAC's Gaussian heads,
    `SquashedGaussianPolicy`), so every numpy layer runs here. Every layer is `dense` (the same
    actions on every CPU), or `blas_dense` in a process started with native arithmetic.
    """
    last = len(layers) - 1
    layer = blas_dense if arithmetic.status()["arithmetic"] == "native" else dense

    def policy(obs: np.ndarray) -> np.ndarray:
        h = np.asarray(obs, np.float32)
        for i, (w, b) in enumerate(layers):
            h = layer(h, w, b)
            if i < last:
                np.maximum(h, 0.0, out=h)
        return max_action * np.tanh(h) if head is None else head(h)

    return policy


# -- SAC's stochastic actors ----------------------------------------------------------------------
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0  # log σ clipped as in the SAC papers' code (softlearning, Spinning Up)
# The kinds of numpy actor an algorithm family exports (its `policy_kind`): policy.npz meta "policy"
# (absent: deterministic).
DETERMINISTIC = "deterministic"  # max_action · tanh(MLP(s)): the TD3 family
GAUSSIAN_POLICY = "squashed-gaussian"  # μ and log σ heads: the SAC family
POLICY_KINDS = (DETERMINISTIC, GAUSSIAN_POLICY)


def policy_out_dim(act_dim: int, kind: str) -> int:
    """Width of an actor's last layer: |A| (deterministic), or 2|A| for SAC's μ and log σ heads."""
    if kind not in POLICY_KINDS:
        raise ValueError(f"unknown policy kind {kind!r}; mam's numpy actors are {', '.join(POLICY_KINDS)}")
    return 2 * act_dim if kind == GAUSSIAN_POLICY else act_dim


def numpy_policy(kind: str, layers: Sequence[tuple[np.ndarray, np.ndarray]], max_action: np.ndarray) -> Any:
    """The numpy actor of `kind` on `layers`: `mlp_policy`, or a `SquashedGaussianPolicy`."""
    if kind == GAUSSIAN_POLICY:
        return SquashedGaussianPolicy(layers, max_action)
    if kind == DETERMINISTIC:
        return mlp_policy(layers, max_action)
    raise ValueError(f"unknown policy kind {kind!r}; mam's numpy actors are {', '.join(POLICY_KINDS)}")


class SquashedGaussianPolicy:
    """π_k(·|s) = max_action · tanh(N(μ(s), σ(s)²)) from one MLP whose last layer holds both heads:
    outputs [:|A|] are μ, outputs [|A|:] are log σ, clipped to [LOG_STD_MIN, LOG_STD_MAX] (the
    learner's `GaussianActorEnsemble`). Called, it is the mean action max_action · tanh(μ(s)),
    with which evaluations and competitions act; `sample` draws an action."""

    def __init__(self, layers: Sequence[tuple[np.ndarray, np.ndarray]], max_action: np.ndarray) -> None:
        a = int(np.asarray(max_action).shape[-1])
        self.max_action = max_action
        self._mean = mlp_policy(layers, max_action, head=lambda h: max_action * np.tanh(h[..., :a]))
        self._heads = mlp_policy(layers, max_action,
                                 head=lambda h: (h[..., :a], np.clip(h[..., a:], LOG_STD_MIN, LOG_STD_MAX)))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self._mean(obs)

    def heads(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(μ, log σ) of the pre-squash Gaussian, each [..., |A|]."""
        return self._heads(obs)

    def sample(self, obs: np.ndarray, noise: np.random.Generator) -> np.ndarray:
        """a = max_action · tanh(μ + σ·ε), ε ~ N(0, I) drawn from `noise` (a slot's seeded stream)."""
        mu, log_std = self.heads(obs)
        eps = noise.normal(0.0, 1.0, mu.shape).astype(np.float32)
        return self.max_action * np.tanh(mu + np.exp(log_std) * eps)


def params_digest(params: Mapping[str, np.ndarray]) -> str:
    """A short digest of an actor's parameters (float32, by name): the learner and a worker
    compare it to know that a row was acted with the very weights the learner computed.

    SHA-256 (64 bits of it kept): OpenSSL's runs on the CPU's SHA extensions, 2x BLAKE2b's speed
    on an actor of 284 KB (158 against 298 us here), and every weights message pays it twice (the
    learner publishing, the worker receiving). The arrays are hashed in place, not copied."""
    h = hashlib.sha256()
    for name in sorted(params):
        h.update(name.encode())
        h.update(memoryview(np.ascontiguousarray(params[name], np.float32)).cast("B"))
    return h.hexdigest()[:16]


class NumpyActors:
    """K actors' parameters as float32 arrays, for acting only (no gradients, no torch).

    Zero until `load_member` fills them from the weights topic: callers act with actor k
    only once its weights have arrived (workers and the referee track versions for that).
    """

    def __init__(self, n_actors: int, spec: EnvSpec, hidden: Sequence[int], kind: str = DETERMINISTIC) -> None:
        self.n_actors = n_actors
        self.shapes = member_shapes(spec.obs_dim, hidden, policy_out_dim(spec.act_dim, kind))
        self.max_action = np.asarray(spec.max_action, np.float32)
        self.params = [{name: np.zeros(shape, np.float32) for name, shape in self.shapes.items()}
                       for _ in range(n_actors)]
        n_layers = len(self.shapes) // 2
        # b{i}[0]: a [out] view of the [1, out] wire layout, so one observation gives one action
        self._policies = [numpy_policy(kind, [(p[f"w{i}"], p[f"b{i}"][0]) for i in range(n_layers)], self.max_action)
                          for p in self.params]

    def load_member(self, k: int, params: Mapping[str, np.ndarray]) -> None:
        """Copy actor k's parameters in place (policies handed out earlier see them)."""
        for name, shape in self.shapes.items():
            value = np.asarray(params[name], np.float32)
            if value.shape != shape:
                raise ValueError(f"{name}: shape {value.shape}, expected {shape}")
            self.params[k][name][...] = value

    def policy(self, k: int) -> Policy:
        return self._policies[k]


# -- trained policies on disk -------------------------------------------------------------------
POLICY_FILE = "policy.npz"  # in RUN_DIR/checkpoints/, next to learner.pt
POLICY_FORMAT = 1
_META_KEY = "meta"
_REQUIRED_META = ("format", "env_id", "obs_dim", "act_dim", "max_action", "hidden", "actors")


class PolicyFileError(ValueError):
    """A policy file that is corrupt, incomplete or does not match what it claims."""


def save_policy_file(path: Path, params: Sequence[Mapping[str, np.ndarray]], meta: Mapping[str, Any]) -> Path:
    """Write K actors' parameters and a JSON `meta` to an .npz atomically (no pickle anywhere).

    Arrays are named `actor{k}.{w0,b0,w1,...}` in the wire layout of `member_shapes`; `meta`
    is stored as UTF-8 JSON bytes in the uint8 array `meta`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": POLICY_FORMAT, **meta, "actors": len(params)}
    arrays: dict[str, np.ndarray] = {_META_KEY: np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    for k, member in enumerate(params):
        for name, value in member.items():
            arrays[f"actor{k}.{name}"] = np.ascontiguousarray(value, np.float32)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    os.replace(tmp, path)
    return path


def policy_path(run: str | os.PathLike[str]) -> Path:
    """RUN_DIR -> RUN_DIR/checkpoints/policy.npz; a path to an .npz file is kept as it is."""
    p = Path(run)
    return p if p.suffix == ".npz" else p / "checkpoints" / POLICY_FILE


def read_policy_file(path: str | os.PathLike[str]) -> tuple[dict[str, Any], list[dict[str, np.ndarray]]]:
    """(meta, [actor k's parameters]) from a policy file, checked; FileNotFoundError or PolicyFileError."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no trained policy at {path} (the learner writes it at every checkpoint and at "
                                "the end of a run)")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise PolicyFileError(f"{path} is not a readable policy file ({type(e).__name__}: {e})") from e
    try:
        meta = json.loads(arrays.pop(_META_KEY).tobytes().decode())
        missing = [k for k in _REQUIRED_META if k not in meta]
        if missing:
            raise PolicyFileError(f"missing {missing} in its meta")
        if meta["format"] != POLICY_FORMAT:
            raise PolicyFileError(f"format {meta['format']}, this mam reads format {POLICY_FORMAT}")
        obs_dim, act_dim, n = int(meta["obs_dim"]), int(meta["act_dim"]), int(meta["actors"])
        if len(meta["max_action"]) != act_dim or n < 1:
            raise PolicyFileError("max_action does not have act_dim entries, or no actors")
        kind = meta.get("policy", DETERMINISTIC)
        if kind not in POLICY_KINDS:
            raise PolicyFileError(f"policy kind {kind!r}; this mam reads {', '.join(POLICY_KINDS)}")
        shapes = member_shapes(obs_dim, [int(h) for h in meta["hidden"]], policy_out_dim(act_dim, kind))
        params = []
        for k in range(n):
            member = {}
            for name, shape in shapes.items():
                value = arrays[f"actor{k}.{name}"]
                if value.shape != shape or value.dtype != np.float32:
                    raise PolicyFileError(f"actor{k}.{name}: {value.dtype}{list(value.shape)}, expected "
                                          f"float32{list(shape)}")
                if not np.all(np.isfinite(value)):
                    raise PolicyFileError(f"actor{k}.{name} holds non-finite values")
                member[name] = value
            params.append(member)
    except PolicyFileError as e:
        raise PolicyFileError(f"{path}: {e}") from None
    except (KeyError, ValueError, TypeError, UnicodeDecodeError) as e:
        raise PolicyFileError(f"{path}: corrupt policy file ({type(e).__name__}: {e})") from e
    return meta, params


class TrainedPolicy:
    """One actor of a finished (or running) run as a numpy function, with what it was trained on.

    `pi(obs)` maps [obs_dim] -> [act_dim] or [B, obs_dim] -> [B, act_dim] (float32,
    deterministic: max_action · tanh(MLP(obs)), the function the learner's actor computes; for a
    SAC run the mean action max_action · tanh(μ(obs))). A SAC run's actor also samples:
    `pi.sample(obs, np.random.default_rng(seed))` (`stochastic` is True).
    """

    def __init__(self, meta: Mapping[str, Any], params: Mapping[str, np.ndarray], actor: int,
                 source: Path | None = None) -> None:
        self.meta = dict(meta)
        self.actor = actor
        self.source = source
        self.spec = EnvSpec(int(meta["obs_dim"]), int(meta["act_dim"]), tuple(float(x) for x in meta["max_action"]))
        self.env_id: str = str(meta["env_id"])
        self.env_kwargs: dict[str, Any] = dict(meta.get("env_kwargs") or {})
        self.hidden = tuple(int(h) for h in meta["hidden"])
        self.max_action = np.asarray(self.spec.max_action, np.float32)
        n_layers = len(params) // 2
        self._layers = [(np.ascontiguousarray(params[f"w{i}"], np.float32),
                         np.asarray(params[f"b{i}"], np.float32).reshape(-1))
                        for i in range(n_layers)]
        self.kind = self.meta.get("policy", DETERMINISTIC)
        self.stochastic = self.kind == GAUSSIAN_POLICY
        self._policy = numpy_policy(self.kind, self._layers, self.max_action)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self._policy(self._checked(obs))

    def _checked(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.spec.obs_dim:
            raise ValueError(f"observation of shape {obs.shape}: this policy takes [{self.spec.obs_dim}] or "
                             f"[B, {self.spec.obs_dim}] ({self.env_id})")
        return obs

    def sample(self, obs: np.ndarray, noise: np.random.Generator) -> np.ndarray:
        """A SAC actor's sampled action, max_action · tanh(μ + σ·ε), ε drawn from `noise`."""
        if not isinstance(self._policy, SquashedGaussianPolicy):
            raise ValueError(f"actor {self.actor} of this run is deterministic ({self.meta.get('algo')}): "
                             "it has no distribution to sample")
        return self._policy.sample(self._checked(obs), noise)

    def make_env(self, **make_kwargs: Any) -> Any:
        """A fresh env of the kind this policy was trained on: `gym.make(env_id, **env_kwargs,
        **make_kwargs)` (e.g. `render_mode="rgb_array"`), with AppleCollect registered and a
        `module:EnvId` module imported (mam_core.envs.make_env). Imports gymnasium; the policy
        itself needs numpy only."""
        from mam_core.envs import make_env

        return make_env(self.env_id, self.env_kwargs, **make_kwargs)

    def __repr__(self) -> str:
        return (f"TrainedPolicy(actor={self.actor}, env={self.env_id!r}, obs_dim={self.spec.obs_dim}, "
                f"act_dim={self.spec.act_dim}, hidden={list(self.hidden)}, env_steps={self.meta.get('env_steps')})")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def default_actor(meta: Mapping[str, Any], run_dir: Path | None) -> int:
    """The survivor; before an elimination, the best actor of the run's last evaluation
    (summary.json's final returns, else the last row of eval.jsonl); actor 0 when K = 1."""
    n = int(meta["actors"])
    if meta.get("survivor") is not None:
        return int(meta["survivor"])
    if n == 1:
        return 0
    if run_dir is not None:
        summary = _read_json(run_dir / "summary.json") or {}
        if summary.get("survivor") is not None:
            return int(summary["survivor"])
        means = summary.get("final_returns")
        if not means and (run_dir / "eval.jsonl").is_file():
            rows = [line for line in (run_dir / "eval.jsonl").read_text().splitlines() if line.strip()]
            try:
                means = json.loads(rows[-1]).get("mean") if rows else None
            except ValueError:
                means = None
        known = [(m, k) for k, m in enumerate(means or []) if m is not None and k < n]
        if known:
            return max(known, key=lambda mk: (mk[0], -mk[1]))[1]  # ties: the lowest index, as argmax
    raise PolicyFileError(f"{n} actors, no survivor and no evaluation yet: choose one with actor=0..{n - 1}")


def load_policy(run: str | os.PathLike[str], actor: int | str = "survivor") -> TrainedPolicy:
    """The trained policy of a run directory (or of a policy .npz file), numpy only.

    `actor` is an index 0..K-1 or "survivor" (see `default_actor`).
    """
    path = policy_path(run)
    meta, params = read_policy_file(path)
    run_dir = path.parent.parent if path.name == POLICY_FILE and path.parent.name == "checkpoints" else None
    if actor == "survivor":
        k = default_actor(meta, run_dir)
    else:
        try:
            k = int(actor)
        except (TypeError, ValueError):
            raise ValueError(f"actor must be an index or 'survivor', not {actor!r}") from None
    if not 0 <= k < len(params):
        raise ValueError(f"actor {k} out of range: this run has {len(params)} actor(s)")
    return TrainedPolicy(meta, params[k], k, path)
