"""What portable arithmetic costs (docs/PERFORMANCE.md, "Portable arithmetic").

    python -m mam_lab.bench_arithmetic [--rounds 7] [--updates 20] [--steps 2000]

* **learner** — MA-TD3 (K = 2) and TD3 updates/s, 256x256 networks, batch 256, HalfCheetah
  shapes, one torch thread, one process per arithmetic (each library reads its pins when it
  loads): `native` (nothing pinned, the machine's own kernels), `portable` (mam's default: the
  pins of `mam_core.arithmetic.PINS`, the GEMMs in mam_core's own kernels, one FMA chain an
  element), `portable-threads` (the same over 2 threads: the same bits), `portable-avx2` and
  `portable-avx2-threads` (their AVX2 kernel, what a CPU without AVX-512 runs, 1 and 2 threads:
  the same bits), `portable-openblas` and
  `portable-openblas-threads` (the GEMMs in pinned OpenBLAS, 1 and 2 threads: the default before
  the chain kernels, other bits), `portable-mkl` (the GEMMs in MKL's COMPATIBLE branch: the
  default before OpenBLAS, other bits again). The processes take turns in rounds whose order
  rotates; a ratio is the median over rounds of the within-round ratio. `--sides` times a few of
  them (`native` always, the reference).
* **actor** — the workers' and referee's forward pass (HalfCheetah shapes, 256x256): `dense`
  (fixed order, `mam_core.policy`) against `x @ w + b` (BLAS), batch 1 and 10, interleaved in
  this process; and worker steps/s: a HalfCheetah-v5 `env.step` plus the actor forward.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any, Callable

import typer

import services  # noqa: F401  (OPENBLAS_NUM_THREADS=1 as in a worker; mam_core pins first)
from mam_core import arithmetic

GEMM_THREADS_ENV = "MAM_BENCH_GEMM_THREADS"
ISA_ENV = "MAM_CHAIN_ISA"  # mam_core.chain.Chain.ISA_ENV (not imported: that module loads torch)
# name: (the child's MAM_ARITHMETIC, extra variables)
LEARNER_ARITHMETICS: dict[str, tuple[str, dict[str, str]]] = {
    "native": ("native", {}),
    "portable": ("portable", {}),
    "portable-threads": ("portable", {GEMM_THREADS_ENV: "2"}),
    "portable-avx2": ("portable", {ISA_ENV: "2"}),
    "portable-avx2-threads": ("portable", {ISA_ENV: "2", GEMM_THREADS_ENV: "2"}),
    "portable-openblas": ("portable", {arithmetic.GEMM_ENV: "openblas"}),
    "portable-openblas-threads": ("portable", {arithmetic.GEMM_ENV: "openblas", GEMM_THREADS_ENV: "2"}),
    "portable-mkl": ("portable", {arithmetic.GEMM_ENV: "mkl"}),
}


def _median(xs: list[float]) -> float:
    s = sorted(xs)
    n = len(s)
    return s[n // 2] if n % 2 else (s[n // 2 - 1] + s[n // 2]) / 2


def learner_child() -> None:
    """One arithmetic's learner: reads `N` per line, runs N updates of each contender, prints the seconds."""
    import numpy as np
    import torch

    from mam_core import gemm
    from mam_core.agent import EnvSpec, MultiActorAgent
    from mam_core.config import resolve
    from mam_lab.bench_learner import random_replay

    arithmetic.portable_gemm()  # decided now: the GEMMs this child computes with
    torch.set_num_threads(1)
    gemm.set_threads(int(os.environ.get(GEMM_THREADS_ENV, "1")))
    buf = random_replay(17, 6, 1.0, 5120, "cpu")
    steps: dict[str, Callable[[], Any]] = {}
    for name, k in (("td3", 1), ("ma-td3", 2)):
        cfg = resolve("ma-td3", actors=k, hidden=(256, 256), batch_size=256, seed=0)
        agent = MultiActorAgent(cfg, EnvSpec(17, 6, (1.0,) * 6), "cpu")
        steps[name] = (lambda a=agent: a.update(buf.sample(256, a.batch_groups)))
    for f in steps.values():
        for _ in range(4):
            f()
    print(json.dumps({"ready": torch.backends.cpu.get_cpu_capability(), "numpy": np.__version__,
                      "gemm": arithmetic.status().get("gemm"), "gemm_threads": gemm.threads()}), flush=True)
    for line in sys.stdin:
        n = int(line)
        out = {}
        for name, f in steps.items():
            t = time.perf_counter()
            for _ in range(n):
                f()
            out[name] = n / (time.perf_counter() - t)
        print(json.dumps(out), flush=True)


def bench_learner_arithmetic(rounds: int, updates: int, log: Callable[[str], None] = print,
                             sides: list[str] | None = None) -> dict[str, Any]:
    procs = {}
    chosen = {"native", *(sides or LEARNER_ARITHMETICS)}
    for name, (mode, extra) in LEARNER_ARITHMETICS.items():
        if name not in chosen:
            continue
        env = {k: v for k, v in os.environ.items() if k not in (*arithmetic.PINS, arithmetic.GEMM_ENV, ISA_ENV)}
        env.update(extra, **{arithmetic.ARITHMETIC_ENV: mode})  # the child pins (or not) as it starts
        procs[name] = subprocess.Popen([sys.executable, "-m", "mam_lab.bench_arithmetic", "--child"], env=env,
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        for name, p in procs.items():
            log(f"learner {name}: {p.stdout.readline().strip()}")
        rates: dict[str, dict[str, list[float]]] = {n: {"td3": [], "ma-td3": []} for n in procs}
        names = list(procs)
        for r in range(rounds):
            for name in names[r % len(names):] + names[: r % len(names)]:
                procs[name].stdin.write(f"{updates}\n")
                procs[name].stdin.flush()
                for c, v in json.loads(procs[name].stdout.readline()).items():
                    rates[name][c].append(v)
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait(30)
    out: dict[str, Any] = {}
    for name in names:
        for c in ("td3", "ma-td3"):
            out[f"learner_{c}_{name}_updates_per_s"] = round(_median(rates[name][c]), 2)
            if name != "native":
                out[f"learner_{c}_{name}_vs_native"] = round(_median(
                    [a / b for a, b in zip(rates[name][c], rates["native"][c])]), 3)
    return out


def bench_actor(rounds: int, steps: int) -> dict[str, Any]:
    """The actor forward, dense against BLAS, and HalfCheetah worker steps/s with each."""
    import numpy as np

    from mam_core.envs import make_env
    from mam_core.policy import dense

    rng = np.random.default_rng(0)
    sizes = [17, 256, 256, 6]
    layers = [((rng.normal(size=(i, o)) / np.sqrt(i)).astype(np.float32), np.zeros(o, np.float32))
              for i, o in zip(sizes[:-1], sizes[1:])]

    def forward(layer: Callable) -> Callable[[np.ndarray], np.ndarray]:
        def f(x: np.ndarray) -> np.ndarray:
            h = x
            for i, (w, b) in enumerate(layers):
                h = layer(h, w, b)
                if i < len(layers) - 1:
                    np.maximum(h, 0.0, out=h)
            return np.tanh(h)
        return f

    kinds = {"dense": forward(dense), "blas": forward(lambda x, w, b: x @ w + b)}
    out: dict[str, Any] = {}
    for batch in (1, 10):
        x = rng.normal(size=(batch, 17)).astype(np.float32)[0 if batch == 1 else slice(None)]
        per: dict[str, list[float]] = {k: [] for k in kinds}
        for r in range(rounds):
            for k, f in kinds.items():
                t = time.perf_counter()
                for _ in range(500):
                    f(x)
                per[k].append((time.perf_counter() - t) / 500 * 1e6)
        for k in kinds:
            out[f"actor_b{batch}_{k}_us"] = round(_median(per[k]), 1)
        out[f"actor_b{batch}_dense_vs_blas"] = round(_median([a / b for a, b in zip(per["dense"], per["blas"])]), 2)
    env = make_env("HalfCheetah-v5")
    obs, _ = env.reset(seed=0)
    per = {k: [] for k in kinds}
    for r in range(rounds):
        for k, f in kinds.items():
            t = time.perf_counter()
            for _ in range(steps):
                obs, _, term, trunc, _ = env.step(f(np.asarray(obs, np.float32)))
                if term or trunc:
                    obs, _ = env.reset()
            per[k].append(steps / (time.perf_counter() - t))
    env.close()
    for k in kinds:
        out[f"worker_step_{k}_per_s"] = round(_median(per[k]), 1)
    out["worker_step_dense_vs_blas"] = round(_median([a / b for a, b in zip(per["dense"], per["blas"])]), 3)
    return out


def main(rounds: int = typer.Option(7, help="interleaved rounds"),
         updates: int = typer.Option(20, help="learner updates per contender per round"),
         steps: int = typer.Option(2000, help="worker steps per contender per round"),
         sides: str = typer.Option("", help=f"learner sides to time, comma-separated (default all: "
                                            f"{','.join(LEARNER_ARITHMETICS)}); native always"),
         child: bool = typer.Option(False, "--child", hidden=True)) -> None:
    """Print what the portable arithmetic costs, as one JSON object on the last line."""
    if child:
        learner_child()
        return
    chosen = [s for s in sides.split(",") if s]
    unknown = [s for s in chosen if s not in LEARNER_ARITHMETICS]
    if unknown:
        raise typer.BadParameter(f"unknown side(s) {', '.join(unknown)}; give some of {', '.join(LEARNER_ARITHMETICS)}",
                                 param_hint="--sides")
    out: dict[str, Any] = {"arithmetic": arithmetic.status()["arithmetic"]}
    out.update(bench_actor(rounds, steps))
    out.update(bench_learner_arithmetic(rounds, updates, sides=chosen or None))
    print(json.dumps(out))


if __name__ == "__main__":
    typer.run(main)
