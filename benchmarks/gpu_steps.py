"""The steps of benchmarks/gpu.sh that need Python: each writes one JSON object to --out.

    python benchmarks/gpu_steps.py wheels-check --out FILE
    python benchmarks/gpu_steps.py e2e --device cuda --seconds 30 --workers 3 --lag 2 --tag m3-lag2 \
        --work DIR --out FILE
    python benchmarks/gpu_steps.py graphs-check --device cuda --out FILE
    python benchmarks/gpu_steps.py experiment --device cuda --parallel 8 --seconds 75 --work DIR --out FILE
    python benchmarks/gpu_steps.py combine --bench B.json --e2e E1.json E2.json [...] --out gpu.json

`wheels-check` imports only the carried wheels' packages (mujoco, gymnasium, zenoh) and numpy, so
it runs in a fresh venv that has nothing else. The others run the project's own commands (`mam run`,
`mam experiment`) as child processes of this Python, stop them with SIGTERM (their launchers stop
every process of the run and the learner checkpoints) and read the figures off the runs' own
`learner.jsonl` rows: nothing here times the learner from the inside.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LEARNER_LOG = "learner.jsonl"  # services/run/rundir.py


def write(path: str, obj: dict[str, Any]) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(obj, indent=1, default=str, allow_nan=True) + "\n")


# --------------------------------------------------------------------------- wheels


def wheels_check(args: argparse.Namespace) -> dict[str, Any]:
    """The carried wheels import and work: HalfCheetah-v5 steps, a Zenoh session puts and gets."""
    import importlib.metadata as md

    import gymnasium as gym
    import mujoco
    import numpy as np
    import zenoh

    out: dict[str, Any] = {"python": sys.version.split()[0], "executable": sys.executable,
                           "versions": {d: md.version(d) for d in ("mujoco", "gymnasium", "eclipse-zenoh", "numpy")}}
    out["mujoco_version"] = mujoco.__version__
    env = gym.make("HalfCheetah-v5")
    env.reset(seed=0)
    env.action_space.seed(0)
    n = args.steps
    t0 = time.perf_counter()
    for _ in range(n):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    out["halfcheetah_steps_per_s"] = n / (time.perf_counter() - t0)
    env.close()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    got: list[bytes] = []
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber("mam/gpu-check/x", lambda s: got.append(s.payload.to_bytes()))
        time.sleep(0.2)
        for i in range(10):
            session.put("mam/gpu-check/x", np.int32(i).tobytes())
        deadline = time.monotonic() + 5
        while len(got) < 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
    out["zenoh_messages"] = len(got)
    out["ok"] = len(got) == 10 and out["halfcheetah_steps_per_s"] > 0
    return out


# --------------------------------------------------------------------------- runs


def read_rows(path: Path) -> list[dict[str, Any]]:
    rows = []
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:  # the row being written when the run stopped
                pass
    return rows


def last_row(path: Path) -> dict[str, Any] | None:
    rows = read_rows(path)
    return rows[-1] if rows else None


class GpuSampler:
    """`nvidia-smi` utilization and memory every `period` s in a thread (nothing where it is absent)."""

    def __init__(self, period: float = 1.0) -> None:
        self.samples: list[tuple[float, float, float]] = []  # (monotonic, util %, memory MiB)
        self.available = shutil.which("nvidia-smi") is not None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)

    def __enter__(self) -> "GpuSampler":
        if self.available:
            self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)

    def _run(self, period: float) -> None:
        while not self._stop.is_set():
            try:
                text = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu,memory.used",
                                       "--format=csv,noheader,nounits"], capture_output=True, text=True,
                                      timeout=10).stdout
                util, mem = (float(v) for v in text.strip().splitlines()[0].split(","))
                self.samples.append((time.monotonic(), util, mem))
            except (OSError, ValueError, IndexError, subprocess.SubprocessError):
                pass
            self._stop.wait(period)

    def summary(self, start: float | None, end: float | None) -> dict[str, Any]:
        if not self.available:
            return {"nvidia_smi": False}
        window = [s for s in self.samples if start is not None and end is not None and start <= s[0] <= end]
        return {"nvidia_smi": True, "samples": len(window),
                "util_mean_pct": statistics.fmean(s[1] for s in window) if window else None,
                "memory_max_mib": max(s[2] for s in window) if window else None}


def stop(proc: subprocess.Popen, grace: float) -> int:
    """SIGTERM to the command (its launcher stops its processes), SIGKILL to its group after `grace`."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # its own session (start_new_session): only what it started
            proc.wait(10)
    return proc.returncode


def run_flags(args: argparse.Namespace) -> list[str]:
    flags = ["--device", args.device, "--hidden", args.hidden, "--batch-size", str(args.batch_size),
             "--start-steps", str(args.start_steps), "--eval-episodes", str(args.eval_episodes),
             "--compete-every", str(args.compete_every), "--schedule", "paper", "--no-plot"]
    return flags


def e2e(args: argparse.Namespace) -> dict[str, Any]:
    """`mam run --algo ma-td3` (K=2, M workers, paper schedule) for `seconds` of training after its
    random start phase, then SIGTERM; rates from its learner.jsonl (one row a second)."""
    work = Path(args.work)
    run_dir = work / f"e2e-{args.tag}"
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", args.env, "--algo", "ma-td3",
           "--workers", str(args.workers), "--steps", str(args.steps), "--seed", "0", "--run-dir", str(run_dir),
           "--lag", str(args.lag), "--run", f"gpu-e2e-{os.getpid()}-{args.tag}", *run_flags(args)]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    if args.no_graphs:
        env["MAM_CUDA_GRAPHS"] = "0"
    log = open(work / f"{run_dir.name}.log", "wb")
    t0 = time.monotonic()
    marks: dict[str, float] = {}
    with GpuSampler() as gpu:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env=env)
        try:
            while proc.poll() is None:
                now = time.monotonic()
                row = last_row(run_dir / LEARNER_LOG)
                if row and row.get("env_steps", 0) > 0:
                    marks.setdefault("first_transition", now)
                if row and row.get("updates", 0) > 0:
                    marks.setdefault("train_start", now)
                if "train_start" in marks and now - marks["train_start"] >= args.seconds:
                    break
                if now - t0 > args.seconds + args.startup_timeout:
                    marks["timed_out"] = now
                    break
                time.sleep(0.5)
            marks["stop"] = time.monotonic()
        finally:
            rc = stop(proc, args.grace)
            log.close()
    rows = read_rows(run_dir / LEARNER_LOG)
    train = [r for r in rows if r.get("updates", 0) > 0]
    out: dict[str, Any] = {
        "command": " ".join(cmd[3:]), "returncode": rc, "exited_by_itself": "stop" not in marks,
        "tag": args.tag, "lag": args.lag, "cuda_graphs": not args.no_graphs, "workers": args.workers, "actors": 2,
        "hidden": args.hidden, "batch_size": args.batch_size, "start_steps": args.start_steps,
        "window_s": args.seconds, "rows": len(rows), "timed_out": "timed_out" in marks,
        "startup_s": marks.get("first_transition", math.nan) - t0,
        "random_phase_s": marks.get("train_start", math.nan) - marks.get("first_transition", math.nan),
        "gpu": gpu.summary(marks.get("train_start"), marks.get("stop")),
    }
    if len(train) >= 2:
        a, b = train[0], train[-1]
        dt = b["t"] - a["t"]
        out.update({"train_seconds": dt, "env_steps_per_s": (b["env_steps"] - a["env_steps"]) / dt,
                    "updates_per_s": (b["updates"] - a["updates"]) / dt,
                    "iterations_per_s": (b["iterations"] - a["iterations"]) / dt,
                    "updates": b["updates"], "env_steps": b["env_steps"], "utd": b.get("utd"),
                    "lost": b.get("lost"), "rejected": b.get("rejected")})
        if "exact_wait_s" in b and "exact_wait_s" in a:  # seconds the learner waited for the iteration's rows
            out["learner_wait_share"] = (b["exact_wait_s"] - a["exact_wait_s"]) / dt
    if rows:
        out["all_env_steps_per_s"] = rows[-1]["env_steps"] / max(rows[-1]["t"], 1e-9)
    return out


def experiment(args: argparse.Namespace) -> dict[str, Any]:
    """`mam experiment --parallel P` of GPU learners (a grid of ma-td3 and td3 seeds) for at most
    `seconds`; grid throughput = transitions and updates of all its runs ÷ the command's wall time."""
    work = Path(args.work)
    exp_dir = work / "experiment"
    shutil.rmtree(exp_dir, ignore_errors=True)
    cmd = [sys.executable, "-m", "services.cli", "experiment", "--name", "gpu-grid", "--exp-dir", str(exp_dir),
           "--envs", args.env, "--algos", args.algos, "--seeds", str(args.seeds), "--steps", str(args.steps),
           "--parallel", str(args.parallel), "--no-report", "--no-ledger", *run_flags(args)]
    log = open(work / "experiment.log", "wb")
    t0 = time.monotonic()
    with GpuSampler() as gpu:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env=dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="120"))
        try:
            proc.wait(args.seconds)
        except subprocess.TimeoutExpired:
            pass
        wall = time.monotonic() - t0
        finished_by_itself = proc.poll() is not None
        rc = stop(proc, args.grace)
        log.close()
    runs = [last_row(p) for p in sorted(exp_dir.rglob(LEARNER_LOG))]
    runs = [r for r in runs if r]
    steps = sum(r["env_steps"] for r in runs)
    updates = sum(r["updates"] for r in runs)
    return {"command": " ".join(cmd[3:]), "returncode": rc, "finished_by_itself": finished_by_itself,
            "parallel": args.parallel, "wall_s": wall, "runs_started": len(runs),
            "runs_finished": len(list(exp_dir.rglob("summary.json"))),
            "runs_per_hour": len(list(exp_dir.rglob("summary.json"))) / wall * 3600,
            "env_steps": steps, "updates": updates, "grid_env_steps_per_s": steps / wall,
            "grid_updates_per_s": updates / wall, "gpu": gpu.summary(t0, t0 + wall)}


# --------------------------------------------------------------------------- the one JSON


def load(path: str | None) -> dict[str, Any] | None:
    if not path or not Path(path).is_file():
        return None
    return json.loads(Path(path).read_text().strip().splitlines()[-1] if path.endswith(".jsonl")
                      else Path(path).read_text())


def finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def combine(args: argparse.Namespace) -> dict[str, Any]:
    bench = load(args.bench) or {}
    runs = [r for r in (load(p) for p in (args.e2e or [])) if r]
    by_tag = {r.get("tag"): r for r in runs}
    check = load(args.graphs_check) or {}
    grid = load(args.experiment)
    shape = "halfcheetah"
    k2_bench = bench.get(f"learner_{shape}_k2_updates_per_s")
    k2_device_ms = bench.get(f"learner_{shape}_k2_device_ms_per_update")
    main = by_tag.get("m3-lag2") or (runs[0] if runs else {})
    ups = main.get("updates_per_s")
    derived: dict[str, Any] = {
        "k2_updates_per_s": k2_bench,
        "k2_eager_updates_per_s": bench.get(f"learner_{shape}_k2_eager_updates_per_s"),
        "k2_graph_vs_eager": bench.get(f"learner_{shape}_k2_graph_vs_eager"),
        "k2_vs_td3": bench.get("learner_k2_vs_td3"),
        "k2_bf16_vs_td3": bench.get("learner_k2_bf16_vs_td3"),
        "k2_device_ms_per_update": k2_device_ms,
        # the device's busy share of a graphed update in the bench: busy time per update x updates/s
        "k2_device_busy_share": k2_bench * k2_device_ms / 1e3 if finite(k2_bench) and finite(k2_device_ms) else None,
        "device_time_source": bench.get("learner_device_time_source"),
        "graphs_vs_eager_equal_bits": check.get("graphs_vs_eager", {}).get("equal_bits"),
        "graphs_vs_eager_max_abs_diff": check.get("graphs_vs_eager", {}).get("max_abs_diff"),
        "same_seed_same_policy": check.get("same_seed", {}).get("equal_bits"),
        "e2e": {tag: {k: r.get(k) for k in ("workers", "lag", "cuda_graphs", "env_steps_per_s", "updates_per_s",
                                            "learner_wait_share", "train_seconds", "random_phase_s")}
                | {"nvidia_smi_util_mean_pct": (r.get("gpu") or {}).get("util_mean_pct")}
                for tag, r in by_tag.items()},
        "e2e_m3_lag2_env_steps_per_s": main.get("env_steps_per_s"),
        "learner_update_share": ups / k2_bench if finite(ups) and finite(k2_bench) else None,
        "grid_env_steps_per_s": grid.get("grid_env_steps_per_s") if grid else None,
    }

    def goal(value: Any, target: float) -> bool | None:
        return (value >= target) if finite(value) else None

    goals = {"k2_updates_per_s >= 1500 (graphed, H200)": goal(k2_bench, 1500.0),
             "k2_device_busy_share >= 0.5": goal(derived["k2_device_busy_share"], 0.5),
             "e2e m3 lag2 env_steps_per_s >= 1000": goal(main.get("env_steps_per_s"), 1000.0),
             "graphed == eager within tolerance (100 updates)": check.get("graphs_vs_eager", {}).get("close"),
             "same seed, same policy bits (GPU)": check.get("same_seed", {}).get("equal_bits")}
    timings = load(args.timings) or {}
    return {"dry_run": args.dry_run, "device": bench.get("device", args.device), "machine": bench.get("machine"),
            "versions": bench.get("versions"), "setup": load(args.setup), "derived": derived, "goals": goals,
            "learner_bench": bench, "e2e": runs, "graphs_check": check, "experiment": grid,
            "wheels_check": load(args.wheels), "timings_s": timings}


# --------------------------------------------------------------------------- graphs check


def graphs_check(args: argparse.Namespace) -> dict[str, Any]:
    """The graphed update against the eager one (same seed, same replay data, `updates` updates,
    the elimination half-way: a recapture), and two graphed runs of one seed (run_reference)."""
    import mam_core  # noqa: F401, I001  (pins the arithmetic before numpy and torch load)
    import numpy as np
    import torch
    from mam_core.agent import EnvSpec, MultiActorAgent
    from mam_core.config import resolve
    from mam_core.reference import run_reference
    from mam_lab.bench_learner import random_replay

    device = args.device
    out: dict[str, Any] = {"device": device, "torch": torch.__version__,
                           "gpu": torch.cuda.get_device_name() if device.startswith("cuda") else None}
    obs_dim, act_dim, max_action, batch = 17, 6, 1.0, args.batch_size
    hidden = tuple(int(h) for h in args.hidden.split(","))
    spec = EnvSpec(obs_dim, act_dim, (max_action,) * act_dim)

    def trained(algo: str, graphs: bool) -> tuple[MultiActorAgent, int]:
        os.environ["MAM_CUDA_GRAPHS"] = "1" if graphs else "0"
        buf = random_replay(obs_dim, act_dim, max_action, 20 * batch, device, seed=3)
        agent = MultiActorAgent(resolve(algo, actors=2, hidden=hidden, batch_size=batch, seed=5), spec, device)
        sample = agent.sampler(buf, batch)
        eliminated = False
        for _ in range(args.updates):  # as Algorithm1.run_updates: the elimination before an actor phase
            staged = sample()
            agent.update_critics(staged)
            if agent.actor_phase_due:
                if not eliminated and agent.updates >= args.updates // 2:
                    agent.eliminate(1)
                    eliminated = True
                agent.update_actors(staged)
        torch.cuda.synchronize() if device.startswith("cuda") else None
        return agent, ({"captures": agent.graphs.captures, "failed": agent.graphs.failed}
                       if agent.graphs is not None else {"captures": 0, "failed": "no graphs here"})

    def compare(a: MultiActorAgent, b: MultiActorAgent) -> dict[str, Any]:
        diffs = [float((p - q).abs().max()) for p, q in zip(a.state_dict()["actor"].values(),
                                                             b.state_dict()["actor"].values())]
        diffs += [float((p - q).abs().max()) for p, q in zip(a.state_dict()["critic"].values(),
                                                              b.state_dict()["critic"].values())]
        close = all(torch.allclose(p, q, rtol=1e-4, atol=1e-5) for p, q in
                    zip(list(a.state_dict()["actor"].values()) + list(a.state_dict()["critic"].values()),
                        list(b.state_dict()["actor"].values()) + list(b.state_dict()["critic"].values())))
        return {"max_abs_diff": max(diffs), "equal_bits": max(diffs) == 0.0, "close": bool(close)}

    t0 = time.perf_counter()
    for algo in ("ma-td3", "ma-sac"):
        eager, _ = trained(algo, False)
        graphed, info = trained(algo, True)
        out[f"{algo}_graphs_vs_eager"] = compare(eager, graphed) | info | {"updates": args.updates}
    out["graphs_vs_eager"] = {k: (all(out[f"{a}_graphs_vs_eager"][k] for a in ("ma-td3", "ma-sac"))
                                  if k != "max_abs_diff" else max(out[f"{a}_graphs_vs_eager"][k]
                                                                  for a in ("ma-td3", "ma-sac")))
                              for k in ("max_abs_diff", "equal_bits", "close")}
    out["graphs_vs_eager_s"] = time.perf_counter() - t0
    os.environ["MAM_CUDA_GRAPHS"] = "1"
    t0 = time.perf_counter()
    cfg = resolve("ma-td3", actors=2, workers=3, hidden=hidden, batch_size=batch, seed=11, device=device,
                  start_steps=args.start_steps, compete_every=args.compete_every, eval_episodes=2)
    runs = [run_reference("HalfCheetah-v5", cfg, args.steps) for _ in range(2)]
    same = all(np.array_equal(x[name], y[name]) for x, y in zip(runs[0].policy, runs[1].policy) for name in x)
    out["same_seed"] = {"equal_bits": bool(same), "steps": args.steps, "updates": runs[0].updates,
                        "survivor": runs[0].survivor, "wall_s": [r.wall_time_s for r in runs]}
    out["same_seed_s"] = time.perf_counter() - t0
    return out


def _terminate(signum: int, frame: Any) -> None:
    """SIGTERM (gpu.sh's `timeout`) unwinds like an exception, so the `finally` blocks stop the runs this
    process started in their own sessions: left running, they would outlive the script on the GPU machine."""
    raise SystemExit(128 + signum)


def main() -> None:
    signal.signal(signal.SIGTERM, _terminate)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="step", required=True)
    w = sub.add_parser("wheels-check")
    w.add_argument("--steps", type=int, default=2000)
    for name in ("e2e", "experiment"):
        s = sub.add_parser(name)
        s.add_argument("--device", default="cuda")
        s.add_argument("--env", default="HalfCheetah-v5")
        s.add_argument("--seconds", type=float, required=True)
        s.add_argument("--work", required=True)
        s.add_argument("--hidden", default="256,256")
        s.add_argument("--batch-size", type=int, default=256)
        s.add_argument("--start-steps", type=int, default=5000, help="iterations (paper schedule)")
        s.add_argument("--compete-every", type=int, default=5000, help="[A] iterations")
        s.add_argument("--eval-episodes", type=int, default=20)
        s.add_argument("--grace", type=float, default=60.0)
        if name == "e2e":
            s.add_argument("--workers", type=int, default=3)
            s.add_argument("--lag", type=int, default=0)
            s.add_argument("--tag", default="default", help="names the run directory and the JSON row")
            s.add_argument("--no-graphs", action="store_true", help="MAM_CUDA_GRAPHS=0 for the run")
            s.add_argument("--steps", type=int, default=1_000_000, help="budget (iterations): not reached")
            s.add_argument("--startup-timeout", type=float, default=240.0)
        else:
            s.add_argument("--parallel", type=int, default=8)
            s.add_argument("--algos", default="ma-td3,td3")
            s.add_argument("--seeds", type=int, default=4)
            s.add_argument("--steps", type=int, default=20_000)
    g = sub.add_parser("graphs-check")
    g.add_argument("--device", default="cuda")
    g.add_argument("--hidden", default="256,256")
    g.add_argument("--batch-size", type=int, default=256)
    g.add_argument("--updates", type=int, default=100)
    g.add_argument("--steps", type=int, default=1500, help="run_reference iterations (twice)")
    g.add_argument("--start-steps", type=int, default=500)
    g.add_argument("--compete-every", type=int, default=500)
    c = sub.add_parser("combine")
    for opt in ("bench", "experiment", "wheels", "setup", "timings", "graphs-check"):
        c.add_argument(f"--{opt}")
    c.add_argument("--e2e", nargs="*", default=[])
    c.add_argument("--device", default="cuda")
    c.add_argument("--dry-run", action="store_true")
    for s in sub.choices.values():
        s.add_argument("--out", required=True)
    args = p.parse_args()
    step = {"wheels-check": wheels_check, "e2e": e2e, "experiment": experiment, "graphs-check": graphs_check,
            "combine": combine}[args.step]
    write(args.out, step(args))


if __name__ == "__main__":
    main()
