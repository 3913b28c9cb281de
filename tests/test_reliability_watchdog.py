"""The stall watchdog of `mam run` (LocalCluster.check_stall): what it blames and kills, on real
child processes, from the learner stats it has seen."""

from __future__ import annotations

import io
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rich.console import Console

from mam_core.config import resolve
from services.messaging.codec import LearnerStats
from services.run.cluster import STARTUP_GRACE_S, Child, LocalCluster
from services.run.config import RunConfig
from services.run.errors import RunStalled

ROLES = ("learner", "referee", "worker-0", "worker-1")


@pytest.fixture
def cluster(tmp_path: Path):
    cfg = RunConfig(run="wd", env_id="AppleCollect-v0", steps=2000, algo=resolve("ma-ddpg", actors=2, workers=2),
                    stall_timeout=5.0)
    out = io.StringIO()
    c = LocalCluster(cfg, tmp_path, "tcp/127.0.0.1:1", console=Console(file=out, width=400))
    c.out = out
    for role in ROLES:
        proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
        c.children.append(Child(role, proc, tmp_path / f"{role}.log"))
    yield c
    for child in c.children:
        if child.proc.poll() is None:
            child.proc.kill()
        child.proc.wait()


def stats(env_steps: int, updates: int, iteration: int = 0, awaiting: tuple[int, ...] = ()) -> LearnerStats:
    return LearnerStats(env_steps=env_steps, updates=updates, accept_until=2000, utd=1.0, versions=(3, 3),
                        workers=2, rejected={"future_version": 7}, iteration=iteration, awaiting=awaiting)


def killed(c: LocalCluster) -> list[str]:
    time.sleep(0.3)
    return [ch.role for ch in c.children if ch.proc.poll() is not None]


def test_a_learner_without_stats_gets_the_startup_grace_then_is_killed(cluster: LocalCluster) -> None:
    t0 = cluster.progress_at
    cluster.check_stall(t0 + 10)  # past stall_timeout, within the start-up grace
    assert killed(cluster) == []
    cluster.check_stall(t0 + STARTUP_GRACE_S + 1)
    assert killed(cluster) == ["learner"]
    text = " ".join(cluster.out.getvalue().split())
    assert "stalled: no new transition or update for 61 s; learner stats: never" in text
    assert "restarting learner" in text


def test_frozen_stats_blame_the_learner(cluster: LocalCluster) -> None:
    cluster.observe(stats(800, 400, 400))
    now = cluster.progress_at + 6
    cluster.check_stall(now)
    assert killed(cluster) == ["learner"]
    assert "learner stats: not for 6 s" in cluster.out.getvalue()


def test_a_learner_waiting_for_the_elimination_blames_the_referee(cluster: LocalCluster) -> None:
    cluster.observe(stats(1200, 600, 600, awaiting=(-1,)))
    cluster.last_stats_at = cluster.progress_at + 5.5  # stats still come, nothing moves
    cluster.check_stall(cluster.progress_at + 6)
    assert killed(cluster) == ["referee"]
    text = " ".join(cluster.out.getvalue().split())
    assert "waiting for the referee's elimination decision" in text and "learner at iteration 600" in text


def test_rows_missing_from_a_slot_blame_its_worker_then_stop_the_run(cluster: LocalCluster) -> None:
    cluster.observe(stats(1000, 900, 500, awaiting=(1,)))
    for _ in range(2):  # two watchdog restarts without progress ...
        now = cluster.progress_at + 6
        cluster.last_stats_at = now - 0.5
        cluster.check_stall(now)
    assert killed(cluster) == ["worker-1"]
    text = " ".join(cluster.out.getvalue().split())
    assert "waiting for iteration 501's transitions from slots [1]" in text
    assert "rejected {'future_version': 7}" in text and "versions [3, 3]" in text
    now = cluster.progress_at + 6
    cluster.last_stats_at = now - 0.5
    with pytest.raises(RunStalled, match="the run is stalled: .*2 watchdog restarts did not help"):
        cluster.check_stall(now)  # ... and the third stall stops the run


def test_a_learner_that_waits_for_nothing_and_does_not_move_is_restarted(cluster: LocalCluster) -> None:
    cluster.observe(stats(1000, 900, 500))
    now = cluster.progress_at + 6
    cluster.last_stats_at = now - 0.5
    cluster.check_stall(now)
    assert killed(cluster) == ["learner"]
    assert "the learner waits for nothing and does not update" in cluster.out.getvalue()


def test_progress_resets_the_watchdog(cluster: LocalCluster) -> None:
    cluster.observe(stats(100, 10, 400))
    t = cluster.progress_at
    cluster.observe(stats(132, 10, 400))
    assert cluster.progress_at >= t and cluster.stall_actions == 0
    cluster.check_stall(cluster.progress_at + 4.9)
    assert killed(cluster) == []


def test_no_connection_to_the_learner_stops_the_run_naming_the_endpoint_and_its_log(tmp_path: Path) -> None:
    """A learner that never stays up long enough to accept the launcher's session (killed over and
    over as it starts, seen with `mam chaos --kill-every 1,2`) stops the run with a sentence, not a
    ZError traceback."""
    from services.messaging import bus
    from services.run.errors import RunStopped
    from services.run.launcher import supervised_session

    cfg = RunConfig(run="nc", env_id="AppleCollect-v0", steps=2000, algo=resolve("ma-ddpg", actors=2, workers=2))
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())  # nothing listens there
    cluster = LocalCluster(cfg, tmp_path, endpoint, console=Console(file=io.StringIO()))
    t0 = time.monotonic()
    with pytest.raises(RunStopped) as e:
        with supervised_session(bus.make_config(connect=[endpoint]), cluster, timeout=1.0):
            pass
    assert time.monotonic() - t0 < 30
    text = str(e.value)
    assert f"no connection to the learner at {endpoint} within 1 s (0 restarts of it meanwhile" in text
    assert text.endswith(str(tmp_path / "logs" / "learner.log"))
