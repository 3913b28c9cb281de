"""The role skeleton: the weights history and screen, the periodic timer, and what each role module imports."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mam_core.policy import EnvSpec, member_shapes, params_digest
from services.messaging import bus, keys
from services.messaging.codec import LearnerStats, Weights
from services.roles.lockstep import WeightsHistory
from services.roles.role import MAX_VERSION_LEAD, Decodes, Every, plausible_version, weights_screen

ROOT = Path(__file__).resolve().parents[1]
ROLE_MODULES = ("learner", "worker", "referee", "monitor", "router")
SPEC = EnvSpec(obs_dim=3, act_dim=2, max_action=(1.0, 1.0))
HIDDEN = (4,)


def weights_item(k: int, version: int, fill: float) -> tuple[str, bus.Received]:
    params = {name: np.full(shape, fill, np.float32) for name, shape in member_shapes(3, HIDDEN, 2).items()}
    payload = Weights(k, version, params, 3, 2, 1.0, HIDDEN).to_bytes("learner", version)
    key = keys.weights("r", k)
    return key, bus.Received(key, payload, None, 0.0)


def test_weights_history_keeps_one_copy_per_version_and_prefers_the_current_learner():
    """A version names one set of parameters of one learner incarnation: a repeat (a resend, a
    cache replay) is not copied again; after a learner restart the successor's copy of a
    version replaces the dead one's, and never the other way round."""
    h = WeightsHistory(2)
    params = dict(_params(1.0))
    assert h.add(0, 5, params, "old") and h.source(0, 5) == "old"
    assert not h.add(0, 5, dict(_params(2.0)), "old")  # the same version of the same learner
    assert np.all(h.get(0, 5)["w0"] == 1.0)
    assert h.add(0, 5, dict(_params(3.0)), "new", prefer="new") and h.source(0, 5) == "new"
    assert not h.add(0, 5, dict(_params(4.0)), "old", prefer="new")  # a late copy of the dead one's
    assert np.all(h.get(0, 5)["w0"] == 3.0)
    params["w0"][:] = 9.0  # the history holds copies
    assert np.all(h.get(0, 5)["w0"] == 3.0)
    h.add(1, 7, dict(_params(1.0)))
    h.forget_below(6)
    assert not h.has(0, 5) and h.has(1, 7)


def test_the_slots_of_one_process_decode_each_message_once_between_them():
    """Slots stepped by one worker process (WorkerGroup) share a `Decodes`: a weights message
    each slot's subscription receives (its own copy of the bytes) is decoded once, its held copy
    and digest made once; junk is rejected and counted by each slot and keeps nothing."""
    decodes, shapes = Decodes(), member_shapes(3, HIDDEN, 2)
    rejects = [bus.RejectLog(None, "message") for _ in range(2)]
    screens = [weights_screen(shapes, 2, r, decodes) for r in rejects]
    key, item = weights_item(1, 3, 0.5)
    admitted = [screen(item._replace(payload=bytes(bytearray(item.payload)))) for screen in screens]
    assert admitted[0].payload is not admitted[1].payload and admitted[0].value is admitted[1].value
    histories = [WeightsHistory(2, decodes) for _ in range(2)]
    for h, got in zip(histories, admitted):
        w = got.value
        assert h.add(w.actor, w.version, w.params, w.incarnation, payload=got.payload)
    held = [h.get(1, 3) for h in histories]
    assert held[0] is held[1] and held[0]["w0"] is not admitted[0].value.params["w0"]  # one copy, of its own
    assert histories[0].digest(1, 3) == histories[1].digest(1, 3) == params_digest(admitted[0].value.params)
    alone = WeightsHistory(2)  # a process with one slot: its own copy, the same digest
    assert alone.add(1, 3, admitted[0].value.params) and alone.digest(1, 3) == histories[0].digest(1, 3)
    kept = len(decodes._values)
    for screen in screens:
        assert screen(bus.Received(key, b"\x93garbage", None, 0.0)) is None
    assert [r.total for r in rejects] == [1, 1] and len(decodes._values) == kept
    calls = []
    for i in range(Decodes.KEEP + 10):  # it keeps the last few only
        decodes.get("stats", i.to_bytes(4, "big"), lambda: calls.append(1) or len(calls))
    assert len(decodes._values) <= Decodes.KEEP and len(calls) == Decodes.KEEP + 10
    assert decodes.get("stats", (Decodes.KEEP + 9).to_bytes(4, "big"), lambda: -1) == Decodes.KEEP + 10


def test_weights_screen_rejects_malformed_messages_in_the_callback():
    rejects = bus.RejectLog(None, "message")
    screen = weights_screen(member_shapes(3, HIDDEN, 2), 2, rejects)
    key, item = weights_item(1, 3, 1.0)
    assert screen(item)
    assert not screen(bus.Received(key, b"\x93garbage", None, 0.0))
    other = Weights(0, 1, dict(_params(1.0, hidden=(5,))), 3, 2, 1.0, (5,)).to_bytes("learner", 1)
    assert not screen(bus.Received(key, other, None, 0.0))  # another run's shapes
    assert rejects.total == 2
    assert plausible_version(Weights(0, MAX_VERSION_LEAD, dict(_params(1.0)), 3, 2, 1.0, HIDDEN), None)
    stats = LearnerStats(env_steps=0, updates=0, accept_until=0, utd=0.0, versions=(10, 10))
    assert not plausible_version(Weights(1, 11 + MAX_VERSION_LEAD, dict(_params(1.0)), 3, 2, 1.0, HIDDEN), stats)


def _params(fill: float, hidden: tuple[int, ...] = HIDDEN):
    return {name: np.full(shape, fill, np.float32) for name, shape in member_shapes(3, hidden, 2).items()}.items()


def test_every_is_due_once_per_period():
    clock = [100.0]
    every = Every(1.0, clock=lambda: clock[0])
    assert every.due()  # the first call is due
    assert not every.due()
    clock[0] += 0.99
    assert not every.due() and every.elapsed() == pytest.approx(0.99)
    clock[0] += 0.01
    assert every.due() and not every.due()
    every.reset(clock[0] + 5.0)
    assert not every.due(clock[0] + 5.5) and every.due(clock[0] + 6.0)


def _imported_roles(path: Path) -> set[str]:
    """The role modules (services.roles.<role>) a source file imports, anywhere in it."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "services.roles":
                names.update(a.name for a in node.names)
            elif node.module.startswith("services.roles."):
                names.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            names.update(a.name.split(".")[2] for a in node.names if a.name.startswith("services.roles."))
    return names


@pytest.mark.parametrize("role", ROLE_MODULES)
def test_no_role_module_imports_another(role: str):
    others = set(ROLE_MODULES) - {role}
    assert not _imported_roles(ROOT / "services" / "roles" / f"{role}.py") & others  # in the source, anywhere
    code = (f"import sys, json; import services.roles.{role}; "
            f"print(json.dumps(sorted(m for m in {sorted(others)!r} if 'services.roles.' + m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []  # nor through what it imports


def test_the_services_floor_shows_the_architecture_and_fits_on_a_screen_or_two():
    """Sub-packages by concern; no role module over 400 lines, no services/ file over 500."""
    packages = {p.name for p in (ROOT / "services").iterdir() if (p / "__init__.py").is_file()}
    assert packages == {"roles", "run", "messaging", "cli"}
    assert [p.name for p in (ROOT / "services").glob("*.py")] == ["__init__.py"]  # nothing loose at the top
    for path in (ROOT / "services").rglob("*.py"):
        lines = len(path.read_text().splitlines())
        limit = 400 if path.parent.name == "roles" and path.stem in ROLE_MODULES else 500
        assert lines <= limit, f"{path.relative_to(ROOT)}: {lines} lines (at most {limit})"


HEAVY = ("torch", "matplotlib")


@pytest.mark.parametrize("argv", [["services.roles.worker", "--help"], ["services.roles.referee", "--help"],
                                  ["services.cli", "worker", "--help"], ["services.cli", "referee", "--help"]])
def test_role_commands_import_neither_torch_nor_matplotlib(argv: list[str]):
    code = ("import json, runpy, sys\n"
            f"sys.argv = {argv!r}\n"
            "try:\n"
            f"    runpy.run_module({argv[0]!r}, run_name='__main__', alter_sys=True)\n"
            "except SystemExit as e:\n"
            "    assert e.code in (0, None), e.code\n"
            f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "--run" in out.stdout  # the role's own help was printed
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_the_learner_does_import_torch():
    """The check above can fail: the learner's --help does load torch."""
    code = ("import runpy, sys\nsys.argv = ['services.roles.learner', '--help']\n"
            "try:\n    runpy.run_module('services.roles.learner', run_name='__main__', alter_sys=True)\n"
            "except SystemExit:\n    pass\nprint('torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.stdout.strip().splitlines()[-1] == "True"


def test_a_finished_role_exits_at_once_with_its_logs_and_output_flushed(tmp_path: Path):
    """`role.exit_finished` skips the interpreter's teardown (os._exit): what the role logged to a
    file and printed to a pipe (both buffered) is still there, and the status is the one given."""
    log = tmp_path / "role.log"
    code = ("import logging, sys; from services.roles import role; "
            f"logging.basicConfig(filename={str(log)!r}, level=logging.INFO); "
            "logging.getLogger('mam.test').info('the last line of work'); "
            "sys.stdout.write('printed, not yet flushed'); "
            "import atexit; atexit.register(lambda: print('an atexit handler ran')); "
            "role.exit_finished(3)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 3, out.stderr
    assert out.stdout == "printed, not yet flushed"  # flushed, and no teardown ran after it
    assert "the last line of work" in log.read_text()


def test_a_role_whose_teardown_hangs_leaves_within_its_bound() -> None:
    """`role.leave_within`: a process whose work is done (here: nothing) and whose teardown then
    hangs (here: a sleep of a minute) exits 0 after the bound, and says so in its log."""
    import time

    code = ("import logging, time; from services.roles import role; logging.basicConfig(level=logging.INFO)\n"
            "role.leave_within(1.0, 'the test role'); time.sleep(60)")
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=50)
    took = time.monotonic() - t0
    assert out.returncode == 0 and took < 30, (out.returncode, took, out.stderr[-2000:])
    assert "the test role: its teardown took over 1 s after its work was done; leaving without it" in out.stderr
