"""Issue 38, the pieces a recovery reads back: the actor versions and referee snapshots a
checkpoint keeps (pickle-free, checked against the run's shapes) and the referee's state on disk
before it reports an evaluation done (fsync)."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_core.replay import ReplayBuffer
from services.roles import referee as referee_role
from services.roles.checkpoint import load_checkpoint, save_checkpoint
from services.roles.learner_files import kept_weights_from, kept_weights_state
from services.run.config import RunConfig

ENV = "AppleCollect-v1"


def test_the_checkpoint_keeps_older_actor_versions_and_reads_them_back_checked(tmp_path: Path) -> None:
    algo = resolve("ma-ddpg", actors=2, hidden=(8, 8))
    cfg, spec = RunConfig(run="kept", env_id=ENV, steps=1000, algo=algo), EnvSpec.from_env_id(ENV)
    agent = MultiActorAgent(algo, spec)
    rng = np.random.default_rng(0)
    kept = [(v, k, v, {n: rng.normal(size=s).astype(np.float32) for n, s in agent.actor_shapes().items()})
            for v in (6, 7) for k in range(2)]
    save_checkpoint(tmp_path, agent, ReplayBuffer(10, spec.obs_dim, spec.act_dim), {"env_steps": 0}, cfg,
                    extra={"kept_weights": kept_weights_state(kept)})
    state = load_checkpoint(tmp_path)  # torch.load(weights_only=True): no pickle
    back = kept_weights_from(state["kept_weights"], agent.actor_shapes(), algo.actors)
    assert [row[:3] for row in back] == [row[:3] for row in kept]
    assert all(np.array_equal(a[3][n], b[3][n]) for a, b in zip(back, kept) for n in a[3])
    with pytest.raises(ValueError, match="not of this run's shapes"):  # another run's nets
        kept_weights_from(state["kept_weights"], {"w0": (3, 3)}, algo.actors)
    with pytest.raises(ValueError, match="not of this run's shapes"):  # an actor the run does not have
        kept_weights_from(state["kept_weights"], agent.actor_shapes(), 1)
    with pytest.raises(ValueError, match="not \\[version"):
        kept_weights_from([[1, 2, "x", {}]], agent.actor_shapes(), algo.actors)
    assert kept_weights_from([], agent.actor_shapes(), algo.actors) == []
    wrong = [[6, 0, 6, {n: torch.zeros(s) for n, s in agent.actor_shapes().items()} | {"w9": torch.zeros(1)}]]
    with pytest.raises(ValueError):
        kept_weights_from(wrong, agent.actor_shapes(), algo.actors)


def test_the_referee_state_is_fsynced_with_its_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = RunConfig(run="state", env_id=ENV, steps=300, algo=resolve("ma-ddpg", actors=2, hidden=(8, 8)))
    referee = referee_role.Referee(cfg, None, tmp_path)
    synced: list[str] = []
    real = os.fsync

    def fsync(fd: int) -> None:
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    state = tmp_path / referee_role.STATE_FILE
    referee.state.save(state, referee.wall())
    assert state.is_file() and not state.with_suffix(".json.tmp").exists()
    # the file before the rename, then its directory
    assert synced == [str(state.with_suffix(".json.tmp")), str(tmp_path)]
    assert referee_role.Referee(cfg, None, tmp_path).resumed  # a successor reads it back


def _stopped_run(run_dir: Path, save_replay: bool = True) -> RunConfig:
    """A run directory as a killed `mam run` leaves it: config.json and a verified checkpoint at
    iteration 40 (120 transitions), its replay on disk or not (--no-save-replay)."""
    from services.run.rundir import write_json

    algo = resolve("ma-ddpg", actors=2, workers=3, hidden=(8, 8), start_steps=60)
    cfg = RunConfig(run="stopped", env_id=ENV, steps=300, algo=algo, save_replay=save_replay)
    spec = EnvSpec.from_env_id(ENV)
    write_json(run_dir / "config.json", cfg.to_dict())
    buffer = ReplayBuffer(1000, spec.obs_dim, spec.act_dim)
    save_checkpoint(run_dir, MultiActorAgent(algo, spec), buffer, {"env_steps": 120, "iteration": 40}, cfg)
    return cfg


def test_a_resume_without_the_replay_says_so_and_is_not_exact(tmp_path: Path) -> None:
    from services.roles.learner import Learner

    cfg = _stopped_run(tmp_path, save_replay=False)
    learner = Learner(cfg, None, tmp_path, load_checkpoint(tmp_path))
    assert learner.iteration == 40 and len(learner.buffer) == 0
    assert "empty replay buffer" in learner.inexact and "--no-save-replay" in learner.inexact, learner.inexact
    assert "120 transitions" in learner.inexact


def test_a_resume_onto_other_library_versions_is_refused_naming_both(tmp_path: Path) -> None:
    import json
    import subprocess
    import sys

    from mam_lab.provenance import run_code
    from services.run import codecheck
    from tests.e2e import ROOT

    _stopped_run(tmp_path)
    codecheck.record(tmp_path, run_code())  # what the first part ran: this code ...
    data = json.loads((tmp_path / "code.json").read_text())
    now = data["versions"]["torch"]
    data["versions"]["torch"] = "0.0.1"  # ... but another torch
    (tmp_path / "code.json").write_text(json.dumps(data))
    got = subprocess.run([sys.executable, "-m", "services.cli", "run", "--resume", str(tmp_path)], cwd=ROOT, text=True,
                         capture_output=True, timeout=120, env=dict(os.environ, COLUMNS="300"))
    text = " ".join(got.stderr.replace("│", " ").split())
    assert got.returncode == 2, got.stdout + got.stderr
    assert f"torch 0.0.1 (the run's) vs {now} (this code)" in text and "--allow-other-code" in text, text
    assert not (tmp_path / "logs").exists()  # refused before anything started
    assert codecheck.differences(tmp_path, run_code()) == [f"torch 0.0.1 (the run's) vs {now} (this code)"]
    # Forced: the record keeps what was accepted, and the resumed learner is not exact from then on.
    codecheck.record(tmp_path, run_code(), codecheck.differences(tmp_path, run_code()))
    from services.roles.learner import Learner

    cfg = RunConfig.from_dict(json.loads((tmp_path / "config.json").read_text()))
    learner = Learner(cfg, None, tmp_path, load_checkpoint(tmp_path))
    assert "resumed with other code" in learner.inexact and "torch 0.0.1" in learner.inexact, learner.inexact


def test_a_batch_acted_with_a_learned_version_and_no_weights_digest_is_refused() -> None:
    """Issue 38 item 8, in part: a batch that does not say which weights it acted with is refused
    (counted by reason, its rows told back as rejected), not trusted; the random phase's rows
    (version -1) carry none and are taken."""
    import time

    from services.messaging import bus
    from services.messaging.codec import TransitionBatch, TransitionSpec
    from services.roles.intake import Intake

    spec = TransitionSpec(3, 2, 1, max_rows=64, max_action=1.0)
    intake = Intake(ReplayBuffer(100, 3, 2), spec, 1 << 20)
    z = np.zeros

    def batch(version: int, digest: str) -> bus.Received:
        b = TransitionBatch("w0", "a", 0, 0, version, z((2, 3), np.float32), z((2, 2), np.float32),
                            z(2, np.float32), z((2, 3), np.float32), z(2, np.bool_), iteration=1, slot=0,
                            policy_digest=digest)
        return bus.Received("mam/r/transitions/w0", b.to_bytes(), None, time.monotonic())

    assert intake.validate(batch(2, ""), [5]) is None
    assert intake.rejects.counts() == {"no_digest": 1}
    assert intake.workers["w0"].rejected_rows == 2
    assert intake.validate(batch(2, "ab" * 16), [5]) is not None
    assert intake.validate(batch(-1, ""), [5]) is not None  # the random phase


def test_learner_epochs_rise_at_every_start_and_order_incarnations(tmp_path: Path) -> None:
    """Item 5, in part: each start of a run's learner takes the next epoch from
    RUN_DIR/learner_epoch.json (durably, whatever checkpoint it resumes from), and every role
    orders learner incarnations by it."""
    from services.roles.learner_files import next_epoch
    from services.roles.role import learner_order

    assert [next_epoch(tmp_path) for _ in range(3)] == [1, 2, 3]
    assert learner_order("e10-aa") > learner_order("e9-ff") > learner_order("e9-00") > learner_order("0123abc")
    assert learner_order("") == (0, "") and learner_order("e-1") == (0, "e-1") and learner_order("ex-1")[0] == 0


def test_an_episode_query_answered_differently_by_another_process_is_not_taken() -> None:
    """Item 8, in part: a worker taking a slot over reads every answer to its episode query (real
    Zenoh sessions on loopback); when a process that is not the run's learner answers otherwise,
    none is taken (counted, logged) and it asks again; the learner's alone is taken."""
    import threading

    from services.messaging import bus, keys
    from services.messaging.codec import SlotEpisode
    from services.roles.takeover import agreed_episode
    from tests.e2e import unique_run

    run, endpoint = unique_run("answers"), bus.loopback_endpoint(bus.free_tcp_port())
    rows = np.arange(6, dtype=np.float32).reshape(2, 3)
    mine = SlotEpisode(1, 5, 7, rows, rows[:, :2], rows + 1)
    forged = SlotEpisode(1, 5, 7, rows, rows[:, :2] * 0, rows + 1)
    hub = bus.open_session(bus.make_config(listen=[endpoint]))
    sessions = [bus.open_session(bus.make_config(connect=[endpoint]), retry_for=10) for _ in range(3)]
    stop, thread = threading.Event(), None
    try:
        learner = bus.Answers(sessions[0], keys.episode_all(run))
        intruder = bus.Answers(sessions[1], keys.episode_all(run))

        def answer() -> None:
            while not stop.is_set():
                learner.poll(lambda _key, _payload: mine.to_bytes("learner", 1))
                if intruder is not None:
                    intruder.poll(lambda _key, _payload: forged.to_bytes("intruder", 1))
                time.sleep(0.01)

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        time.sleep(0.5)
        rejects = bus.RejectLog(logging.getLogger("test"), "message")
        payloads = bus.ask_all(sessions[2], keys.episode(run, 1), 5.0)
        assert len(payloads) == 2  # both answers, none merged away
        assert agreed_episode(payloads, 1, 3, 2, rejects) is None
        assert rejects.counts() == {"disagreeing_answers": 1}
        stop.set()
        thread.join(5)
        intruder.close()
        intruder = None
        stop.clear()
        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        time.sleep(0.5)
        got = agreed_episode(bus.ask_all(sessions[2], keys.episode(run, 1), 5.0), 1, 3, 2, rejects)
        assert got is not None and np.array_equal(got.action, mine.action)
    finally:
        stop.set()
        if thread is not None:  # it polls the sessions' queryables: done before they close
            thread.join(5)
        for s in (*sessions, hub):
            s.close()


def test_a_resume_of_a_config_that_lacks_settings_is_refused_naming_them(tmp_path: Path) -> None:
    """Item 7: a config.json written by an older mam lacks settings this code has; a resume would
    take this code's defaults for them silently: refused, naming each with its default."""
    import json
    import subprocess
    import sys

    from mam_lab.provenance import run_code
    from services.run import codecheck
    from tests.e2e import ROOT

    _stopped_run(tmp_path)
    codecheck.record(tmp_path, run_code())
    config = json.loads((tmp_path / "config.json").read_text())
    del config["bias_horizon"], config["algo"]["lag"]
    (tmp_path / "config.json").write_text(json.dumps(config))
    got = subprocess.run([sys.executable, "-m", "services.cli", "run", "--resume", str(tmp_path)], cwd=ROOT, text=True,
                         capture_output=True, timeout=120, env=dict(os.environ, COLUMNS="300"))
    text = " ".join(got.stderr.replace("│", " ").split())
    assert got.returncode == 2, got.stdout + got.stderr
    assert "bias_horizon not in the run's config.json (this code's default: 'critic')" in text, text
    assert "algo.lag not in the run's config.json (this code's default: 0)" in text, text
