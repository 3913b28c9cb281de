"""Helpers the lab's tests share: run directories, experiments and a stand-in launcher."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from rich.console import Console

from mam_lab.grid import make_grid
from mam_lab.scheduler import Launch
from services.run.rundir import write_json

ROOT = Path(__file__).resolve().parents[1]


PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SPACING, STEPS = 100, 2000


def quiet() -> Console:
    return Console(file=open(os.devnull, "w"), width=120)


def write_run(run_dir: Path, algo: str, seed: int, k: int, score, finished: bool = True,
              final: float | None = None) -> None:
    """A run directory as the system writes it: config.json, eval.jsonl, allocation.jsonl, summary.json.

    `score(step)` is the best actor's return; with k > 1 the other actors score 10 less before the
    elimination at C = 1000 (and are not evaluated after it). Multi-actor runs also evaluate at
    every round A = 50 before C (off the grid), and evaluations land 3 steps late.
    """
    run_dir.mkdir(parents=True)
    cfg = {"run": f"r{seed}", "env_id": "Toy-v0", "steps": STEPS,
           "algo": {"algo": algo, "actors": k, "workers": 3 if k > 1 else 1, "eval_every": SPACING,
                    "eliminate_at": 1000, "compete_every": 50, "eta": 0.1 if k > 1 else 0.0, "no_ot": False,
                    "no_wt": False, "seed": seed, "utd": 1.0}}
    (run_dir / "config.json").write_text(json.dumps(cfg))
    rows, allocs = [], []
    steps = list(range(SPACING, STEPS + 1, SPACING))
    if k > 1:  # rounds every A = 50 before the elimination at C = 1000
        steps = sorted(set(steps) | set(range(50, 1000, 50)))
    for i, step in enumerate(steps):
        best = score(step)
        if k > 1 and step < 1000:
            mean = [best - 10.0] * (k - 1) + [best]
            allocs.append({"env_steps": step + 3, "counts": [1] * (k - 1) + [2], "probabilities":
                           [0.2] * (k - 1) + [1 - 0.2 * (k - 1)], "reason": "round", "returns": mean})
        elif k > 1 and step == 1000:  # the elimination's competition: the best actor survives
            allocs.append({"env_steps": step + 3, "probabilities": [0.0] * (k - 1) + [1.0], "reason": "elimination",
                           "returns": [best - 10.0] * (k - 1) + [best], "survivor": k - 1})
        elif k > 1:
            mean = [None] * (k - 1) + [best]
        else:
            mean = [best]
        rows.append({"round": i + 1, "env_steps": step + 3, "mean": mean, "returns": [[m] if m is not None else []
                                                                                      for m in mean]})
    if finished:
        rows.append({"round": 999, "env_steps": STEPS + 3, "mean": rows[-1]["mean"], "returns": []})
    with open(run_dir / "eval.jsonl", "w") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    with open(run_dir / "allocation.jsonl", "w") as f:
        for r in allocs:
            f.write(json.dumps(r) + "\n")
    if finished:
        finals = rows[-1]["mean"] if final is None else [None] * (k - 1) + [final]
        (run_dir / "summary.json").write_text(json.dumps({
            "final_returns": finals, "survivor": k - 1, "env_steps": STEPS + 3, "updates": STEPS - 100,
            "wall_time_s": 10.0 + seed, "launcher_wall_time_s": 20.0 + seed}))


def make_experiment(exp: Path) -> None:
    # ma-td3: score = step/100 + seed (seeds 0, 1, 2); td3: score = step/200 (seeds 0, 1)
    for seed in (0, 1, 2):
        write_run(exp / "Toy-v0" / "ma-td3" / f"seed{seed}", "ma-td3", seed, 2, lambda s, seed=seed: s / 100 + seed)
    for seed in (0, 1):
        write_run(exp / "Toy-v0" / "td3" / f"seed{seed}", "td3", seed, 1, lambda s: s / 200)
    write_run(exp / "Toy-v0" / "td3" / "seed2", "td3", 2, 1, lambda s: 1e6, finished=False)  # interrupted
    planned = [f"Toy-v0/{v}/seed{s}" for s in (0, 1, 2) for v in ("ma-td3", "td3")]
    write_json(exp / "experiment.json", {"name": "toy", "runs": [{"path": p} for p in planned]})


FAKE_RUN = r"""
import json, os, signal, sys, time
run_dir, mode, delay = sys.argv[1], sys.argv[2], float(sys.argv[3])
launch = json.load(open(os.path.join(run_dir, "launch.json")))
if launch["cores"]:
    os.sched_setaffinity(0, launch["cores"])
assert not os.path.exists(os.path.join(run_dir, "junk")), "a partial run was not cleared"
cfg = launch["config"]
json.dump(cfg, open(os.path.join(run_dir, "config.json"), "w"))
os.makedirs(os.path.join(run_dir, "logs"))
open(os.path.join(run_dir, "logs", "learner.log"), "w").write("boom" if mode == "fail" else "ok")
t0 = time.time()
if mode == "hang":
    signal.signal(signal.SIGTERM, lambda *a: sys.exit(130))
    print("hanging", flush=True)
    time.sleep(120)
    sys.exit(1)
time.sleep(delay)
if mode == "fail":
    sys.exit(3)
if mode == "interrupt":
    sys.exit(130)
with open(os.path.join(run_dir, "learner.jsonl"), "w") as f:
    for i in range(1000):
        row = {"env_steps": i, "updates": i}
        if i % 100 == 99:  # a training episode ended: 10 rows carry its return
            row.update(train_return=i / 10, train_episodes=2)
        f.write(json.dumps(row) + "\n")
with open(os.path.join(run_dir, "eval.jsonl"), "w") as f:
    f.write(json.dumps({"env_steps": cfg["steps"], "mean": [1.0]}) + "\n")
os.makedirs(os.path.join(run_dir, "checkpoints"))
open(os.path.join(run_dir, "checkpoints", "learner.pt"), "wb").write(b"x" * 1000)
json.dump({"start": t0, "end": time.time(), "cores": sorted(os.sched_getaffinity(0))},
          open(os.path.join(run_dir, "timing.json"), "w"))
json.dump({"final_returns": [1.0], "survivor": 0, "env_steps": cfg["steps"], "updates": 1, "wall_time_s": 1},
          open(os.path.join(run_dir, "summary.json"), "w"))
"""


class FakeLauncher:
    """Starts FAKE_RUN as the run's process; `modes` gives each successive start its mode (then "ok")."""

    def __init__(self, *modes: str, delay: float = 0.0) -> None:
        self.modes = list(modes)
        self.delay = delay
        self.calls: list[Path] = []
        self.cores: list[tuple[int, ...]] = []

    def __call__(self, job: Launch) -> subprocess.Popen:
        self.calls.append(job.run_dir)
        self.cores.append(job.cores)
        mode = self.modes.pop(0) if self.modes else "ok"
        write_json(job.run_dir / "launch.json", {"config": job.cfg.to_dict(), "cores": list(job.cores) or None})
        return subprocess.Popen([sys.executable, "-c", FAKE_RUN, str(job.run_dir), mode, str(self.delay)],
                                stdout=job.log, stderr=subprocess.STDOUT, start_new_session=True)


def finish_fake(spec, exp: Path) -> None:
    """A finished run directory, as FAKE_RUN leaves it."""
    run_dir = _mkdir(exp / spec.path)
    write_json(run_dir / "launch.json", {"config": spec.run_config("x").to_dict(), "cores": None})
    subprocess.run([sys.executable, "-c", FAKE_RUN, str(run_dir), "ok", "0"], check=True)


def small_grid():
    return make_grid(envs="AppleCollect-v0", algos="ma-ddpg,ddpg", seeds="2", steps=300,
                     flags={"hidden": "8,8", "batch_size": 8})


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True)
    return path


def write_bias(run_dir: Path, rows: list[tuple[int, int, float]]) -> None:
    """bias.jsonl as the learner writes it: one row per (point, live actor)."""
    with open(run_dir / "bias.jsonl", "w") as f:
        for point, actor, rate in rows:
            f.write(json.dumps({"env_steps": point + 2, "point": point, "updates": point, "bias": {
                "actor": actor, "q_estimate": 1.0, "q_true": 1.0, "bias": 0.0, "bias_rate": rate}}) + "\n")


def _timing(exp: Path, spec) -> dict[str, Any]:
    return json.loads((exp / spec.path / "timing.json").read_text())


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


def _set_record(run_dir: Path, commit: str, dirty: bool = False) -> None:
    write_json(run_dir / "record.json", {"commit": commit, "dirty": dirty})

