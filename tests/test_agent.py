"""The update step against hand-computed numbers and hand-written TD3 / DDPG."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core.agent import EnvSpec, MultiActorAgent, critic_loss, critic_target, weighted_target
from mam_core.config import resolve
from mam_core.replay import ReplayBuffer
from mam_core.td3 import actor_loss

SMALL = dict(hidden=(32, 32), batch_size=16)


def q_tensor(rows: list[list[float]]) -> torch.Tensor:
    """[K][n] numbers -> q_next [K, n, 1]."""
    return torch.tensor(rows, dtype=torch.float64).unsqueeze(-1)


# -- Eq. 9 by hand ------------------------------------------------------------------------------
@pytest.mark.parametrize("rows, eta, expected", [
    # K=2, n=2: coefficient η/(n(K-1)) = 0.1/2. k=0: 0.9·1 + 0.05·(5+7) = 1.5; k=1: 0.9·5 + 0.05·(1+3) = 4.7
    ([[1, 3], [5, 7]], 0.1, [1.5, 4.7]),
    # K=3, n=2: coefficient 0.2/4 = 0.05.
    # k=0: 0.8·1 + 0.05·24 = 2.0; k=1: 0.8·5 + 0.05·16 = 4.8; k=2: 0.8·2 + 0.05·16 = 2.4
    ([[1, 3], [5, 7], [2, 10]], 0.2, [2.0, 4.8, 2.4]),
    # K=2, n=1: coefficient 0.5. k=0: 0.5·2 + 0.5·6 = 4; k=1: 0.5·6 + 0.5·2 = 4
    ([[2], [6]], 0.5, [4.0, 4.0]),
    # K=3, n=1: coefficient 0.3/2 = 0.15. k=0: 0.7 + 0.15·6 = 1.6; k=1: 1.4 + 0.15·5 = 2.15; k=2: 2.8 + 0.15·3 = 3.25
    ([[1], [2], [4]], 0.3, [1.6, 2.15, 3.25]),
])
def test_weighted_target_hand_computed(rows, eta, expected):
    y = weighted_target(q_tensor(rows), eta)
    assert y.shape == (len(rows), 1)
    np.testing.assert_allclose(y[:, 0].numpy(), expected, rtol=1e-12)


def test_critic_target_reward_discount_and_terminal():
    q = q_tensor([[1, 3], [5, 7]]).repeat(1, 1, 2)  # B=2
    reward = torch.tensor([1.0, 1.0], dtype=torch.float64)
    not_done = torch.tensor([1.0, 0.0], dtype=torch.float64)  # second row terminal
    y = critic_target(reward, not_done, q, gamma=0.5, eta=0.1)
    np.testing.assert_allclose(y.numpy(), [[1 + 0.5 * 1.5, 1.0], [1 + 0.5 * 4.7, 1.0]])


@pytest.mark.parametrize("n", [1, 2])
def test_eta_zero_or_single_actor_is_plain_target(n):
    g = torch.Generator().manual_seed(0)
    q = torch.randn(3, n, 50, generator=g, dtype=torch.float64)
    own = q.min(dim=1).values if n == 2 else q[:, 0]
    torch.testing.assert_close(weighted_target(q, 0.0), own)
    torch.testing.assert_close(weighted_target(q[:1], 0.7), own[:1])


# -- Theorems 1 and 2 by Monte Carlo ---------------------------------------------------------------
def test_theorem1_bias_of_weighted_estimator():
    lam, mu, eta = 0.1, 1.0, 0.1
    g = torch.Generator().manual_seed(1)
    errors = lam - mu + 2 * mu * torch.rand(2, 2, 400_000, generator=g, dtype=torch.float64)
    bias = weighted_target(errors, eta)[0].mean().item()
    assert bias == pytest.approx(lam - mu * (1 - eta) / 3, abs=3e-3)  # λ − μ(1−η)/3 = −0.2
    td3_bias = errors[0].min(dim=0).values.mean().item()
    assert td3_bias == pytest.approx(lam - mu / 3, abs=3e-3)  # Eq. 11
    assert bias - td3_bias == pytest.approx(mu * eta / 3, abs=3e-3)  # Eq. 14


def test_theorem2_variance_falls_with_more_actors():
    lam, mu, eta = 0.0, 1.0, 0.5
    g = torch.Generator().manual_seed(2)
    variances = []
    for k in (2, 3, 5):
        errors = lam - mu + 2 * mu * torch.rand(k, 2, 400_000, generator=g, dtype=torch.float64)
        var = weighted_target(errors, eta)[0].var().item()
        # Eq. 15 with Var(min of two U(λ±μ)) = 2μ²/9.
        expected = (1 - eta) ** 2 * 2 * mu**2 / 9 + eta**2 * mu**2 / (6 * k - 6)
        assert var == pytest.approx(expected, rel=0.02)
        variances.append(var)
    assert variances[0] > variances[1] > variances[2]


# -- the agent's update step against hand-written TD3 / DDPG ----------------------------------------
def mlp(x: torch.Tensor, weights: list[torch.Tensor], biases: list[torch.Tensor], member: int) -> torch.Tensor:
    for i, (w, b) in enumerate(zip(weights, biases)):
        x = x @ w[member] + b[member, 0]
        if i < len(weights) - 1:
            x = torch.relu(x)
    return x


def random_batch(spec: EnvSpec, b: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "obs": torch.randn(b, spec.obs_dim, generator=g),
        "action": (torch.rand(b, spec.act_dim, generator=g) * 2 - 1) * torch.tensor(spec.max_action),
        "reward": torch.randn(b, generator=g),
        "next_obs": torch.randn(b, spec.obs_dim, generator=g),
        "not_done": (torch.rand(b, generator=g) > 0.2).float(),
    }


@pytest.mark.parametrize("algo", ["td3", "ddpg"])
def test_single_actor_update_equals_plain_algorithm(algo):
    spec = EnvSpec(5, 2, (0.4, 0.4))  # Humanoid-like ±0.4 bounds: noise and actions scale with them
    cfg = resolve(algo, **SMALL, seed=3)
    agent = MultiActorAgent(cfg, spec)
    batch = random_batch(spec, 16, seed=4)
    aw = [w.detach().clone() for w in agent.actor_target.net.weights]
    ab = [b.detach().clone() for b in agent.actor_target.net.biases]
    cw = [w.detach().clone() for w in agent.critic_target.net.weights]
    cb = [b.detach().clone() for b in agent.critic_target.net.biases]
    ow = [w.detach().clone() for w in agent.critic.net.weights]
    obias = [b.detach().clone() for b in agent.critic.net.biases]
    gen_state = agent.noise_gen.get_state()

    # TD3 / DDPG target written out (Fujimoto et al. 2018), with the agent's noise stream.
    max_a = torch.tensor(spec.max_action)
    next_a = max_a * torch.tanh(mlp(batch["next_obs"], aw, ab, 0))
    if cfg.target_smoothing:
        g = torch.Generator().set_state(gen_state)
        noise = (torch.randn((1, 16, 2), generator=g)[0] * 0.2 * max_a).clamp(-0.5 * max_a, 0.5 * max_a)
        next_a = torch.max(torch.min(next_a + noise, max_a), -max_a)
    sa_next = torch.cat([batch["next_obs"], next_a], dim=1)
    q_next = [mlp(sa_next, cw, cb, i)[:, 0] for i in range(cfg.critics_per_actor)]
    target_q = torch.stack(q_next).min(dim=0).values
    y = batch["reward"] + cfg.gamma * batch["not_done"] * target_q
    sa = torch.cat([batch["obs"], batch["action"]], dim=1)
    expected = sum(((mlp(sa, ow, obias, i)[:, 0] - y) ** 2).mean() for i in range(cfg.critics_per_actor))

    metrics = agent.update(batch)
    assert metrics["loss/critic"] == pytest.approx(expected.item(), rel=1e-5)
    with torch.no_grad():
        acts = agent.actor(torch.randn(100, 5) * 10)
    assert acts.abs().max().item() <= 0.4 + 1e-6


def test_actor_k_gradients_reach_only_actor_k():
    spec = EnvSpec(4, 2, (1.0, 1.0))
    agent = MultiActorAgent(resolve("ma-td3", actors=3, **SMALL), spec)
    obs = torch.randn(8, 4)
    q1 = agent.critic(obs, agent.actor(obs), members=agent.first_critics)
    live = torch.tensor([0.0, 1.0, 0.0])
    grads = torch.autograd.grad(actor_loss(q1, live), list(agent.actor.parameters()))
    for g in grads:
        assert g[1].abs().sum() > 0
        assert g[0].abs().sum() == 0 and g[2].abs().sum() == 0

    # Critic loss of actor 2 reaches only critics (2,0) and (2,1).
    batch = random_batch(spec, 8, seed=0)
    q = agent.critic(batch["obs"], batch["action"].unsqueeze(0).expand(6, -1, -1)).view(3, 2, -1)
    y = torch.zeros(3, 8)
    grads = torch.autograd.grad(critic_loss(q, y, torch.tensor([0.0, 0.0, 1.0])), list(agent.critic.parameters()))
    for g in grads:
        norms = g.flatten(1).abs().sum(dim=1)
        assert (norms[4:] > 0).all() and (norms[:4] == 0).all()


def test_eliminated_actors_are_frozen_but_serve_the_target():
    spec = EnvSpec(4, 2, (1.0, 1.0))
    cfg = resolve("ma-td3", actors=3, **SMALL, policy_delay=1)
    agent = MultiActorAgent(cfg, spec)
    for s in range(5):
        agent.update(random_batch(spec, 16, seed=s))
    agent.eliminate(1)
    before = {name: t.detach().clone() for name, t in
              [("actor", agent.actor.net.weights[0]), ("critic", agent.critic.net.weights[0]),
               ("actor_t", agent.actor_target.net.weights[0]), ("critic_t", agent.critic_target.net.weights[0])]}
    versions = list(agent.versions)
    for s in range(5, 15):
        agent.update(random_batch(spec, 16, seed=s))
    after = {"actor": agent.actor.net.weights[0], "critic": agent.critic.net.weights[0],
             "actor_t": agent.actor_target.net.weights[0], "critic_t": agent.critic_target.net.weights[0]}
    for name in before:
        frozen = [0, 2] if name.startswith("actor") else [0, 1, 4, 5]
        moving = [1] if name.startswith("actor") else [2, 3]
        assert torch.equal(before[name][frozen], after[name][frozen].detach()), name
        assert not torch.equal(before[name][moving], after[name][moving].detach()), name
    assert agent.versions[0] == versions[0] and agent.versions[2] == versions[2]
    assert agent.versions[1] == versions[1] + 10
    assert agent.live_actors == [False, True, False]


def test_seeded_runs_reproduce_first_1000_updates():
    spec = EnvSpec(3, 1, (2.0,))

    def losses(seed: int) -> list[float]:
        torch.manual_seed(123)  # global state must not matter
        cfg = resolve("ma-td3", hidden=(16, 16), batch_size=8, seed=seed)
        agent = MultiActorAgent(cfg, spec)
        buf = ReplayBuffer(500, 3, 1, seed=seed)
        rng = np.random.default_rng(seed)
        buf.add_batch(rng.normal(size=(500, 3)).astype(np.float32), rng.uniform(-2, 2, (500, 1)).astype(np.float32),
                      rng.normal(size=500).astype(np.float32), rng.normal(size=(500, 3)).astype(np.float32),
                      rng.random(500) < 0.1)
        return [agent.update(buf.sample(8))["loss/critic"] for _ in range(1000)]

    first = losses(7)
    assert first == losses(7)
    assert first != losses(8)


def test_checkpoint_round_trip_continues_identically(tmp_path):
    spec = EnvSpec(4, 2, (1.0, 1.0))
    cfg = resolve("ma-td3", **SMALL, seed=5)
    a = MultiActorAgent(cfg, spec)
    batches = [random_batch(spec, 16, seed=s) for s in range(12)]
    for b in batches[:6]:
        a.update(b)
    a.eliminate(0)
    path = tmp_path / "agent.pt"
    torch.save(a.state_dict(), path)
    b_agent = MultiActorAgent(cfg, spec)
    b_agent.load_state_dict(torch.load(path, weights_only=True))
    assert b_agent.live_actors == [True, False]
    assert [a.update(b) for b in batches[6:]] == [b_agent.update(b) for b in batches[6:]]


def test_actor_params_round_trip_to_wire_arrays():
    spec = EnvSpec(4, 2, (1.0, 1.0))
    src = MultiActorAgent(resolve("ma-td3", **SMALL, seed=1), spec)
    dst = MultiActorAgent(resolve("ma-td3", **SMALL, seed=2), spec)
    params = src.actor_params(1)
    assert {k: v.shape for k, v in params.items()} == src.actor_shapes()
    dst.actor.net.load_member(0, params)
    obs = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    np.testing.assert_array_equal(src.act(obs, 1), dst.act(obs, 0))


def test_replay_buffer_ring_and_sampling():
    buf = ReplayBuffer(5, 2, 1, seed=0)
    for start in (0, 3, 6):  # 9 rows into a ring of 5: rows 4..8 survive
        rows = np.arange(start, start + 3, dtype=np.float32)
        buf.add_batch(np.stack([rows, rows], 1), rows[:, None], rows, np.stack([rows, rows], 1),
                      rows % 2 == 0, actor=start // 3, version=np.arange(3) + start)
    assert len(buf) == 5 and buf.inserted == 9
    assert sorted(buf.reward.tolist()) == [4, 5, 6, 7, 8]
    assert buf.not_done[buf.reward == 6][0] == 0.0 and buf.not_done[buf.reward == 7][0] == 1.0
    batch = buf.sample(64)
    assert batch["obs"].shape == (64, 2) and batch["obs"].dtype == torch.float32
    assert set(batch["reward"].tolist()) <= {4.0, 5.0, 6.0, 7.0, 8.0}
    np.testing.assert_array_equal(buf.version[buf.reward == 8], [8])
    state = buf.state_dict()
    blob = io.BytesIO()
    torch.save(state, blob)
    blob.seek(0)
    other = ReplayBuffer(5, 2, 1, seed=99)
    other.load_state_dict(torch.load(blob, weights_only=True))
    torch.testing.assert_close(other.sample(10), buf.sample(10))


# -- mixed precision (--precision bf16) ------------------------------------------------------------
@pytest.mark.parametrize("rows", [64, 8, 1])  # feature-major, row-major and one-row paths
def test_bf16_forward_is_close_to_fp32_and_keeps_float32_outputs_and_grads(rows):
    from mam_core.ensemble import EnsembleMLP

    torch.manual_seed(0)
    net = EnsembleMLP(3, 17, (256, 256), 1)
    x = torch.randn(3, rows, 17)
    ref = net(x)
    net.low_precision = torch.bfloat16
    out = net(x)
    assert out.dtype == torch.float32
    scale = ref.abs().mean().item()
    assert (out - ref).abs().max().item() < 0.05 * scale + 1e-3  # bf16: 8-bit mantissa in the hidden layers
    assert (out - ref).abs().max().item() > 0.0  # the GEMMs did run in bf16
    out.sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in net.parameters())
    single = net(x[1:2], members=slice(1, 2))  # one member: the plain 2-D GEMM path
    assert single.dtype == torch.float32
    assert (single[0] - ref[1]).abs().max().item() < 0.05 * scale + 1e-3


def test_bf16_training_tracks_fp32_training():
    """The same seeded MA-TD3 fed the same 400 batches: critic losses, Q values and actions stay
    close to the float32 run (rounding differs, the learning does not)."""
    spec = EnvSpec(6, 2, (1.0, 1.0))
    buf = ReplayBuffer(4000, 6, 2, seed=0)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(4000, 6)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(4000, 2)).astype(np.float32)
    reward = (obs[:, 0] - (act ** 2).sum(1)).astype(np.float32)  # a learnable reward
    buf.add_batch(obs, act, reward, np.roll(obs, 1, axis=0), np.zeros(4000, bool))
    agents = {p: MultiActorAgent(resolve("ma-td3", actors=2, batch_size=128, hidden=(64, 64), seed=1, precision=p),
                                 spec) for p in ("fp32", "bf16")}
    losses = {p: [] for p in agents}
    for step in range(400):
        batch = buf.sample(128)
        for p, agent in agents.items():
            losses[p].append(agent.update(batch)["loss/critic"])
    early = {p: float(np.mean(v[:20])) for p, v in losses.items()}
    late = {p: float(np.mean(v[-50:])) for p, v in losses.items()}
    assert late["fp32"] < 0.5 * early["fp32"] and late["bf16"] < 0.5 * early["bf16"]  # both learn
    assert late["bf16"] == pytest.approx(late["fp32"], rel=0.25)
    probe = obs[:256]
    for k in range(2):
        q32 = agents["fp32"].q_value(probe, agents["fp32"].act(probe, k), k)
        q16 = agents["bf16"].q_value(probe, agents["bf16"].act(probe, k), k)
        assert np.abs(q16 - q32).mean() < 0.1 * np.abs(q32).mean() + 0.05
        a32, a16 = agents["fp32"].act(probe, k), agents["bf16"].act(probe, k)
        assert np.abs(a16 - a32).mean() < 0.1


def test_precision_is_validated():
    with pytest.raises(ValueError, match="precision"):
        resolve("ma-td3", precision="fp8")


@pytest.mark.parametrize("schedule", ["paper", "equal-data"])
def test_many_updates_track_the_reference_td3(schedule):
    """K=1 TD3 and the plain reference (benchmarks/td3_reference.py, nn.Sequential + torch Adam)
    from the same weights on the same 300 batches (no smoothing noise: the two draw it from
    different streams) agree to float rounding. One update is not enough to see an optimizer bug:
    a fused Adam reading transposed gradients passed the one-step loss check and failed this."""
    import copy
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks.td3_reference import TD3

    obs_dim, act_dim = 11, 2
    agent = MultiActorAgent(resolve("td3", hidden=(64, 64), batch_size=64, policy_noise=0.0, seed=0, schedule=schedule),
                            EnvSpec(obs_dim, act_dim, (1.0,) * act_dim))
    assert agent.batch_groups is None  # K = 1: one mini-batch, as the reference draws
    ref = TD3(obs_dim, act_dim, 1.0, policy_noise=0.0, hidden=64)

    def linears(seq):
        return [m for m in seq if isinstance(m, torch.nn.Linear)]

    with torch.no_grad():
        for seq, net, member in ((ref.actor.net, agent.actor.net, 0), (ref.critic.q1, agent.critic.net, 0),
                                 (ref.critic.q2, agent.critic.net, 1)):
            for i, lin in enumerate(linears(seq)):
                lin.weight.copy_(net.weights[i][member].T)
                lin.bias.copy_(net.biases[i][member, 0])
    ref.actor_target, ref.critic_target = copy.deepcopy(ref.actor), copy.deepcopy(ref.critic)
    ref.actor_optimizer = torch.optim.Adam(ref.actor.parameters(), lr=3e-4)
    ref.critic_optimizer = torch.optim.Adam(ref.critic.parameters(), lr=3e-4)
    g = torch.Generator().manual_seed(0)
    w = torch.randn(obs_dim, generator=g)
    for _ in range(300):
        s, s2 = torch.randn(64, obs_dim, generator=g), torch.randn(64, obs_dim, generator=g)
        a = torch.rand(64, act_dim, generator=g) * 2 - 1
        r = s @ w - (a ** 2).sum(1)
        agent.update({"obs": s, "action": a, "reward": r, "next_obs": s2, "not_done": torch.ones(64)})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref.train(s, a, r.unsqueeze(1), s2, torch.ones(64, 1))
    with torch.no_grad():
        for seq, net, member in ((ref.actor.net, agent.actor.net, 0), (ref.critic.q1, agent.critic.net, 0),
                                 (ref.critic.q2, agent.critic.net, 1),
                                 (ref.actor_target.net, agent.actor_target.net, 0),
                                 (ref.critic_target.q2, agent.critic_target.net, 1)):
            for i, lin in enumerate(linears(seq)):
                torch.testing.assert_close(net.weights[i][member].T, lin.weight, rtol=0, atol=1e-5)
                torch.testing.assert_close(net.biases[i][member, 0], lin.bias, rtol=0, atol=1e-5)
