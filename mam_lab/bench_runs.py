"""`mam bench` pieces that run the real processes: end to end (`mam run --algo td3` against one
process that steps the env and trains the reference TD3) and collection scaling (M real
`mam-worker` processes feeding a real `mam-learner`)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mam_lab.bench_learner import reference_td3
from mam_lab.bench_sizes import ROOT, BenchSizes, child_env, stop_children
from services.run import cpu, rundir


def single_process_td3(env_id: str, steps: int, start_steps: int, sizes: BenchSizes, device: str,
                       seed: int = 0) -> float:
    """Seconds for one process to collect `steps` transitions and train the reference TD3
    once per transition after `start_steps` (sfujim's `main.py` loop), env creation included."""
    import gymnasium as gym
    import torch

    import mam_core.envs  # noqa: F401  (AppleCollect-v0)
    from mam_core.agent import EnvSpec
    from mam_core.replay import ReplayBuffer

    t0 = time.perf_counter()
    env = gym.make(env_id)
    spec = EnvSpec.from_env(env)
    max_a = np.asarray(spec.max_action, np.float32)
    td3 = reference_td3(spec.obs_dim, spec.act_dim, float(max_a.max()), sizes.hidden, device)
    buf = ReplayBuffer(steps, spec.obs_dim, spec.act_dim, device, seed)
    rng = np.random.default_rng(seed)
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    dev = torch.device(device)
    for t in range(steps):
        if t < start_steps:
            action = env.action_space.sample().astype(np.float32)
        else:
            with torch.no_grad():
                o = torch.as_tensor(np.asarray(obs, np.float32), device=dev).reshape(1, -1)
                action = td3.actor(o)[0].cpu().numpy()
            noise = rng.normal(0.0, 0.1, spec.act_dim).astype(np.float32) * max_a
            action = np.clip(action + noise, -max_a, max_a)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        buf.add_batch(np.asarray(obs, np.float32)[None], action[None], np.array([reward], np.float32),
                      np.asarray(next_obs, np.float32)[None], np.array([terminated]))
        obs = env.reset()[0] if terminated or truncated else next_obs
        if t >= start_steps and len(buf) >= sizes.batch_size:
            b = buf.sample(sizes.batch_size)
            td3.train(b["obs"], b["action"], b["reward"].unsqueeze(1), b["next_obs"], b["not_done"].unsqueeze(1))
    env.close()
    return time.perf_counter() - t0


def _watch_learner(endpoint: str, run: str, until: Callable[[Any, float], bool], timeout: float,
                   procs: list[subprocess.Popen], run_dir: Path | None = None) -> None:
    """Follow the run's learner stats as a client until `until(stats, t_received)` is true
    (a `mam run` in `run_dir` admits a client that presents its secret: services/run/secret.py)."""
    from services.messaging import bus, keys
    from services.messaging.codec import LearnerStats, MessageError
    from services.run import secret

    conf = bus.make_config(connect=[endpoint], auth_file=secret.of_run(run_dir))
    deadline = time.monotonic() + timeout
    with bus.session_scope(conf, retry_for=min(60.0, timeout)) as session:
        latest = bus.Latest.subscribe(session, keys.learner_stats(run))
        try:
            while time.monotonic() < deadline:
                if any(p.poll() not in (None, 0) for p in procs):
                    raise RuntimeError("a child process of the bench failed: " +
                                       ", ".join(f"{p.args[2:4]} -> {p.returncode}" for p in procs if p.poll()))
                if not latest.wait_fresh(timeout=0.5):
                    continue
                item = latest.fresh().get(keys.learner_stats(run))
                if item is None:
                    continue
                try:
                    stats = LearnerStats.from_bytes(item.payload)
                except MessageError:
                    continue
                if until(stats, item.t):
                    return
            raise TimeoutError(f"run {run} did not get there within {timeout:.0f} s")
        finally:
            latest.close()


def distributed_run(env_id: str, steps: int, start_steps: int, sizes: BenchSizes, device: str,
                    work_dir: Path, seed: int = 0, precision: str = "fp32") -> dict[str, float]:
    """`mam run --algo td3` (learner + referee + 1 worker) to `steps` transitions at utd=1.

    Returns the command's wall time and, seen from a client of the run, the time from the
    command's start to the first transition and to the learner's `done`.
    """
    run = f"bench-e2e-{uuid.uuid4().hex[:8]}"
    run_dir = work_dir / run
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", env_id, "--algo", "td3", "--steps", str(steps),
           "--start-steps", str(start_steps), "--workers", "1", "--utd", "1", "--seed", str(seed),
           "--batch-size", str(sizes.batch_size), "--hidden", ",".join(map(str, sizes.hidden)),
           "--eval-episodes", "1", "--eval-every", str(100 * steps), "--device", device, "--precision", precision,
           "--run", run, "--run-dir", str(run_dir), "--no-plot"]
    t0 = time.monotonic()
    log_path = work_dir / f"{run}.out"
    with open(log_path, "wb") as out:
        # bf16 is measured even on a CPU without native bf16, where `mam run` refuses it by default
        env = child_env(**({cpu.ALLOW_SLOW_BF16: "1"} if precision == "bf16" else {}))
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    marks: dict[str, float] = {}
    try:
        config = run_dir / rundir.CONFIG
        while not config.is_file():
            if proc.poll() is not None or time.monotonic() - t0 > sizes.timeout_s:
                raise RuntimeError(f"mam run did not start: {log_path.read_text()[-2000:]}")
            time.sleep(0.05)
        endpoint = json.loads(config.read_text())["endpoint"]

        def until(stats: Any, t: float) -> bool:
            if stats.env_steps > 0 and "first" not in marks:
                marks["first"] = t
            if stats.done:
                marks["done"] = t
                return True
            return False

        _watch_learner(endpoint, run, until, sizes.timeout_s, [proc], run_dir)
        proc.wait(timeout=sizes.timeout_s)
    finally:
        stop_children([proc])
    if proc.returncode != 0:
        raise RuntimeError(f"mam run exited {proc.returncode}: {log_path.read_text()[-2000:]}")
    t_end = time.monotonic()
    return {"wall_s": t_end - t0, "to_done_s": marks["done"] - t0,
            "startup_s": marks.get("first", marks["done"]) - t0}


def bench_e2e(sizes: BenchSizes, device: str = "cpu", threads: int = 1, log: Callable[[str], None] = print,
              work_dir: Path | None = None) -> dict[str, Any]:
    import torch

    torch.set_num_threads(threads)
    n, start = sizes.e2e_steps, sizes.e2e_start_steps
    log(f"end to end: mam run --algo td3 on {sizes.e2e_env} to {n} transitions (utd 1, start {start}) "
        f"vs one process")
    with tempfile.TemporaryDirectory(prefix="mam-bench-") as tmp:
        work = Path(work_dir or tmp)
        single = single_process_td3(sizes.e2e_env, n, start, sizes, device)
        dist = distributed_run(sizes.e2e_env, n, start, sizes, device, work)
        log("end to end: the same with --precision bf16")
        bf16 = distributed_run(sizes.e2e_env, n, start, sizes, device, work, precision="bf16")
    return {
        "e2e_bf16_vs_single_process": bf16["to_done_s"] / single, "e2e_bf16_mam_run_to_done_s": bf16["to_done_s"],
        "bf16_native_cpu": cpu.native_bf16_cpu(),
        "e2e_env": sizes.e2e_env, "e2e_steps": n, "e2e_start_steps": start,
        "e2e_single_process_s": single,
        "e2e_mam_run_to_done_s": dist["to_done_s"], "e2e_mam_run_wall_s": dist["wall_s"],
        "e2e_mam_run_startup_s": dist["startup_s"],
        "e2e_vs_single_process": dist["to_done_s"] / single,
        "e2e_wall_vs_single_process": dist["wall_s"] / single,
        "e2e_after_startup_vs_single_process": (dist["to_done_s"] - dist["startup_s"]) / single,
    }


# --------------------------------------------------------------------------- collection scaling


def collection_rate(workers: int, sizes: BenchSizes, work_dir: Path, seed: int = 0) -> float:
    """Env steps/s of `workers` real worker processes feeding a real learner in lock-step (one row
    per slot per iteration) that rarely updates, so weights rarely change and never hold them."""
    from services.messaging import bus

    run = f"bench-col-{uuid.uuid4().hex[:8]}"
    run_dir = work_dir / run
    run_dir.mkdir(parents=True, exist_ok=True)
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    learner = [sys.executable, "-m", "services.roles.learner", "--env", sizes.collection_env, "--algo", "td3",
               "--steps", "1000000000", "--utd", "0.001", "--start-steps", str(sizes.collection_start_steps),
               "--workers", str(workers), "--batch-size", str(sizes.batch_size),
               "--hidden", ",".join(map(str, sizes.hidden)), "--seed", str(seed), "--device", "cpu",
               "--run", run, "--listen", endpoint, "--run-dir", str(run_dir)]  # no referee: K = 1 needs no decision
    procs: list[subprocess.Popen] = []
    logs = []
    try:
        for i, cmd in enumerate([learner] + [
                [sys.executable, "-m", "services.roles.worker", "--run", run, "--connect", endpoint, "--id", f"w{j}",
                 "--slot", str(j)] for j in range(workers)]):
            out = open(run_dir / f"proc{i}.log", "wb")
            logs.append(out)
            procs.append(subprocess.Popen(cmd, cwd=ROOT, env=child_env(), stdout=out, stderr=subprocess.STDOUT,
                                          stdin=subprocess.DEVNULL, start_new_session=True))
        warm = sizes.collection_start_steps + 200 * workers  # past the random phase: the policy runs
        marks: list[tuple[float, int]] = []

        def until(stats: Any, t: float) -> bool:
            if stats.env_steps < warm:
                return False
            marks.append((t, stats.env_steps))
            return t - marks[0][0] >= sizes.collection_window_s

        _watch_learner(endpoint, run, until, sizes.timeout_s, procs)
    finally:
        stop_children(procs)
        for f in logs:
            f.close()
    (t0, s0), (t1, s1) = marks[0], marks[-1]
    return (s1 - s0) / max(t1 - t0, 1e-9)


def bench_collection(sizes: BenchSizes, log: Callable[[str], None] = print,
                     work_dir: Path | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"collection_env": sizes.collection_env,
                           "collection_setup": "real mam-learner (lock-step, --utd 0.001) + M mam-worker"}
    with tempfile.TemporaryDirectory(prefix="mam-bench-") as tmp:
        for m in sizes.collection_workers:
            log(f"collection: {m} worker process(es) on {sizes.collection_env}, "
                f"{sizes.collection_window_s:.0f} s window")
            out[f"collection_steps_per_s_m{m}"] = collection_rate(m, sizes, Path(work_dir or tmp))
    first = sizes.collection_workers[0]
    for m in sizes.collection_workers[1:]:
        out[f"collection_scaling_m{m}_vs_m{first}"] = out[f"collection_steps_per_s_m{m}"] / out[
            f"collection_steps_per_s_m{first}"]
    return out
