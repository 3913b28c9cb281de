"""`mam watch` without the network: MonitorState fed with decoded messages, rendered to text."""

import pytest
from rich.console import Console

from mam_core.config import resolve
from services.roles.monitor_view import MonitorState, PlainLines, render


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _text(state: MonitorState) -> str:
    console = Console(record=True, width=140, color_system=None)
    console.print(render(state))
    return console.export_text()


def _stats(env_steps: int, updates: int, received: dict[str, int], done: bool = False) -> dict:
    return {
        "env_steps": env_steps, "updates": updates, "accept_until": env_steps + 500, "utd": 0.98,
        "losses": {"critic": 0.125, "actor": -3.5}, "q_means": [12.5, 20.25], "versions": [40, 41],
        "per_worker": {w: {"received": n, "last_seq": n // 50, "actor": i % 2, "lag": i, "rate": None}
                       for i, (w, n) in enumerate(received.items())},
        "rejected": {"bad_shape": 2}, "done": done,
    }


def _allocation(rnd: int, step: int, p: list[float], counts: list[int], slots: dict, survivor=None, reason="round"):
    return {"t": 1.0, "round": rnd, "env_steps": step, "returns": None, "probabilities": p, "counts": counts,
            "slots": slots, "eliminated": [survivor is not None and k != survivor for k in range(len(p))],
            "survivor": survivor, "reason": reason}


def test_empty_state_renders_waiting():
    state = MonitorState(now=FakeClock())
    text = _text(state)
    assert "waiting for learner" in text
    assert "no workers yet" in text
    assert "no allocation yet" in text


def test_state_tracks_allocation_eval_and_rates():
    clock = FakeClock(100.0)
    state = MonitorState(run="r1", env_id="Hopper-v5", algo="ma-td3", steps=1_000_000, now=clock)
    state.on_config({"run": "r1", "env_id": "Hopper-v5", "algo": "ma-td3", "steps": 1_000_000,
                     "algo_config": resolve("ma-td3", schedule="equal-data").to_dict()})
    state.on_alive("learner", "0", True)
    for w in ("w0", "w1", "w2"):
        state.on_alive("worker", w, True)
    state.on_allocation(_allocation(0, 0, [0.5, 0.5], [2, 1], {"w0": 0, "w1": 0, "w2": 1}, reason="initial"))
    state.on_allocation(_allocation(1, 5_000, [0.25, 0.75], [1, 2], {"w0": 1, "w1": 0, "w2": 1}))
    assert state.probabilities == [0.25, 0.75]
    assert state.counts == [1, 2]
    assert state.workers["w0"].actor == 1
    assert len(state.history) == 2

    state.on_eval({"t": 2.0, "round": 1, "env_steps": 5_000, "returns": [[1.0, 2.0], [3.0, 5.0]],
                   "mean": [1.5, 4.0], "versions": [10, 10], "bias": None})
    assert state.last_mean == [1.5, 4.0]

    state.on_stats(_stats(10_000, 8_000, {"w0": 3_000, "w1": 3_000, "w2": 4_000}))
    assert state.steps_per_s is None  # one stats message gives no rate yet
    clock.t = 102.0
    state.on_stats(_stats(12_000, 9_000, {"w0": 3_800, "w1": 3_000, "w2": 5_200}))
    assert state.steps_per_s == pytest.approx(1_000.0)
    assert state.updates_per_s == pytest.approx(500.0)
    assert state.workers["w0"].rate == pytest.approx(400.0)  # derived from received when rate is absent
    assert state.workers["w2"].received == 5_200
    assert state.workers["w0"].last_seen == 102.0
    assert state.workers["w1"].last_seen == 100.0  # nothing new from w1 in the second stats

    clock.t = 105.0
    state.on_alive("worker", "w1", False)
    assert state.workers["w1"].alive is False
    assert state.workers["w1"].last_seen == 105.0
    clock.t = 107.5
    assert state.seconds_ago(state.workers["w1"].last_seen) == pytest.approx(2.5)

    text = _text(state)
    for expected in ("r1", "ma-td3", "Hopper-v5", "12,000 / 1,000,000", "0.250", "0.750", "500.0", "1000.0",
                     "w0", "w1", "w2", "gone", "alive", "2.5s ago", "bad_shape=2", "4.00"):
        assert expected in text, expected
    assert "waiting for learner" not in text


def test_elimination_marks_survivor_and_keeps_last_returns():
    state = MonitorState(now=FakeClock())
    for w in ("w0", "w1", "w2"):
        state.on_alive("worker", w, True)
    state.on_allocation(_allocation(1, 1_000, [0.2, 0.3, 0.5], [1, 1, 3], {"w0": 0, "w1": 1, "w2": 2}))
    state.on_eval({"t": 3.0, "round": 2, "env_steps": 24_000, "returns": [[1.0], [2.0], [9.0]],
                   "mean": [1.0, 2.0, 9.0], "versions": [1, 1, 1], "bias": None})
    state.on_allocation(_allocation(2, 24_000, [0.0, 0.0, 1.0], [0, 0, 3], {"w0": 2, "w1": 2, "w2": 2},
                                    survivor=2, reason="elimination"))
    # After elimination only the survivor is evaluated; the others keep their last return.
    state.on_eval({"t": 4.0, "round": 3, "env_steps": 25_000, "returns": [[], [], [10.0]],
                   "mean": [None, None, 10.0], "versions": [1, 1, 2], "bias": None})
    assert state.survivor == 2
    assert state.eliminated == [True, True, False]
    assert state.last_mean == [1.0, 2.0, 10.0]
    assert [state.actor_status(k) for k in range(3)] == ["eliminated", "eliminated", "survivor"]
    assert {w.actor for w in state.workers.values()} == {2}

    state.on_stats(_stats(25_000, 24_000, {"w0": 9_000}, done=True))
    state.on_done({"final_returns": [1.0, 2.0, 10.0], "survivor": 2, "env_steps": 25_000, "updates": 24_000,
                   "wall_time_s": 321.0})
    text = _text(state)
    assert "survivor" in text and "eliminated" in text
    assert "1.000" in text and "elimination" in text
    assert "done" in text and "321s" in text


def _paper_demo_state(clock: FakeClock) -> MonitorState:
    """MA-DDPG under the paper's schedule: 4,000 iterations, C = 3,000, M = 5: 16,000 transitions."""
    state = MonitorState(now=clock)
    algo = resolve("ma-ddpg", eliminate_at=3000, compete_every=200, start_steps=400)
    state.on_config({"run": "demo", "env_id": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 4000,
                     "algo_config": algo.to_dict()})
    return state


def test_header_counts_each_figure_in_one_unit():
    """Iterations against T and transitions against the budget in transitions, never mixed."""
    clock = FakeClock(100.0)
    state = _paper_demo_state(clock)
    state.on_stats(_stats(12_000, 2_000, {"w0": 6_000}))
    text = _text(state)
    assert "iteration 2,400 / 4,000" in text and "transitions 12,000 / 16,000" in text
    assert "12,000 / 4,000" not in text
    assert state.at(15_500) == "iteration 3,500 (15,500 transitions)"


def test_plain_lines_one_per_update():
    """`mam watch` without a terminal: a line per config, allocation (with R_k), evaluation and done;
    learner progress at most every few seconds."""
    clock = FakeClock(100.0)
    state = _paper_demo_state(clock)
    lines = PlainLines(state, every_s=5.0)
    assert lines.after("config") == ["run demo · ma-ddpg · AppleCollect-v1: budget 4,000 iterations "
                                     "(16,000 transitions)"]
    state.on_allocation({**_allocation(3, 3_000, [0.5, 0.3, 0.2], [3, 1, 1], {"w0": 0}),
                         "returns": [49.94, 9.96, -1.0000000000000004]})
    assert lines.after("allocation") == ["allocation round 3 (round) at iteration 600 (3,000 transitions): "
                                         "R=[49.94 9.96 -1.00] P=[0.50 0.30 0.20] I=[3 1 1]"]
    state.on_eval({"env_steps": 3_000, "mean": [49.94, None, -1.0]})
    assert lines.after("eval") == ["evaluation at iteration 600 (3,000 transitions): mean returns [49.94 — -1.00]"]
    state.on_stats(_stats(3_000, 200, {"w0": 3_000}))
    assert lines.after("stats") == ["iteration 600 / 4,000   transitions 3,000 / 16,000   updates 200"]
    clock.t = 102.0
    state.on_stats(_stats(3_500, 300, {"w0": 3_500}))
    assert lines.after("stats") == []  # within every_s of the last progress line
    clock.t = 106.0
    state.on_stats(_stats(4_000, 400, {"w0": 4_000}))
    assert lines.after("stats") == ["iteration 800 / 4,000   transitions 4,000 / 16,000   updates 400   "
                                    "125.0 transitions/s   25.0 updates/s"]
    state.on_done({"survivor": 0, "wall_time_s": 171.2, "final_returns": [49.94, None, None]})
    assert lines.after("done") == ["done in 171 s: final returns [49.94 — —], survivor 0"]


def test_split_role_workers_under_their_ids_and_the_returns_the_elimination_was_decided_on():
    """Workers b0 and b1 (split roles), an exact-mode allocation whose slots are named w0 and w1,
    and an elimination decided on R = [49.94 49.94 49.94] after a curve evaluation that gave
    actor 1 -1.00: no w0/w1 rows, and every actor shows 49.94 (what eval.jsonl holds)."""
    state = MonitorState(now=FakeClock())
    for w in ("b0", "b1"):
        state.on_alive("worker", w, True)
    state.on_allocation(_allocation(0, 0, [1 / 3] * 3, [1, 1, 0], {"w0": 0, "w1": 1}, reason="initial"))
    state.on_eval({"env_steps": 2_000, "mean": [49.94, -1.0, 9.96]})
    state.on_stats(_stats(3_000, 1_000, {"b0": 1_500, "b1": 1_500}))
    state.on_allocation({**_allocation(1, 3_000, [0.0, 0.0, 1.0], [0, 0, 2], {"w0": 2, "w1": 2}, survivor=2,
                                       reason="elimination"), "returns": [49.94, 49.94, 49.94]})
    state.on_eval({"env_steps": 3_200, "mean": [None, None, 49.94]})  # only the survivor from now on
    assert sorted(state.workers) == ["b0", "b1"]
    assert [state.shown_return(k) for k in range(3)] == [49.94, 49.94, 49.94]
    text = _text(state)
    rows = [line.split() for line in text.splitlines()]
    assert not [r for r in rows if r and r[0].strip("│┃ ") in ("w0", "w1")], text
    assert any("b0" in r[0] or (len(r) > 1 and r[1] == "b0") for r in rows if r), text
    assert "-1.00" not in text, text
    assert text.count("49.94") == 3, text


@pytest.mark.slow
def test_watch_a_split_role_run_with_workers_b0_b1_through_its_elimination(tmp_path):
    """Real processes on loopback: a learner, a referee and workers `b0`/`b1` (slots 0 and 1, whose
    allocation names the slots w0/w1), watched by `watch` to the end: only b0 and b1 are listed, and
    every actor shows the return eval.jsonl and the elimination hold."""
    import json

    from services.messaging import bus
    from services.roles.monitor import watch
    from services.run.rundir import read_jsonl
    from tests.e2e import processes_of, spawn, stop, unique_run

    run = unique_run("watch-split")
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    common = ["--run", run, "--connect", endpoint, "--run-dir", str(tmp_path)]
    procs = [spawn("learner", "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--actors", "2", "--workers", "2",
                   "--steps", "400", "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300",
                   "--hidden", "16,16", "--batch-size", "16", "--eval-episodes", "2", "--eval-every", "100",
                   "--run", run, "--listen", endpoint, "--run-dir", str(tmp_path), log=tmp_path / "learner.log"),
             spawn("referee", *common, log=tmp_path / "referee.log")]
    procs += [spawn("worker", *common, "--id", f"b{i}", "--slot", str(i), log=tmp_path / f"b{i}.log")
              for i in range(2)]
    try:
        console = Console(record=True, width=160, force_terminal=False)
        state = watch(run, bus.make_config(connect=[endpoint]), console=console, timeout=120, plain=True)
    finally:
        stop(*procs)
    assert processes_of(run) == []
    assert state.done and sorted(state.workers) == ["b0", "b1"], sorted(state.workers)
    elimination = next(r for r in read_jsonl(tmp_path / "allocation.jsonl") if r["reason"] == "elimination")
    decided = next(r for r in read_jsonl(tmp_path / "eval.jsonl") if r.get("purpose") == "elimination")
    assert elimination["returns"] == decided["mean"]
    survivor = elimination["survivor"]
    for k in range(2):
        if k != survivor:
            assert state.shown_return(k) == pytest.approx(decided["mean"][k]), (k, json.dumps(decided))
    text = _text(state)
    assert "w0" not in text and "w1" not in text, text


def test_plain_done_line_without_an_elimination_says_so():
    state = MonitorState(now=FakeClock())
    state.on_allocation(_allocation(1, 1_000, [0.5, 0.5], [1, 1], {"w0": 0, "w1": 1}))
    state.on_done({"survivor": None, "wall_time_s": 12.0, "final_returns": [1.0, 2.0]})
    assert PlainLines(state).after("done") == ["done in 12 s: final returns [1.00 2.00], no elimination in this budget"]


def test_each_actor_shows_its_own_actor_loss():
    state = MonitorState(now=FakeClock())
    state.on_allocation(_allocation(1, 1_000, [0.5, 0.5], [1, 1], {"w0": 0, "w1": 1}))
    state.on_stats({**_stats(2_000, 1_000, {"w0": 1_000}),
                    "losses": {"critic": 0.5, "actor": -7.0, "actor0": -2.25, "actor1": -4.75}})
    text = _text(state)
    assert "actor loss (sum) -7" in text and "-2.25" in text and "-4.75" in text, text
