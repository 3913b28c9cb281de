"""The return of a uniform random policy on the MuJoCo tasks: the floor `mam run` prints a
MuJoCo outcome beside (services/run/progress.py, RANDOM_POLICY_RETURNS; docs/RESULTS.md).

Each episode draws every action uniformly from the env's action box with a generator seeded by
(seed, episode), from `env.reset(seed=episode)`, until the env terminates or truncates (the
registered time limit: 1,000 steps, 50 on Reacher). Undiscounted returns, as `mam`'s evaluation.

    .venv/bin/python benchmarks/random_policy_returns.py --episodes 100
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np

TASKS = ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5", "Reacher-v5",
         "InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Swimmer-v5")


def random_returns(env_id: str, episodes: int, seed: int = 0) -> np.ndarray:
    env = gym.make(env_id)
    low, high = env.action_space.low, env.action_space.high
    out = []
    try:
        for ep in range(episodes):
            rng = np.random.default_rng([seed, ep])
            env.reset(seed=ep)
            total, done = 0.0, False
            while not done:
                _, reward, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(np.float32))
                total, done = total + float(reward), terminated or truncated
            out.append(total)
    finally:
        env.close()
    return np.asarray(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--envs", default=",".join(TASKS))
    args = parser.parse_args()
    for env_id in args.envs.split(","):
        started = time.monotonic()
        r = random_returns(env_id, args.episodes, args.seed)
        print(json.dumps({"env": env_id, "episodes": len(r), "mean": round(float(r.mean()), 2),
                          "std": round(float(r.std()), 2), "min": round(float(r.min()), 2),
                          "max": round(float(r.max()), 2), "seconds": round(time.monotonic() - started, 1)}),
              flush=True)


if __name__ == "__main__":
    main()
