"""The referee on its own, with made-up messages and no network: its first allocation is the one
every worker computes, a competition's allocation is tagged with where it applies, and a
restarted referee stands where its predecessor stood."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mam_core.obsolescence import competition_returns, initial_allocation
from services.messaging.codec import Allocation
from services.roles.referee import STATE_FILE, Referee
from services.run import rundir
from services.run.options import build_run_config

FLAGS = {"env": "Pendulum-v1", "algo": "ma-td3", "steps": 40, "workers": 3, "actors": 2, "start_steps": 4,
         "compete_every": 10, "eliminate_at": 30, "hidden": "8", "batch_size": 4, "lag": 2, "seed": 5}


class Sink:
    """Stands for a publisher and a JSONL log: keeps what is put or written."""

    def __init__(self) -> None:
        self.items: list[Any] = []

    def put(self, payload: bytes) -> None:
        self.items.append(Allocation.from_bytes(payload, 2))

    def write(self, row: dict[str, Any]) -> None:
        self.items.append(row)


def referee(tmp_path: Path) -> tuple[Referee, Sink, Sink]:
    r = Referee(build_run_config(FLAGS, None), None, tmp_path)
    r.alloc_pub, r.alloc_log = Sink(), Sink()
    return r, r.alloc_pub, r.alloc_log


def test_the_first_allocation_is_the_one_every_worker_computes(tmp_path: Path):
    r, pub, log = referee(tmp_path)
    r.publish_allocation(0, "initial", None)
    first = initial_allocation(r.algo, r.cfg.steps)
    assert pub.items[0].slots == {f"w{i}": k for i, k in enumerate(first)} and pub.items[0].iteration == 0
    assert log.items[0]["applies_from_iteration"] == 1 and log.items[0]["reason"] == "initial"


def test_a_competition_applies_lag_plus_one_iterations_later_and_survives_a_restart(tmp_path: Path):
    r, pub, log = referee(tmp_path)
    r.publish_allocation(0, "initial", None)
    index, purpose = r.plan.events()[0]
    assert purpose.competes
    returns = [-100.0, -300.0]
    r.state.obsolescence.record_evaluation(r.plan.iteration(index).units[1], competition_returns(returns),
                                           rng=r.state.rng)
    r.publish_allocation(index, purpose.value, returns)
    decided = pub.items[-1]
    assert decided.iteration == index and decided.previous == (0, pub.items[0].slots)
    assert log.items[-1]["applies_from_iteration"] == index + 1 + 2 == r.plan.applies_from(index)
    assert r.plan.decision_for(index + 3) == index and r.plan.decision_for(index + 2) == 0
    assert decided.probabilities[0] > decided.probabilities[1]  # the better actor is drawn more (Eq. 8)
    r.state.events_done = 1
    r.state.save(tmp_path / STATE_FILE, wall=12.5)
    again, _, _ = referee(tmp_path)  # a restarted referee reads referee_state.json
    assert again.resumed and again.state.events_done == 1 and again.state.decision == r.state.decision
    assert again.state.obsolescence.probabilities.tolist() == r.state.obsolescence.probabilities.tolist()
    assert again.state.rng.bit_generator.state == r.state.rng.bit_generator.state
    assert again.state.wall_before == 12.5 and again.state.previous == r.state.previous
    (tmp_path / STATE_FILE).write_text("{not json")  # unreadable: the evaluations start again
    fresh, _, _ = referee(tmp_path)
    assert not fresh.resumed and fresh.state.events_done == 0 and fresh.state.decision is None


def test_a_restarted_referee_drops_the_rows_it_logs_again(tmp_path: Path):
    """A referee killed after it logged an evaluation but before it saved its state: its
    successor logs that evaluation (and, with no state saved at all, the initial allocation)
    again, so the predecessor's rows past the saved state go."""
    def rows(name: str) -> list[dict[str, Any]]:
        return rundir.read_jsonl(tmp_path / name)

    def log(name: str, *tags: str) -> None:
        (tmp_path / name).write_text("".join(json.dumps({"tag": t}) + "\n" for t in tags))

    # Killed after its first round's eval row, before any state was saved: every row is done again.
    log(rundir.ALLOCATION, "initial")
    log(rundir.EVAL, "round 1")
    r, _, _ = referee(tmp_path)
    assert not r.resumed
    r.drop_rows_done_again()
    assert rows(rundir.EVAL) == [] and rows(rundir.ALLOCATION) == []
    # State saved after the first competition; killed after the next one's eval row: that row goes.
    r.state.events_done = 1
    r.state.save(tmp_path / STATE_FILE, wall=1.0)
    log(rundir.ALLOCATION, "initial", "round 1", "round 2")
    log(rundir.EVAL, "round 1", "round 2")
    again, _, _ = referee(tmp_path)
    assert again.resumed and again.plan.competitions_among(1) == 1
    again.drop_rows_done_again()
    assert [row["tag"] for row in rows(rundir.EVAL)] == ["round 1"]
    assert [row["tag"] for row in rows(rundir.ALLOCATION)] == ["initial", "round 1"]
