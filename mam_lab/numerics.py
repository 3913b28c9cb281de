"""A digest of Algorithm 1's numerics at the checkout that runs: does a code change alter results?

    python -m mam_lab.numerics [--env HalfCheetah-v5] [--steps 1500] [--seed 7] [--algo ma-td3]
                               [--hidden 256,256] [--batch-size 256]

Runs `mam_core.reference.run_reference` (one process, the same plan a distributed exact-mode run
follows bit for bit, tests/test_exact.py) for MA-TD3 (or `--algo`, e.g. ma-sac) under both
schedules on a small budget, with the default networks, and prints per schedule a sha256 over
every evaluation's returns and every final actor parameter. Two checkouts that print the same
digests compute the same runs from the same seed, so ledger records made at either commit can be
pooled (docs/RESULTS.md). Run it from each checkout with `PYTHONPATH=<checkout>` so that
checkout's code is imported. The arithmetic is pinned (mam_core/arithmetic.py): any x86-64
machine with AVX2 prints the same digests, and the JSON says which arithmetic computed them
(`MAM_ARITHMETIC=native` gives this machine's own).
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np
import typer

from mam_core import arithmetic
from mam_core.config import resolve
from mam_core.reference import ReferenceResult, run_reference

SCHEDULES = ("paper", "equal-data")


def digest(result: ReferenceResult) -> str:
    """sha256 (16 hex digits) over the evaluations (iteration, purpose, returns) and the final
    actors' parameters, in a fixed order."""
    h = hashlib.sha256()
    for e in result.evaluations:
        h.update(json.dumps([e.get("iterations"), e.get("purpose"), e.get("returns")]).encode())
    for actor in result.policy:
        for name in sorted(actor):
            h.update(name.encode())
            h.update(np.ascontiguousarray(actor[name]).tobytes())
    return h.hexdigest()[:16]


def numerics(env_id: str, steps: int, seed: int, algo: str = "ma-td3", **overrides: Any) -> dict[str, dict[str, Any]]:
    """Per schedule: the digest, the survivor and the updates of a small reference run of `algo`."""
    import torch

    torch.set_num_threads(1)
    start = max(steps // 5, 1)
    out = {}
    for schedule in SCHEDULES:
        cfg = resolve(algo, start_steps=start, compete_every=start, eliminate_at=3 * start, eval_episodes=2,
                      eval_every=start, seed=seed, schedule=schedule, **overrides)
        result = run_reference(env_id, cfg, steps)
        out[schedule] = {"digest": digest(result), "survivor": result.survivor, "updates": result.updates}
    return out


def main(env: str = typer.Option("HalfCheetah-v5", help="gymnasium env id"),
         steps: int = typer.Option(1500, help="schedule steps per run (start, A = steps / 5, C = 3A)"),
         seed: int = typer.Option(7, help="the runs' --seed"),
         algo: str = typer.Option("ma-td3", help="the algorithm (a multi-actor one: ma-td3, ma-ddpg, ma-sac)"),
         hidden: str = typer.Option("256,256", help="hidden layer widths (small ones for a quick check)"),
         batch_size: int = typer.Option(256, help="mini-batch size")) -> None:
    """Print the numerics digest of this checkout as one JSON object (the algo named only when not
    ma-td3, so the default output stays what older checkouts print)."""
    widths = tuple(int(h) for h in hidden.split(","))
    overrides: dict[str, Any] = {}
    if widths != (256, 256) or batch_size != 256:  # the defaults: the digests docs/RESULTS.md quotes
        overrides = dict(hidden=widths, batch_size=batch_size)
    named = {} if algo == "ma-td3" else {"algo": algo}
    digests = numerics(env, steps, seed, algo, **overrides)
    state = arithmetic.status()
    label = "portable" if state["portable"] else f"{state['arithmetic']}, machine-bound: {state['machine_bound']}"
    if state["portable"] and state.get("gemm") != "chain":  # the default GEMMs go unnamed, as before
        label += f", GEMMs {state.get('gemm')}"
    print(json.dumps({"env": env, "steps": steps, "seed": seed, **named, **overrides, "arithmetic": label,
                      **digests}))


if __name__ == "__main__":
    typer.run(main)
