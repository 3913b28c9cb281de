"""What every piece of `mam bench` shares: the sizes of a bench (`BenchSizes`), the env shapes of
the learner bench, and the helpers for child processes and figures. Imports nothing heavy: the
transport bench's child processes import it.
"""

from __future__ import annotations

import os
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Environment shapes of the learner bench: (obs_dim, act_dim, max_action).
SHAPES: dict[str, tuple[int, int, float]] = {
    "halfcheetah": (17, 6, 1.0),
    "humanoid": (348, 17, 0.4),
}


ROOT = Path(__file__).resolve().parents[1]


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
                   collection_workers=(4,), collection_window_s=0.5, collection_start_steps=64, timeout_s=240.0)


def median(xs: list[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


def percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q)) if xs else float("nan")


def child_env(**extra: str) -> dict[str, str]:
    return dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="160", **extra)


def stop_children(procs: list[subprocess.Popen], grace: float = 10.0) -> None:
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


def python_c(code: str, *args: str) -> list[str]:
    return [sys.executable, "-c", code, *args]
