"""A trained policy: policy.npz, `load_policy` (numpy only), `mam eval` (returns, video)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.agent import MultiActorAgent
from mam_core.config import resolve
from mam_core.evaluation import evaluate_policy
from mam_core.policy import POLICY_FILE, EnvSpec, PolicyFileError, load_policy, read_policy_file
from mam_core.seeding import evaluation_seed
from services.roles.policy_export import write_policy
from services.run.config import RunConfig
from tests.e2e import ROOT, mam

SPEC = EnvSpec(5, 3, (0.4, 1.0, 2.0))  # per-dimension bounds, as Humanoid (±0.4) and others have


def trained_agent(spec: EnvSpec, actors: int = 3, updates: int = 20, seed: int = 0) -> MultiActorAgent:
    """A MultiActorAgent after a few real updates on random transitions."""
    cfg = resolve("ma-td3", actors=actors, hidden=(16, 8), batch_size=8, seed=seed)
    agent = MultiActorAgent(cfg, spec)
    rng = np.random.default_rng(seed)
    for _ in range(updates):
        agent.update({
            "obs": torch.as_tensor(rng.normal(size=(8, spec.obs_dim)), dtype=torch.float32),
            "action": torch.as_tensor(rng.uniform(-0.4, 0.4, size=(8, spec.act_dim)), dtype=torch.float32),
            "reward": torch.as_tensor(rng.normal(size=8), dtype=torch.float32),
            "next_obs": torch.as_tensor(rng.normal(size=(8, spec.obs_dim)), dtype=torch.float32),
            "not_done": torch.ones(8)})
    return agent


def write_run(run_dir: Path, agent: MultiActorAgent, env_id: str, survivor: int | None = None,
              env_steps: int = 1234) -> RunConfig:
    cfg = RunConfig(run="t", env_id=env_id, steps=env_steps, algo=agent.cfg)
    write_policy(run_dir, cfg, agent, env_steps, survivor)
    return cfg


def test_load_policy_returns_the_learners_actions(tmp_path: Path):
    agent = trained_agent(SPEC)
    agent.eliminate(2)
    write_run(tmp_path, agent, "AppleCollect-v0", survivor=2)
    obs = np.random.default_rng(1).normal(size=(7, SPEC.obs_dim)).astype(np.float32)
    for k in range(3):
        pi = load_policy(tmp_path, actor=k)
        expected = agent.act(obs, k)
        np.testing.assert_allclose(pi(obs), expected, rtol=1e-5, atol=1e-6)  # a batch
        np.testing.assert_allclose(pi(obs[3]), expected[3], rtol=1e-5, atol=1e-6)  # one observation
        assert pi(obs[3]).shape == (3,) and pi(obs).dtype == np.float32
    assert not np.allclose(load_policy(tmp_path, 0)(obs), load_policy(tmp_path, 1)(obs))
    pi = load_policy(tmp_path)  # the survivor by default
    assert pi.actor == 2 and pi.spec == SPEC and pi.env_id == "AppleCollect-v0"
    assert pi.meta["env_steps"] == 1234 and pi.meta["live"] == [False, False, True]
    assert load_policy(tmp_path / "checkpoints" / POLICY_FILE).actor == 2  # the file itself works too
    with pytest.raises(ValueError, match="obs"):
        pi(np.zeros(4, np.float32))


def test_default_actor_before_elimination_is_the_best_of_the_last_evaluation(tmp_path: Path):
    write_run(tmp_path, trained_agent(SPEC, actors=3), "AppleCollect-v0")
    with pytest.raises(PolicyFileError, match="actor=0..2"):
        load_policy(tmp_path)
    (tmp_path / "eval.jsonl").write_text(json.dumps({"env_steps": 5, "mean": [1.0, 3.0, 2.0]}) + "\n")
    assert load_policy(tmp_path).actor == 1
    (tmp_path / "summary.json").write_text(json.dumps({"final_returns": [None, 1.0, 4.0], "survivor": None}))
    assert load_policy(tmp_path).actor == 2
    single = tmp_path / "single"
    write_run(single, trained_agent(SPEC, actors=1), "AppleCollect-v0")
    assert load_policy(single).actor == 0


def test_broken_policy_files_are_clear_errors(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="no trained policy"):
        load_policy(tmp_path)
    write_run(tmp_path, trained_agent(SPEC, actors=2), "AppleCollect-v0", survivor=0)
    path = tmp_path / "checkpoints" / POLICY_FILE
    good = path.read_bytes()
    with pytest.raises(ValueError, match="out of range"):
        load_policy(tmp_path, actor=5)
    path.write_bytes(good[: len(good) // 2])  # truncated
    with pytest.raises(PolicyFileError, match="not a readable policy file"):
        load_policy(tmp_path)
    path.write_bytes(b"not a zip at all")
    with pytest.raises(PolicyFileError, match="not a readable policy file"):
        load_policy(tmp_path)
    path.write_bytes(good)
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["actor1.w1"] = np.zeros((3, 3), np.float32)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(PolicyFileError, match=r"actor1.w1: float32\[3, 3\], expected float32\[16, 8\]"):
        read_policy_file(path)
    arrays["meta"] = np.frombuffer(b"{not json", np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(PolicyFileError, match="corrupt"):
        read_policy_file(path)


def test_load_policy_and_mam_eval_need_no_torch_and_no_zenoh(tmp_path: Path):
    spec = EnvSpec.from_env_id("AppleCollect-v0")
    write_run(tmp_path, trained_agent(spec, actors=2), "AppleCollect-v0", survivor=1)
    code = ("import sys, numpy as np; from mam_core.policy import load_policy; import services.cli.eval_command; "
            f"pi = load_policy({str(tmp_path)!r}); a = pi(np.zeros(2, np.float32)); b = pi(np.zeros((4, 2)));"
            "print(a.shape, b.shape, sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'zenoh')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "(2,) (4, 2) []", out.stdout + out.stderr


def test_mam_eval_prints_the_returns_of_the_policy(tmp_path: Path):
    spec = EnvSpec.from_env_id("AppleCollect-v0")
    agent = trained_agent(spec, actors=2)
    write_run(tmp_path, agent, "AppleCollect-v0", survivor=1)
    out = json.loads(mam("eval", str(tmp_path), "--episodes", "3", "--seed", "11", "--json").stdout)
    expected = evaluate_policy(lambda o: agent.act(o, 1), "AppleCollect-v0", 3, seed=11)
    assert out["actor"] == 1 and out["seed"] == 11 and out["deterministic"]
    np.testing.assert_allclose(out["returns"], expected, rtol=1e-6)
    assert out["mean"] == pytest.approx(np.mean(expected)) and out["std"] == pytest.approx(np.std(expected))
    assert len(out["lengths"]) == 3 and all(1 <= n <= 100 for n in out["lengths"])
    text = mam("eval", str(tmp_path), "--episodes", "3", "--seed", "11", "--actor", "0").stdout
    assert "actor 0" in text and "± " in text and "length" in text
    noisy = json.loads(mam("eval", str(tmp_path), "--episodes", "3", "--seed", "11", "--noise", "--json").stdout)
    assert not noisy["deterministic"] and noisy["returns"] != out["returns"]


def _fails(*args: str) -> str:
    proc = subprocess.run([sys.executable, "-m", "services.cli", "eval", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    return proc.stderr


def test_mam_eval_errors_are_clear(tmp_path: Path):
    assert "does not exist" in _fails(str(tmp_path / "nope"))
    assert "no trained policy" in _fails(str(tmp_path))
    spec = EnvSpec.from_env_id("AppleCollect-v0")
    write_run(tmp_path, trained_agent(spec, actors=1), "AppleCollect-v0")
    assert "does not match the policy" in _fails(str(tmp_path), "--env", "InvertedPendulum-v5")
    (tmp_path / "checkpoints" / POLICY_FILE).write_bytes(b"garbage")
    assert "not a readable policy file" in _fails(str(tmp_path))


def _playable(video: Path) -> tuple[int, tuple[int, ...]]:
    """Decode every frame with the bundled ffmpeg (errors fail); (frames, frame shape)."""
    import imageio.v2 as imageio
    import imageio_ffmpeg

    check = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(video), "-f", "null", "-"],
                           capture_output=True, text=True)
    assert check.returncode == 0 and check.stderr == "", check.stderr
    frames = imageio.mimread(str(video), memtest=False)
    return len(frames), frames[0].shape


def test_mam_eval_video_of_apple_collect_needs_no_gl(tmp_path: Path):
    spec = EnvSpec.from_env_id("AppleCollect-v0")
    write_run(tmp_path, trained_agent(spec, actors=1), "AppleCollect-v0")
    video = tmp_path / "out.mp4"
    out = json.loads(mam("eval", str(tmp_path), "--episodes", "2", "--seed", "4", "--video", str(video),
                         "--json").stdout)
    assert out["frames"] == sum(out["lengths"]) + 2  # the reset frame, then one per step
    assert _playable(video) == (out["frames"], (256, 256, 3))
    plain = json.loads(mam("eval", str(tmp_path), "--episodes", "2", "--seed", "4", "--json").stdout)
    np.testing.assert_allclose(out["returns"], plain["returns"], rtol=1e-6)  # recording changes nothing


def offscreen_gl_problem() -> str | None:
    """None when MuJoCo renders offscreen here (MUJOCO_GL=egl), else why not."""
    code = ("import os; os.environ.setdefault('MUJOCO_GL', 'egl'); import gymnasium as gym; "
            "e = gym.make('InvertedPendulum-v5', render_mode='rgb_array'); e.reset(seed=0); print(e.render().shape)")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return "offscreen rendering timed out"
    if out.returncode != 0:
        return "no offscreen GL for MuJoCo (apt-get install libegl1 libegl-mesa0): " + out.stderr.strip()[-300:]
    return None


def test_mam_eval_video_of_a_mujoco_task(tmp_path: Path):
    problem = offscreen_gl_problem()
    if problem:
        pytest.skip(problem)
    spec = EnvSpec.from_env_id("InvertedPendulum-v5")
    write_run(tmp_path, trained_agent(spec, actors=1), "InvertedPendulum-v5")
    video = tmp_path / "pendulum.mp4"
    out = json.loads(mam("eval", str(tmp_path), "--episodes", "1", "--video", str(video), "--json").stdout)
    frames, shape = _playable(video)
    assert frames == out["frames"] == out["lengths"][0] + 1 and shape == (480, 480, 3)


# -- after a real `mam run` ---------------------------------------------------------------------
SMALL = ["--hidden", "32,32", "--batch-size", "32", "--eval-episodes", "3"]


@pytest.mark.slow
def test_after_a_short_run_tensorboard_mam_eval_video_and_load_policy(tmp_path: Path):
    from tests.e2e import load, processes_of, unique_run
    from tests.test_tb import scalars

    run_name, run_dir = unique_run("e2e-use"), tmp_path / "run"
    mam("run", "--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--actors", "2", "--workers", "2",
        "--steps", "1600", "--start-steps", "400", "--compete-every", "400", "--eliminate-at", "800",
        "--eval-every", "400", "--bias-every", "800", "--bias-rollouts", "3", "--seed", "2", *SMALL,
        "--run", run_name, "--run-dir", str(run_dir), "--no-plot")
    run = load(run_dir)
    summary, last_eval = run["summary"], run["eval"][-1]
    survivor = summary["survivor"]
    assert survivor in (0, 1) and processes_of(run_name) == []

    # TensorBoard: every tag, read back with TensorBoard's reader, equal to the JSONL rows.
    learner, referee = scalars(run_dir / "tb" / "learner"), scalars(run_dir / "tb" / "referee")
    for tag in ("loss/critic", "loss/actor", "q/actor0", "q/actor1", "learner/updates_per_s", "learner/utd",
                "learner/replay_size", "learner/transitions_per_s", "learner/updates",
                f"bias/rate/actor{survivor}", f"bias/q_estimate/actor{survivor}", f"bias/q_true/actor{survivor}"):
        assert tag in learner, (tag, sorted(learner))
    for tag in ("eval/return/actor0", "eval/return/actor1", "allocation/P/actor0", "allocation/P/actor1",
                "allocation/I/actor0", "allocation/I/actor1", "allocation/survivor", "allocation/round",
                "allocation/eliminated/actor0", "allocation/eliminated/actor1"):
        assert tag in referee, (tag, sorted(referee))
    rows = run["learner"]
    assert learner["learner/replay_size"] == [(r["env_steps"], float(r["buffer"])) for r in rows]
    assert learner["learner/updates"][-1] == (rows[-1]["env_steps"], float(rows[-1]["updates"]))
    assert referee["allocation/survivor"][-1][1] == survivor
    assert referee["allocation/survivor"][0][1] == -1.0  # none before the elimination
    final = referee[f"eval/return/actor{survivor}"][-1]
    assert final[0] == summary["env_steps"] and final[1] == pytest.approx(summary["final_returns"][survivor])
    assert [s for s, _ in referee["allocation/P/actor0"]] == [r["env_steps"] for r in run["allocation"]]

    # mam eval reproduces the final evaluation: same seed, same episodes, same returns.
    out = json.loads(mam("eval", str(run_dir), "--episodes", "3", "--json").stdout)
    assert out["actor"] == survivor and out["final_eval_weights"]
    # the final evaluation's episodes: its own stream of --seed (mam_core.seeding), by its purpose
    assert out["seed"] == summary["final_eval"]["seed"] == last_eval["seed"] == \
        evaluation_seed(2, last_eval["purpose"], summary["iterations"] // 400)
    np.testing.assert_allclose(out["returns"], last_eval["returns"][survivor], rtol=0, atol=1e-9)
    assert out["mean"] == pytest.approx(summary["final_returns"][survivor], abs=1e-9)
    text = mam("eval", str(run_dir), "--episodes", "3").stdout
    assert f"return {summary['final_returns'][survivor]:.3f} ± " in text

    # load_policy computes the learner's actor, as restored from its torch checkpoint.
    state = torch.load(run_dir / "checkpoints" / "learner.pt", weights_only=True)
    cfg = RunConfig.from_dict(json.loads(state["config"]))
    agent = MultiActorAgent(cfg.algo, EnvSpec.from_env_id(cfg.env_id))
    agent.load_state_dict(state["agent"])
    obs = np.random.default_rng(0).uniform(-1, 1, size=(16, 2)).astype(np.float32)
    pi = load_policy(run_dir)
    assert pi.actor == survivor
    np.testing.assert_allclose(pi(obs), agent.act(obs, survivor), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pi(obs[0]), agent.act(obs[:1], survivor)[0], rtol=1e-5, atol=1e-6)

    # ... and a playable video of those episodes.
    video = tmp_path / "apple.mp4"
    rec = json.loads(mam("eval", str(run_dir), "--episodes", "3", "--video", str(video), "--json").stdout)
    assert _playable(video) == (rec["frames"], (256, 256, 3))
    np.testing.assert_allclose(rec["returns"], out["returns"], atol=1e-9)


@pytest.mark.slow
def test_a_custom_env_from_a_module_trains_end_to_end(tmp_path: Path):
    """`mam run --env tests.envs.tiny:Tiny-v0 --env-kwargs ...`: learner, referee and workers all
    import the module and make the env with the kwargs (the replay holds the goal of the kwargs)."""
    from tests.e2e import assert_exactly_once, load, processes_of, unique_run

    run_name, run_dir = unique_run("e2e-tiny"), tmp_path / "run"
    mam("run", "--env", "tests.envs.tiny:Tiny-v0", "--env-kwargs", '{"goal": -0.5}', "--algo", "td3",
        "--workers", "2", "--steps", "2000", "--start-steps", "300", "--eval-every", "500", "--seed", "3",
        "--save-replay", *SMALL, "--run", run_name, "--run-dir", str(run_dir), "--no-plot")
    run = load(run_dir)
    assert_exactly_once(run)
    assert run["config"]["env_id"] == "tests.envs.tiny:Tiny-v0" and run["config"]["env_kwargs"] == {"goal": -0.5}
    assert run["summary"]["env_steps"] >= 2000 and run["learner"][-1]["updates"] > 1500
    from services.roles.checkpoint import load_replay

    replay = load_replay(run_dir)  # the chunks the checkpoint counts
    goals = replay.obs[: len(replay), 1]
    assert len(replay) >= 2000 and np.all(goals == -0.5)  # every worker made the env with the kwargs
    # It learned: better than standing still, on the final evaluation's episodes.
    out = json.loads(mam("eval", str(run_dir), "--json").stdout)
    assert out["mean"] == pytest.approx(run["summary"]["final_returns"][0], abs=1e-9)
    still = evaluate_policy(lambda o: np.zeros((len(o), 1), np.float32), "tests.envs.tiny:Tiny-v0",
                            out["episodes"], seed=out["seed"], env_kwargs={"goal": -0.5})
    assert out["mean"] > still.mean() + 2.0, (out["mean"], still.mean())
    assert processes_of(run_name) == []


@pytest.mark.slow
def test_after_a_short_mujoco_run_mam_eval_matches_and_records_a_video(tmp_path: Path):
    problem = offscreen_gl_problem()
    from tests.e2e import load, unique_run

    run_dir = tmp_path / "run"
    mam("run", "--env", "InvertedPendulum-v5", "--algo", "td3", "--workers", "1", "--steps", "600",
        "--start-steps", "300", "--seed", "5", *SMALL, "--run", unique_run("e2e-pend"), "--run-dir", str(run_dir),
        "--no-plot")
    summary = load(run_dir)["summary"]
    out = json.loads(mam("eval", str(run_dir), "--json").stdout)
    assert out["episodes"] == 3 and out["final_eval_weights"]
    assert out["mean"] == pytest.approx(summary["final_returns"][0], abs=1e-9)
    if problem:
        pytest.skip(problem)
    video = tmp_path / "pendulum.mp4"
    rec = json.loads(mam("eval", str(run_dir), "--episodes", "1", "--video", str(video), "--json").stdout)
    assert _playable(video) == (rec["frames"], (480, 480, 3)) and rec["frames"] == rec["lengths"][0] + 1
    assert rec["returns"][0] == pytest.approx(out["returns"][0], abs=1e-6)


def test_mam_eval_says_the_episode_lengths_in_one_phrase():
    from services.cli.eval_command import lengths_text

    assert lengths_text([200] * 20) == "length 200 (every episode)"
    assert lengths_text([12, 200, 100]) == "lengths 12–200 (mean 104.0)"
    assert lengths_text([7]) == "length 7 (one episode)"
