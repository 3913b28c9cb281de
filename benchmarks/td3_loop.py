"""A plain single-process TD3 training loop: the yardstick a `mam run --algo td3` is timed against.

    python benchmarks/td3_loop.py --env HalfCheetah-v5 --steps 10000 --start-steps 5000 [--eval-episodes 10]

What a user would write (or get from CleanRL's `td3_continuous_action.py` or Stable-Baselines3's
TD3 with the paper's hyperparameters): one environment, uniform random actions for `start_steps`,
then per step an action with Gaussian noise (0.1 · max_action), one transition into a numpy ring
buffer and one update of `benchmarks/td3_reference.TD3` (256×256, batch 256, the reference TD3's
defaults), then `eval_episodes` deterministic episodes. torch with the machine's own kernels (it
never imports mam_core, so nothing is pinned) and one thread unless `--threads`. Prints one JSON
object: wall time, its parts, the final mean return.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.td3_reference import TD3  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="HalfCheetah-v5")
    p.add_argument("--steps", type=int, default=10_000)
    p.add_argument("--start-steps", type=int, default=5_000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    t0 = time.perf_counter()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    env = gym.make(args.env)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    max_action = float(env.action_space.high[0])
    agent = TD3(obs_dim, act_dim, max_action)
    rng = np.random.default_rng(args.seed)
    n = args.steps
    buf = {"s": np.zeros((n, obs_dim), np.float32), "a": np.zeros((n, act_dim), np.float32),
           "r": np.zeros((n, 1), np.float32), "s2": np.zeros((n, obs_dim), np.float32),
           "nd": np.zeros((n, 1), np.float32)}
    obs, _ = env.reset(seed=args.seed)
    env.action_space.seed(args.seed)
    t_start = time.perf_counter()
    updates = 0
    for t in range(n):
        if t < args.start_steps:
            action = env.action_space.sample()
        else:
            action = agent.act(np.asarray(obs, np.float32))
            action = np.clip(action + rng.normal(0, 0.1 * max_action, act_dim), -max_action, max_action)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        for key, value in (("s", obs), ("a", action), ("r", reward), ("s2", next_obs), ("nd", 1.0 - terminated)):
            buf[key][t] = value
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
        if t >= args.start_steps:
            idx = rng.integers(0, t + 1, args.batch_size)
            agent.train(*(torch.from_numpy(buf[key][idx]) for key in ("s", "a", "r", "s2", "nd")))
            updates += 1
    t_train = time.perf_counter()
    returns = []
    for e in range(args.eval_episodes):
        obs, _ = env.reset(seed=args.seed + 100 + e)
        done, total = False, 0.0
        while not done:
            obs, reward, terminated, truncated, _ = env.step(agent.act(np.asarray(obs, np.float32)))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    end = time.perf_counter()
    print(json.dumps({"env": args.env, "steps": n, "updates": updates, "wall_s": round(end - t0, 2),
                      "startup_s": round(t_start - t0, 2), "train_s": round(t_train - t_start, 2),
                      "eval_s": round(end - t_train, 2), "final_return": float(np.mean(returns)),
                      "torch": torch.__version__, "threads": args.threads}))


if __name__ == "__main__":
    main()
