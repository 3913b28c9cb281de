"""CUDA graphs of the update (mam_core/graphs.py): skipped cleanly on a CPU, equal to the eager
update on a GPU (where there is one; benchmarks/gpu.sh runs the same check on the GPU machine)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mam_core import graphs
from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_core.replay import ReplayBuffer

SPEC = EnvSpec(5, 2, (1.0, 1.0))


def filled(device: str, rows: int = 256, resident: bool | None = None) -> ReplayBuffer:
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(rows, SPEC.obs_dim, SPEC.act_dim, device, seed=3, resident=resident)
    buf.add_batch(rng.normal(size=(rows, 5)).astype(np.float32), rng.uniform(-1, 1, (rows, 2)).astype(np.float32),
                  rng.normal(size=rows).astype(np.float32), rng.normal(size=(rows, 5)).astype(np.float32),
                  rng.random(rows) < 0.05)
    return buf


def train(agent: MultiActorAgent, sample, updates: int, eliminate_at: int) -> list[dict[str, float]]:
    """As Algorithm1.run_updates: the elimination right before an actor phase."""
    seen = []
    for _ in range(updates):
        batch = sample()
        metrics = agent.update_critics(batch)
        if agent.actor_phase_due:
            if agent.updates == eliminate_at:
                agent.eliminate(1)
            metrics.update(agent.update_actors(batch))
        seen.append(dict(metrics))
    return seen


def test_cpu_takes_no_graphs_even_with_a_resident_replay() -> None:
    cfg = resolve("ma-td3", actors=2, hidden=(16, 16), batch_size=8, seed=1)
    agent = MultiActorAgent(cfg, SPEC, "cpu")
    buf = filled("cpu", resident=True)  # a device copy on the CPU: still no graphs there
    assert buf.resident and not agent.accel.cuda_graphs and not graphs.usable(agent, buf)
    sample = agent.sampler(buf)
    assert agent.graphs is None
    batch = sample()
    assert isinstance(batch, dict) and batch["obs"].shape == (2, 8, 5)  # a mini-batch per actor, as before
    # The sampler draws what buffer.sample draws: the same agent trained both ways is the same.
    a, b = (MultiActorAgent(cfg, SPEC, "cpu") for _ in range(2))
    buf_a, buf_b = filled("cpu"), filled("cpu")
    ma = train(a, a.sampler(buf_a), 12, eliminate_at=6)
    mb = train(b, lambda: buf_b.sample(8, b.batch_groups), 12, eliminate_at=6)
    assert ma == mb and set(ma[-1]) == {"loss/critic", "q/actor0", "q/actor1", "loss/actor", "loss/actor0",
                                        "loss/actor1"}
    for p, q in zip(a.actor.parameters(), b.actor.parameters()):
        assert torch.equal(p, q)


def test_switch_reads_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(graphs.GRAPHS_ENV, raising=False)
    assert graphs.enabled()
    for off in ("0", "off", "False", "no"):
        monkeypatch.setenv(graphs.GRAPHS_ENV, off)
        assert not graphs.enabled()
    monkeypatch.setenv(graphs.GRAPHS_ENV, "1")
    assert graphs.enabled()


def test_lazy_metrics_read_once_and_merge_unread() -> None:
    critic = graphs.LazyMetrics(["loss/critic", "q/actor0"], torch.tensor([0.5, -1.0]))
    actor = graphs.LazyMetrics(["loss/actor"], torch.tensor([2.0]))
    critic.update(actor)
    assert len(critic) == 3 and critic._read is None  # counted without reading the values
    assert dict(critic) == {"loss/critic": 0.5, "q/actor0": -1.0, "loss/actor": 2.0}
    critic["extra"] = 1.0
    critic.update({"more": 3.0})
    assert critic["more"] == 3.0 and len(critic) == 5


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (benchmarks/gpu.sh checks it there)")
@pytest.mark.parametrize("algo", ["ma-td3", "ma-sac"])
def test_graphed_update_equals_eager_on_cuda(algo: str, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = resolve(algo, actors=2, hidden=(64, 64), batch_size=32, seed=2)
    monkeypatch.setenv(graphs.GRAPHS_ENV, "0")
    eager = MultiActorAgent(cfg, SPEC, "cuda")
    m_eager = train(eager, eager.sampler(filled("cuda")), 100, eliminate_at=50)
    monkeypatch.setenv(graphs.GRAPHS_ENV, "1")
    graphed = MultiActorAgent(cfg, SPEC, "cuda")
    m_graphed = train(graphed, graphed.sampler(filled("cuda")), 100, eliminate_at=50)
    assert graphed.graphs is not None and graphed.graphs.captures == 2 and not graphed.graphs.failed
    for p, q in zip(eager.state_dict()["actor"].values(), graphed.state_dict()["actor"].values()):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5)
    assert m_eager[-1].keys() == m_graphed[-1].keys()
