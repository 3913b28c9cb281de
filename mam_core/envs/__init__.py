"""The project's own gymnasium environments; importing this package registers them."""

from __future__ import annotations

import gymnasium as gym

APPLE_COLLECT_ID = "AppleCollect-v0"  # the readings of the published runs
APPLE_COLLECT_V1_ID = "AppleCollect-v1"  # readings under which Fig. 1's premise holds (docs/APPLECOLLECT.md)
V1_KWARGS = {"move_bound": "radius", "apple_radius": 0.04, "leave_ends": True}


def register_envs() -> None:
    """Register AppleCollect-v0 and -v1 once (safe to call again, e.g. after a module reload)."""
    for env_id, kwargs in ((APPLE_COLLECT_ID, {}), (APPLE_COLLECT_V1_ID, V1_KWARGS)):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="mam_core.envs.apple_collect:AppleCollectEnv",
                         max_episode_steps=100, kwargs=dict(kwargs))


register_envs()
