"""`mam bench`: the performance figures of the issue, each as a ratio against a reference
measured in the same run, with its target beside it.

What is measured (docs/PERFORMANCE.md has the figures and the profiles):

* **learner** — updates/s of `MultiActorAgent` (MA-TD3, n=2, K=1,2,3) against the plain
  single TD3 of `benchmarks/td3_reference.py` on the same random replay data, in this
  process, with the same torch thread count. Contenders run in rounds, interleaved
  (A, B, C, A, B, C, ...; the order rotates every round); a ratio is the median over
  rounds of the within-round ratio, so a noisy, shared machine moves both sides alike.
* **end to end** — `mam run --algo td3` (learner + referee + one worker as processes over
  loopback Zenoh) to N transitions at utd=1 against one process that steps the env and
  trains the reference TD3 in one loop (the shape of sfujim's `main.py`), same N.
* **transport** — transitions/s that a learner-like consumer (`bus.Inbox` → codec
  `TransitionBatch` decode and validation → `ReplayBuffer.add_batch`) ingests from M
  worker-like publisher processes (HalfCheetah rows, 32 per message) over loopback
  Zenoh; weights broadcast latency (learner-side `actor_params` + encode + put → received,
  decoded, validated and loaded in a subscriber process); bytes per transition.
* **collection** — env steps/s of M = 1, 2, 4 real `mam-worker` processes feeding a real
  `mam-learner` whose rate limiter never holds them back (`--utd 0.001`, rate-limiter band
  raised above the budget): the learner ingests and trains ~1 update per 1000 transitions.

`--json` prints the same figures as one JSON object on the last line. `--quick` (the
default) keeps the whole bench to a few minutes on 2 cores; `--full` measures longer.
Child processes of the transport bench re-enter this module through `python -c`, so this
module imports torch, gymnasium and the services lazily: a publisher starts in ~0.2 s.
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
import platform
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import typer

from services import options

# Targets of the issue: (comparison, value). "ge": the figure must be >= value.
TARGETS: dict[str, tuple[str, float]] = {
    "learner_k2_vs_td3": ("ge", 0.8),  # 0.95 on CUDA, see target_for()
    "learner_k2_bf16_vs_td3": ("ge", 0.8),  # the same target, met with the opt-in mixed precision?
    "e2e_vs_single_process": ("le", 0.7),
    "e2e_bf16_vs_single_process": ("le", 0.7),
    "transport_transitions_per_s": ("ge", 50_000.0),
    "weights_latency_p99_ms": ("le", 10.0),
}

# Environment shapes of the learner bench: (obs_dim, act_dim, max_action).
SHAPES: dict[str, tuple[int, int, float]] = {
    "halfcheetah": (17, 6, 1.0),
    "humanoid": (348, 17, 0.4),
}

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS_WARMUP = 3  # broadcasts not counted in the latency figures


@dataclass(frozen=True)
class BenchSizes:
    """How much each piece measures. `quick()` (default), `full()`, `tiny()` (tests)."""

    learner_rounds: int = 5  # interleaved rounds per shape
    learner_updates: int = 20  # updates per contender per round
    learner_ks: tuple[int, ...] = (1, 2, 3)
    learner_shapes: tuple[str, ...] = ("halfcheetah", "humanoid")
    hidden: tuple[int, ...] = (256, 256)
    batch_size: int = 256
    e2e_env: str = "HalfCheetah-v5"
    e2e_steps: int = 2000  # N transitions
    e2e_start_steps: int = 500
    transport_publishers: int = 2  # M worker-like publisher processes
    transport_batches: int = 1500  # messages per publisher
    transport_rows: int = 32  # transitions per message (the worker's send_batch)
    weights_messages: int = 40  # per actor size
    weights_hidden: tuple[int, ...] = (256, 256)  # the actor sizes, in every mode
    weights_interval_s: float = 0.025
    collection_env: str = "HalfCheetah-v5"
    collection_workers: tuple[int, ...] = (1, 2, 4)
    collection_window_s: float = 4.0
    collection_start_steps: int = 1000
    timeout_s: float = 300.0  # per child process group

    @classmethod
    def quick(cls) -> "BenchSizes":
        return cls()

    @classmethod
    def full(cls) -> "BenchSizes":
        return cls(learner_rounds=11, learner_updates=50, e2e_steps=5000, e2e_start_steps=1000,
                   transport_publishers=4, transport_batches=3000, weights_messages=200,
                   collection_window_s=10.0, timeout_s=900.0)

    @classmethod
    def tiny(cls) -> "BenchSizes":
        """Seconds, not minutes: the smoke test. Figures from it mean nothing."""
        return cls(learner_rounds=2, learner_updates=3, learner_ks=(1, 2), learner_shapes=("halfcheetah",),
                   hidden=(32, 32), batch_size=32, e2e_steps=150, e2e_start_steps=64,
                   transport_publishers=1, transport_batches=60, weights_messages=5, weights_interval_s=0.01,
                   collection_workers=(4,), collection_window_s=0.5, collection_start_steps=64, timeout_s=120.0)


def target_for(key: str, device: str = "cpu") -> tuple[str, float] | None:
    if key in ("learner_k2_vs_td3", "learner_k2_bf16_vs_td3") and device.startswith("cuda"):
        return ("ge", 0.95)
    return TARGETS.get(key)


def meets(key: str, value: float, device: str = "cpu") -> bool | None:
    t = target_for(key, device)
    if t is None or not math.isfinite(value):
        return None
    return value >= t[1] if t[0] == "ge" else value <= t[1]


# --------------------------------------------------------------------------- environment facts


def versions() -> dict[str, str]:
    """Versions of what the figures depend on."""
    out = {"python": platform.python_version(), "numpy": np.__version__}
    for name, dist in (("torch", "torch"), ("zenoh", "eclipse-zenoh"), ("mujoco", "mujoco"),
                       ("gymnasium", "gymnasium"), ("msgpack", "msgpack")):
        try:
            out[name] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine(device: str, threads: int) -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {"device": device, "cpu": cpu_model(), "cpu_cores": os.cpu_count(),
                            "torch_threads": threads, "platform": platform.platform()}
    if device.startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    try:
        info["load_average_1min"] = round(os.getloadavg()[0], 2)
    except OSError:
        pass
    return info


def resolve_device(device: str) -> str:
    from mam_core.agent import pick_device

    return str(pick_device(device))


def _median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


def _percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q)) if xs else float("nan")


# --------------------------------------------------------------------------- learner


def random_replay(obs_dim: int, act_dim: int, max_action: float, rows: int, device: str, seed: int = 0):
    """A replay buffer full of random transitions (the update rate does not depend on the data)."""
    from mam_core.replay import ReplayBuffer

    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(rows, obs_dim, act_dim, device, seed)
    buf.add_batch(rng.normal(size=(rows, obs_dim)).astype(np.float32),
                  rng.uniform(-max_action, max_action, (rows, act_dim)).astype(np.float32),
                  rng.normal(size=rows).astype(np.float32), rng.normal(size=(rows, obs_dim)).astype(np.float32),
                  rng.random(rows) < 0.01)
    return buf


def reference_td3(obs_dim: int, act_dim: int, max_action: float, hidden: tuple[int, ...], device: str):
    """`benchmarks/td3_reference.TD3` on `device` (it only knows equal hidden widths)."""
    if len(hidden) != 2 or hidden[0] != hidden[1]:
        raise ValueError(f"the reference TD3 has two hidden layers of one width, not {hidden}")
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks.td3_reference import TD3

    import warnings

    warnings.filterwarnings("ignore", message="Converting a tensor with requires_grad=True")  # its float(loss)
    td3 = TD3(obs_dim, act_dim, max_action, hidden=hidden[0])
    for net in (td3.actor, td3.actor_target, td3.critic, td3.critic_target):
        net.to(device)  # same Parameter objects: the optimizers still hold them
    return td3


def learner_contenders(shape: str, sizes: BenchSizes, device: str, seed: int = 0) -> dict[str, Callable[[], Any]]:
    """One update step of each contender, sampling from the same replay buffer."""
    from mam_core.agent import EnvSpec, MultiActorAgent
    from mam_core.config import resolve

    obs_dim, act_dim, max_action = SHAPES[shape]
    buf = random_replay(obs_dim, act_dim, max_action, max(20 * sizes.batch_size, 5000), device, seed)
    td3 = reference_td3(obs_dim, act_dim, max_action, sizes.hidden, device)
    batch = sizes.batch_size

    def td3_step() -> float:
        b = buf.sample(batch)
        return td3.train(b["obs"], b["action"], b["reward"].unsqueeze(1), b["next_obs"], b["not_done"].unsqueeze(1))

    out: dict[str, Callable[[], Any]] = {"td3": td3_step}
    spec = EnvSpec(obs_dim, act_dim, (max_action,) * act_dim)
    for k in sizes.learner_ks:  # one mini-batch per actor (Algorithm 1, the default)
        cfg = resolve("ma-td3", actors=k, hidden=sizes.hidden, batch_size=batch, seed=seed)
        agent = MultiActorAgent(cfg, spec, device)
        out[f"k{k}"] = (lambda a=agent: a.update(buf.sample(batch, a.batch_groups)))
    if 2 in sizes.learner_ks:
        # --shared-batch: one mini-batch for all actors (Eq. 9's target pass then runs on B rows, not K·B)
        cfg = resolve("ma-td3", actors=2, hidden=sizes.hidden, batch_size=batch, seed=seed, shared_batch=True)
        agent = MultiActorAgent(cfg, spec, device)
        out["k2_shared"] = (lambda a=agent: a.update(buf.sample(batch)))
        # the opt-in mixed precision (--precision bf16) against the same fp32 reference
        cfg = resolve("ma-td3", actors=2, hidden=sizes.hidden, batch_size=batch, seed=seed, precision="bf16")
        agent = MultiActorAgent(cfg, spec, device)
        out["k2_bf16"] = (lambda a=agent: a.update(buf.sample(batch, a.batch_groups)))
    return out


def interleaved_rates(steps: dict[str, Callable[[], Any]], rounds: int, per_round: int,
                      warmup: int = 4) -> dict[str, dict[str, list[float]]]:
    """Rates (calls/s by wall clock and by process CPU time) per contender per round.

    The order rotates every round so no contender always follows the same one.
    """
    names = list(steps)
    for name in names:
        for _ in range(warmup):
            steps[name]()
    wall: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    for r in range(rounds):
        order = names[r % len(names):] + names[: r % len(names)]
        for name in order:
            f = steps[name]
            t, c = time.perf_counter(), time.process_time()
            for _ in range(per_round):
                f()
            wall[name].append(per_round / max(time.perf_counter() - t, 1e-9))
            cpu[name].append(per_round / max(time.process_time() - c, 1e-9))
    return {"wall": wall, "cpu": cpu}


def ratio_of_medians_per_round(a: list[float], b: list[float]) -> float:
    """Median over rounds of a[r] / b[r] (same round: same machine conditions)."""
    return _median([x / y for x, y in zip(a, b)])


def bench_learner(sizes: BenchSizes, device: str = "cpu", threads: int = 1, log: Callable[[str], None] = print,
                  seed: int = 0) -> dict[str, Any]:
    """MA-TD3 updates/s at K = sizes.learner_ks against the reference TD3, per env shape."""
    import torch

    torch.set_num_threads(threads)
    out: dict[str, Any] = {}
    for shape in sizes.learner_shapes:
        log(f"learner: {shape} shapes, K={list(sizes.learner_ks)} vs reference TD3 "
            f"({sizes.learner_rounds} rounds x {sizes.learner_updates} updates)")
        rates = interleaved_rates(learner_contenders(shape, sizes, device, seed), sizes.learner_rounds,
                                  sizes.learner_updates)
        wall, cpu = rates["wall"], rates["cpu"]
        out[f"learner_{shape}_td3_updates_per_s"] = _median(wall["td3"])
        for k in sizes.learner_ks:
            out[f"learner_{shape}_k{k}_updates_per_s"] = _median(wall[f"k{k}"])
            out[f"learner_{shape}_k{k}_vs_td3"] = ratio_of_medians_per_round(wall[f"k{k}"], wall["td3"])
            out[f"learner_{shape}_k{k}_vs_td3_cpu_time"] = ratio_of_medians_per_round(cpu[f"k{k}"], cpu["td3"])
        if "k2_shared" in wall:
            out[f"learner_{shape}_k2_shared_updates_per_s"] = _median(wall["k2_shared"])
            out[f"learner_{shape}_k2_shared_vs_td3"] = ratio_of_medians_per_round(wall["k2_shared"], wall["td3"])
            out[f"learner_{shape}_k2_per_actor_vs_shared"] = ratio_of_medians_per_round(wall["k2"], wall["k2_shared"])
        if "k2_bf16" in wall:
            out[f"learner_{shape}_k2_bf16_updates_per_s"] = _median(wall["k2_bf16"])
            out[f"learner_{shape}_k2_bf16_vs_td3"] = ratio_of_medians_per_round(wall["k2_bf16"], wall["td3"])
    first = sizes.learner_shapes[0]
    if 2 in sizes.learner_ks:
        out["learner_k2_vs_td3"] = out[f"learner_{first}_k2_vs_td3"]
        out["learner_k2_vs_td3_shape"] = first
        out["learner_k2_bf16_vs_td3"] = out[f"learner_{first}_k2_bf16_vs_td3"]
    return out


# --------------------------------------------------------------------------- end to end


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


def _child_env(**extra: str) -> dict[str, str]:
    return dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="160", **extra)


def _stop(procs: list[subprocess.Popen], grace: float = 10.0) -> None:
    """SIGTERM the processes this bench started, then SIGKILL what is left after `grace`."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace
    for p in procs:
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def _watch_learner(endpoint: str, run: str, until: Callable[[Any, float], bool], timeout: float,
                   procs: list[subprocess.Popen]) -> None:
    """Follow the run's learner stats as a client until `until(stats, t_received)` is true."""
    from services import bus, keys
    from services.codec import LearnerStats, MessageError

    conf = bus.make_config(connect=[endpoint])
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
        env = _child_env(**({options.ALLOW_SLOW_BF16: "1"} if precision == "bf16" else {}))
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    marks: dict[str, float] = {}
    try:
        config = run_dir / "config.json"
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

        _watch_learner(endpoint, run, until, sizes.timeout_s, [proc])
        proc.wait(timeout=sizes.timeout_s)
    finally:
        _stop([proc])
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
        "bf16_native_cpu": options.native_bf16_cpu(),
        "e2e_env": sizes.e2e_env, "e2e_steps": n, "e2e_start_steps": start,
        "e2e_single_process_s": single,
        "e2e_mam_run_to_done_s": dist["to_done_s"], "e2e_mam_run_wall_s": dist["wall_s"],
        "e2e_mam_run_startup_s": dist["startup_s"],
        "e2e_vs_single_process": dist["to_done_s"] / single,
        "e2e_wall_vs_single_process": dist["wall_s"] / single,
        "e2e_after_startup_vs_single_process": (dist["to_done_s"] - dist["startup_s"]) / single,
    }


# --------------------------------------------------------------------------- transport


def _python_c(code: str, *args: str) -> list[str]:
    return [sys.executable, "-c", code, *args]


def publisher_process(argv: list[str] | None = None) -> None:
    """Worker-like publisher (a child process): `batches` TransitionBatch messages of `rows`
    HalfCheetah-shaped rows, encoded one by one and put RELIABLE + BLOCK as fast as allowed."""
    from services import bus, keys
    from services.codec import TransitionBatch

    endpoint, run, wid, batches, rows, obs_dim, act_dim = (argv or sys.argv[1:])[:7]
    batches, rows, obs_dim, act_dim = int(batches), int(rows), int(obs_dim), int(act_dim)
    rng = np.random.default_rng(abs(hash(wid)) % 2**32)
    variants = [(rng.normal(size=(rows, obs_dim)).astype(np.float32),
                 rng.uniform(-1, 1, (rows, act_dim)).astype(np.float32),
                 rng.normal(size=rows).astype(np.float32),
                 rng.normal(size=(rows, obs_dim)).astype(np.float32),
                 rng.random(rows) < 0.01) for _ in range(8)]
    incarnation = uuid.uuid4().hex[:12]
    with bus.session_scope(bus.make_config(connect=[endpoint]), retry_for=30.0) as session:
        pub = bus.declare_reliable_publisher(session, keys.transitions(run, wid))
        deadline = time.monotonic() + 30.0
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        for seq in range(batches):
            o, a, r, o2, d = variants[seq % len(variants)]
            pub.put(TransitionBatch(wid, incarnation, seq, 0, -1, o, a, r, o2, d).to_bytes())
        time.sleep(1.0)  # the last puts before close can be lost (ZENOH.md): let them drain
        pub.undeclare()


def bench_transport(sizes: BenchSizes, log: Callable[[str], None] = print,
                    obs_dim: int = 17, act_dim: int = 6) -> dict[str, Any]:
    """Transitions/s into a learner-like consumer from M publisher processes over loopback."""
    from mam_core.replay import ReplayBuffer
    from services import bus, keys
    from services.codec import TransitionBatch, TransitionSpec

    m, per, rows = sizes.transport_publishers, sizes.transport_batches, sizes.transport_rows
    log(f"transport: {m} publisher process(es) x {per} messages of {rows} transitions -> Inbox, decode, replay")
    run = f"bench-tx-{uuid.uuid4().hex[:8]}"
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    spec = TransitionSpec(obs_dim, act_dim, 1, max_rows=4096, max_action=1.0)
    expected = m * per * rows
    buffer = ReplayBuffer(expected, obs_dim, act_dim)
    tracker = bus.SequenceTracker()
    procs: list[subprocess.Popen] = []
    code = "import sys; from services.bench import publisher_process; publisher_process(sys.argv[1:])"
    received = payload_bytes = messages = 0
    t_first = t_last = 0.0
    rows_first = 0
    with bus.session_scope(bus.make_config(listen=[endpoint])) as session:
        inbox = bus.Inbox(maxsize=8192).subscribe(session, keys.transitions_all(run))
        try:
            for i in range(m):
                procs.append(subprocess.Popen(
                    _python_c(code, endpoint, run, f"p{i}", str(per), str(rows), str(obs_dim), str(act_dim)),
                    cwd=ROOT, env=_child_env(), stdin=subprocess.DEVNULL, start_new_session=True))
            idle_deadline = time.monotonic() + sizes.timeout_s
            while received < expected and time.monotonic() < idle_deadline:
                items = inbox.drain(256)
                if not items:
                    item = inbox.get(timeout=0.5)
                    if item is None:
                        if any(p.poll() not in (None, 0) for p in procs):
                            raise RuntimeError("a publisher process failed")
                        continue
                    items = [item]
                for item in items:
                    batch = TransitionBatch.from_bytes(item.payload, spec)
                    tracker.observe(batch.worker, batch.incarnation, batch.batch_seq)
                    buffer.add_batch(batch.obs, batch.action, batch.reward, batch.next_obs, batch.terminated,
                                     actor=batch.actor, version=batch.version)
                    if messages == 0:
                        t_first, rows_first = time.perf_counter(), batch.rows
                    received += batch.rows
                    payload_bytes += len(item.payload)
                    messages += 1
                t_last = time.perf_counter()
                idle_deadline = time.monotonic() + 10.0
        finally:
            dropped = inbox.dropped
            inbox.close()
            _stop(procs)
    if received == 0:
        raise RuntimeError("no transition arrived")
    span = max(t_last - t_first, 1e-9)
    return {
        "transport_publishers": m, "transport_rows_per_message": rows,
        "transport_transitions_per_s": (received - rows_first) / span if messages > 1 else float("nan"),
        "transport_messages_per_s": (messages - 1) / span if messages > 1 else float("nan"),
        "transport_received": received, "transport_expected": expected,
        "transport_lost": tracker.lost + (expected - received), "transport_inbox_dropped": dropped,
        "transport_bytes_per_transition": payload_bytes / received,
    }


def weights_subscriber_process(argv: list[str] | None = None) -> None:
    """Worker-like weights subscriber (a child process): on every new weights sample, decode,
    validate against the actor's shapes and load it; print the latencies as JSON."""
    import torch

    from mam_core.ensemble import ActorEnsemble
    from services import bus, keys
    from services.codec import Weights

    endpoint, run, obs_dim, act_dim, hidden, count, warmup = (argv or sys.argv[1:])[:7]
    obs_dim, act_dim, count, warmup = int(obs_dim), int(act_dim), int(count), int(warmup)
    hidden_t = tuple(int(h) for h in hidden.split(","))
    torch.set_num_threads(1)
    actors = ActorEnsemble(1, obs_dim, act_dim, hidden_t, 1.0).requires_grad_(False)
    shapes = actors.net.member_shapes()
    latencies: list[float] = []
    with bus.session_scope(bus.make_config(connect=[endpoint]), retry_for=30.0) as session:
        latest = bus.Latest.subscribe(session, keys.weights_all(run))
        token = bus.declare_alive(session, run, "worker", "latency")
        deadline = time.monotonic() + 120.0
        last_version = 0
        while last_version < warmup + count and time.monotonic() < deadline:
            if not latest.wait_fresh(timeout=0.5):
                continue
            for item in latest.fresh().values():
                w = Weights.from_bytes(item.payload, shapes, 1)
                actors.net.load_member(0, w.params)
                done = time.perf_counter()  # CLOCK_MONOTONIC: one clock for every process on the host
                if w.version > last_version and item.attachment is not None:
                    (sent,) = struct.unpack("<d", item.attachment)
                    if w.version > warmup:  # the first broadcasts also set up routes and caches
                        latencies.append((done - sent) * 1e3)
                    last_version = w.version
        token.undeclare()
        latest.close()
    print(json.dumps({"latencies_ms": latencies}), flush=True)


def bench_weights(sizes: BenchSizes, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Latency of one weights broadcast: learner-side `actor_params` + encode + put, to decoded,
    validated and loaded in a worker-like subscriber process. Per actor size."""
    import torch

    from mam_core.ensemble import ActorEnsemble
    from services import bus, keys
    from services.codec import Weights

    out: dict[str, Any] = {}
    code = "import sys; from services.bench import weights_subscriber_process; weights_subscriber_process(sys.argv[1:])"
    for shape in ("halfcheetah", "humanoid"):
        obs_dim, act_dim, max_action = SHAPES[shape]
        hidden = sizes.weights_hidden
        log(f"weights: {shape} actor ({obs_dim}->{'x'.join(map(str, hidden))}->{act_dim}), "
            f"{sizes.weights_messages} broadcasts")
        run = f"bench-w-{uuid.uuid4().hex[:8]}"
        endpoint = bus.loopback_endpoint(bus.free_tcp_port())
        torch.set_num_threads(1)
        actor = ActorEnsemble(1, obs_dim, act_dim, hidden, max_action).requires_grad_(False)
        encode_ms: list[float] = []
        size = 0
        with bus.session_scope(bus.make_config(listen=[endpoint])) as session:
            pub = bus.declare_latest_publisher(session, keys.weights(run, 0))
            alive = bus.watch_alive(session, run, "worker")
            proc = subprocess.Popen(_python_c(code, endpoint, run, str(obs_dim), str(act_dim),
                                              ",".join(map(str, hidden)), str(sizes.weights_messages),
                                              str(WEIGHTS_WARMUP)),
                                    cwd=ROOT, env=_child_env(), stdout=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                    start_new_session=True)
            try:
                if not alive.wait_for(lambda ids: "latency" in ids, timeout=60.0):
                    raise RuntimeError("the weights subscriber did not come up")
                time.sleep(0.2)
                for version in range(1, WEIGHTS_WARMUP + sizes.weights_messages + 1):
                    t0 = time.perf_counter()
                    params = actor.net.member_state(0)  # the learner's actor_params(k)
                    msg = Weights(0, version, params, obs_dim, act_dim, max_action, hidden)
                    payload = msg.to_bytes("bench", version)
                    if version > WEIGHTS_WARMUP:
                        encode_ms.append((time.perf_counter() - t0) * 1e3)
                    size = len(payload)
                    pub.put(payload, attachment=struct.pack("<d", t0))
                    time.sleep(sizes.weights_interval_s)
                stdout, _ = proc.communicate(timeout=60.0)
            finally:
                alive.close()
                _stop([proc])
        lat = json.loads(stdout.decode().strip().splitlines()[-1])["latencies_ms"]
        if not lat:
            raise RuntimeError(f"no weights latency measured for {shape}")
        out[f"weights_{shape}_p50_ms"] = _percentile(lat, 50)
        out[f"weights_{shape}_p99_ms"] = _percentile(lat, 99)
        out[f"weights_{shape}_encode_ms"] = _median(encode_ms)
        out[f"weights_{shape}_bytes"] = size
        out[f"weights_{shape}_samples"] = len(lat)
    out["weights_latency_p50_ms"] = max(out["weights_halfcheetah_p50_ms"], out["weights_humanoid_p50_ms"])
    out["weights_latency_p99_ms"] = max(out["weights_halfcheetah_p99_ms"], out["weights_humanoid_p99_ms"])
    return out


# --------------------------------------------------------------------------- collection scaling


def collection_rate(workers: int, sizes: BenchSizes, work_dir: Path, seed: int = 0) -> float:
    """Env steps/s of `workers` real worker processes feeding a real learner that never pauses them."""
    from services import bus

    run = f"bench-col-{uuid.uuid4().hex[:8]}"
    run_dir = work_dir / run
    run_dir.mkdir(parents=True, exist_ok=True)
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    # The rate limiter's band above the budget: credit never runs out, the learner only ingests
    # (and trains ~1 update per 1000 transitions).
    toml = run_dir / "bench.toml"
    toml.write_text("band = 1000000000\n")
    learner = [sys.executable, "-m", "services.learner", "--env", sizes.collection_env, "--algo", "td3",
               "--steps", "1000000000", "--utd", "0.001", "--start-steps", str(sizes.collection_start_steps),
               "--workers", str(workers), "--batch-size", str(sizes.batch_size),
               "--hidden", ",".join(map(str, sizes.hidden)), "--seed", str(seed), "--device", "cpu",
               "--config", str(toml), "--run", run, "--listen", endpoint, "--run-dir", str(run_dir)]
    procs: list[subprocess.Popen] = []
    logs = []
    try:
        for i, cmd in enumerate([learner] + [
                [sys.executable, "-m", "services.worker", "--run", run, "--connect", endpoint, "--id", f"w{j}",
                 "--slot", str(j)] for j in range(workers)]):
            out = open(run_dir / f"proc{i}.log", "wb")
            logs.append(out)
            procs.append(subprocess.Popen(cmd, cwd=ROOT, env=_child_env(), stdout=out, stderr=subprocess.STDOUT,
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
        _stop(procs)
        for f in logs:
            f.close()
    (t0, s0), (t1, s1) = marks[0], marks[-1]
    return (s1 - s0) / max(t1 - t0, 1e-9)


def bench_collection(sizes: BenchSizes, log: Callable[[str], None] = print,
                     work_dir: Path | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"collection_env": sizes.collection_env,
                           "collection_setup": "real mam-learner (--utd 0.001, band above budget) + M mam-worker"}
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


# --------------------------------------------------------------------------- profiles


def profile_learner_step(shape: str = "halfcheetah", k: int = 2, updates: int = 40, device: str = "cpu",
                         threads: int = 1, sizes: BenchSizes | None = None) -> dict[str, float]:
    """Where one MA-TD3 update goes (torch.profiler, ms per update by kind of op)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    torch.set_num_threads(threads)
    sizes = replace(sizes or BenchSizes(), learner_ks=(k,))
    step = learner_contenders(shape, sizes, device)[f"k{k}"]
    for _ in range(6):
        step()
    t0 = time.perf_counter()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(updates):
            step()
    wall = (time.perf_counter() - t0) / updates * 1e3
    kinds = {"matmul": ("aten::bmm", "aten::baddbmm", "aten::mm", "aten::addmm", "aten::matmul"),
             "optimizer (fused Adam)": ("aten::_fused_adam_",),
             "soft target update": ("aten::lerp_", "aten::_foreach_lerp_"),
             "relu and its backward": ("aten::relu_", "aten::relu", "aten::clamp_min_", "aten::clamp_min",
                                       "aten::threshold_backward"),
             "copies, cat, sums": ("aten::copy_", "aten::cat", "aten::sum", "aten::clone", "aten::index_select"),
             }
    out = {name: 0.0 for name in kinds}
    other = 0.0
    for ev in prof.key_averages():
        ms = ev.self_cpu_time_total / 1e3 / updates
        for name, ops in kinds.items():
            if ev.key in ops:
                out[name] += ms
                break
        else:
            if ev.key.startswith("aten::") or ev.key.startswith("Optimizer"):
                other += ms
    out["other aten ops"] = other
    out["python and dispatch (rest)"] = max(wall - sum(out.values()), 0.0)
    out["total (profiled)"] = wall
    return out


def profile_worker_step(env_id: str = "HalfCheetah-v5", steps: int = 2000, hidden: tuple[int, ...] = (256, 256),
                        send_batch: int = 32) -> dict[str, float]:
    """Where one worker step goes: env.step, the 1-row policy forward (as the worker runs it,
    numpy `NumpyActors`, and as it ran before, a torch forward), encoding and publishing (µs per
    transition).
    Publishing goes to a subscriber of the same session (no network). The two policy paths
    alternate by episode chunk so both see the same cache state after MuJoCo's step."""
    import gymnasium as gym
    import torch

    import mam_core.envs  # noqa: F401
    from mam_core.ensemble import ActorEnsemble
    from mam_core.policy import EnvSpec, NumpyActors
    from services import bus
    from services.codec import TransitionBatch

    torch.set_num_threads(1)
    env = gym.make(env_id)
    spec = EnvSpec.from_env(env)
    max_a = np.asarray(spec.max_action, np.float32)
    actors = ActorEnsemble(1, spec.obs_dim, spec.act_dim, hidden, max_a).requires_grad_(False)
    members = torch.tensor([0])
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    numpy_actors = NumpyActors(1, spec, hidden)
    numpy_actors.load_member(0, actors.net.member_state(0))
    numpy_policy = numpy_actors.policy(0)
    t_env = t_pol = t_np = t_enc = t_pub = 0.0
    n_torch = n_np = 0
    buf_o = np.empty((send_batch, spec.obs_dim), np.float32)
    buf_a = np.empty((send_batch, spec.act_dim), np.float32)
    buf_r = np.empty(send_batch, np.float32)
    buf_o2 = np.empty((send_batch, spec.obs_dim), np.float32)
    buf_d = np.empty(send_batch, np.bool_)
    with bus.session_scope(bus.make_config()) as session:
        inbox = bus.Inbox(maxsize=1 << 16).subscribe(session, "mam/bench-profile/transitions/*")
        pub = bus.declare_reliable_publisher(session, "mam/bench-profile/transitions/w0")
        n = 0
        for t in range(steps):
            use_torch = (t // 100) % 2 == 0
            t0 = time.perf_counter()
            if use_torch:  # services.worker's forward before it dropped torch
                with torch.inference_mode():
                    a = actors(torch.from_numpy(np.asarray(obs, np.float32)).view(1, -1), members=members)[0, 0].numpy()
            else:
                a = numpy_policy(obs)
            t1 = time.perf_counter()
            a = np.clip(a + rng.normal(0, 0.1, spec.act_dim).astype(np.float32) * max_a, -max_a, max_a)
            next_obs, r, term, trunc, _ = env.step(a)
            t2 = time.perf_counter()
            buf_o[n], buf_a[n], buf_r[n], buf_o2[n], buf_d[n] = obs, a, r, next_obs, term
            n += 1
            obs = env.reset()[0] if term or trunc else next_obs
            if use_torch:
                t_pol, n_torch = t_pol + t1 - t0, n_torch + 1
            else:
                t_np, n_np = t_np + t1 - t0, n_np + 1
            t_env += t2 - t1
            if n == send_batch:
                t3 = time.perf_counter()
                payload = TransitionBatch("w0", "profile", t // send_batch, 0, 0, buf_o, buf_a, buf_r, buf_o2,
                                          buf_d).to_bytes()
                t4 = time.perf_counter()
                pub.put(payload)
                t5 = time.perf_counter()
                t_enc += t4 - t3
                t_pub += t5 - t4
                n = 0
                inbox.drain()
        inbox.close()
    env.close()
    us = 1e6 / steps
    torch_us, numpy_us = t_pol * 1e6 / max(n_torch, 1), t_np * 1e6 / max(n_np, 1)
    rest = (t_env + t_enc + t_pub) * us
    return {"env.step (+ noise, clip)": t_env * us, "policy forward, torch (the worker before numpy)": torch_us,
            "policy forward, numpy (NumpyActors)": numpy_us, "encode (per transition)": t_enc * us,
            "publish (per transition)": t_pub * us, "total with the torch forward": rest + torch_us,
            "total with the numpy forward": rest + numpy_us}


# --------------------------------------------------------------------------- the whole bench


PIECES = ("learner", "e2e", "transport", "weights", "collection")
EXTRA_PIECES = ("replay",)  # only when asked for: --only replay


def bench_replay(rows: int = 1_000_000, obs_dim: int = 17, act_dim: int = 6, increment: int = 20_000,
                 log: Callable[[str], None] = print, work_dir: Path | None = None) -> dict[str, Any]:
    """Checkpoint time and disk size of a full replay buffer (default: 1M HalfCheetah rows).

    Times, on the same random buffer: the chunk log's first checkpoint (every row new), one
    incremental checkpoint (`increment` new rows, the default `checkpoint_rows`), restoring the
    whole buffer from its chunks, and for comparison the previous format (the whole buffer in
    the torch checkpoint, rewritten every time). The page cache is warm: these are the costs of
    serialising and writing, not of a cold disk.
    """
    import torch

    from mam_core.replay import ReplayBuffer, ReplayLog

    def fill(buf: ReplayBuffer, n: int, rng: np.random.Generator) -> None:
        for start in range(0, n, 100_000):
            k = min(100_000, n - start)
            buf.add_batch(rng.standard_normal((k, obs_dim), np.float32), rng.uniform(-1, 1, (k, act_dim)).astype(np.float32),
                          rng.standard_normal(k).astype(np.float32), rng.standard_normal((k, obs_dim), np.float32),
                          rng.random(k) < 0.001, actor=start % 2, version=start)

    def du(path: Path) -> int:
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())

    rng = np.random.default_rng(0)
    log(f"replay: {rows:,} rows (obs {obs_dim}, act {act_dim}) as chunks, +{increment:,} rows, restore; "
        f"and the whole buffer in the torch checkpoint")
    with tempfile.TemporaryDirectory(prefix="mam-bench-replay-") as tmp:
        work = Path(work_dir or tmp)
        buf = ReplayBuffer(rows, obs_dim, act_dim)
        fill(buf, rows, rng)
        chunks = ReplayLog(work / "replay")
        t0 = time.perf_counter()
        manifest = chunks.append(buf)
        full_s = time.perf_counter() - t0
        full_bytes = du(work / "replay")
        fill(buf, increment, rng)  # the ring wraps: the oldest rows leave the manifest
        t0 = time.perf_counter()
        manifest = chunks.append(buf)
        chunks.prune()
        inc_s = time.perf_counter() - t0
        disk_bytes = du(work / "replay")
        again = ReplayBuffer(rows, obs_dim, act_dim)
        t0 = time.perf_counter()
        ReplayLog(work / "replay").restore(again, manifest, buf.inserted)
        restore_s = time.perf_counter() - t0
        assert np.array_equal(again.obs, buf.obs) and np.array_equal(again.version, buf.version)
        t0 = time.perf_counter()
        torch.save({"replay": buf.state_dict()}, work / "old.pt")
        old_s = time.perf_counter() - t0
        old_bytes = (work / "old.pt").stat().st_size
        t0 = time.perf_counter()
        ReplayBuffer(rows, obs_dim, act_dim).load_state_dict(torch.load(work / "old.pt", weights_only=True)["replay"])
        old_restore_s = time.perf_counter() - t0
    row_bytes = 4 * (2 * obs_dim + act_dim + 2) + 2 + 4
    return {"replay_rows": rows, "replay_row_bytes": row_bytes, "replay_increment_rows": increment,
            "replay_full_checkpoint_s": full_s, "replay_full_checkpoint_bytes": full_bytes,
            "replay_incremental_checkpoint_s": inc_s, "replay_disk_bytes_after_wrap": disk_bytes,
            "replay_restore_s": restore_s, "replay_torch_checkpoint_s": old_s,
            "replay_torch_checkpoint_bytes": old_bytes, "replay_torch_restore_s": old_restore_s}


def run_bench(sizes: BenchSizes, pieces: tuple[str, ...] = PIECES, device: str = "auto", threads: int = 1,
              log: Callable[[str], None] = print, profile: bool = False) -> dict[str, Any]:
    """Every selected piece; one flat dict (the `--json` object)."""
    unknown = set(pieces) - set(PIECES) - set(EXTRA_PIECES)
    if unknown:
        raise ValueError(f"unknown bench piece(s) {sorted(unknown)}; choose from {PIECES + EXTRA_PIECES}")
    device = resolve_device(device)
    started = time.perf_counter()
    result: dict[str, Any] = {"device": device, "torch_threads": threads, "versions": versions(),
                              "machine": machine(device, threads), "sizes": asdict(sizes)}
    if "learner" in pieces:
        result.update(bench_learner(sizes, device, threads, log))
    if "e2e" in pieces:
        result.update(bench_e2e(sizes, device, threads, log))
    if "transport" in pieces:
        result.update(bench_transport(sizes, log))
    if "weights" in pieces:
        result.update(bench_weights(sizes, log))
    if "collection" in pieces:
        result.update(bench_collection(sizes, log))
    if "replay" in pieces:
        result.update(bench_replay(log=log))
    if profile:
        log("profiles: one learner update step, one worker step")
        result["profile_learner_ms"] = profile_learner_step(device=device, threads=threads, sizes=sizes)
        result["profile_worker_us"] = profile_worker_step(sizes.collection_env, hidden=sizes.hidden)
    result["bench_seconds"] = time.perf_counter() - started
    return result


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        if abs(v) >= 1000:
            return f"{v:,.0f}"
        return f"{v:.3g}" if abs(v) < 10 else f"{v:.1f}"
    return str(v)


ROWS: tuple[tuple[str, str], ...] = (
    ("learner_k2_vs_td3", "MA-TD3 K=2 ÷ TD3 updates/s (HalfCheetah shapes, a mini-batch per actor)"),
    ("learner_halfcheetah_k2_shared_vs_td3", "  same, --shared-batch ÷ TD3"),
    ("learner_halfcheetah_k2_per_actor_vs_shared", "  a mini-batch per actor ÷ --shared-batch"),
    ("learner_k2_bf16_vs_td3", "same, MA-TD3 with --precision bf16 ÷ TD3 (fp32)"),
    ("learner_humanoid_k2_bf16_vs_td3", "  bf16, Humanoid"),
    ("learner_halfcheetah_k1_vs_td3", "K=1 ÷ TD3, HalfCheetah"),
    ("learner_halfcheetah_k3_vs_td3", "K=3 ÷ TD3, HalfCheetah"),
    ("learner_humanoid_k1_vs_td3", "K=1 ÷ TD3, Humanoid"),
    ("learner_humanoid_k2_vs_td3", "K=2 ÷ TD3, Humanoid"),
    ("learner_humanoid_k3_vs_td3", "K=3 ÷ TD3, Humanoid"),
    ("learner_halfcheetah_td3_updates_per_s", "TD3 reference updates/s, HalfCheetah"),
    ("learner_halfcheetah_k2_updates_per_s", "MA-TD3 K=2 updates/s, HalfCheetah"),
    ("learner_humanoid_td3_updates_per_s", "TD3 reference updates/s, Humanoid"),
    ("learner_humanoid_k2_updates_per_s", "MA-TD3 K=2 updates/s, Humanoid"),
    ("e2e_vs_single_process", "mam run to N ÷ single process (time)"),
    ("e2e_after_startup_vs_single_process", "  same, without process start-up"),
    ("e2e_bf16_vs_single_process", "  same, mam run --precision bf16 ÷ single process (fp32)"),
    ("e2e_single_process_s", "single-process TD3 loop, s"),
    ("e2e_mam_run_to_done_s", "mam run: start to learner done, s"),
    ("e2e_mam_run_startup_s", "mam run: start to first transition, s"),
    ("transport_transitions_per_s", "transitions/s into the learner's replay"),
    ("transport_bytes_per_transition", "bytes per transition (msgpack payload)"),
    ("transport_lost", "transitions lost"),
    ("weights_latency_p99_ms", "weights broadcast p99, ms (worst size)"),
    ("weights_halfcheetah_p50_ms", "weights p50, HalfCheetah actor, ms"),
    ("weights_halfcheetah_p99_ms", "weights p99, HalfCheetah actor, ms"),
    ("weights_humanoid_p50_ms", "weights p50, Humanoid actor, ms"),
    ("weights_humanoid_p99_ms", "weights p99, Humanoid actor, ms"),
    ("collection_steps_per_s_m1", "env steps/s, 1 worker"),
    ("collection_steps_per_s_m2", "env steps/s, 2 workers"),
    ("collection_steps_per_s_m4", "env steps/s, 4 workers"),
)


def print_report(result: dict[str, Any], console: Any = None) -> None:
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    device = result.get("device", "cpu")
    m = result.get("machine", {})
    v = result.get("versions", {})
    table = Table(title=f"mam bench — {device}, {m.get('cpu', '?')}, {m.get('cpu_cores', '?')} cores, "
                        f"torch threads {result.get('torch_threads')}")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("target", justify="right")
    table.add_column("", justify="center")
    for key, label in ROWS:
        if key not in result:
            continue
        t = target_for(key, device)
        ok = meets(key, result[key], device)
        mark = "" if ok is None else ("[green]met[/]" if ok else "[red]not met[/]")
        table.add_row(label, _fmt(result[key]), "" if t is None else ("≥ " if t[0] == "ge" else "≤ ") + _fmt(t[1]),
                      mark)
    console.print(table)
    for key, unit in (("profile_learner_ms", "ms per update"), ("profile_worker_us", "µs per transition")):
        if key in result:
            prof = Table(title=f"{key.replace('_', ' ')} ({unit})")
            prof.add_column("part")
            prof.add_column(unit, justify="right")
            for part, val in result[key].items():
                prof.add_row(part, _fmt(val))
            console.print(prof)
    console.print("versions: " + ", ".join(f"{k} {val}" for k, val in v.items()))


app = typer.Typer(add_completion=False, help=__doc__)


@app.command()
def bench_command(
    full: bool = typer.Option(False, "--full/--quick",
                              help="--quick (default): a few minutes on 2 cores; --full: longer, steadier figures"),
    json_out: bool = typer.Option(False, "--json", help="also print all figures as one JSON object on the last line"),
    only: str = typer.Option(",".join(PIECES), "--only", help=f"comma-separated pieces among {','.join(PIECES + EXTRA_PIECES)} "
                                                            "(replay: checkpoint of a 1M-row buffer, only when named)"),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda: the learner's device"),
    threads: int = typer.Option(1, "--threads", help="torch threads of the learner bench (the learner's default: 1)"),
    profile: bool = typer.Option(False, "--profile", help="also profile one learner update and one worker step"),
    tiny: bool = typer.Option(False, "--tiny", hidden=True, help="smoke-test sizes: seconds, meaningless figures"),
    out: Path = typer.Option(None, "--out", help="also write the JSON object to this file"),
) -> None:
    """Learner, end-to-end, transport and collection figures, each against its reference and target."""
    import logging

    from rich.console import Console

    logging.basicConfig(level=logging.WARNING)
    sizes = BenchSizes.tiny() if tiny else BenchSizes.full() if full else BenchSizes.quick()
    pieces = tuple(p.strip() for p in only.split(",") if p.strip())
    console = Console(stderr=json_out)
    try:
        result = run_bench(sizes, pieces, device, threads, log=lambda s: console.print(f"[dim]{s}[/]"),
                           profile=profile)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    print_report(result, console)
    text = json.dumps(result, allow_nan=True, default=str)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    if json_out:
        print(text, flush=True)


def cli() -> None:
    app()


if __name__ == "__main__":
    cli()
