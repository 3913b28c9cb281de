"""AppleCollect-v0 geometry, rewards and gymnasium conformance."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import mam_core.envs
from mam_core.envs.apple_collect import AppleCollectEnv


def _make() -> gym.Env:
    return gym.make("AppleCollect-v0")


def _run(env: gym.Env, actions) -> list[tuple]:
    return [env.step(np.asarray(a, dtype=np.float32)) for a in actions]


def test_spaces_and_reset():
    env = _make()
    assert env.observation_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    assert env.action_space == gym.spaces.Box(-0.2, 0.2, (2,), np.float32)
    obs, info = env.reset(seed=3)
    assert obs.dtype == np.float32 and obs.tolist() == [0.0, 0.0]
    assert env.spec.max_episode_steps == 100


def test_straight_to_big_apple_in_four_steps():
    env = _make()
    env.reset(seed=0)
    steps = _run(env, [(0.2, 0.2)] * 4)
    rewards = [s[1] for s in steps]
    assert rewards[:3] == [-0.01, -0.01, -0.01]
    assert rewards[3] == pytest.approx(49.99, abs=1e-12)
    assert [s[2] for s in steps] == [False, False, False, True]  # terminated on the apple
    assert not any(s[3] for s in steps)
    np.testing.assert_allclose(steps[3][0], [0.8, 0.8], atol=1e-6)
    assert steps[3][4]["apple"] == 50.0
    assert sum(rewards) == pytest.approx(49.96, abs=1e-9)


def test_other_big_apple_and_small_apples():
    env = _make()
    env.reset()
    steps = _run(env, [(-0.2, -0.2)] * 4)
    assert steps[-1][2] and steps[-1][1] == pytest.approx(49.99)
    # (0.5, -0.5): two full steps reach (0.4, -0.4), a 0.1 step lands on the apple
    env.reset()
    steps = _run(env, [(0.2, -0.2), (0.2, -0.2), (0.1, -0.1)])
    assert [s[2] for s in steps] == [False, False, True]
    assert steps[-1][1] == pytest.approx(9.99) and steps[-1][4]["apple"] == 10.0
    # (-0.5, 0.5) collected by a move that passes over it: (-0.4, 0.4) -> (-0.6, 0.6)
    env.reset()
    steps = _run(env, [(-0.2, 0.2)] * 3)
    assert [s[2] for s in steps] == [False, False, True]
    assert steps[-1][1] == pytest.approx(9.99)


def test_apple_radius_edge():
    env = AppleCollectEnv()
    env.reset()
    # end at (0.5, -0.39): 0.11 from the (0.5, -0.5) apple -> not collected
    _run(env, [(0.2, -0.2), (0.2, -0.19)])
    obs, r, terminated, _, _ = env.step(np.array([0.1, 0.0], np.float32))
    assert not terminated and r == -0.01
    np.testing.assert_allclose(obs, [0.5, -0.39], atol=1e-6)
    # one more step of 0.02 down: 0.09 from the apple -> collected
    _, r, terminated, _, _ = env.step(np.array([0.0, -0.02], np.float32))
    assert terminated and r == pytest.approx(9.99)


def test_border_clipping():
    env = AppleCollectEnv()
    env.reset()
    # 6 steps of +0.2 in x: 1.2 unclipped, stays at the wall x = 1 (passes no apple)
    steps = _run(env, [(0.2, 0.0)] * 6)
    assert not any(s[2] for s in steps)
    np.testing.assert_allclose(steps[-1][0], [1.0, 0.0], atol=1e-6)
    assert steps[-1][0].dtype == np.float32
    # sliding along the wall in y
    obs, *_ = env.step(np.array([0.2, -0.2], np.float32))
    np.testing.assert_allclose(obs, [1.0, -0.2], atol=1e-6)


def test_actions_are_clipped_to_max_move():
    env = AppleCollectEnv()
    env.reset()
    obs, *_ = env.step(np.array([5.0, -0.05], np.float32))
    np.testing.assert_allclose(obs, [0.2, -0.05], atol=1e-6)
    obs, *_ = env.step(np.array([-3.0, -3.0], np.float32))
    np.testing.assert_allclose(obs, [0.0, -0.25], atol=1e-6)
    with pytest.raises(ValueError):
        env.step(np.array([np.nan, 0.0], np.float32))


def test_standing_still_truncates_at_100_steps():
    env = _make()
    env.reset(seed=1)
    total, n = 0.0, 0
    while True:
        _, r, terminated, truncated, _ = env.step(np.zeros(2, np.float32))
        total += r
        n += 1
        assert not terminated
        if truncated:
            break
    assert n == 100
    assert total == pytest.approx(-1.0, abs=1e-12)


def test_deterministic_across_seeds():
    a, b = _make(), _make()
    assert a.reset(seed=1)[0].tolist() == b.reset(seed=999)[0].tolist()
    acts = np.random.default_rng(0).uniform(-0.2, 0.2, size=(30, 2)).astype(np.float32)
    for act in acts:
        sa, sb = a.step(act), b.step(act)
        assert sa[0].tolist() == sb[0].tolist() and sa[1:4] == sb[1:4]
        if sa[2]:
            break


def test_registration_is_idempotent_and_env_checker_passes():
    mam_core.envs.register_envs()
    mam_core.envs.register_envs()
    check_env(_make().unwrapped, skip_render_check=True)
    check_env(AppleCollectEnv(), skip_render_check=True)


def test_rgb_array_render_draws_square_apples_trail_and_agent_with_numpy():
    env = gym.make("AppleCollect-v0", render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (256, 256, 3) and first.dtype == np.uint8
    n = 256

    def pixel(x: float, y: float) -> tuple[int, ...]:  # world -> pixel (y up, the square fills the frame)
        col = int((x + 1.06) / 2.12 * n)
        row = int((1.06 - y) / 2.12 * n)
        return tuple(int(v) for v in env.render()[row, col])

    assert pixel(0.8, 0.8) == (215, 35, 35) and pixel(-0.8, -0.8) == (215, 35, 35)  # 50 apples: red
    assert pixel(0.5, -0.5) == (50, 165, 60) and pixel(-0.5, 0.5) == (50, 165, 60)  # 10 apples: green
    assert pixel(0.0, 0.0) == (40, 80, 230)  # the agent at the start
    assert pixel(0.3, -0.3) == (246, 244, 236)  # empty floor
    assert pixel(-1.04, 0.0) == (200, 200, 200)  # outside the square
    for _ in range(3):
        env.step(np.array([0.2, 0.0], np.float32))
    assert pixel(0.6, 0.0) == (40, 80, 230)  # the agent moved
    assert pixel(0.3, 0.0) == (90, 120, 235)  # the path it walked
    assert pixel(0.0, 0.0) == (90, 120, 235)
    env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), first)  # reset clears the trail
    assert gym.make("AppleCollect-v0").unwrapped.render() is None  # no render_mode: no frame
    with pytest.raises(ValueError, match="render_mode"):
        AppleCollectEnv(render_mode="human")
