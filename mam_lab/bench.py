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
  `mam-learner` in lock-step that trains ~1 update per 1000 transitions (`--utd 0.001`), so
  weights rarely change and never hold the workers.
* **lag** (only with `--only lag`: three HalfCheetah runs a round, in two configurations:
  learner-bound and collection-heavy) — `mam run --lag 0` and `--lag 2` against the one-process
  reference computing the same run, interleaved; speed = the reference's wall time ÷ `mam run`'s,
  with the learner's wait share and the reference's update share (mam_lab/bench_lag.py).

`--json` prints the same figures as one JSON object on the last line. `--quick` (the
default) keeps the whole bench to a few minutes on 2 cores; `--full` measures longer.
"""

from __future__ import annotations

import json
import math
import os
import platform
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable

import typer

from mam_lab.bench_lag import bench_lag
from mam_lab.bench_learner import VARIANTS, bench_learner, bench_replay, profile_learner_step
from mam_lab.bench_runs import bench_collection, bench_e2e
from mam_lab.bench_sizes import SHAPES, BenchSizes
from mam_lab.bench_transport import bench_transport, bench_weights, profile_worker_step
from mam_lab.provenance import versions
from services.run import options

# The pieces: mam_lab.bench_learner (learner, its profile, replay checkpoints), mam_lab.bench_runs
# (end to end, collection) and mam_lab.bench_transport (transport, weights, the worker's profile).


# Targets of the issue: (comparison, value). "ge": the figure must be >= value.
TARGETS: dict[str, tuple[str, float]] = {
    "learner_k2_vs_td3": ("ge", 0.8),  # 0.95 on CUDA, see target_for()
    "learner_k2_bf16_vs_td3": ("ge", 0.8),  # the same target, met with the opt-in mixed precision?
    "learner_sac_k1_vs_sac": ("ge", 1.0),  # mam's SAC against a plain single-process SAC (issue 27)
    "e2e_vs_single_process": ("le", 0.7),
    "e2e_bf16_vs_single_process": ("le", 0.7),
    "transport_transitions_per_s": ("ge", 50_000.0),
    "weights_latency_p99_ms": ("le", 10.0),
    "lag0_speed_vs_reference": ("ge", 1.0),  # one process's wall ÷ mam run's, the same run (Algorithm 1)
    "lag2_speed_vs_reference": ("ge", 1.0),  # learner-bound: little to overlap
    "collection_lag0_speed_vs_reference": ("ge", 1.0),
    "collection_lag2_speed_vs_reference": ("ge", 1.2),  # lag 2: workers and evaluations overlap the learner
    "collection_lag2_packed_speed_vs_reference": ("ge", 1.2),  # ... with three slots a worker process
}


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


# Versions of what the figures depend on (mam_lab.provenance.versions): label -> distribution.
BENCH_LIBRARIES = {"numpy": "numpy", "torch": "torch", "zenoh": "eclipse-zenoh", "mujoco": "mujoco",
                   "gymnasium": "gymnasium", "msgpack": "msgpack"}

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
        from mam_core.accel import for_device

        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
        info["cuda"] = torch.version.cuda
        info["gpu_bf16"] = for_device(device).bf16_supported()
    try:
        info["load_average_1min"] = round(os.getloadavg()[0], 2)
    except OSError:
        pass
    return info


def resolve_device(device: str) -> str:
    from mam_core.agent import pick_device

    return str(pick_device(device))


# --------------------------------------------------------------------------- the whole bench


PIECES = ("learner", "e2e", "transport", "weights", "collection")
EXTRA_PIECES = ("replay", "lag")  # only when asked for: --only replay, --only lag


def run_bench(sizes: BenchSizes, pieces: tuple[str, ...] = PIECES, device: str = "auto", threads: int = 1,
              log: Callable[[str], None] = print, profile: bool = False, variants: str = "default",
              device_time: bool = False) -> dict[str, Any]:
    """Every selected piece; one flat dict (the `--json` object). `variants` and `device_time`:
    `bench_learner`'s."""
    unknown = set(pieces) - set(PIECES) - set(EXTRA_PIECES)
    if unknown:
        raise ValueError(f"unknown bench piece(s) {sorted(unknown)}; choose from {PIECES + EXTRA_PIECES}")
    device = resolve_device(device)
    started = time.perf_counter()
    result: dict[str, Any] = {"device": device, "torch_threads": threads,
                              "versions": versions(BENCH_LIBRARIES, missing="absent", commit=False),
                              "machine": machine(device, threads), "sizes": asdict(sizes)}
    if "learner" in pieces:
        result.update(bench_learner(sizes, device, threads, log, variants=variants, device_time=device_time))
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
    if "lag" in pieces:
        result.update(bench_lag(sizes, log))
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
    ("learner_halfcheetah_k3_shared_vs_td3", "K=3 --shared-batch ÷ TD3, HalfCheetah (--variants all)"),
    ("learner_halfcheetah_k1_bf16_vs_td3", "K=1 bf16 ÷ TD3, HalfCheetah (--variants all)"),
    ("learner_halfcheetah_k3_bf16_vs_td3", "K=3 bf16 ÷ TD3, HalfCheetah (--variants all)"),
    ("learner_halfcheetah_k2_shared_bf16_vs_td3", "K=2 --shared-batch bf16 ÷ TD3, HalfCheetah (--variants all)"),
    ("learner_halfcheetah_k2_device_ms_per_update", "K=2 device busy ms per update (--device-time)"),
    ("learner_halfcheetah_td3_device_ms_per_update", "TD3 device busy ms per update (--device-time)"),
    ("learner_humanoid_k1_vs_td3", "K=1 ÷ TD3, Humanoid"),
    ("learner_humanoid_k2_vs_td3", "K=2 ÷ TD3, Humanoid"),
    ("learner_humanoid_k3_vs_td3", "K=3 ÷ TD3, Humanoid"),
    ("learner_sac_k1_vs_sac", "SAC (K=1) ÷ plain SAC updates/s (HalfCheetah shapes)"),
    ("learner_sac_k2_vs_sac", "MA-SAC K=2 ÷ plain SAC (goal: ≥ MA-TD3 K=2 ÷ TD3)"),
    ("learner_halfcheetah_sac_updates_per_s", "plain SAC updates/s, HalfCheetah"),
    ("learner_humanoid_sac_k1_vs_sac", "SAC (K=1) ÷ plain SAC, Humanoid"),
    ("learner_humanoid_sac_k2_vs_sac", "MA-SAC K=2 ÷ plain SAC, Humanoid"),
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
    ("lag0_speed_vs_reference", "speed: reference wall ÷ mam run --lag 0 wall, the same run"),
    ("lag2_speed_vs_reference", "speed: reference wall ÷ mam run --lag 2 wall"),
    ("lag0_learner_wait_share", "  learner's wait for rows, share of training time, lag 0"),
    ("lag2_learner_wait_share", "  learner's wait for rows, share of training time, lag 2"),
    ("lag_reference_wall_s", "one-process reference, wall s"),
    ("lag_reference_update_share", "  its share in updates (the rest: stepping, acting, evaluating)"),
    ("collection_lag0_speed_vs_reference", "collection-heavy (M=6, 32x32, utd 0.5): speed, lag 0"),
    ("collection_lag2_speed_vs_reference", "collection-heavy: speed, lag 2"),
    ("collection_lag2_packed_speed_vs_reference", "collection-heavy: speed, lag 2, 3 slots a worker process"),
    ("collection_lag_reference_update_share", "  its reference's share in updates"),
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


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(v) for v in text.split(",") if v.strip())


def override_sizes(sizes: BenchSizes, ks: str | None = None, shapes: str | None = None, rounds: int | None = None,
                   updates: int | None = None, hidden: str | None = None,
                   batch_size: int | None = None) -> BenchSizes:
    """`sizes` with the flags that were given (None: keep); ValueError on a bad value."""
    changes: dict[str, Any] = {}
    if ks is not None:
        changes["learner_ks"] = _ints(ks)
        if not changes["learner_ks"] or min(changes["learner_ks"]) < 1:
            raise ValueError(f"--ks needs positive integers, not {ks!r}")
    if shapes is not None:
        changes["learner_shapes"] = tuple(s.strip() for s in shapes.split(",") if s.strip())
        unknown = set(changes["learner_shapes"]) - set(SHAPES)
        if unknown or not changes["learner_shapes"]:
            raise ValueError(f"--shapes: choose among {','.join(SHAPES)}, not {shapes!r}")
    for key, value in (("learner_rounds", rounds), ("learner_updates", updates), ("batch_size", batch_size)):
        if value is not None:
            if value < 1:
                raise ValueError(f"{key} must be >= 1")
            changes[key] = value
    if hidden is not None:
        changes["hidden"] = _ints(hidden)
    return replace(sizes, **changes)


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags)
def bench_command(
    full: bool = typer.Option(False, "--full/--quick",
                              help="--quick (default): a few minutes on 2 cores; --full: longer, steadier figures"),
    json_out: bool = typer.Option(False, "--json", help="also print all figures as one JSON object on the last line"),
    only: str = typer.Option(",".join(PIECES), "--only",
                             help=f"comma-separated pieces among {','.join(PIECES + EXTRA_PIECES)} "
                                  "(replay: checkpoint of a 1M-row buffer, only when named)"),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda: the learner's device"),
    threads: int = typer.Option(1, "--threads", help="torch threads of the learner bench (the learner's default: 1)"),
    profile: bool = typer.Option(False, "--profile", help="also profile one learner update and one worker step"),
    tiny: bool = typer.Option(False, "--tiny", hidden=True, help="smoke-test sizes: seconds, meaningless figures"),
    out: Path = typer.Option(None, "--out", help="also write the JSON object to this file"),
    ks: str = typer.Option(None, "--ks", help="learner: comma-separated K values to time (default 1,2,3)"),
    shapes: str = typer.Option(None, "--shapes", help=f"learner: env shapes among {','.join(SHAPES)}"),
    variants: str = typer.Option("default", "--variants",
                                 help="learner: default (every K per actor, K=2 shared and K=2 bf16) or all "
                                      "(every K x per-actor/shared x fp32/bf16)"),
    device_time: bool = typer.Option(False, "--device-time",
                                     help="learner: also the device's busy ms per update (CUDA: kernel time "
                                          "by torch.profiler; CPU: process CPU time)"),
    rounds: int = typer.Option(None, "--rounds", help="learner: interleaved rounds (overrides the size)"),
    updates: int = typer.Option(None, "--updates", help="learner: updates per contender per round"),
    hidden: str = typer.Option(None, "--hidden", help="learner and runs: hidden sizes, e.g. 256,256"),
    batch_size: int = typer.Option(None, "--batch-size", help="learner and runs: mini-batch size"),
) -> None:
    """Learner, end-to-end, transport and collection figures, each against its reference and target."""
    import logging

    from rich.console import Console

    logging.basicConfig(level=logging.WARNING)
    sizes = BenchSizes.tiny() if tiny else BenchSizes.full() if full else BenchSizes.quick()
    try:
        sizes = override_sizes(sizes, ks=ks, shapes=shapes, rounds=rounds, updates=updates, hidden=hidden,
                               batch_size=batch_size)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from e
    if variants not in VARIANTS:
        raise typer.BadParameter(f"--variants must be one of {', '.join(VARIANTS)}")
    pieces = tuple(p.strip() for p in only.split(",") if p.strip())
    console = Console(stderr=json_out)
    try:
        result = run_bench(sizes, pieces, device, threads, log=lambda s: console.print(f"[dim]{s}[/]"),
                           profile=profile, variants=variants, device_time=device_time)
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
