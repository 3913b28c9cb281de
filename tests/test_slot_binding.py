"""Issue 38: a slot bound to the worker's id (`slot_binding`, services/run/binding.py).

Under TLS the router's access control ties a certificate to the worker ids it may publish as; the
run's slot binding ties each worker id to the slots it may claim. The learner's intake refuses a
batch claiming any other slot (`unbound_slot`), counted and logged once, and the run goes on
unchanged; a worker told to take a slot its binding does not allow refuses to start (exit 78).

* fast: the option (syntax, unknown slots, duplicates; flag, TOML string and table, config.json,
  `mam-learner` exiting 2), and the intake alone on real encoded batches.
* slow: a split-role run started by hand (learner, referee, two workers) with a binding, where a
  session publishes real batches on worker w0's key claiming slot 1, and a worker with no entry
  tries to join: refused, logged, and the run is still the reference run bit for bit. (Without
  the binding the same batches take slot 1 over again and again: measured on 2026-12-05, the run
  stood at iteration 183 of 300 after 120 s, slot 1 fed with the forged rows.)
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import typer

from mam_core.config import resolve
from mam_core.reference import run_reference
from services.messaging import bus, keys
from services.messaging.codec import TransitionBatch
from services.roles import role
from services.run import binding
from services.run.binding import SlotBinding
from services.run.config import RunConfig
from services.run.options import build_run_config, load_toml
from services.run.preflight import EXIT_CONFIG
from tests.e2e import ROOT, learner_iterations, processes_of, spawn, stop, unique_run
from tests.test_exact import _equals_reference, _record
from tests.test_intake import VERSIONS, batch, new_intake, received

APPLE = ["--env", "AppleCollect-v1", "--steps", "10"]


# -- the option ----------------------------------------------------------------------------------
def test_a_binding_reads_as_ids_or_prefixes_and_their_slots() -> None:
    assert binding.parse("w0=0,w1=1,spare-a=*", 4) == {"w0": [0], "w1": [1], "spare-a": "*"}
    assert binding.parse(" b-*=0-2 , c-*=3,1 ,c-7=2", 4) == {"b-*": [0, 1, 2], "c-*": [1, 3], "c-7": [2]}
    table = {"w0": 0, "spare": "*", "b-*": [2, 3], "c": "0-1"}
    assert binding.parse(table, 4) == {"w0": [0], "spare": "*", "b-*": [2, 3], "c": [0, 1]}
    assert binding.parse(binding.parse(table, 4), 4) == binding.parse(table, 4)  # config.json's form reads back
    assert binding.parse("", 4) == binding.parse(None, 4) == {}
    bound = SlotBinding(binding.parse("b-*=0-1,b-spare=*,b-x*=3,c0=2", 4))
    assert bound.allows("b-1", 1) and not bound.allows("b-1", 2)  # the prefix b-*
    assert bound.allows("b-spare", 3) and bound.allows("b-xy", 3) and not bound.allows("b-xy", 0)  # best match wins
    assert bound.allows("c0", 2) and not bound.allows("c0", 0) and not bound.allows("c1", 2)  # no entry: no slot
    assert not bound.allows("b-0", -1)  # a batch that names no slot claims none the binding holds
    assert "no entry" in bound.describe("zz") and "slots 0, 1 (slot_binding entry b-*)" in bound.describe("b-3")
    assert SlotBinding({}).allows("anyone", 7) and SlotBinding(binding.parse("*=1", 2)).allows("anyone", 1)


@pytest.mark.parametrize("value, message", [
    ("w0", "no ID=SLOTS entry"),
    ("w0=a", "want a slot I, a range I-J or"),
    ("w0=-1", "want a slot I"),
    ("w0=4", "slot 4 does not exist"),
    ("w0=2-5", "slot 5 does not exist"),
    ("w0=3-1", "an empty range"),
    ("w0=0,w0=1", "w0 is named twice"),
    ("w0=0,0", "slot 0 is named twice"),
    ("w/0=0", "may only contain"),
    ("=0", "must not be empty"),
    ({"w0": True}, "want a slot"),
    (7, "want a string"),
])
def test_a_bad_binding_is_a_clear_error(value: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        binding.parse(value, 4)


def test_the_flag_a_toml_string_or_table_and_config_json_give_the_same_binding(tmp_path: Path) -> None:
    flag = build_run_config({"env": "AppleCollect-v1", "steps": 10, "workers": 3, "slot_binding": "w0=0,w1=1,s=*"},
                            None)
    assert flag.slot_binding == {"w0": [0], "w1": [1], "s": "*"}
    f = tmp_path / "run.toml"
    f.write_text('env = "AppleCollect-v1"\nsteps = 10\nworkers = 3\n[slot_binding]\nw0 = 0\nw1 = [1]\ns = "*"\n')
    assert load_toml(f)["slot_binding"] == {"w0": 0, "w1": [1], "s": "*"}  # a table, not a section of options
    assert build_run_config({}, f).slot_binding == flag.slot_binding
    assert RunConfig.from_dict(json.loads(json.dumps(flag.to_dict()))) == flag
    assert build_run_config({"env": "AppleCollect-v1", "steps": 10}, None).slot_binding == {}
    with pytest.raises(typer.BadParameter, match="slot 3 does not exist"):  # M = 3 here: slots 0..2
        build_run_config({"slot_binding": "w0=3"}, f)


def test_mam_learner_refuses_a_bad_binding_before_it_starts(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "services.roles.learner", *APPLE, "--workers", "2", "--slot-binding",
                           "w0=0,w1=2", "--run-dir", str(tmp_path / "run")], cwd=ROOT, capture_output=True, text=True,
                          timeout=120, env=dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore"))
    assert proc.returncode == 2 and "slot 2 does not exist" in proc.stderr, (proc.returncode, proc.stderr[-2000:])
    assert not (tmp_path / "run").exists()


def test_a_worker_its_binding_does_not_allow_refuses_to_start(caplog: pytest.LogCaptureFixture) -> None:
    cfg = build_run_config({"env": "AppleCollect-v1", "steps": 10, "workers": 3, "slot_binding": "w0=0,s*=1-2"},
                           None)
    log = logging.getLogger("test.binding")
    role.refuse_unbound(cfg, "w0", [0], "slot 0", log)  # allowed: nothing happens
    role.refuse_unbound(cfg, "s1", [0, 1, 2], "any slot as a spare", log)
    for worker, slots in (("w0", [1]), ("w9", [0]), ("w9", [0, 1, 2])):
        with pytest.raises(SystemExit) as stopped:
            role.refuse_unbound(cfg, worker, slots, "that slot", log)
        assert stopped.value.code == EXIT_CONFIG
    assert "worker w9 may not take that slot" in caplog.text and "no entry" in caplog.text


# -- the intake ----------------------------------------------------------------------------------
def on_slot(slot: int, seq: int = 0, incarnation: str = "a") -> TransitionBatch:
    """test_intake's batch of worker w0 (three rows from iteration 1), claiming `slot`."""
    return dataclasses.replace(batch(seq), slot=slot, incarnation=incarnation)


def test_the_intake_refuses_a_batch_claiming_a_slot_its_worker_is_not_bound_to(
        caplog: pytest.LogCaptureFixture) -> None:
    i = new_intake()
    i.binding = SlotBinding(binding.parse("w0=0,spare=*", 2))
    assert i.validate(received(on_slot(0)), VERSIONS) is not None  # bound: admitted
    for seq in (1, 2, 3):  # claims slot 1: refused each time, logged once
        assert i.validate(received(on_slot(1, seq, "rogue")), VERSIONS) is None
    assert i.rejects.counts() == {"unbound_slot": 3}
    assert caplog.text.count("unbound_slot") == 1
    assert "w0 claims slot 1; the run's slot binding allows it slot 0 (slot_binding entry w0)" in caplog.text
    assert i.workers == {} and i.tracker.received == 0 and i.buffer.inserted == 0  # w0's own counters untouched
    other = dataclasses.replace(on_slot(1), worker="w5")  # no entry: no slot at all
    assert i.validate(received(other, key_worker="w5"), VERSIONS) is None
    spare = dataclasses.replace(on_slot(1), worker="spare")
    assert i.validate(received(spare, key_worker="spare"), VERSIONS) is not None  # `*`: any slot
    assert i.rejects.counts() == {"unbound_slot": 4}
    # The key decides, not the payload: a batch on w0's key naming the spare is refused before its slot
    assert i.validate(received(spare, key_worker="w0"), VERSIONS) is None
    assert i.rejects.counts() == {"unbound_slot": 4, "sender_mismatch": 1}


def test_without_a_binding_any_worker_claims_any_slot() -> None:
    i = new_intake()
    assert i.validate(received(on_slot(1)), VERSIONS) is not None and i.rejects.total == 0


# -- a split-role run ----------------------------------------------------------------------------
STEPS = 300
FLAGS = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(STEPS), "--workers", "2", "--actors", "2",
         "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "200", "--eval-episodes", "2",
         "--eval-every", "100", "--hidden", "16,16", "--batch-size", "16", "--seed", "3"]
ALGO = dict(workers=2, actors=2, start_steps=100, compete_every=100, eliminate_at=200, eval_episodes=2,
            eval_every=100, hidden=(16, 16), batch_size=16, seed=3)


def rogue_batch(iteration: int, seq: int, obs_dim: int, act_dim: int) -> TransitionBatch:
    """A well-formed start-phase row (version -1: no weights digest needed) of worker w0, claiming
    slot 1 as a new incarnation of w0 each time: unrefused, each takes slot 1 over (the learner
    retires w1's rows, and w1 leaves the slot: services/roles/lockstep.py, takeover.py)."""
    obs, action = np.zeros((1, obs_dim), np.float32), np.zeros((1, act_dim), np.float32)
    return TransitionBatch("w0", f"rogue{seq}", 0, 0, -1, obs, action, np.ones(1, np.float32), obs, np.zeros(1, bool),
                           iteration=iteration, slot=1, episode_starts=(0,))


@pytest.mark.slow
def test_a_worker_claiming_a_slot_outside_its_binding_is_refused_and_the_run_stays_exact(tmp_path: Path) -> None:
    from mam_core.agent import EnvSpec

    run, run_dir, logs = unique_run("bound"), tmp_path / "run", tmp_path / "logs"
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    spec = EnvSpec.from_env_id("AppleCollect-v1")
    learner = spawn("learner", *FLAGS, "--run", run, "--listen", endpoint, "--run-dir", str(run_dir),
                    "--slot-binding", "w0=0,w1=1", log=logs / "learner.log")
    client = ["--run", run, "--connect", endpoint]
    procs = [learner, spawn("referee", *client, "--run-dir", str(run_dir), log=logs / "referee.log")]
    procs += [spawn("worker", *client, "--id", f"w{i}", "--slot", str(i), log=logs / f"w{i}.log") for i in (0, 1)]
    intruder = spawn("worker", *client, "--id", "w9", "--slot", "1", log=logs / "w9.log")  # no entry
    sent = 0
    try:
        assert intruder.wait(120) == EXIT_CONFIG, (logs / "w9.log").read_text()[-2000:]
        with bus.session_scope(bus.make_config(connect=[endpoint]), retry_for=30) as session:
            pub = bus.declare_reliable_publisher(session, keys.transitions(run, "w0"))
            deadline = time.monotonic() + 120
            while learner.poll() is None and learner_iterations(run_dir) < STEPS - 20:
                assert time.monotonic() < deadline, (logs / "learner.log").read_text()[-3000:]
                at = learner_iterations(run_dir) + 1
                pub.put(rogue_batch(at, sent, spec.obs_dim, spec.act_dim).to_bytes())
                sent += 1
                time.sleep(0.02)
            pub.undeclare()
        assert learner.wait(180) == 0, (logs / "learner.log").read_text()[-3000:]
        for p in procs[1:]:
            assert p.wait(60) == 0
    finally:
        stop(*reversed(procs), intruder)
    assert sent >= 3
    log = (logs / "learner.log").read_text(errors="replace")
    assert "slot binding: w0=0, w1=1" in log
    assert log.count("rejected transitions from w0: unbound_slot") == 1, log[-3000:]  # logged once
    assert "worker w9 may not take slot 1 of run" in (logs / "w9.log").read_text()
    transport = json.loads((run_dir / "transport.json").read_text())
    assert transport["rejected"] == {"unbound_slot": sent}, transport  # every one counted, nothing else refused
    assert transport["lost"] == 0 and transport["duplicates"] == 0
    torch.set_num_threads(1)
    record = _record(run_dir)
    assert record["summary"]["exact"] is True, record["summary"]
    _equals_reference(record, run_reference("AppleCollect-v1", resolve("ma-ddpg", **ALGO), STEPS))
    assert processes_of(run) == []
