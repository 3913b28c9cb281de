"""The project's own gymnasium environments; importing this package registers them."""

from __future__ import annotations

import gymnasium as gym

APPLE_COLLECT_ID = "AppleCollect-v0"


def register_envs() -> None:
    """Register AppleCollect-v0 once (safe to call again, e.g. after a module reload)."""
    if APPLE_COLLECT_ID not in gym.registry:
        gym.register(
            id=APPLE_COLLECT_ID,
            entry_point="mam_core.envs.apple_collect:AppleCollectEnv",
            max_episode_steps=100,
        )


register_envs()
