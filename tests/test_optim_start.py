"""mam_core/optim_start.py: building, saving and loading the agent's optimizers imports nothing
(a learner's config goes out ~1 s sooner), neither do its steps (`optim_start.step`), and every
bit the agent computes is the same as with torch's own wrapped methods. Each side runs in a fresh
process: this one may have imported `torch._dynamo` already."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.e2e import ROOT

SCRIPT = r"""
import hashlib, json, sys
import mam_core  # pins the arithmetic before numpy and torch
import numpy as np, torch
from mam_core import optim_start
from mam_core.agent import EnvSpec, MultiActorAgent
from mam_core.config import resolve
from mam_core.replay import ReplayBuffer

out = {"marked": optim_start.defer_dynamo_import() if sys.argv[1] == "defer" else 0}
optim_start.UNWRAP = sys.argv[1] == "defer"  # plain: opt.step() with torch's wrappers
spec = EnvSpec(3, 1, (2.0,))
agent = MultiActorAgent(resolve(sys.argv[2], hidden=(16, 16), batch_size=8, seed=3), spec)
agent.load_state_dict(agent.state_dict())  # a checkpoint and a resume
agent.actor_opt.zero_grad()
out["imported_after_build"] = optim_start.dynamo_imported()
buf = ReplayBuffer(200, 3, 1, seed=3)
rng = np.random.default_rng(3)
buf.add_batch(rng.normal(size=(200, 3)).astype(np.float32), rng.uniform(-2, 2, (200, 1)).astype(np.float32),
              rng.normal(size=200).astype(np.float32), rng.normal(size=(200, 3)).astype(np.float32),
              rng.random(200) < 0.1)
for _ in range(40):
    agent.update(buf.sample(8, agent.batch_groups))
out["imported_after_steps"] = optim_start.dynamo_imported()
h = hashlib.sha256()
for name, t in sorted(agent.state_dict()["actor"].items()) + sorted(agent.state_dict()["critic"].items()):
    h.update(name.encode()); h.update(t.detach().numpy().tobytes())
out["params"] = h.hexdigest()[:16]
print(json.dumps(out))
"""


def run_side(how: str, algo: str) -> dict:
    got = subprocess.run([sys.executable, "-c", SCRIPT, how, algo], cwd=ROOT, capture_output=True, text=True,
                         timeout=180)
    assert got.returncode == 0, got.stderr[-3000:]
    return json.loads(got.stdout.strip().splitlines()[-1])


def test_the_agents_optimizers_build_without_the_import_and_compute_the_same_bits() -> None:
    for algo in ("td3", "ma-sac"):  # Adam over the nets; MA-SAC's temperature has one of its own
        deferred, plain = run_side("defer", algo), run_side("plain", algo)
        assert deferred["marked"] >= 3  # add_param_group (the constructor's), state_dict, load_state_dict, ...
        assert not deferred["imported_after_build"]  # nothing imported building, saving and loading
        assert plain["imported_after_build"]  # (what torch does by itself: the test would see a change)
        assert not deferred["imported_after_steps"]  # nor do its steps
        assert plain["imported_after_steps"]
        assert deferred["params"] == plain["params"], algo  # every bit the same
