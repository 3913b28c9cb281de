"""`mam bench --only lag`: `mam run` at lag 0 and at lag 2 against the one-process reference.

HalfCheetah-v5 MA-TD3 (K = 2, paper schedule) for the same number of iterations, three ways per
round, interleaved (the order rotates every round) so a shared machine slows all of them alike:
`run_reference` in a process of its own, `mam run --lag 0` and `mam run --lag 2`. Two
configurations (`CONFIGS`): **learner-bound** (M = 3, the bench's networks: the updates are nearly
all of the reference's time) and **collection-heavy** (M = 6, 32×32 networks, batch 64, 4
evaluation episodes a competition, an update every second iteration: stepping and evaluating
take a third or more of it, so the lag has work to overlap), where a fourth side runs `--lag 2`
with three slots a worker process (`--slots-per-worker 3`, services/roles/worker_group.py). The
reference reports the share of its wall time spent in updates (`reference_update_share`); the
rest is stepping, acting and evaluating. The figure of each lag is a *speed*: the reference's
wall time ÷ `mam run`'s wall time (above 1: the distributed run is faster than one process
computing the same run), the median over rounds.
The learner's wait share (the time its loop waited for an iteration's rows, learner.jsonl's
`exact_wait_s`, over its training part) says where the time goes.
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
from typing import Any, Callable, NamedTuple

from mam_lab.bench_sizes import ROOT, BenchSizes, child_env, stop_children

LAGS = (0, 2)


class LagConfig(NamedTuple):
    prefix: str  # of its figures' keys
    workers: int  # M
    hidden: tuple[int, ...] | None  # None: the bench's networks
    batch: int | None  # None: the bench's mini-batch
    episodes: int  # evaluation episodes a competition
    scale: int  # its iterations: this multiple of the bench's (the collection-heavy run's iterations are
    # short, and at 1x its reference took 15 s, mostly `mam run`'s start-up on the other side)
    packed: int | None  # slots a worker process steps in a fourth side, `--lag 2 --slots-per-worker N`
    utd: float = 1.0  # updates an iteration


# The collection-heavy run makes an update every second iteration: at one an iteration (until
# 2026-12-07) its reference spent 71% of its time in updates, short of the third or more that
# stepping and evaluating are to take there (docs/PERFORMANCE.md, "The collection-heavy bench").
CONFIGS = {"learner-bound": LagConfig("", 3, None, None, 1, 1, None),
           "collection-heavy": LagConfig("collection_", 6, (32, 32), 64, 4, 4, 3, utd=0.5)}


def run_args(sizes: BenchSizes, iterations: int, seed: int, config: str = "learner-bound") -> list[str]:
    """The run's options (shared by `mam run` and the reference)."""
    c = CONFIGS[config]
    start, elim = iterations // 4, iterations // 2
    return ["--env", "HalfCheetah-v5", "--algo", "ma-td3", "--workers", str(c.workers), "--steps", str(iterations),
            "--start-steps", str(start), "--compete-every", str(elim // 2), "--eliminate-at", str(elim),
            "--eval-episodes", str(c.episodes), "--eval-every", str(10 * iterations),
            "--hidden", ",".join(map(str, c.hidden or sizes.hidden)), "--batch-size", str(c.batch or sizes.batch_size),
            "--utd", str(c.utd), "--seed", str(seed)]


REFERENCE = """
import json, sys, time
import mam_core, torch
from mam_core.algorithm1 import Algorithm1
from mam_core.config import resolve
from mam_core.reference import run_reference
torch.set_num_threads(1)
a = dict(zip(sys.argv[1::2], sys.argv[2::2]))
cfg = resolve("ma-td3", workers=int(a["--workers"]), start_steps=int(a["--start-steps"]),
              compete_every=int(a["--compete-every"]), eliminate_at=int(a["--eliminate-at"]),
              eval_episodes=int(a["--eval-episodes"]), eval_every=int(a["--eval-every"]),
              hidden=tuple(int(h) for h in a["--hidden"].split(",")), batch_size=int(a["--batch-size"]),
              utd=float(a["--utd"]), seed=int(a["--seed"]))
spent = [0.0]
updates = Algorithm1.run_updates
def timed_updates(*args, **kw):
    t = time.perf_counter()
    try:
        return updates(*args, **kw)
    finally:
        spent[0] += time.perf_counter() - t
Algorithm1.run_updates = timed_updates
t0 = time.perf_counter()
run_reference(a["--env"], cfg, int(a["--steps"]))
print(json.dumps({"update_share": spent[0] / (time.perf_counter() - t0)}))
"""


def wait_share(rows: list[dict[str, Any]], field: str = "exact_wait_s") -> float:
    """The share of its training time (from the first learner.jsonl row with updates to the last)
    the learner's loop waited for rows (`field` "update_s": spent in its updates)."""
    train = [r for r in rows if r.get("updates", 0) > 0 and "t" in r]
    if len(train) < 2 or field not in train[0]:
        return float("nan")
    a, b = train[0], train[-1]
    return (b[field] - a[field]) / max(b["t"] - a["t"], 1e-9)


def timed(cmd: list[str], out: Path, timeout: float) -> float:
    t0 = time.monotonic()
    with open(out, "wb") as f:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=child_env(), stdout=f, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=timeout)
    finally:
        stop_children([proc])
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} exited {proc.returncode}: {out.read_text()[-2000:]}")
    return time.monotonic() - t0


def bench_lag(sizes: BenchSizes, log: Callable[[str], None] = print, rounds: int = 2,
              iterations: int | None = None, configs: tuple[str, ...] = tuple(CONFIGS)) -> dict[str, Any]:
    iterations = iterations or (400 if sizes.hidden[0] <= 32 else 3000)
    out: dict[str, Any] = {"lag_iterations": iterations, "lag_rounds": rounds}
    for config in configs:
        out.update(_bench_config(sizes, log, rounds, iterations, config))
    return out


def _bench_config(sizes: BenchSizes, log: Callable[[str], None], rounds: int, iterations: int,
                  config: str) -> dict[str, Any]:
    c = CONFIGS[config]
    prefix, workers, iterations, packed = c.prefix, c.workers, iterations * c.scale, c.packed
    log(f"lag ({config}): HalfCheetah-v5 ma-td3, K=2, M={workers}, paper schedule, {iterations} iterations, "
        f"{c.utd:g} update(s) an iteration: the "
        f"one-process reference, mam run --lag {LAGS[0]} and --lag {LAGS[1]}"
        f"{f', and --lag 2 with {packed} slots a worker process' if packed else ''}, {rounds} interleaved rounds")
    sides = ["reference", *(f"lag{b}" for b in LAGS), *(["lag2_packed"] if packed else [])]
    walls: dict[str, list[float]] = {side: [] for side in sides}
    waits: dict[str, list[float]] = {side: [] for side in sides[1:]}
    busy: dict[str, list[float]] = {side: [] for side in sides[1:]}
    shares: list[float] = []
    with tempfile.TemporaryDirectory(prefix="mam-bench-lag-") as tmp:
        work = Path(tmp)
        for r in range(rounds):
            args = run_args(sizes, iterations, seed=r, config=config)
            for side in sides[r % len(sides):] + sides[:r % len(sides)]:
                if side == "reference":
                    cmd = [sys.executable, "-c", REFERENCE, *args]
                    walls[side].append(timed(cmd, work / f"ref-{r}.out", sizes.timeout_s * 4))
                    shares.append(json.loads((work / f"ref-{r}.out").read_text().strip().splitlines()[-1])
                                  ["update_share"])
                    continue
                run = f"bench-{side}-{uuid.uuid4().hex[:6]}"
                lag = side.removeprefix("lag").split("_")[0]
                cmd = [sys.executable, "-m", "services.cli", "run", *args, "--lag", lag, "--run", run,
                       "--run-dir", str(work / run), "--no-plot",
                       *(["--slots-per-worker", str(packed)] if side.endswith("packed") else [])]
                walls[side].append(timed(cmd, work / f"{run}.out", sizes.timeout_s * 4))
                rows = [json.loads(line) for line in (work / run / "learner.jsonl").read_text().splitlines() if line]
                waits[side].append(wait_share(rows))
                busy[side].append(wait_share(rows, "update_s"))
            log(f"round {r + 1}: " + ", ".join(f"{side} {walls[side][-1]:.1f} s" for side in sides))
    med = statistics.median
    out: dict[str, Any] = {f"{prefix}lag_reference_wall_s": med(walls["reference"]),
                           f"{prefix}lag_reference_update_share": med(shares), f"{prefix}lag_workers": workers,
                           f"{prefix}lag_config_iterations": iterations, f"{prefix}lag_utd": c.utd}
    if packed:
        out[f"{prefix}lag2_packed_slots_per_worker"] = packed
    for side in sides[1:]:
        b = side[3:]
        out[f"{prefix}lag{b}_speed_vs_reference"] = med(ref / w for ref, w in zip(walls["reference"], walls[side]))
        out[f"{prefix}lag{b}_wall_s"] = med(walls[side])
        out[f"{prefix}lag{b}_learner_wait_share"] = med(waits[side])
        # the rest of the learner's time, besides waiting and updating: receiving, inserting, publishing, logging
        out[f"{prefix}lag{b}_learner_update_share"] = med(busy[side])
    return out
