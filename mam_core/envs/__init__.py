"""The project's own gymnasium environments, and making any env by id.

Importing this package registers AppleCollect-v0. `make_env` makes any registered id and
gymnasium's `module.path:EnvId` form (the module registers the env when imported), with
keyword arguments, and turns a module that does not import or an unknown id into an
`EnvError` that says so.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Mapping
from types import ModuleType
from typing import Any

import gymnasium as gym

APPLE_COLLECT_ID = "AppleCollect-v0"  # the readings of the published runs
APPLE_COLLECT_V1_ID = "AppleCollect-v1"  # readings under which Fig. 1's premise holds (docs/APPLECOLLECT.md)
V1_KWARGS = {"move_bound": "radius", "apple_radius": 0.04, "leave_ends": True}


class EnvError(ValueError):
    """An env that cannot be made, or that mam cannot train on."""


def register_envs() -> None:
    """Register AppleCollect-v0 and -v1 once (safe to call again, e.g. after a module reload)."""
    for env_id, kwargs in ((APPLE_COLLECT_ID, {}), (APPLE_COLLECT_V1_ID, V1_KWARGS)):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="mam_core.envs.apple_collect:AppleCollectEnv",
                         max_episode_steps=100, kwargs=dict(kwargs))


def import_env_module(env_id: str) -> None:
    """Import the module of a `module.path:EnvId` id (no-op for a plain id)."""
    if ":" not in env_id:
        return
    module = env_id.split(":", 1)[0]
    try:
        import_module_from_cwd(module)
    except Exception as e:  # ImportError, or anything the module raises while importing
        raise EnvError(
            f"env {env_id!r}: module {module!r} does not import ({type(e).__name__}: {e}). It must be "
            "importable on every host that runs a learner, referee, worker or `mam eval` "
            "(installed, on PYTHONPATH, or in the directory the command starts in)") from e


def import_module_from_cwd(module: str) -> ModuleType:
    """`importlib.import_module(module)`, searching the current directory last, as `python -m`
    does: console scripts (`mam`, `mam-worker`) find a module next to where they are started
    (a `module:EnvId` env, a `module:Name` algorithm family)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        cwd = os.getcwd()
        top = module.split(".")[0]
        if e.name != top or cwd in sys.path or "" in sys.path or not _has_module(cwd, top):
            raise
        sys.path.append(cwd)
        return importlib.import_module(module)


def _has_module(directory: str, name: str) -> bool:
    return os.path.isfile(os.path.join(directory, name + ".py")) or \
        os.path.isfile(os.path.join(directory, name, "__init__.py"))


def quiet_mujoco() -> None:
    """MuJoCo prints every warning on stdout and appends it to MUJOCO_LOG.TXT in the working directory
    (HalfCheetah's deprecated `settotalmass`, once per env made: dozens of times in a referee). Route
    them to the `mam.mujoco` logger at DEBUG instead (`--verbose` shows them). Idempotent."""
    global _MUJOCO_QUIET
    if _MUJOCO_QUIET:
        return
    try:
        import mujoco
    except ImportError:
        return
    import logging

    logger = logging.getLogger("mam.mujoco")
    mujoco.set_mju_user_warning(lambda message: logger.debug("MuJoCo warning: %s", message))
    _MUJOCO_QUIET = True


_MUJOCO_QUIET = False


def _uses_mujoco(env_id: str) -> bool:
    try:
        return "mujoco" in str(gym.spec(env_id).entry_point)
    except gym.error.Error:
        return False


def make_env(env_id: str, env_kwargs: Mapping[str, Any] | None = None, **make_kwargs: Any) -> gym.Env:
    """`gym.make(env_id, **env_kwargs, **make_kwargs)` with clear errors (`EnvError`); MuJoCo's
    warnings go to the log, not the terminal or the working directory (`quiet_mujoco`)."""
    import_env_module(env_id)
    if _uses_mujoco(env_id):
        quiet_mujoco()
    try:
        return gym.make(env_id, **dict(env_kwargs or {}), **make_kwargs)
    except gym.error.Error as e:
        raise EnvError(f"env {env_id!r}: {e}") from e
    except TypeError as e:  # a keyword the env's constructor does not take
        raise EnvError(f"env {env_id!r} with kwargs {dict(env_kwargs or {})}: {e}") from e


register_envs()
