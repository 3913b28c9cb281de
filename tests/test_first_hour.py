"""The first hour of a newcomer (issue 19): `mam watch --run NAME` finds a local run, no silent
no-op runs, M < K explained, `mam-learner` says where it listens, the outcome in the task's words.

Real processes on loopback: `mam run` (learner, referee, workers) and `mam watch` as a user runs
them, with unique run names and ports; the registry of local runs in a temporary directory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.run.config import budget_warnings
from services.run.options import build_run_config
from tests.e2e import ROOT, processes_of, spawn, stop, unique_run

TINY = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--hidden", "32,32", "--batch-size", "32",
        "--eval-episodes", "2"]


def _env(tmp_path: Path) -> dict[str, str]:
    return dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore", MAM_RUNS_REGISTRY=str(tmp_path / "registry"))


def _mam(tmp_path: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=tmp_path, env=_env(tmp_path),
                          text=True, capture_output=True, timeout=timeout)


def _flat(text: str) -> str:
    return " ".join(text.split())  # rich wraps long lines


@pytest.mark.slow
def test_watch_finds_a_local_run_by_name_and_prints_plain_lines(tmp_path: Path) -> None:
    """`mam watch --run NAME` without --connect, output not a terminal: it finds where the run
    listens (the registry `mam run` writes), prints one plain line per update, sees the allocation
    rounds and the elimination, and exits 0 when the run is done. Then the trained policy makes
    its own env (`pi.make_env()`)."""
    run, run_dir = unique_run("watch-local"), tmp_path / "run"
    out = tmp_path / "run.out"
    with open(out, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *TINY, "--steps", "400",
                                 "--start-steps", "50", "--compete-every", "50", "--eliminate-at", "300",
                                 "--eval-every", "50", "--workers", "3", "--run", run, "--run-dir", str(run_dir),
                                 "--no-plot"], cwd=tmp_path, env=_env(tmp_path), stdout=f, stderr=subprocess.STDOUT)
    try:
        watch = _mam(tmp_path, "watch", "--run", run, "--timeout", "120", timeout=400)
        proc.wait(300)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = watch.stdout + watch.stderr
    assert watch.returncode == 0, text
    assert "Traceback" not in text and "\x1b[" not in watch.stdout  # plain: no live view, no escape codes
    assert f"run {run}: tcp/127.0.0.1:" in text and "registry" in text  # where it found the endpoint
    assert f"run {run} · ma-ddpg · AppleCollect-v1: budget 400 iterations (1,000 transitions)" in text
    rounds = [line for line in watch.stdout.splitlines() if line.startswith("allocation round")]
    assert any("(round)" in line and "R=[" in line and "P=[" in line and "I=[" in line for line in rounds), text
    assert any("(elimination)" in line and "survivor" in line for line in rounds), text
    assert "done" in watch.stdout.splitlines()[-1]
    assert proc.returncode == 0, out.read_text()
    assert not (tmp_path / "registry" / f"{run}.json").exists()  # the run took its entry out at the end
    run_text = out.read_text()
    assert f"watch live: mam watch --run {run}" in _flat(run_text)
    assert "of 49.94 possible" in _flat(run_text).split("duplicated")[-1], run_text  # the outcome, last

    from mam_core.policy import load_policy

    pi = load_policy(run_dir)
    env = pi.make_env()  # AppleCollect-v1 with the run's kwargs, registered by the call
    obs, _ = env.reset(seed=0)
    _, reward, *_ = env.step(pi(obs))
    assert env.spec.id == "AppleCollect-v1" and isinstance(reward, float)
    env.close()
    assert processes_of(run) == []


def test_watch_refuses_a_bad_name_and_gives_up_on_an_unknown_run(tmp_path: Path) -> None:
    bad = _mam(tmp_path, "watch", "--run", "bad/name*")
    assert bad.returncode == 2 and "Traceback" not in bad.stdout + bad.stderr
    assert "run name" in _flat(bad.stdout + bad.stderr)
    started = time.monotonic()
    unknown = _mam(tmp_path, "watch", "--run", unique_run("nobody"), "--timeout", "1.5")
    text = _flat(unknown.stdout + unknown.stderr)
    assert unknown.returncode == 1 and "Traceback" not in text
    assert "waiting for run" in text and "no local run" in text and "--connect" in text
    assert time.monotonic() - started < 60


def _warnings(**cli) -> str:
    return " | ".join(budget_warnings(build_run_config({"env": "AppleCollect-v1", **cli}, None)))


def test_budget_notes_name_what_is_left_out_and_the_flag():
    """The issue's run: MA-DDPG's defaults (start 10,000, C = 24,000) above a 4,000-iteration budget."""
    text = _warnings(algo="ma-ddpg", steps=4000)
    assert "no update" in text and "--start-steps 10,000" in text and "--steps 4,000 iterations" in text
    assert "no elimination: C = 24,000 iterations (--eliminate-at)" in text
    assert "no allocation round" not in text  # rounds from A = 1,000 on, in the random phase too
    text = _warnings(algo="ma-ddpg", steps=4000, compete_every=5000, eliminate_at=3000, start_steps=100)
    assert text.startswith("no allocation round: the first would be at iteration 5,000 (--compete-every 5,000)")
    assert "no update" not in text and "no elimination" not in text
    assert "transitions" in _warnings(algo="ma-ddpg", steps=4000, schedule="equal-data")  # the schedule's unit
    assert _warnings(algo="ma-ddpg", steps=4000, start_steps=400, compete_every=200, eliminate_at=3000) == ""
    assert _warnings(algo="td3", steps=100) == "no update: the budget (--steps 100 iterations) ends within the " \
                                               "random start phase (--start-steps 25,000); lower --start-steps " \
                                               "or raise --steps"


def test_fewer_slots_than_actors_is_explained():
    """M < K is allowed (each round draws the M slots from P_k) and said, with the flag for M = K."""
    text = _warnings(algo="ma-ddpg", steps=4000, start_steps=400, compete_every=200, eliminate_at=3000, workers=1)
    assert text == ("M = 1 worker slot for K = 3 actors: each round draws the 1 slot from P_k, so at least 2 "
                    "actors collect nothing in a round (all still learn from the shared replay and are evaluated); "
                    "--workers 3 gives every actor a slot")
    assert _warnings(algo="ddpg", steps=4000, start_steps=400, workers=1) == ""  # K = 1


@pytest.mark.slow
def test_mam_run_says_at_start_what_the_budget_leaves_out(tmp_path: Path) -> None:
    """`mam run --workers 1 --actors 3` with a budget inside the random phase and before C: one note per
    thing left out, and the run still ends normally."""
    run = unique_run("noop")
    r = _mam(tmp_path, "run", *TINY, "--steps", "60", "--start-steps", "80", "--compete-every", "100",
             "--eliminate-at", "200", "--workers", "1", "--actors", "3", "--allow-no-updates",
             "--run", run, "--run-dir",
             str(tmp_path / "run"), "--no-plot")
    text = _flat(r.stdout + r.stderr)
    assert r.returncode == 0, text
    for note in ("note: no update: the budget (--steps 60 iterations) ends within the random start phase "
                 "(--start-steps 80); lower --start-steps or raise --steps",
                 "note: no allocation round: the first would be at iteration 100 (--compete-every 100)",
                 "note: no elimination: C = 200 iterations (--eliminate-at) is past the budget (--steps 60)",
                 "note: M = 1 worker slot for K = 3 actors"):
        assert note in text, note
    assert processes_of(run) == []


def test_a_referee_that_comes_up_after_the_run_reached_its_budget_still_evaluates_it(tmp_path: Path) -> None:
    """A run so short that the learner reaches its budget before its referee is up (CI saw `mam
    run` wait 300 s for a referee that found the learner gone): the learner stays for the referee,
    which evaluates the final policy; every role exits 0."""
    from services.messaging import bus

    run, endpoint, run_dir = unique_run("late-referee"), bus.loopback_endpoint(bus.free_tcp_port()), tmp_path / "run"
    common = ["--run", run, "--run-dir", str(run_dir)]
    learner = spawn("learner", *TINY, "--steps", "60", "--start-steps", "40", "--workers", "1", "--actors", "2",
                    "--listen", endpoint, *common, log=tmp_path / "learner.log")
    worker = spawn("worker", *common, "--connect", endpoint, "--id", "w0", "--slot", "0", log=tmp_path / "worker.log")
    referee = None
    try:
        deadline = time.monotonic() + 120
        while "at iteration 60, " not in (tmp_path / "learner.log").read_text():  # its last checkpoint
            assert time.monotonic() < deadline and learner.poll() is None, (tmp_path / "learner.log").read_text()
            time.sleep(0.2)
        referee = spawn("referee", *common, "--connect", endpoint, log=tmp_path / "referee.log")
        for proc in (learner, worker, referee):
            assert proc.wait(120) == 0, (tmp_path / "learner.log").read_text()[-2000:]
    finally:
        stop(*(p for p in (learner, worker, referee) if p is not None))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert len(summary["final_returns"]) == 2 and summary["env_steps"] == 60, summary


@pytest.mark.slow
def test_split_learner_says_where_it_listens_and_warns_about_missing_workers(tmp_path: Path) -> None:
    """A `mam-learner` started by hand logs its endpoint and what it waits for, the budget notes, and,
    once its grace is over, that fewer than M workers are up."""
    from services.messaging import bus

    run, endpoint = unique_run("split"), bus.loopback_endpoint(bus.free_tcp_port())
    log = tmp_path / "learner.log"
    os.environ["MAM_WORKER_GRACE_S"] = "2"
    try:
        learner = spawn("learner", *TINY, "--steps", "4000", "--workers", "2", "--run", run, "--listen", endpoint,
                        "--run-dir", str(tmp_path / "run"), log=log)
    finally:
        del os.environ["MAM_WORKER_GRACE_S"]
    try:
        deadline = time.monotonic() + 120
        while "only 0 of M = 2 workers" not in log.read_text() and time.monotonic() < deadline:
            assert learner.poll() is None, log.read_text()
            time.sleep(0.5)
    finally:
        stop(learner)
    text = log.read_text()
    assert f"learner of run '{run}' listening on {endpoint}; waiting for a referee (mam-referee --run {run} " \
           f"--connect {endpoint}) and M = 2 workers" in text
    assert "note: no update" in text and "note: no elimination" in text
    assert "only 0 of M = 2 workers" in text and "--workers" in text


def test_outcome_in_the_task_s_words():
    from mam_core.envs.apple_collect import best_apple_return
    from services.run.progress import outcome_text

    cfg = build_run_config({"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 4000}, None)
    assert best_apple_return("AppleCollect-v1", {}) == pytest.approx(49.94)
    assert best_apple_return("AppleCollect-v0", {}) == pytest.approx(49.96)
    assert outcome_text(cfg, {"final_returns": [49.940000000000005, None, None], "survivor": 0}) == \
        "survivor 0 reaches the 50 apple in 6 steps: 49.94 of 49.94 possible"
    assert outcome_text(cfg, {"final_returns": [None, 9.96, None], "survivor": 1}) == \
        "survivor 1 settles for a 10 apple in 4 steps: 9.96 of 49.94 possible (the 50 apple is missed)"
    assert outcome_text(cfg, {"final_returns": [-1.0000000000000004, None, None], "survivor": 0}).startswith(
        "survivor 0 reaches no apple")
    single = build_run_config({"env": "AppleCollect-v1", "algo": "ddpg", "steps": 4000}, None)
    assert outcome_text(single, {"final_returns": [49.94], "survivor": 0}).startswith("survivor 0 reaches the 50")
    other = build_run_config({"env": "tests.envs.tiny:Tiny-v0", "algo": "td3", "steps": 100}, None)
    assert outcome_text(other, {"final_returns": [1.5], "survivor": 0}) == ""  # the done line has the returns


def test_mujoco_warnings_stay_out_of_the_terminal_and_the_working_directory(tmp_path: Path) -> None:
    """HalfCheetah's deprecated `settotalmass`: MuJoCo printed it and wrote MUJOCO_LOG.TXT in the cwd."""
    pytest.importorskip("mujoco")
    code = ("from mam_core.envs import make_env\n"
            "for _ in range(3):\n"
            "    env = make_env('HalfCheetah-v5'); env.reset(seed=0); env.close()\n"
            "print('made')\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "made" and "settotalmass" not in r.stdout + r.stderr
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_a_budget_that_trains_nothing_is_refused_with_the_flags_unless_asked(tmp_path: Path):
    """`mam run --algo sac --steps 3000`: the whole budget is the random phase (25,000): refused at once,
    naming --steps, --start-steps and --allow-no-updates; with --allow-no-updates it gets past the check."""
    from typer.testing import CliRunner

    from services.cli.app import app

    args = ["run", "--env", "Pendulum-v1", "--algo", "sac", "--steps", "3000", "--run-dir", str(tmp_path / "r")]
    r = CliRunner().invoke(app, args, env={"COLUMNS": "300"})
    text = _flat(r.output)
    assert r.exit_code == 2 and "no update" in text and "--start-steps 25,000" in text, text
    assert "--allow-no-updates" in text and "raise --steps" in text
    assert not (tmp_path / "r").exists()
    ran = []
    import services.run.launcher as launcher

    def fake_run_local(cfg, run_dir, **kw):
        ran.append(cfg.steps)
        return {"ok": True}

    original, launcher.run_local = launcher.run_local, fake_run_local
    try:
        r = CliRunner().invoke(app, [*args, "--allow-no-updates"], env={"COLUMNS": "300"})
    finally:
        launcher.run_local = original
    assert r.exit_code == 0 and ran == [3000], r.output


def test_a_learning_curve_of_few_points_names_the_flag():
    from services.run.config import curve_points

    few = build_run_config({"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 4000}, None)
    assert curve_points(few).endswith("--eval-every 400 gives 10"), curve_points(few)
    many = build_run_config({"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 4000, "eval_every": 400}, None)
    assert curve_points(many) == ""


def test_the_demo_config_shows_everything_it_promises():
    """`make run`'s deploy/demo.toml: updates, rounds, the elimination, a learning curve of more than
    a few points: no budget note, no refusal (the demo's run itself is a slow test's business)."""
    from services.run.config import curve_points, no_updates

    cfg = build_run_config({}, ROOT / "deploy" / "demo.toml")
    assert (cfg.env_id, cfg.algo.algo, cfg.steps) == ("AppleCollect-v1", "ma-ddpg", 3400)
    assert budget_warnings(cfg) == [] and no_updates(cfg) == "" and curve_points(cfg) == ""


def test_a_grid_s_plan_says_what_its_budgets_leave_out():
    """`mam experiment --dry-run` prints the notes `mam run` would: here SAC's random phase (25,000)
    covers a 3,000-iteration budget."""
    from rich.console import Console

    from mam_lab.grid import make_grid, plan
    from mam_lab.view import describe_plan

    grid = make_grid({"name": "g", "envs": ["Pendulum-v1"], "algos": ["sac"], "seeds": 1, "steps": 3000})
    console = Console(record=True, width=300)
    describe_plan(plan(grid), {}, ROOT / "runs" / "none", console)
    text = _flat(console.export_text())
    assert "note: Pendulum-v1 sac: no update: the budget (--steps 3,000 iterations)" in text, text
    assert "--eval-every" in text
