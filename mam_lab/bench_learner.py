"""`mam bench` learner pieces: MA-TD3 updates/s against the reference TD3 and SAC / MA-SAC
against a plain SAC on the same replay data (interleaved rounds), a profile of one update step,
and the replay buffer's checkpoint costs. torch is imported by each function, not by the module."""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mam_lab.bench_sizes import ROOT, SHAPES, BenchSizes, median


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
    import warnings

    from benchmarks.td3_reference import TD3

    warnings.filterwarnings("ignore", message="Converting a tensor with requires_grad=True")  # its float(loss)
    td3 = TD3(obs_dim, act_dim, max_action, hidden=hidden[0])
    for net in (td3.actor, td3.actor_target, td3.critic, td3.critic_target):
        net.to(device)  # same Parameter objects: the optimizers still hold them
    return td3


def reference_sac(obs_dim: int, act_dim: int, max_action: float, hidden: tuple[int, ...], device: str, seed: int = 0):
    """`benchmarks/sac_reference.SAC` on `device` (two hidden layers of one width), drawing its
    Gaussian noise from a generator on that device."""
    import torch

    if len(hidden) != 2 or hidden[0] != hidden[1]:
        raise ValueError(f"the reference SAC has two hidden layers of one width, not {hidden}")
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks.sac_reference import SAC

    sac = SAC(obs_dim, act_dim, max_action, hidden=hidden[0],
              generator=torch.Generator(device=device).manual_seed(seed + 1))
    for net in (sac.actor, sac.critic, sac.critic_target):
        net.to(device)  # same Parameter objects: the optimizers still hold them
    with torch.no_grad():  # log α moves in place: its optimizer keeps holding it
        sac.log_alpha.data = sac.log_alpha.data.to(device)
    sac.noise = lambda rows: torch.randn((rows, act_dim), generator=sac.generator, device=device)
    return sac


def sac_contenders(shape: str, sizes: BenchSizes, device: str, seed: int = 0) -> dict[str, Callable[[], Any]]:
    """One update step of the plain SAC ("sac"), mam's SAC (K = 1, "sac_k1") and MA-SAC K = 2 (a
    mini-batch per actor, "sac_k2"), sampling from the same replay buffer."""
    from mam_core.agent import EnvSpec, MultiActorAgent
    from mam_core.config import resolve

    obs_dim, act_dim, max_action = SHAPES[shape]
    buf = random_replay(obs_dim, act_dim, max_action, max(20 * sizes.batch_size, 5000), device, seed)
    sac = reference_sac(obs_dim, act_dim, max_action, sizes.hidden, device, seed)
    batch = sizes.batch_size

    def sac_step() -> float:
        b = buf.sample(batch)
        return sac.train(b["obs"], b["action"], b["reward"].unsqueeze(1), b["next_obs"], b["not_done"].unsqueeze(1))

    out: dict[str, Callable[[], Any]] = {"sac": sac_step}
    spec = EnvSpec(obs_dim, act_dim, (max_action,) * act_dim)
    for name, algo, k in (("sac_k1", "sac", 1), ("sac_k2", "ma-sac", 2)):
        agent = MultiActorAgent(resolve(algo, actors=k, hidden=sizes.hidden, batch_size=batch, seed=seed), spec, device)
        out[name] = _update_step(agent, buf, batch)
    return out


def _update_step(agent: Any, buf: Any, batch: int) -> Callable[[], Any]:
    """One `agent.update` on a mini-batch drawn as the learner draws it (`agent.sampler`: on a
    GPU, indices staged for the CUDA graphs)."""
    sample = agent.sampler(buf, batch)
    return lambda: agent.update(sample())


def bench_sac(sizes: BenchSizes, device: str, log: Callable[[str], None], seed: int = 0,
              sync: Callable[[], Any] | None = None) -> dict[str, Any]:
    """SAC K = 1 and MA-SAC K = 2 against the plain SAC, per env shape, interleaved rounds:
    `learner_<shape>_sac_updates_per_s` (the plain SAC), `learner_<shape>_sac_k<K>_updates_per_s`
    and `learner_<shape>_sac_k<K>_vs_sac` (median over rounds of the within-round ratio)."""
    out: dict[str, Any] = {}
    for shape in sizes.learner_shapes:
        steps = sac_contenders(shape, sizes, device, seed)
        log(f"learner: {shape} shapes, {', '.join(steps)} ({sizes.learner_rounds} rounds x "
            f"{sizes.learner_updates} updates, interleaved)")
        wall = interleaved_rates(steps, sizes.learner_rounds, sizes.learner_updates, sync=sync)["wall"]
        out[f"learner_{shape}_sac_updates_per_s"] = median(wall["sac"])
        for name in ("sac_k1", "sac_k2"):
            out[f"learner_{shape}_{name}_updates_per_s"] = median(wall[name])
            out[f"learner_{shape}_{name}_vs_sac"] = ratio_of_medians_per_round(wall[name], wall["sac"])
    first = sizes.learner_shapes[0]
    out["learner_sac_k1_vs_sac"] = out[f"learner_{first}_sac_k1_vs_sac"]
    out["learner_sac_k2_vs_sac"] = out[f"learner_{first}_sac_k2_vs_sac"]
    return out


VARIANTS = ("default", "all")  # which MA-TD3 variants the learner bench times beside the reference


def variant_names(ks: tuple[int, ...], variants: str = "default") -> list[str]:
    """Contender names besides "td3": `k{K}` (a mini-batch per actor, fp32) for every K, then
    `default`: `k2_shared` and `k2_bf16`; `all`: for every K a `_shared` (K > 1) and a `_bf16`
    of each batch mode (`k{K}_bf16`, `k{K}_shared_bf16`)."""
    if variants not in VARIANTS:
        raise ValueError(f"unknown learner variants {variants!r}; choose from {VARIANTS}")
    names = [f"k{k}" for k in ks]
    if variants == "default":
        return names + (["k2_shared", "k2_bf16"] if 2 in ks else [])
    for k in ks:
        names += [f"k{k}_shared"] * (k > 1) + [f"k{k}_bf16"] + [f"k{k}_shared_bf16"] * (k > 1)
    return names


def learner_contenders(shape: str, sizes: BenchSizes, device: str, seed: int = 0,
                       variants: str = "default") -> dict[str, Callable[[], Any]]:
    """One update step of each contender, sampling from the same replay buffer: the reference
    TD3 ("td3") and the MA-TD3 variants of `variant_names`."""
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
    for name in variant_names(sizes.learner_ks, variants):
        k = int(name[1:].split("_")[0])
        # a mini-batch per actor (Algorithm 1, the default) or --shared-batch (one mini-batch for all
        # actors: Eq. 9's target pass then runs on B rows, not K·B); the opt-in mixed precision
        # (--precision bf16) against the same fp32 reference
        cfg = resolve("ma-td3", actors=k, hidden=sizes.hidden, batch_size=batch, seed=seed,
                      shared_batch=True if "_shared" in name else None,
                      precision="bf16" if name.endswith("_bf16") else None)
        agent = MultiActorAgent(cfg, spec, device)
        out[name] = _update_step(agent, buf, batch)
    if graphs_on(device):  # the same updates launched op by op, for the graphs' gain
        for k in sizes.learner_ks:
            cfg = resolve("ma-td3", actors=k, hidden=sizes.hidden, batch_size=batch, seed=seed)
            agent = MultiActorAgent(cfg, spec, device)
            out[f"k{k}_eager"] = (lambda a=agent: a.update(buf.sample(batch, a.batch_groups)))
    return out


def graphs_on(device: str) -> bool:
    """Does an agent on `device` update through CUDA graphs (mam_core/graphs.py)?"""
    from mam_core import graphs
    from mam_core.accel import for_device

    return for_device(device).cuda_graphs and graphs.enabled()


def interleaved_rates(steps: dict[str, Callable[[], Any]], rounds: int, per_round: int,
                      warmup: int = 4, sync: Callable[[], Any] | None = None) -> dict[str, dict[str, list[float]]]:
    """Rates (calls/s by wall clock and by process CPU time) per contender per round.

    The order rotates every round so no contender always follows the same one. `sync` (e.g.
    `torch.cuda.synchronize`) runs before a contender's timer starts and before it stops, so
    queued device work is counted where it was issued.
    """
    sync = sync or (lambda: None)
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
            sync()
            t, c = time.perf_counter(), time.process_time()
            for _ in range(per_round):
                f()
            sync()
            wall[name].append(per_round / max(time.perf_counter() - t, 1e-9))
            cpu[name].append(per_round / max(time.process_time() - c, 1e-9))
    return {"wall": wall, "cpu": cpu}


def device_ms_per_update(step: Callable[[], Any], device: str, updates: int = 20) -> tuple[float, str]:
    """The device's busy time per call of `step`, in ms, and what was measured.

    CUDA: the summed durations of the kernels and copies that the calls ran on the GPU
    (torch.profiler with CUPTI), over `updates` calls after a warm-up: the GPU's work, without
    the gaps between kernels where it waited for the host. Else: the process's CPU time per
    call (the CPU is the device).
    """
    import torch

    for _ in range(3):
        step()
    if not device.startswith("cuda"):
        c = time.process_time()
        for _ in range(updates):
            step()
        return (time.process_time() - c) / updates * 1e3, "process cpu time"
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    try:
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(updates):
                step()
            torch.cuda.synchronize()
        busy_us = sum(e.time_range.elapsed_us() for e in prof.events()
                      if e.device_type == torch.autograd.DeviceType.CUDA)
        if busy_us <= 0:  # device events not listed as such: each kernel's time is some op's self device time
            busy_us = sum(getattr(e, "self_device_time_total", 0) or getattr(e, "self_cuda_time_total", 0)
                          for e in prof.key_averages())
    except Exception as e:  # a profiler that does not work there must not lose the bench's other figures
        return float("nan"), f"cuda profiler failed: {type(e).__name__}: {e}"[:200]
    if busy_us <= 0:
        return float("nan"), "cuda profiler saw no device events"
    return busy_us / updates / 1e3, "cuda kernels and copies (torch.profiler)"


def ratio_of_medians_per_round(a: list[float], b: list[float]) -> float:
    """Median over rounds of a[r] / b[r] (same round: same machine conditions)."""
    return median([x / y for x, y in zip(a, b)])


def bench_learner(sizes: BenchSizes, device: str = "cpu", threads: int = 1, log: Callable[[str], None] = print,
                  seed: int = 0, variants: str = "default", device_time: bool = False) -> dict[str, Any]:
    """MA-TD3 updates/s at K = sizes.learner_ks against the reference TD3, per env shape.

    Keys per shape and contender c (`variant_names`): `learner_<shape>_<c>_updates_per_s` and
    `learner_<shape>_<c>_vs_td3` (median over rounds of the within-round ratio); per-actor fp32
    contenders also `..._vs_td3_cpu_time`; `..._k<K>_per_actor_vs_shared` where both ran; with
    `device_time`, `learner_<shape>_<c>_device_ms_per_update` (`device_ms_per_update`).
    """
    import torch

    torch.set_num_threads(threads)
    sync = torch.cuda.synchronize if device.startswith("cuda") else None
    out: dict[str, Any] = {"learner_variants": variants, "learner_ks": list(sizes.learner_ks),
                           "learner_rounds": sizes.learner_rounds, "learner_updates_per_round": sizes.learner_updates}
    for shape in sizes.learner_shapes:
        steps = learner_contenders(shape, sizes, device, seed, variants)
        log(f"learner: {shape} shapes, {', '.join(steps)} ({sizes.learner_rounds} rounds x "
            f"{sizes.learner_updates} updates, interleaved)")
        rates = interleaved_rates(steps, sizes.learner_rounds, sizes.learner_updates, sync=sync)
        wall, cpu = rates["wall"], rates["cpu"]
        out[f"learner_{shape}_td3_updates_per_s"] = median(wall["td3"])
        for name in (n for n in steps if n != "td3"):
            out[f"learner_{shape}_{name}_updates_per_s"] = median(wall[name])
            out[f"learner_{shape}_{name}_vs_td3"] = ratio_of_medians_per_round(wall[name], wall["td3"])
            if "_" not in name:
                out[f"learner_{shape}_{name}_vs_td3_cpu_time"] = ratio_of_medians_per_round(cpu[name], cpu["td3"])
            if f"{name}_eager" in wall:  # CUDA graphs against the same update launched op by op
                out[f"learner_{shape}_{name}_graph_vs_eager"] = ratio_of_medians_per_round(
                    wall[name], wall[f"{name}_eager"])
            if f"{name}_shared" in wall and "_" not in name:
                out[f"learner_{shape}_{name}_per_actor_vs_shared"] = ratio_of_medians_per_round(
                    wall[name], wall[f"{name}_shared"])
        if device_time:
            for name, step in steps.items():
                ms, source = device_ms_per_update(step, device, max(sizes.learner_updates, 10))
                out[f"learner_{shape}_{name}_device_ms_per_update"] = ms
                out["learner_device_time_source"] = source
    out.update(bench_sac(sizes, device, log, seed, sync))
    first = sizes.learner_shapes[0]
    if 2 in sizes.learner_ks:
        out["learner_k2_vs_td3"] = out[f"learner_{first}_k2_vs_td3"]
        out["learner_k2_vs_td3_shape"] = first
        if f"learner_{first}_k2_bf16_vs_td3" in out:
            out["learner_k2_bf16_vs_td3"] = out[f"learner_{first}_k2_bf16_vs_td3"]
    return out


# --------------------------------------------------------------------------- profile


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


# --------------------------------------------------------------------------- replay checkpoints


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
            buf.add_batch(rng.standard_normal((k, obs_dim), np.float32),
                          rng.uniform(-1, 1, (k, act_dim)).astype(np.float32),
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
