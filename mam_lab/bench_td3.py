"""`mam run --algo td3` against the single-process TD3 a user would run instead, interleaved.

    python -m mam_lab.bench_td3 [--rounds 2] [--steps 10000] [--start-steps 5000] [--sb3-path DIR]

HalfCheetah-v5, the paper's TD3 hyperparameters, `steps` env steps of which `start_steps` random,
one update per step after them, 10 evaluation episodes at the end, one torch thread where the
program sets threads. Per round, in rotating order, each as a process of its own (wall time from
start to exit, start-up and the final evaluation included):

* `loop` — `benchmarks/td3_loop.py`: a plain loop over `benchmarks/td3_reference.TD3`, the
  machine's own kernels (nothing of mam imported);
* `mam` — `mam run --algo td3` with the default, portable arithmetic;
* `mam-native` — the same with `--arithmetic native`;
* `sb3` — Stable-Baselines3's TD3 with the same hyperparameters (`--sb3-path`: a folder where
  `stable_baselines3` and its needs are installed, e.g. `pip install --target DIR stable-baselines3`);
  left out where it does not import.

A ratio is the median over rounds of the within-round ratio of wall times. One JSON object on the
last line.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import typer

from mam_core import arithmetic
from mam_lab.bench import cpu_model
from mam_lab.bench_sizes import ROOT

SB3 = """
import sys, time, json
t0 = time.perf_counter()
import numpy as np, torch, gymnasium as gym
from stable_baselines3 import TD3
from stable_baselines3.common.noise import NormalActionNoise
torch.set_num_threads(1)
steps, start = int(sys.argv[1]), int(sys.argv[2])
env = gym.make("HalfCheetah-v5")
act = env.action_space.shape[0]
model = TD3("MlpPolicy", env, learning_starts=start, batch_size=256, learning_rate=3e-4, buffer_size=steps,
            action_noise=NormalActionNoise(np.zeros(act), 0.1 * np.ones(act)), policy_kwargs=dict(net_arch=[256, 256]),
            seed=0, device="cpu", verbose=0)
model.learn(total_timesteps=steps)
returns = []
for e in range(10):
    obs, _ = env.reset(seed=100 + e)
    done, total = False, 0.0
    while not done:
        obs, r, term, trunc, _ = env.step(model.predict(obs, deterministic=True)[0])
        total += float(r); done = term or trunc
    returns.append(total)
print(json.dumps({"wall_s": time.perf_counter() - t0, "final_return": float(np.mean(returns))}))
"""


def _run(cmd: list[str], env: dict[str, str], out: Path, timeout: float) -> float:
    t0 = time.monotonic()
    with open(out, "wb") as f:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:5])} exited {proc.returncode}: {out.read_text()[-2000:]}")
    return time.monotonic() - t0


def _check_arithmetic(run_dir: Path, want: str) -> None:
    """The run's learner computed with `want` arithmetic (its log's "arithmetic ..." line)."""
    log = (run_dir / "logs" / "learner.log").read_text(errors="replace")
    said = re.search(r"arithmetic (\w+), GEMMs ([\w-]+)", log)
    if said is None or said.group(1) != want or (want == "native") != (said.group(2) == "native"):
        raise RuntimeError(f"{run_dir}: the learner was to compute with {want} arithmetic; its log says "
                           f"{said.group(0) if said else 'nothing of it'}")


def sb3_importable(path: str) -> bool:
    env = dict(arithmetic.unpinned_environ(), PYTHONPATH=path)
    return subprocess.run([sys.executable, "-c", "import stable_baselines3"], env=env, capture_output=True,
                          timeout=120).returncode == 0


def bench_sides(steps: int, start_steps: int, sb3_path: str = "") -> dict[str, tuple[list[str], dict[str, str]]]:
    """Each side's command and environment. Every side starts from the environment this process
    had before it pinned the arithmetic (`arithmetic.unpinned_environ`), as from a user's shell:
    a `mam run` pins its own kernels, or, with `--arithmetic native`, hands its roles the variables
    it found. Given this process's pins instead, `mam run --arithmetic native` took them for the
    user's and computed in MKL's COMPATIBLE branch (the records up to `td3-1c047b8-intel`)."""
    plain = dict(arithmetic.unpinned_environ(), PYTHONWARNINGS="ignore", COLUMNS="160")
    sides: dict[str, tuple[list[str], dict[str, str]]] = {
        "loop": ([sys.executable, "benchmarks/td3_loop.py", "--steps", str(steps), "--start-steps", str(start_steps)],
                 plain)}
    run = ["run", "--env", "HalfCheetah-v5", "--algo", "td3", "--steps", str(steps), "--start-steps", str(start_steps),
           "--eval-episodes", "10", "--eval-every", str(10 * steps), "--seed", "0", "--no-plot"]
    sides["mam"] = ([sys.executable, "-m", "services.cli", *run], plain)
    sides["mam-native"] = ([sys.executable, "-m", "services.cli", *run, "--arithmetic", "native"], plain)
    if sb3_path and sb3_importable(sb3_path):
        sides["sb3"] = ([sys.executable, "-c", SB3, str(steps), str(start_steps)], dict(plain, PYTHONPATH=sb3_path))
    return sides


def main(rounds: int = typer.Option(2), steps: int = typer.Option(10_000), start_steps: int = typer.Option(5_000),
         sb3_path: str = typer.Option("", help="folder with stable_baselines3 installed (else no sb3 side)"),
         timeout: float = typer.Option(1800.0)) -> None:
    """Print the wall times of each side and their ratios, one JSON object on the last line."""
    sides = bench_sides(steps, start_steps, sb3_path)
    walls: dict[str, list[float]] = {s: [] for s in sides}
    names = list(sides)
    with tempfile.TemporaryDirectory(prefix="mam-bench-td3-") as tmp:
        for r in range(rounds):
            for name in names[r % len(names):] + names[:r % len(names)]:
                cmd, env = sides[name]
                if name.startswith("mam"):
                    cmd = [*cmd, "--run", f"bench-td3-{uuid.uuid4().hex[:6]}", "--run-dir", f"{tmp}/{name}-{r}"]
                walls[name].append(_run(cmd, env, Path(tmp) / f"{name}-{r}.out", timeout))
                if name.startswith("mam"):
                    _check_arithmetic(Path(tmp) / f"{name}-{r}", "native" if name == "mam-native" else "portable")
                print(f"round {r + 1}: {name} {walls[name][-1]:.1f} s", flush=True)
    med = statistics.median
    out: dict[str, Any] = {"steps": steps, "start_steps": start_steps, "rounds": rounds,
                           "cpu": cpu_model(), "load_1min": os.getloadavg()[0]}
    for name in names:
        out[f"{name}_wall_s"] = round(med(walls[name]), 1)
    for name in names[1:]:
        out[f"{name}_vs_loop"] = round(med(w / ref for w, ref in zip(walls[name], walls["loop"])), 3)
    out["mam_portable_vs_native"] = round(med(a / b for a, b in zip(walls["mam"], walls["mam-native"])), 3)
    if "sb3" in walls:
        out["mam_vs_sb3"] = round(med(a / b for a, b in zip(walls["mam"], walls["sb3"])), 3)
    print(json.dumps(out))



if __name__ == "__main__":
    typer.run(main)
