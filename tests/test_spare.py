"""`mam-worker --spare`: the rule (which slot, when), spares on real Zenoh sessions, and a run whose
worker is killed and taken over by a spare (real processes)."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from mam_core.config import resolve
from mam_core.policy import read_policy_file
from mam_core.reference import run_reference
from services.messaging import bus, keys
from services.messaging.codec import Done, LearnerStats
from services.roles import role
from services.roles.spare import MIN_TAKE_OVER_S, Spare, Watch, decide, rank, take_over_limit
from services.run.config import RunConfig
from services.run.rundir import read_jsonl
from tests.e2e import ROOT, processes_of, spawn, stop, unique_run

LIMIT = 3.0


# --------------------------------------------------------------------------- the rule


def test_no_slot_is_taken_while_none_is_awaited_or_its_worker_is_live():
    assert decide((), {0, 1, 2}, 0, None, 0.0, LIMIT) == (None, Watch(None, 0.0))
    assert decide((-1,), set(), 0, None, 0.0, LIMIT)[0] is None  # -1 (the referee's decision) is not a slot
    _, watch = decide((1,), {0, 1, 2}, 0, None, 0.0, LIMIT)  # awaited, but its worker is live
    assert decide((1,), {0, 1, 2}, 0, watch, 100.0, LIMIT) == (None, Watch(None, 0.0))


def test_an_orphaned_slot_is_taken_after_the_limit_and_any_break_restarts_the_count():
    taken, watch = decide((1,), {0, 2}, 0, None, 10.0, LIMIT)
    assert (taken, watch) == (None, Watch(1, 10.0))
    assert decide((1,), {0, 2}, 0, watch, 10.0 + LIMIT, LIMIT)[0] is None  # not yet: longer than the limit
    assert decide((1,), {0, 2}, 0, watch, 10.1 + LIMIT, LIMIT)[0] == 1
    _, back = decide((1,), {0, 1, 2}, 0, watch, 12.0, LIMIT)  # its worker came back meanwhile ...
    _, again = decide((1,), {0, 2}, 0, back, 12.5, LIMIT)  # ... and left again: the count starts over
    assert again == Watch(1, 12.5)
    assert decide((1,), {0, 2}, 0, again, 12.5 + LIMIT, LIMIT)[0] is None
    assert decide((1,), {0, 2}, 0, again, 12.6 + LIMIT, LIMIT)[0] == 1
    _, idle = decide((), {0, 2}, 0, again, 13.0, LIMIT)  # the learner stopped awaiting it
    assert idle == Watch(None, 13.0)


def test_two_orphaned_slots_go_lowest_first_and_a_spare_ranked_before_takes_the_first():
    taken, watch = decide((2, 1, -1), {0}, 0, None, 0.0, LIMIT)
    assert watch == Watch(1, 0.0) and decide((2, 1), {0}, 0, watch, 3.5, LIMIT)[0] == 1
    # another live spare ranks before this one: it gets slot 1, this one slot 2 ...
    _, watch = decide((1, 2), {0}, 1, None, 0.0, LIMIT)
    assert watch == Watch(2, 0.0) and decide((1, 2), {0}, 1, watch, 3.5, LIMIT)[0] == 2
    # ... and nothing when one slot only is orphaned
    assert decide((1,), {0, 2}, 1, None, 0.0, LIMIT) == (None, Watch(None, 0.0))
    # when the spare before it leaves (it took slot 1), this one's slot changes: a full count again
    _, watch = decide((1,), {0, 2}, 1, None, 0.0, LIMIT)
    taken, watch = decide((1,), {0, 2}, 0, watch, 50.0, LIMIT)
    assert (taken, watch) == (None, Watch(1, 50.0))
    assert rank("spare-b", {"spare-a", "spare-b", "spare-c"}) == 1 and rank("spare-a", {"spare-b"}) == 0


def test_the_limit_defaults_to_the_runs_stall_timeout():
    cfg = RunConfig(run="r", env_id="AppleCollect-v1", steps=1000, algo=resolve("ma-ddpg"), stall_timeout=120.0)
    assert take_over_limit(cfg, None) == 120.0 and take_over_limit(cfg, 3.0) == 3.0
    assert take_over_limit(cfg, 0.1) == MIN_TAKE_OVER_S
    assert take_over_limit(RunConfig(run="r", env_id="e", steps=1, algo=resolve("ma-ddpg"), stall_timeout=0), None) \
        == 300.0  # no stall policy


def test_no_slot_is_orphaned_while_a_live_worker_has_not_said_its_slot(caplog):
    """A live worker without a report may hold any slot; if that lasts, the spare says why it waits."""
    cfg = RunConfig(run="r", env_id="AppleCollect-v1", steps=1000, algo=resolve("ma-ddpg"))
    spare = Spare(cfg, None, "spare-0", LIMIT, None, None)
    with caplog.at_level(logging.INFO, logger="mam.spare"):
        assert spare.unreported({"w1"}, 0.0) and spare.unreported({"w1"}, LIMIT)
        assert "have sent no report" not in caplog.text
        assert spare.unreported({"w1"}, LIMIT + 0.1) and not spare.unreported(set(), LIMIT + 0.2)
    assert caplog.text.count("live workers ['w1'] have sent no report for 3 s") == 1


# --------------------------------------------------------------------------- the command line


@pytest.mark.parametrize("argv, says", [
    (["--spare", "--slot", "1"], "--spare holds no slot"),
    (["--spare", "--slot", "0"], "--spare holds no slot"),
    (["--take-over-after", "5"], "--take-over-after is for a spare"),
])
def test_spare_options_that_do_not_go_together_are_refused(argv: list[str], says: str):
    out = subprocess.run([sys.executable, "-m", "services.roles.worker", "--run", "r", *argv], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 2, out
    assert says in out.stderr and "Invalid value" in out.stderr


def test_worker_help_names_the_spare_options():
    out = subprocess.run([sys.executable, "-m", "services.roles.worker", "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0
    assert "--spare" in out.stdout and "--take-over-after" in out.stdout and "--stall-timeout" in out.stdout


# --------------------------------------------------------------------------- spares on real sessions


class FakeRun:
    """The learner's stats and the workers' tokens and reports, as a run publishes them."""

    def __init__(self, stack: ExitStack, run: str) -> None:
        self.run, self.stack = run, stack
        self.endpoint = bus.loopback_endpoint(bus.free_tcp_port())
        self.hub = self.session(listen=True)
        self.side = self.session()
        self.stats = bus.declare_latest_publisher(self.side, keys.learner_stats(run))
        self.awaiting: tuple[int, ...] = ()
        self.workers: dict[str, tuple[object, role.RoleReport, int]] = {}
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._publish, daemon=True)
        self.thread.start()
        stack.callback(self.close)

    def session(self, listen: bool = False):
        conf = bus.make_config(listen=[self.endpoint]) if listen else bus.make_config(connect=[self.endpoint])
        s = bus.open_session(conf, retry_for=10)
        self.stack.callback(s.close)
        return s

    def worker(self, worker_id: str, slot: int) -> None:
        token = bus.declare_alive(self.side, self.run, "worker", worker_id)
        self.workers[worker_id] = (token, role.RoleReport(self.side, self.run, "worker", worker_id, 0.0), slot)

    def close(self) -> None:
        self.stopped.set()
        self.thread.join(5)

    def leave(self, worker_id: str) -> None:
        self.workers.pop(worker_id)[0].undeclare()

    def _publish(self) -> None:
        seq = 0
        while not self.stopped.wait(0.1):
            seq += 1
            self.stats.put(LearnerStats(env_steps=seq, updates=0, accept_until=0, utd=0.0,
                                        awaiting=self.awaiting).to_bytes("learner", seq))
            for _, report, slot in list(self.workers.values()):
                report.publish({"slot": slot, "sent_rows": seq}, seq=seq)


@pytest.mark.slow
def test_spares_share_orphaned_slots_by_rank_and_leave_when_the_run_is_done(caplog):
    """Three spares, two slots orphaned one after the other: the first (by id) takes the first,
    the second the next one, neither takes a slot the other took; the third says it was not
    needed when the run ends."""
    caplog.set_level(logging.INFO, logger="mam.spare")
    run = unique_run("spares")
    cfg = RunConfig(run=run, env_id="AppleCollect-v1", steps=1000, algo=resolve("ma-ddpg", workers=3))
    with ExitStack() as stack:
        fake = FakeRun(stack, run)
        for i in range(3):
            fake.worker(f"w{i}", i)
        spares = {i: Spare(cfg, fake.session(), i, 2.0, None, None) for i in ("spare-a", "spare-b", "spare-c")}
        results: dict[str, tuple[int | None, float]] = {}
        threads = [threading.Thread(target=lambda i=i: results.__setitem__(i, spares[i].wait()), daemon=True)
                   for i in spares]
        for t in threads:
            t.start()
        stack.callback(lambda: [setattr(s, "stop_requested", True) for s in spares.values()])
        seen = bus.watch_alive(fake.side, run, keys.SPARE)
        assert seen.wait_for(lambda live: live == set(spares), timeout=10)
        time.sleep(0.5)  # every spare sees the others
        fake.awaiting = (1,)
        fake.leave("w1")
        started = time.monotonic()
        assert _wait(lambda: "spare-a" in results, 15), results
        assert results["spare-a"][0] == 1 and results["spare-a"][1] > 2.0
        assert time.monotonic() - started > 2.0
        fake.worker("spare-a", 1)  # spare-a serves slot 1 now (the learner still awaits it)
        time.sleep(4.0)  # longer than the limit: spare-b (now first) must not take slot 1 too
        assert set(results) == {"spare-a"}
        fake.awaiting = (1, 2)
        fake.leave("w2")
        assert _wait(lambda: "spare-b" in results, 15), results
        assert results["spare-b"][0] == 2
        time.sleep(1.0)
        assert set(results) == {"spare-a", "spare-b"}
        done = bus.declare_latest_publisher(fake.side, keys.done(run))
        done.put(Done("budget", 1000, 0).to_bytes("learner", 1))
        assert _wait(lambda: "spare-c" in results, 10)
        assert results["spare-c"] == (None, 0.0)
        seen.close()
    assert f"run {run} is done: spare spare-c was not needed" in caplog.text


def _wait(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


# --------------------------------------------------------------------------- a real run


SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "3"]


@pytest.mark.slow
def test_a_spare_takes_over_the_slot_of_a_killed_worker(tmp_path: Path) -> None:
    run, endpoint = unique_run("spare"), bus.loopback_endpoint(bus.free_tcp_port())
    steps = 3000
    learner = spawn("learner", "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--schedule", "equal-data",
                    "--steps", str(steps), "--start-steps", "300", "--compete-every", "500", "--eliminate-at",
                    "1000000", *SMALL, "--workers", "3", "--seed", "5", "--run", run, "--listen", endpoint,
                    "--run-dir", str(tmp_path), log=tmp_path / "learner.log")
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(tmp_path),
                    log=tmp_path / "referee.log")
    ws = {f"w{i}": spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i),
                         "--run-dir", str(tmp_path), log=tmp_path / f"w{i}.log") for i in range(3)}
    spare_log = tmp_path / "spare.log"
    spare = None
    session = bus.open_session(bus.make_config(connect=[endpoint]), retry_for=30)
    stats = bus.Latest.subscribe(session, keys.learner_stats(run))

    def learner_at() -> int:
        item = stats.get(keys.learner_stats(run))
        return LearnerStats.from_bytes(item.payload).iteration if item is not None else 0

    try:
        assert _wait(lambda: learner_at() > 50, 120), "the run did not start"
        spare = spawn("worker", "--run", run, "--connect", endpoint, "--id", "spare-0", "--spare",
                      "--take-over-after", str(LIMIT), "--run-dir", str(tmp_path), log=spare_log)
        assert _wait(lambda: spare_log.is_file() and "waits on run" in spare_log.read_text(), 60)
        assert _wait(lambda: learner_at() > 300, 120), "the run did not reach iteration 300"
        assert "takes over slot" not in spare_log.read_text()  # every worker was live so far
        assert "the learner awaits its rows" not in spare_log.read_text()
        ws["w1"].send_signal(signal.SIGKILL)
        ws["w1"].wait()
        assert _wait(lambda: "takes over slot" in spare_log.read_text(), 30), spare_log.read_text()[-2000:]
        assert _wait(lambda: (tmp_path / "summary.json").is_file(), 120), "the run did not finish"
        for name, p in [*ws.items(), ("spare", spare)]:
            if name != "w1":
                assert p.wait(60) == 0, name
        assert learner.wait(60) == 0
    finally:
        stats.close()
        session.close()
        stop(*ws.values(), *([spare] if spare is not None else []), referee, learner)
    text = spare_log.read_text()
    assert "spare spare-0 takes over slot 1: its worker has been gone" in text
    assert "taking slot 1 over at iteration" in text
    transport = json.loads((tmp_path / "transport.json").read_text())
    assert transport["env_steps"] == steps and transport["lost"] == 0
    assert any(s.startswith("spare-0/") for s in transport["rows_per_stream"])
    assert processes_of(run) == []
    # The spare rebuilt slot 1 from its current episode: the run is the seed's, equal to the reference.
    assert "every observation equal" in text
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["exact"] is True, summary
    cfg = resolve("ma-ddpg", schedule="equal-data", start_steps=300, compete_every=500, eliminate_at=1_000_000,
                  hidden=(32, 32), batch_size=32, eval_episodes=3, workers=3, seed=5)
    ref = run_reference("AppleCollect-v1", cfg, steps)
    assert [e["returns"] for e in read_jsonl(tmp_path / "eval.jsonl")] == [e["returns"] for e in ref.evaluations]
    _, params = read_policy_file(tmp_path / "checkpoints" / "policy.npz")
    assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
