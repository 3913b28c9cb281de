"""Workers survive the simulator: exceptions and non-finite values drop the episode, not the worker."""

from __future__ import annotations

import time
import uuid

import numpy as np
import pytest

from services import bus, keys, options
from services.codec import TransitionBatch, TransitionSpec
from services.worker import FAULTS, Worker
from tests.faulty_env import KINDS


def worker_for(env_id: str, session, run: str) -> Worker:
    cfg = options.build_run_config(dict(env=env_id, algo="td3", steps=10_000, hidden="16,16", run=run), None)
    return Worker(cfg, session, "w0", 0, run_dir=None)


def test_each_simulator_fault_drops_the_episode_resets_and_is_counted() -> None:
    run = f"faults-{uuid.uuid4().hex[:8]}"
    with bus.session_scope(bus.make_config()) as session:  # an isolated session: loopback to itself
        inbox = bus.Inbox.subscribe(session, keys.transitions_all(run), maxsize=100_000)
        worker = worker_for("tests.faulty_env:FaultyPendulum-v0", session, run)
        worker.pub = bus.declare_reliable_publisher(session, keys.transitions(run, "w0"))
        env = worker.env.env.env  # OrderEnforcing(PassiveEnvChecker(FaultInjector(...)))
        assert type(env).__name__ == "FaultInjector"
        for _ in range(3000):
            worker.step(random_phase=True)
        worker.flush()
        deadline = time.monotonic() + 10
        batches = []
        while sum(b.rows for b in batches) < worker.sent_rows:
            assert time.monotonic() < deadline, "not every batch arrived"
            item = inbox.get(timeout=1.0)
            if item is not None:
                batches.append(TransitionBatch.from_bytes(item.payload, TransitionSpec(4, 1, 1, max_rows=4096)))
        inbox.close()
    # Every kind was injected and counted by its name, as often as it happened.
    assert set(FAULTS) == set(KINDS)
    assert all(env.injected[k] >= 5 for k in KINDS), env.injected
    assert worker.faults == env.injected
    # Step faults dropped their episode's unsent rows; a reset fault drops no episode.
    step_faults = sum(env.injected[k] for k in KINDS if k != "reset_exception")
    assert worker.dropped_episodes == step_faults and worker.dropped_rows > 0
    # Every good step is either sent or dropped with its episode; nothing non-finite was sent.
    assert worker.sent_rows + worker.dropped_rows == env.steps_ok
    assert sum(b.rows for b in batches) == worker.sent_rows
    for b in batches:
        for a in (b.obs, b.action, b.reward, b.next_obs):
            assert np.isfinite(a).all()
    report = worker.fault_counters()
    assert report["env_faults"] == env.injected and report["dropped_rows"] == worker.dropped_rows
    assert env.episode > 50


def test_a_reset_that_never_works_makes_the_env_anew_then_gives_up() -> None:
    with bus.session_scope(bus.make_config()) as session:
        with pytest.raises(RuntimeError, match="no usable reset"):
            worker_for_broken(session)


def worker_for_broken(session) -> None:
    import tests.faulty_env as fe

    # BrokenResetWorkers-v0 fails only in worker processes; this is one as far as it knows.
    argv0 = fe.sys.argv[0]
    fe.sys.argv[0] = "/x/services/worker.py"
    try:
        worker_for("tests.faulty_env:BrokenResetWorkers-v0", session, f"broken-{uuid.uuid4().hex[:8]}")
    finally:
        fe.sys.argv[0] = argv0
