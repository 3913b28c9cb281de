"""Algorithm 1 as options: the schedule's accounting, per-actor mini-batches, the after-elimination
targets, the seeded tie-break, AppleCollect-v1's premise and Eq. 17 on the critic's horizon."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

import mam_core.envs  # noqa: F401
from mam_core.agent import EnvSpec, MultiActorAgent, weighted_target, weighted_target_per_batch
from mam_core.config import resolve
from mam_core.envs.apple_collect import random_hit_rates
from mam_core.evaluation import bias_rate, estimation_bias
from mam_core.obsolescence import Obsolescence, best_actors, choose_survivor, obsolescence_for
from mam_core.reference import run_reference
from mam_core.replay import ReplayBuffer
from mam_core.schedule import Schedule

# -- the schedule's accounting -------------------------------------------------------------------


def test_paper_schedule_counts_iterations_hand_computed():
    # M = 3, C = 300, T = 1000, start 100: 300 iterations of 3 transitions, then 700 of one.
    s = Schedule("paper", slots=3, steps=1000, start=100, compete_every=50, eliminate_at=300)
    assert s.transitions_at(0) == 0 and s.transitions_at(1) == 3 and s.transitions_at(300) == 900
    assert s.transitions_at(301) == 901 and s.transitions_at(1000) == 1600 == s.budget
    assert [s.units_at(t) for t in (0, 2, 3, 899, 900, 901, 1600)] == [0, 0, 1, 299, 300, 301, 1000]
    assert s.random_until == 300  # 100 iterations of 3 uniform-random transitions
    # One update per iteration after the start: none before 300 transitions, 200 at C, 900 at T.
    assert s.updates_allowed(299) == 0 and s.updates_allowed(300) == 0 and s.updates_allowed(303) == 1
    assert s.updates_allowed(900) == 200 and s.updates_allowed(1600) == 900 == s.total_updates
    assert s.slots_at(299) == 3 and s.slots_at(300) == 1
    for updates in range(1, 901, 7):  # the credit's "consumed" point: the fewest transitions for them
        t = s.transitions_consumed(updates)
        assert s.updates_allowed(t) >= updates > s.updates_allowed(t - 1)


def test_table_4_budget_under_the_paper_schedule():
    cfg = resolve("ma-td3")  # Table 3: K=2, M=3, C=300k, 1M steps
    s = Schedule.for_run(cfg, 1_000_000)
    assert s.budget == 1_600_000 and s.total_updates == 1_000_000 - 25_000


def test_equal_data_and_single_actor_schedules():
    e = Schedule.for_run(resolve("ma-td3", schedule="equal-data", utd=2.0, start_steps=10), 100)
    assert [e.units_at(t) for t in (0, 7, 100)] == [0, 7, 100] and e.budget == 100
    assert e.updates_allowed(15) == 10  # utd 2 per transition after the start
    td3 = Schedule.for_run(resolve("td3"), 5000)  # K = 1, M = 1: both schedules are one run
    assert td3.eliminate_at is None and td3.budget == 5000
    assert td3.updates_allowed(30_000) == Schedule.for_run(resolve("td3", schedule="equal-data"), 5000) \
        .updates_allowed(30_000)
    no_ot = Schedule.for_run(resolve("ma-td3", no_ot=True), 1000)  # no elimination: M slots throughout
    assert no_ot.budget == 3000


def test_rounds_and_barriers_with_and_without_skipping_the_random_phase():
    s = Schedule("paper", slots=2, steps=100, start=25, compete_every=10, eliminate_at=60)
    assert [s.round_due(u, 0) for u in (9, 10, 19, 59, 60)] == [None, 10, 10, 50, None]
    assert s.round_due(15, 10) is None and s.next_barrier(0) == 10 and s.next_barrier(50) == 60
    assert s.next_barrier(60) is None
    skip = dataclasses.replace(s, skip_random_rounds=True)  # first round strictly after start 25: 30
    assert skip.first_round() == 30 and skip.round_due(20, 0) is None and skip.round_due(30, 0) == 30
    assert skip.next_barrier(0) == 30
    obs = obsolescence_for(resolve("ma-ddpg", compete_every=10, eliminate_at=60, start_steps=25,
                                   skip_random_rounds=True))
    assert [obs.due_round(u) for u in (10, 20, 25, 30)] == [False, False, False, True]


def test_reference_driver_paper_schedule_accounting():
    """M = 5, A = 100, C = 300, T = 450 iterations, start 100: 300·5 + 150 = 1650 transitions,
    350 updates; rounds at iterations 100, 200 (transitions 500, 1000), the elimination at 300
    (1500), then one slot."""
    cfg = resolve("ma-ddpg", hidden=(16, 16), batch_size=16, start_steps=100, compete_every=100, eliminate_at=300,
                  workers=5, eval_episodes=2, eval_every=100, seed=3)
    result = run_reference("AppleCollect-v1", cfg, 450)
    assert (result.iterations, result.env_steps, result.updates) == (450, 1650, 350)
    assert [row["env_steps"] for row in result.allocations] == [0, 500, 1000, 1500]
    # the competitions (learning-curve evaluations, on other episodes, sit beside them)
    assert [row["iterations"] for row in result.evaluations if row["purpose"] != "curve"][:3] == [100, 200, 300]


def test_reference_driver_equal_data_schedule_follows_transitions():
    a, c, m = 300, 1200, 5
    cfg = resolve("ma-ddpg", hidden=(32, 32), batch_size=32, start_steps=300, compete_every=a, eliminate_at=c,
                  workers=m, eval_episodes=3, eval_every=300, seed=4, schedule="equal-data")
    result = run_reference("AppleCollect-v0", cfg, 1800)
    assert [row["env_steps"] for row in result.allocations] == [0, 300, 600, 900, 1200]
    assert result.allocations[-1]["slots"] == [result.survivor] * m  # every slot runs the survivor
    assert result.env_steps == result.iterations == 1800 and result.updates == 1800 - 300


# -- per-actor mini-batches ---------------------------------------------------------------------


def test_weighted_target_per_batch_hand_computed():
    # K = 2, n = 2, B = 1. q[j, i, k] = Q'_ji on actor k's batch.
    q = torch.tensor([[[1.0, 10.0], [3.0, 30.0]],  # critics of actor 0: (i=0, i=1) on batches 0, 1
                      [[5.0, 50.0], [7.0, 70.0]]]).unsqueeze(-1)  # critics of actor 1
    eta = 0.1
    y = weighted_target_per_batch(q, eta)
    # actor 0 on batch 0: 0.9·min(1, 3) + 0.1/2·(5 + 7) = 0.9 + 0.6 = 1.5
    # actor 1 on batch 1: 0.9·min(50, 70) + 0.1/2·(10 + 30) = 45 + 2 = 47
    torch.testing.assert_close(y, torch.tensor([[1.5], [47.0]]))
    same = torch.randn(3, 2, 1, 5).expand(3, 2, 3, 5)  # identical batches: Eq. 9 on one batch
    torch.testing.assert_close(weighted_target_per_batch(same, 0.3), weighted_target(same[:, :, 0], 0.3))


def test_replay_draws_independent_batches_per_actor():
    buf = ReplayBuffer(1000, 2, 1, seed=0)
    n = 1000
    buf.add_batch(np.arange(2 * n, dtype=np.float32).reshape(n, 2), np.zeros((n, 1), np.float32),
                  np.arange(n, dtype=np.float32), np.zeros((n, 2), np.float32), np.zeros(n, bool))
    batch = buf.sample(64, groups=3)
    assert batch["obs"].shape == (3, 64, 2) and batch["reward"].shape == (3, 64)
    rows = batch["reward"].long()
    assert not torch.equal(rows[0], rows[1]) and not torch.equal(rows[1], rows[2])
    torch.testing.assert_close(batch["obs"][..., 0], 2 * batch["reward"])  # fields of the same rows


def _agent(**overrides) -> MultiActorAgent:
    cfg = resolve(overrides.pop("algo", "ma-td3"), hidden=(16, 16), batch_size=8, seed=0, **overrides)
    spec = EnvSpec(obs_dim=3, act_dim=2, max_action=(1.0, 1.0))
    return MultiActorAgent(cfg, spec)


def test_per_actor_batches_are_the_default_for_k_above_one_and_k1_is_unchanged():
    assert _agent().batch_groups == 2
    assert _agent(shared_batch=True).batch_groups is None
    assert _agent(algo="td3").batch_groups is None  # K = 1: the reference TD3's single batch


def test_per_actor_update_with_identical_batches_equals_the_shared_update():
    """With the same rows in every actor's batch, the per-actor path is the shared path."""
    torch.manual_seed(0)
    shared = {"obs": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1, "reward": torch.randn(8),
              "next_obs": torch.randn(8, 3), "not_done": torch.ones(8)}
    a, b = _agent(algo="ma-ddpg", eta=0.2), _agent(algo="ma-ddpg", eta=0.2)  # K = 3, no smoothing noise
    per_actor = {k: v.unsqueeze(0).expand(3, *v.shape).contiguous() for k, v in shared.items()}
    for _ in range(3):
        a.update(shared)
        b.update(per_actor)
    for p, q in zip(a.critic.parameters(), b.critic.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    for p, q in zip(a.actor.parameters(), b.actor.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)


# -- after the elimination: what each target converges to on a one-state MDP --------------------


GAMMA, ETA, REWARD = 0.9, 0.1, 1.0


def _train_one_state_mdp(after: str, updates: int = 2500) -> tuple[MultiActorAgent, float]:
    """One state, reward 1 forever (never terminal): Q = 1/(1 − γ) = 10 for every action.

    Two actors train together for 300 updates, then actor 0 survives. Returns the agent and the
    eliminated actor's frozen target-critic value F (measured after the elimination)."""
    cfg = resolve("ma-td3", hidden=(32, 32), batch_size=64, gamma=GAMMA, eta=ETA, tau=0.05, lr=3e-3, seed=1,
                  after_elimination=after, shared_batch=True)
    agent = MultiActorAgent(cfg, EnvSpec(obs_dim=1, act_dim=1, max_action=(1.0,)))
    gen = torch.Generator().manual_seed(0)

    def batch() -> dict[str, torch.Tensor]:
        return {"obs": torch.ones(64, 1), "action": torch.rand(64, 1, generator=gen) * 2 - 1,
                "reward": torch.full((64,), REWARD), "next_obs": torch.ones(64, 1), "not_done": torch.ones(64)}

    for _ in range(300):
        agent.update(batch())
    agent.eliminate(0)
    for _ in range(updates):
        agent.update(batch())
    return agent, _target_value(agent, critic_actor=1)


def _target_value(agent: MultiActorAgent, critic_actor: int) -> float:
    with torch.no_grad():
        obs = torch.ones(16, 1)
        act = torch.linspace(-1, 1, 16).reshape(1, 16, 1).expand(agent.cfg.actors * 2, -1, -1)
        q = agent.critic_target(obs, act).view(agent.cfg.actors, 2, -1)
        return float(q[critic_actor].mean())


def _survivor_value(agent: MultiActorAgent) -> float:
    return float(np.mean(agent.q_value(np.ones((16, 1), np.float32), np.linspace(-1, 1, 16).reshape(16, 1), 0)))


@pytest.mark.parametrize("after", ["frozen", "train-critics", "no-weighting"])
def test_after_elimination_targets_on_a_small_mdp(after):
    agent, frozen_f = _train_one_state_mdp(after)
    q = _survivor_value(agent)
    true_value = REWARD / (1 - GAMMA)  # 10
    if after == "frozen":
        # y = r + γ((1 − η)Q + ηF) with F fixed: Q* = (r + γηF) / (1 − γ(1 − η)), the horizon-
        # shortened value (effective discount γ(1 − η) = 0.81), pulled toward F from step C.
        expected = (REWARD + GAMMA * ETA * frozen_f) / (1 - GAMMA * (1 - ETA))
        assert abs(frozen_f - true_value) > 1.0  # the premise: F at step C is not yet the true value
        assert q == pytest.approx(expected, rel=0.05)
        assert abs(q - true_value) > 0.5
    else:  # the weighting term keeps tracking the data, or is gone: the survivor learns Q = 10
        assert q == pytest.approx(true_value, rel=0.05)
        if after == "train-critics":
            assert frozen_f == pytest.approx(true_value, rel=0.05)  # the eliminated critics kept training


# -- the seeded tie-break -------------------------------------------------------------------------


def test_survivor_ties_are_broken_by_the_seeded_rng():
    returns = [5.0, 5.0, 1.0, 5.0]
    assert best_actors(returns) == [0, 1, 3] and best_actors(returns, [False, True, True, True]) == [1, 3]
    assert choose_survivor(returns) == 0  # without a generator: the lowest index
    picks = [choose_survivor(returns, rng=np.random.default_rng(seed)) for seed in range(30)]
    assert set(picks) == {0, 1, 3}  # every tied actor can win, never the worse one
    again = [choose_survivor(returns, rng=np.random.default_rng(seed)) for seed in range(30)]
    assert picks == again  # the run's seed decides
    schedule = Obsolescence(4, Schedule("paper", slots=1, steps=100, start=0, compete_every=10, eliminate_at=20))
    schedule.record_evaluation(20, returns, rng=np.random.default_rng(7))
    assert schedule.survivor == choose_survivor(returns, rng=np.random.default_rng(7))


# -- AppleCollect-v1: the premise of Fig. 1 --------------------------------------------------------


def test_apple_collect_v1_random_policy_rarely_finds_a_50_apple():
    rates = random_hit_rates("AppleCollect-v1", 2000, seed=0)
    p50, p10 = rates[50.0], rates[10.0]
    assert p50 <= 0.05, p50
    assert p10 >= 3 * p50, (p10, p50)


def test_apple_collect_v1_straight_line_reaches_a_50_apple():
    env = gym.make("AppleCollect-v1")
    env.reset(seed=0)
    total = 0.0
    for step in range(100):
        _, reward, terminated, truncated, info = env.step(np.array([-0.2, -0.2], np.float32))
        total += reward
        if terminated or truncated:
            break
    assert info["apple"] == 50.0 and step + 1 == 6  # |move| <= 0.2: 6 steps of 0.1414 per axis to (-0.8, -0.8)
    assert total == pytest.approx(50.0 - 6 * 0.01)


def test_apple_collect_v1_leaving_the_square_costs_the_forfeited_steps():
    env = gym.make("AppleCollect-v1")
    env.reset(seed=0)
    total = 0.0
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(np.array([0.0, 0.2], np.float32))
        total += reward
        if terminated or truncated:
            break
    assert terminated and info["left"] and info["apple"] == 0.0
    assert total == pytest.approx(-1.0)  # the same as wandering until the time limit


# -- Eq. 17 on the critic's horizon ---------------------------------------------------------------


class ConstantRewardEnv(gym.Env):
    """Reward 1 every step, never terminal; a 10-step time limit (truncation)."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.zeros(1, np.float32), 1.0, False, False, {}


def test_eq17_tail_on_an_env_with_a_known_value():
    if "ConstantReward-v0" not in gym.registry:
        gym.register("ConstantReward-v0", entry_point=ConstantRewardEnv, max_episode_steps=10)
    gamma = 0.9
    value = 1.0 / (1.0 - gamma)  # the infinite-horizon value the critic bootstraps toward: 10

    def policy(obs):
        return np.zeros((len(obs), 1), np.float32)

    def q(obs, act):
        return np.full(len(obs), value)  # a perfect critic

    with_tail = estimation_bias(policy, q, "ConstantReward-v0", 4, gamma, seed=0, horizon="critic")
    assert with_tail["q_true"] == pytest.approx(value) and with_tail["bias_rate"] == pytest.approx(0.0, abs=1e-12)
    assert with_tail["tail"] == pytest.approx(gamma**10 * value)
    cut = estimation_bias(policy, q, "ConstantReward-v0", 4, gamma, seed=0, horizon="episode")
    cut_value = (1 - gamma**10) / (1 - gamma)  # 6.513: the 10-step return
    assert cut["q_true"] == pytest.approx(cut_value)
    assert cut["bias_rate"] == pytest.approx(value / cut_value - 1)  # a perfect critic looks 54% high
    assert "bias_rate_abs" not in cut  # Q* > 0: the two forms agree


def test_eq17_as_printed_and_the_absolute_form_differ_only_for_negative_q():
    assert bias_rate(110.0, 100.0) == bias_rate(110.0, 100.0, absolute=True) == pytest.approx(0.1)
    assert bias_rate(-120.0, -100.0) == pytest.approx(0.2)  # as printed: ÷ Q* (an under-estimate reads > 0)
    assert bias_rate(-120.0, -100.0, absolute=True) == pytest.approx(-0.2)


def test_after_the_elimination_only_the_training_critics_batches_are_targeted():
    """With frozen critics the survivor's Eq. 9 target is computed on its batch alone (K·n critics
    on B rows instead of K·B); it equals the survivor's row of the full computation."""
    agent = _agent(algo="ma-ddpg", eta=0.3)  # K = 3, no smoothing noise: the targets are deterministic
    torch.manual_seed(1)
    next_obs, reward, not_done = torch.randn(3, 8, 3), torch.randn(3, 8), torch.ones(3, 8)
    agent.eliminate(2)
    with torch.no_grad():
        y = agent._targets(next_obs, reward, not_done, per_actor=True)
        agent._training_critics = [0, 1, 2]  # what the full computation does
        full = agent._targets(next_obs, reward, not_done, per_actor=True)
    torch.testing.assert_close(y[2], full[2])
    assert torch.count_nonzero(y[:2]) == 0  # the frozen actors' targets are not computed (masked in the loss)
    trained = _agent(algo="ma-ddpg", eta=0.3, after_elimination="train-critics")
    trained.eliminate(2)
    assert trained._training_critics == [0, 1, 2]  # their critics keep training: every batch is targeted
