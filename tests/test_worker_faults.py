"""Workers survive the simulator: exceptions and non-finite values drop the episode, not the worker."""

from __future__ import annotations

import time
import uuid

import numpy as np
import pytest

from services.messaging import bus, keys
from services.messaging.codec import TransitionBatch, TransitionSpec
from services.roles.worker import FAULTS, Worker
from services.run import options
from tests.faulty_env import KINDS


def worker_for(env_id: str, session, run: str) -> Worker:
    cfg = options.build_run_config(dict(env=env_id, algo="td3", steps=10_000, hidden="16,16", run=run), None)
    return Worker(cfg, session, "w0", 0, run_dir=None)


def test_each_simulator_fault_is_counted_the_env_reset_and_the_step_retried() -> None:
    """Lock-step: every iteration of a slot has one transition, so a fault does not drop rows:
    the env is reset, the step retried, and every batch from then on carries the fault count
    (the learner records that the run is no longer the seed's)."""
    run = f"faults-{uuid.uuid4().hex[:8]}"
    with bus.session_scope(bus.make_config()) as session:  # an isolated session: loopback to itself
        inbox = bus.Inbox.subscribe(session, keys.transitions_all(run), maxsize=100_000)
        worker = worker_for("tests.faulty_env:FaultyPendulum-v0", session, run)
        worker.pub = bus.declare_reliable_publisher(session, keys.transitions(run, "w0"))
        env = worker.env.env.env  # OrderEnforcing(PassiveEnvChecker(FaultInjector(...)))
        assert type(env).__name__ == "FaultInjector"
        for index in range(1, 3001):
            worker.step(index, random_phase=True, actor=0, version=-1)
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
    # One row per iteration, in order: every good step is sent, nothing non-finite.
    assert worker.sent_rows == 3000 == env.steps_ok == sum(b.rows for b in batches)
    first = 1
    for b in sorted(batches, key=lambda b: b.batch_seq):
        assert b.iteration == first and b.slot == 0
        first += b.rows
        for a in (b.obs, b.action, b.reward, b.next_obs):
            assert np.isfinite(a).all()
    assert batches[-1].env_faults == sum(env.injected.values()) > 0
    assert worker.fault_counters()["env_faults"] == env.injected
    assert env.episode > 50


def test_a_reset_that_never_works_makes_the_env_anew_then_gives_up() -> None:
    with bus.session_scope(bus.make_config()) as session:
        with pytest.raises(RuntimeError, match="no usable reset"):
            worker_for_broken(session)


def worker_for_broken(session) -> None:
    import tests.faulty_env as fe

    # BrokenResetWorkers-v0 fails only in worker processes; this is one as far as it knows.
    argv0 = fe.sys.argv[0]
    fe.sys.argv[0] = "/x/services/roles/worker.py"
    try:
        worker_for("tests.faulty_env:BrokenResetWorkers-v0", session, f"broken-{uuid.uuid4().hex[:8]}")
    finally:
        fe.sys.argv[0] = argv0
