"""`mam bench --only exact`: what lock-step Algorithm 1 costs against the asynchronous collection.

HalfCheetah-v5 MA-TD3 under the paper's schedule with M = 3 (K = 2), the same run twice per
round: `--collection exact` and `--collection async`, interleaved (the order alternates every
round), so a shared machine slows both alike. Each side's env steps/s and updates/s come from
its learner.jsonl rows over the training part of the run (from the first update to the end),
and the figures are the median of the within-round ratios exact ÷ async.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any, Callable

from mam_lab.bench_sizes import ROOT, BenchSizes, _child_env, _stop


def training_rates(rows: list[dict[str, Any]]) -> tuple[float, float, float]:
    """Env steps/s, updates/s and the share of the time the exact learner waited for rows,
    between the first learner.jsonl row with updates and the last (NaN share: async)."""
    rows = [r for r in rows if "t" in r]
    train = [r for r in rows if r.get("updates", 0) > 0]
    if len(train) < 2:
        raise ValueError("fewer than two learner rows after the first update: run longer")
    a, b = train[0], train[-1]
    dt = b["t"] - a["t"]
    wait = (b["exact_wait_s"] - a["exact_wait_s"]) / dt if "exact_wait_s" in a and "exact_wait_s" in b else float("nan")
    return (b["env_steps"] - a["env_steps"]) / dt, (b["updates"] - a["updates"]) / dt, wait


def one_run(collection: str, sizes: BenchSizes, work: Path, iterations: int, seed: int) -> dict[str, float]:
    run = f"bench-exact-{collection}-{uuid.uuid4().hex[:6]}"
    run_dir = work / run
    start, c = iterations // 4, iterations // 2
    cmd = [sys.executable, "-m", "services.cli", "run", "--env", "HalfCheetah-v5", "--algo", "ma-td3",
           "--workers", "3", "--steps", str(iterations), "--start-steps", str(start), "--compete-every", str(c // 2),
           "--eliminate-at", str(c), "--eval-episodes", "1", "--eval-every", str(10 * iterations),
           "--hidden", ",".join(map(str, sizes.hidden)), "--batch-size", str(sizes.batch_size), "--seed", str(seed),
           "--collection", collection, "--run", run, "--run-dir", str(run_dir), "--no-plot"]
    t0 = time.monotonic()
    with open(work / f"{run}.out", "wb") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=_child_env(), stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=sizes.timeout_s * 4)
    finally:
        _stop([proc])
    if proc.returncode != 0:
        raise RuntimeError(f"mam run --collection {collection} exited {proc.returncode}: "
                           f"{(work / f'{run}.out').read_text()[-2000:]}")
    rows = [json.loads(line) for line in (run_dir / "learner.jsonl").read_text().splitlines() if line.strip()]
    steps_s, updates_s, wait = training_rates(rows)
    return {"env_steps_per_s": steps_s, "updates_per_s": updates_s, "learner_wait_share": wait,
            "wall_s": time.monotonic() - t0}


def bench_exact(sizes: BenchSizes, log: Callable[[str], None] = print, rounds: int = 2,
                iterations: int | None = None) -> dict[str, Any]:
    iterations = iterations or (400 if sizes.hidden[0] <= 32 else 3000)
    log(f"exact vs async: mam run HalfCheetah-v5 ma-td3, paper schedule, M=3, {iterations} iterations, "
        f"{rounds} interleaved rounds")
    ratios_steps: list[float] = []
    ratios_updates: list[float] = []
    sides: dict[str, list[dict[str, float]]] = {"exact": [], "async": []}
    with tempfile.TemporaryDirectory(prefix="mam-bench-exact-") as tmp:
        for r in range(rounds):
            order = ("exact", "async") if r % 2 == 0 else ("async", "exact")
            got = {mode: one_run(mode, sizes, Path(tmp), iterations, seed=r) for mode in order}
            for mode in order:
                sides[mode].append(got[mode])
            ratios_steps.append(got["exact"]["env_steps_per_s"] / got["async"]["env_steps_per_s"])
            ratios_updates.append(got["exact"]["updates_per_s"] / got["async"]["updates_per_s"])
            log(f"round {r + 1}: exact {got['exact']['env_steps_per_s']:.0f} env steps/s, "
                f"{got['exact']['updates_per_s']:.0f} updates/s; async {got['async']['env_steps_per_s']:.0f}, "
                f"{got['async']['updates_per_s']:.0f}")
    med = statistics.median
    return {"exact_vs_async_env_steps": med(ratios_steps), "exact_vs_async_updates": med(ratios_updates),
            "exact_env_steps_per_s": med(s["env_steps_per_s"] for s in sides["exact"]),
            "async_env_steps_per_s": med(s["env_steps_per_s"] for s in sides["async"]),
            "exact_updates_per_s": med(s["updates_per_s"] for s in sides["exact"]),
            "async_updates_per_s": med(s["updates_per_s"] for s in sides["async"]),
            "exact_learner_wait_share": med(s["learner_wait_share"] for s in sides["exact"]),
            "exact_rounds": rounds, "exact_iterations": iterations}
