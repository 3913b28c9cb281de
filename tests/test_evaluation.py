"""Deterministic evaluation and the Eq. 17 bias rate, on real gymnasium envs."""

import math

import gymnasium as gym
import numpy as np
import pytest

from mam_core.evaluation import bias_rate, estimation_bias, evaluate_policy, monte_carlo_q

TARGET = np.array([0.8, 0.8], np.float32)
# Hand-computed: 3 steps of -0.01, then 50 - 0.01 on the 4th.
APPLE_RETURN = -0.01 * 3 + 49.99
APPLE_Q_099 = -0.01 * (1 + 0.99 + 0.99**2) + 49.99 * 0.99**3  # = 48.47554601


class HeadToApple:
    """Proportional controller to (0.8, 0.8); counts the states it was asked about."""

    def __init__(self) -> None:
        self.rows = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        assert obs.dtype == np.float32 and obs.ndim == 2 and obs.shape[1] == 2
        self.rows += obs.shape[0]
        return np.clip(TARGET - obs, -0.2, 0.2)


def standing_still(obs: np.ndarray) -> np.ndarray:
    return np.zeros((obs.shape[0], 2), np.float32)


def zero_pendulum(obs: np.ndarray) -> np.ndarray:
    return np.zeros((obs.shape[0], 1), np.float32)


def test_hand_written_policy_gets_known_return():
    assert APPLE_Q_099 == pytest.approx(48.47554601, abs=1e-9)
    returns = evaluate_policy(HeadToApple(), "AppleCollect-v0", episodes=3, seed=0)
    assert returns.shape == (3,)
    np.testing.assert_allclose(returns, [APPLE_RETURN] * 3, atol=1e-9)
    np.testing.assert_allclose(evaluate_policy(standing_still, "AppleCollect-v0", 2, seed=0), [-1.0, -1.0], atol=1e-9)


@pytest.mark.parametrize("max_envs", [1, 3, 32])
def test_exactly_n_episodes_are_run(max_envs):
    policy = HeadToApple()
    returns = evaluate_policy(policy, "AppleCollect-v0", episodes=7, seed=5, max_envs=max_envs)
    assert returns.shape == (7,)
    assert policy.rows == 7 * 4  # 4 steps per episode, no extra episode started


def test_monte_carlo_q_matches_hand_computed_discounted_return():
    obs, actions, discounted = monte_carlo_q(HeadToApple(), "AppleCollect-v0", episodes=4, gamma=0.99, seed=0)
    assert obs.shape == (4, 2) and actions.shape == (4, 2) and discounted.shape == (4,)
    np.testing.assert_allclose(obs, 0.0)
    np.testing.assert_allclose(actions, 0.2)
    np.testing.assert_allclose(discounted, APPLE_Q_099, atol=1e-9)
    # a standing-still policy, truncated at 100 steps: -0.01 * (1 - γ^100) / (1 - γ)
    _, _, still = monte_carlo_q(standing_still, "AppleCollect-v0", episodes=1, gamma=0.99, seed=0)
    assert still[0] == pytest.approx(-0.01 * (1 - 0.99**100) / 0.01, abs=1e-9)


def test_bias_rate_hand_computed():
    assert bias_rate(110.0, 100.0) == pytest.approx(0.1)
    assert bias_rate(90.0, 100.0) == pytest.approx(-0.1)
    # negative Q*: Eq. 17 as printed divides by Q* (the sign flips); absolute=True keeps "> 0 is over-estimation"
    assert bias_rate(-90.0, -100.0) == pytest.approx(-0.1)
    assert bias_rate(-90.0, -100.0, absolute=True) == pytest.approx(0.1)
    assert bias_rate(-120.0, -100.0, absolute=True) == pytest.approx(-0.2)
    # ratio of means
    assert bias_rate(np.array([1.0, 3.0]), np.array([1.0, 1.0, 1.0, 1.0])) == pytest.approx(1.0)
    assert math.isnan(bias_rate(1.0, 0.0))
    assert math.isnan(bias_rate(1.0, 1e-12))


def test_estimation_bias_with_a_known_critic():
    # a critic that is 10% too high everywhere: bias rate exactly 0.1
    def q(obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        assert obs.shape == (5, 2) and act.shape == (5, 2)
        return np.full(5, 1.1 * APPLE_Q_099)

    out = estimation_bias(HeadToApple(), q, "AppleCollect-v0", episodes=5, gamma=0.99, seed=0)
    assert out["q_true"] == pytest.approx(APPLE_Q_099, abs=1e-9)
    assert out["q_estimate"] == pytest.approx(1.1 * APPLE_Q_099)
    assert out["bias"] == pytest.approx(0.1 * APPLE_Q_099)
    assert out["bias_rate"] == pytest.approx(0.1)


def test_mujoco_zero_policy_is_finite_reproducible_and_batch_independent():
    a = evaluate_policy(zero_pendulum, "InvertedPendulum-v5", episodes=4, seed=10)
    b = evaluate_policy(zero_pendulum, "InvertedPendulum-v5", episodes=4, seed=10, max_envs=2)
    assert a.shape == (4,) and np.all(np.isfinite(a)) and np.all(a >= 1)
    np.testing.assert_array_equal(a, b)
    # episode i is seeded with seed + i, whatever the batching
    single = [evaluate_policy(zero_pendulum, "InvertedPendulum-v5", episodes=1, seed=10 + i)[0] for i in range(4)]
    np.testing.assert_array_equal(a, single)
    obs, actions, disc = monte_carlo_q(zero_pendulum, "InvertedPendulum-v5", episodes=3, gamma=0.99, seed=10)
    assert obs.shape == (3, 4) and actions.shape == (3, 1) and np.all(np.isfinite(disc))
    # v5 rewards 1 per step until the falling step (0): n = a[i] ones, so Σγ^t r_t = (1 - γ^n) / (1 - γ)
    np.testing.assert_allclose(disc, (1 - 0.99 ** a[:3]) / 0.01, rtol=1e-9)
    # the initial states are the seeded resets, as float32
    env = gym.make("InvertedPendulum-v5")
    expected = np.stack([env.reset(seed=10 + i)[0] for i in range(3)]).astype(np.float32)
    assert obs.dtype == np.float32
    np.testing.assert_array_equal(obs, expected)
    assert len(np.unique(a)) > 1  # seeds differ, so do episode lengths
