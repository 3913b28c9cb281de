"""Issue 38: the stall watchdog names the process waited on. The workers' reports say what their
next iteration waits for (`waits`); when every worker of the awaited slots waits for weights, the
learner lacks a version and is restarted, not the workers; when each waits for an allocation, the
referee (real child processes, as in tests/test_reliability_watchdog.py)."""

from __future__ import annotations

from services.run.cluster import LocalCluster
from tests.test_reliability_watchdog import cluster, killed, stats  # noqa: F401 (the fixture)


def test_workers_waiting_for_a_version_blame_the_learner(cluster: LocalCluster) -> None:  # noqa: F811
    cluster.waits = {"worker-0": "actor 0 at version 1027", "worker-1": "actor 1 at version 1027"}
    cluster.observe(stats(1000, 900, 500, awaiting=(0, 1)))
    now = cluster.progress_at + 6
    cluster.last_stats_at = now - 0.5
    cluster.check_stall(now)
    assert killed(cluster) == ["learner"]
    text = " ".join(cluster.out.getvalue().split())
    assert "worker-0 waits for actor 0 at version 1027, worker-1 waits for actor 1 at version 1027 (the learner " \
           "does not publish it): restarting learner" in text, text


def test_workers_waiting_for_an_allocation_blame_the_referee(cluster: LocalCluster) -> None:  # noqa: F811
    cluster.waits = {"worker-1": "the allocation of iteration 600"}
    cluster.observe(stats(1000, 900, 500, awaiting=(1,)))
    now = cluster.progress_at + 6
    cluster.last_stats_at = now - 0.5
    cluster.check_stall(now)
    assert killed(cluster) == ["referee"]
    assert "worker-1 waits for the allocation of iteration 600 (the referee has not decided it)" in \
        " ".join(cluster.out.getvalue().split())


def test_a_worker_that_says_nothing_or_steps_is_still_the_one_restarted(cluster: LocalCluster) -> None:  # noqa: F811
    cluster.waits = {"worker-0": "actor 0 at version 1027", "worker-1": ""}
    cluster.observe(stats(1000, 900, 500, awaiting=(0, 1)))
    now = cluster.progress_at + 6
    cluster.last_stats_at = now - 0.5
    cluster.check_stall(now)
    assert killed(cluster) == ["worker-0", "worker-1"]
