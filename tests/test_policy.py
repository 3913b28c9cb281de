"""Acting without torch: workers' and the referee's numpy actors compute the learner's policies."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from mam_core.ensemble import ActorEnsemble
from mam_core.policy import EnvSpec, NumpyActors, member_shapes
from tests.e2e import ROOT

SPEC = EnvSpec(5, 3, (0.4, 1.0, 2.0))  # per-dimension bounds, as Humanoid (±0.4) and others have


def test_numpy_actors_compute_the_learners_actor_ensemble() -> None:
    learner = ActorEnsemble(3, SPEC.obs_dim, SPEC.act_dim, (16, 8), np.array(SPEC.max_action, np.float32),
                            torch.Generator().manual_seed(0)).requires_grad_(False)
    actors = NumpyActors(3, SPEC, (16, 8))
    assert actors.shapes == learner.net.member_shapes() == member_shapes(5, (16, 8), 3)
    policies = [actors.policy(k) for k in range(3)]  # handed out before the weights arrive
    for k in range(3):
        actors.load_member(k, learner.net.member_state(k))
    obs = np.random.default_rng(1).normal(size=(6, SPEC.obs_dim)).astype(np.float32)
    expected = learner(torch.from_numpy(obs)).numpy()  # [K, B, act]
    for k in range(3):
        np.testing.assert_allclose(policies[k](obs), expected[k], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(policies[k](obs[2]), expected[k, 2], rtol=1e-5, atol=1e-6)
    assert np.all(np.abs(expected) <= np.array(SPEC.max_action)) and policies[0](obs).dtype == np.float32
    # Actors differ, and loading one member leaves the others as they were.
    assert not np.allclose(expected[0], expected[1])
    actors.load_member(1, learner.net.member_state(2))
    np.testing.assert_allclose(policies[1](obs), expected[2], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(policies[0](obs), expected[0], rtol=1e-5, atol=1e-6)


def test_numpy_actors_refuse_parameters_of_another_shape() -> None:
    actors = NumpyActors(2, SPEC, (16, 8))
    good = {name: np.ones(shape, np.float32) for name, shape in actors.shapes.items()}
    bad = dict(good, w1=np.ones((8, 16), np.float32))
    with pytest.raises(ValueError, match="w1"):
        actors.load_member(0, bad)
    with pytest.raises(KeyError):
        actors.load_member(0, {k: v for k, v in good.items() if k != "b2"})
    actors.load_member(0, good)
    assert all(np.all(p == 1.0) for p in actors.params[0].values())
    assert all(np.all(p == 0.0) for p in actors.params[1].values())


def test_workers_and_the_referee_do_not_import_torch() -> None:
    """Seconds of start-up and ~300 MB per process saved: only the learner needs torch."""
    code = ("import sys, services.roles.worker, services.roles.referee; "
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))[:5])")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
