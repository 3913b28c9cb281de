"""A slot rebuilt mid-run (services/roles/takeover.py) continues exactly as the uninterrupted
slot: episode replay and stream fast-forward (mam_core/slot.py), the plan's count of a slot's
draws (Algorithm1.slot_steps), and the learner's answer with the slot's current episode
(services/roles/episodes.py)."""

from __future__ import annotations

import numpy as np
import pytest

import tests.hidden_env  # noqa: F401  (registers HiddenNoise-v0)
from mam_core.algorithm1 import Algorithm1
from mam_core.config import resolve
from mam_core.envs import make_env
from mam_core.policy import GAUSSIAN_POLICY, EnvSpec, NumpyActors
from mam_core.replay import ReplayBuffer
from mam_core.schedule import Schedule
from mam_core.slot import SlotStreams, act, replay_episode, uniform
from services.messaging import keys
from services.messaging.codec import MessageError, SlotEpisode, TransitionBatch
from services.roles.episodes import SlotEpisodes
from services.roles.lockstep import SlotStage


@pytest.mark.parametrize("mode,eliminate_at,steps", [("paper", 6, 10), ("paper", 6, 9), ("equal-data", 7, 20),
                                                     ("paper", None, 8)])
def test_slot_steps_count_what_the_plan_steps(mode: str, eliminate_at: int | None, steps: int) -> None:
    s = Schedule(mode, slots=3, steps=steps, start=4, compete_every=3, eliminate_at=eliminate_at)
    plan = Algorithm1(s, batch_size=4, policy_delay=2, eval_every=5)
    for slot in range(3):
        for index in range(1, plan.iterations + 2):
            its = [plan.iteration(i) for i in range(1, index) if slot in plan.iteration(i).slots]
            assert plan.slot_steps(slot, index) == (sum(it.random for it in its), sum(not it.random for it in its))


def run_slot(env_id: str, slot: int, plan: Algorithm1, cfg, upto: int, policy, start_at: int = 1, env=None,
             streams: SlotStreams | None = None, obs=None):
    """The slot's iterations start_at..upto as the worker and the reference step them: (rows, episode starts)."""
    env = env or make_env(env_id)
    if streams is None:
        streams = SlotStreams.for_slot(cfg.seed, slot)
        obs = streams.seed_env(env)
    max_action = np.asarray(env.action_space.high, np.float32)
    rows, starts, first = [], [], start_at == 1
    for i in range(start_at, upto):
        it = plan.iteration(i)
        if slot not in it.slots:
            continue
        action = uniform(env) if it.random else act(policy, obs, streams.noise, cfg, max_action)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        next_obs = np.asarray(next_obs, np.float32)
        if first:
            starts.append(i)
        rows.append((i, obs, action, next_obs))
        first = terminated or truncated
        obs = streams.reset(env, i + 1) if first else next_obs
    return rows, starts


@pytest.mark.parametrize("env_id,algo,cuts", [("AppleCollect-v1", "ma-td3", (1, 2, 57, 130, 131, 260)),
                                              ("InvertedPendulum-v5", "ma-td3", (40, 333)),
                                              ("InvertedPendulum-v5", "ma-sac", (150, 260))])
def test_a_rebuilt_slot_continues_exactly_as_the_uninterrupted_one(env_id: str, algo: str,
                                                                   cuts: tuple[int, ...]) -> None:
    """Cut the slot at iteration t, rebuild it in a fresh env from its current episode, step on:
    every later row equals the uninterrupted slot's (random phase, Gaussian noise or SAC's sampled
    actions, episode resets)."""
    cfg = resolve(algo, workers=2, actors=2, start_steps=100, seed=11)
    plan = Algorithm1.for_run(cfg, 400)
    if cfg.stochastic:  # a squashed Gaussian: the slot's noise stream draws its ε
        actors = NumpyActors(1, EnvSpec.from_env(make_env(env_id)), (8,), GAUSSIAN_POLICY)
        actors.load_member(0, {n: np.full(shape, 0.05, np.float32) for n, shape in actors.shapes.items()})
        policy = actors.policy(0)
    else:
        def policy(obs: np.ndarray) -> np.ndarray:
            return np.tanh(np.resize(obs, 1 if env_id.startswith("Inverted") else 2)).astype(np.float32) * 0.1

    whole, starts = run_slot(env_id, 1, plan, cfg, plan.iterations + 1, policy)
    assert len(starts) > 2  # several episodes
    for t in cuts:
        start = max([s for s in starts if s <= t] or [t]) if t > 1 else 1
        episode = [r for r in whole if start <= r[0] < t]
        env, streams = make_env(env_id), SlotStreams.for_slot(cfg.seed, 1)
        o, a = env.observation_space.shape[0], env.action_space.shape[0]
        replayed = replay_episode(env, streams, start, t, np.array([r[1] for r in episode]).reshape(-1, o),
                                  np.array([r[2] for r in episode]).reshape(-1, a),
                                  np.array([r[3] for r in episode]).reshape(-1, o))
        assert replayed.mismatch == ""
        streams.fast_forward(env, *plan.slot_steps(1, t))
        rest, _ = run_slot(env_id, 1, plan, cfg, plan.iterations + 1, policy, start_at=t, env=env, streams=streams,
                           obs=replayed.obs)
        tail = [r for r in whole if r[0] >= t]
        assert len(rest) == len(tail)
        for a, b in zip(rest, tail):
            assert a[0] == b[0] and all(np.array_equal(x, y) for x, y in zip(a[1:], b[1:])), (t, a[0])


def test_an_env_with_randomness_outside_the_seed_is_caught_at_its_first_observation() -> None:
    cfg = resolve("td3", workers=1, start_steps=50, seed=2)
    plan = Algorithm1.for_run(cfg, 60)
    rows, starts = run_slot("HiddenNoise-v0", 0, plan, cfg, 30, lambda obs: obs)
    replayed = replay_episode(make_env("HiddenNoise-v0"), SlotStreams.for_slot(2, 0), 1, 30,
                              np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                              np.array([r[3] for r in rows]))
    assert replayed.mismatch == "the observation before iteration 1 (step 0 of the episode that starts at 1) differs"


def _batch(seq: int, iteration: int, obs: np.ndarray, starts: tuple[int, ...] = ()) -> TransitionBatch:
    n = len(obs)
    return TransitionBatch("w1", "a", seq, 0, -1, obs, obs[:, :1] * 0.0, np.zeros(n, np.float32), obs + 0.5,
                           np.zeros(n, np.bool_), iteration=iteration, slot=1, episode_starts=starts)


def test_the_learners_answer_holds_the_current_episode_from_the_replay_and_the_stage() -> None:
    """Slot 1 of 2; iteration t's rows are inserted in slot order, so slot 1's row of iteration t
    is row 2(t-1)+1. Its episode began at iteration 3; iterations 6-7 are staged, 7 starting anew."""
    plan = Algorithm1(Schedule("equal-data", slots=2, steps=40, start=0, compete_every=10, eliminate_at=None),
                      batch_size=4, policy_delay=2, eval_every=100)
    buffer, stage, episodes = ReplayBuffer(64, 2, 1), SlotStage(2), SlotEpisodes(plan)
    obs = np.arange(40, dtype=np.float32).reshape(20, 2)  # slot 1's observation at iteration t: obs[t]
    stage.add(_batch(0, 1, obs[1:6], starts=(0, 2)))  # episodes begin at iterations 1 and 3
    for t in range(1, 6):
        other = np.full((1, 2), -1.0, np.float32)
        rows = {"obs": np.concatenate([other, obs[t:t + 1]])}
        _, sources, _ = stage.take(t, (1,))
        buffer.add_batch(rows["obs"], np.zeros((2, 1), np.float32), np.zeros(2, np.float32), rows["obs"] + 0.5,
                         np.zeros(2, np.bool_))
        episodes.inserted(t, (0, 1), [(sources[0][0], 0)] + sources)  # (slot 0's row: not an episode start)
    assert episodes.start[1] == 3
    answer = episodes.answer(1, stage, buffer)
    assert (answer.start, answer.next) == (3, 6) and np.array_equal(answer.obs, obs[3:6])
    assert np.array_equal(answer.next_obs, obs[3:6] + 0.5)
    stage.add(_batch(1, 6, obs[6:8], starts=(1,)))  # staged, not inserted; a new episode at iteration 7
    answer = episodes.answer(1, stage, buffer)
    assert (answer.start, answer.next) == (7, 8) and np.array_equal(answer.obs, obs[7:8])
    back = SlotEpisode.from_bytes(answer.to_bytes("learner", 0), 2, 1)
    assert (back.start, back.next, back.why) == (7, 8, "") and np.array_equal(back.obs, answer.obs)
    small = ReplayBuffer(4, 2, 1)  # the episode has left a small replay
    small.add_batch(obs[:12], np.zeros((12, 1), np.float32), np.zeros(12, np.float32), obs[:12], np.zeros(12, bool))
    gone = SlotEpisodes(plan, inserted_through=6)
    gone.start[1] = 3
    assert "has left the replay" in gone.answer(1, SlotStage(2, start=7), small).why
    # The reply on the query key: slot 1's answer, encoded; no answer for another key or before a stage.
    seqs = iter(range(5, 10))
    reply = episodes.reply(keys.episode("run", 1), stage, buffer, "learner", lambda: next(seqs))
    back = SlotEpisode.from_bytes(reply, 2, 1)
    assert (back.slot, back.start, back.next) == (1, 7, 8) and np.array_equal(back.obs, obs[7:8])
    assert episodes.reply(keys.episode("run", 2), stage, buffer, "learner", lambda: 0) is None  # no slot 2
    assert episodes.reply(keys.episode("run", 1), None, buffer, "learner", lambda: 0) is None
    assert episodes.reply("mam/run/episode/spare", stage, buffer, "learner", lambda: 0) is None


def test_slot_episode_and_episode_starts_are_validated() -> None:
    good = SlotEpisode(0, 5, 7, np.zeros((2, 3)), np.zeros((2, 1)), np.zeros((2, 3)))
    with pytest.raises(MessageError):  # the rows do not match next - start
        SlotEpisode.from_bytes(SlotEpisode(0, 5, 8, good.obs, good.action, good.next_obs).to_bytes("l", 0), 3, 1)
    with pytest.raises(MessageError):  # the wrong observation width
        SlotEpisode.from_bytes(good.to_bytes("l", 0), 4, 1)
    from services.messaging.codec import TransitionSpec
    spec = TransitionSpec(2, 1, 1)
    with pytest.raises(MessageError):
        TransitionBatch.from_bytes(_batch(0, 1, np.zeros((2, 2), np.float32), starts=(2,)).to_bytes(), spec)
    assert TransitionBatch.from_bytes(_batch(0, 1, np.zeros((2, 2), np.float32), starts=(1,)).to_bytes(),
                                      spec).episode_starts == (1,)


@pytest.mark.slow
def test_a_restarted_worker_on_an_env_with_hidden_randomness_is_reported_and_the_run_finishes(tmp_path) -> None:
    """`mam run` on an env whose observations carry noise outside every seed: the worker restarted
    after a SIGKILL cannot replay its slot's episode; it says so, the run finishes its budget in
    lock-step, and summary.json names the env, the slot and the step."""
    import json
    import signal
    import subprocess
    import sys

    from tests.e2e import ROOT, processes_of, signal_when, unique_run

    run_dir, name = tmp_path / "hidden", unique_run("hidden")
    args = ["--env", "tests.hidden_env:HiddenNoise-v0", "--algo", "ma-ddpg", "--steps", "1200", "--workers", "3",
            "--actors", "2", "--start-steps", "200", "--compete-every", "300", "--eliminate-at", "900",
            "--eval-episodes", "1", "--eval-every", "600", "--hidden", "16,16", "--batch-size", "16", "--seed", "1",
            "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        signal_when(run_dir, f"services.roles.worker --run {name} .*--id w1 ", 300, signal.SIGKILL, proc)
        out, _ = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exact"] is False and summary["env_steps"] == 3 * 900 + 300, summary
    why = summary["inexact"]
    assert "tests.hidden_env:HiddenNoise-v0 replayed slot 1's episode differently" in why, why
    assert "the env is not deterministic" in why and "iteration" in why
    assert processes_of(name) == []
