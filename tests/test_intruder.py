"""Issue 38, item 8: a local run is closed to other processes. `mam run` hands its children a
per-run secret (RUN_DIR/zenoh-auth, mode 0600, named in their environment, never on their command
line) and its learner admits only sessions that present it (services/run/secret.py). A process of
the box that reads the run's endpoint (from config.json, or `ps`) cannot connect, so it can neither
publish a batch nor answer an episode query; the learner's log says whom it refused."""

from __future__ import annotations

import io
import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from rich.console import Console

from mam_core.agent import EnvSpec
from mam_core.config import resolve
from mam_core.reference import run_reference
from services.messaging import bus, keys
from services.messaging.codec import SlotEpisode, TransitionBatch
from services.run import secret
from services.run.chaos import children_of
from services.run.cluster import LocalCluster
from services.run.config import RunConfig
from tests.e2e import ROOT, processes_of, stop, unique_run
from tests.test_exact import APPLE, APPLE_STEPS, _equals_reference, _record, apple_args

REFUSED_NONE = "UsrPwd extension - Recv InitSyn. Expected extension."  # no credentials (Zenoh, at debug)
REFUSED_WRONG = "UsrPwd extension - Recv OpenSyn. Invalid password."


def password(path: Path) -> str:
    return path.read_text().strip().partition(":")[2]


def guessed(tmp: Path) -> Path:
    """Credentials of the right form with another password, as an intruder would guess them."""
    path = tmp / "guess"
    path.write_text(f"{secret.USER}:{'x' * 43}\n")
    return path


def test_the_secret_is_this_users_alone_and_new_for_every_part(tmp_path: Path) -> None:
    first = secret.create(tmp_path)
    assert first == tmp_path / "zenoh-auth" and stat.S_IMODE(first.stat().st_mode) == 0o600
    user, _, pw = first.read_text().strip().partition(":")
    assert user == secret.USER and len(pw) >= 40  # 32 random bytes
    second = secret.create(tmp_path)  # the next part: the old one's processes cannot rejoin
    assert second == first and password(second) != pw and stat.S_IMODE(second.stat().st_mode) == 0o600
    assert secret.of_run(tmp_path) == second and secret.child_env(second) == {bus.AUTH_ENV: str(second)}
    assert [p.name for p in tmp_path.iterdir()] == ["zenoh-auth"]  # no temporary file left
    secret.remove(second)
    assert secret.of_run(tmp_path) is None and secret.child_env(None) == {}


def test_a_listening_session_with_the_secret_admits_only_sessions_that_present_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(bus.AUTH_ENV, raising=False)
    auth = secret.create(tmp_path)
    conf = bus.make_config(connect=["tcp/127.0.0.1:1"], auth_file=auth)
    assert json.loads(conf.get_json("transport/auth/usrpwd")) == {
        "user": secret.USER, "password": password(auth), "dictionary_file": str(auth)}
    assert json.loads(bus.make_config(connect=["tcp/127.0.0.1:1"]).get_json("transport/auth/usrpwd"))["user"] is None
    monkeypatch.setenv(bus.AUTH_ENV, str(auth))  # how `mam run`'s children get it
    assert json.loads(bus.make_config(listen=["tcp/127.0.0.1:1"]).get_json("transport/auth/usrpwd/user")) == "mam"
    monkeypatch.delenv(bus.AUTH_ENV)
    bad = tmp_path / "bad"
    bad.write_text("no colon\n")
    with pytest.raises(ValueError, match="not one user:password line"):
        bus.make_config(auth_file=bad)
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    with bus.session_scope(bus.make_config(listen=[endpoint], auth_file=auth)):
        with bus.session_scope(bus.make_config(connect=[endpoint], auth_file=auth), retry_for=10):
            pass  # the run's own
        for creds in (None, guessed(tmp_path)):
            with pytest.raises(zenoh.ZError):
                bus.open_session(bus.make_config(connect=[endpoint], auth_file=creds))


def test_the_secret_is_on_no_childs_command_line_and_a_child_logs_whom_it_refused(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A child of `mam run` (here the router role, the quickest to start) gets the secret's path in
    its environment, and the password is on no command line; listening with it, the child admits
    the run's own sessions and logs the refusal of the others."""
    monkeypatch.delenv(bus.AUTH_ENV, raising=False)
    auth = secret.create(tmp_path)
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    cfg = RunConfig(run="closed", env_id="AppleCollect-v1", steps=100, algo=resolve("ma-ddpg"))
    cluster = LocalCluster(cfg, tmp_path, endpoint, console=Console(file=io.StringIO()), secret_file=auth)
    child = cluster.spawn("router", ["--listen", endpoint])
    try:
        bus.open_session(bus.make_config(connect=[endpoint], auth_file=auth), retry_for=30).close()
        for creds in (None, guessed(tmp_path)):
            with pytest.raises(zenoh.ZError):
                bus.open_session(bus.make_config(connect=[endpoint], auth_file=creds))
        cmdline = Path(f"/proc/{child.proc.pid}/cmdline").read_bytes()
        environ = Path(f"/proc/{child.proc.pid}/environ").read_bytes().split(b"\0")
        assert password(auth).encode() not in cmdline and password(auth).encode() not in b"\0".join(environ)
        assert f"{bus.AUTH_ENV}={auth}".encode() in environ
        deadline = time.monotonic() + 10
        while not (REFUSED_NONE in child.log.read_text() and REFUSED_WRONG in child.log.read_text()):
            assert time.monotonic() < deadline, child.log.read_text()[-2000:]
            time.sleep(0.1)
    finally:
        stop(child.proc)


def intrude(run: str, endpoint: str, spec: EnvSpec, tmp: Path) -> None:
    """What a process without the run's secret tries: connect as a client (refused at once, with no
    credentials and with guessed ones), then as a peer, which keeps trying in the background while
    it publishes a well-formed batch on worker w1's key and answers slot 1's episode query."""
    for creds in (None, guessed(tmp)):
        with pytest.raises(zenoh.ZError):
            bus.open_session(bus.make_config(connect=[endpoint], mode="client", auth_file=creds))
    rows, actions = np.zeros((1, spec.obs_dim), np.float32), np.zeros((1, spec.act_dim), np.float32)
    # a start-phase row of slot 1 (version -1: it needs no weights digest), as its worker sends them
    batch = TransitionBatch("w1", "intruder", 0, 0, -1, rows, actions, np.ones(1, np.float32), rows,
                            np.zeros(1, bool), iteration=1, slot=1, episode_starts=(0,))
    episode = SlotEpisode(1, 1, 2, rows, actions, rows).to_bytes("learner", 0)
    asked = []

    def answer(query: zenoh.Query) -> None:
        asked.append(query)
        query.reply(query.key_expr, episode)

    with bus.session_scope(bus.make_config(connect=[endpoint], mode="peer")) as session:
        queryable = session.declare_queryable(keys.episode(run, 1), answer)
        pub = bus.declare_reliable_publisher(session, keys.transitions(run, "w1"))
        for _ in range(30):
            pub.put(batch.to_bytes())
            assert not pub.matching_status.matching  # no learner's subscriber ever in reach
            time.sleep(0.1)
        assert asked == []
        queryable.undeclare()


@pytest.mark.slow
def test_a_local_process_without_the_secret_can_neither_publish_nor_answer_and_the_run_stays_exact(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(bus.AUTH_ENV, raising=False)  # the test process is not one of the run's
    run, run_dir, out = unique_run("intruder"), tmp_path / "intruder", tmp_path / "mam.out"
    command = [sys.executable, "-m", "services.cli", "run", *apple_args(run, run_dir, 3), "--no-plot"]
    with open(out, "wb") as f:
        proc = subprocess.Popen(command, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONWARNINGS="ignore"))
    try:
        deadline = time.monotonic() + 60
        while not json.loads((run_dir / "config.json").read_text() if (run_dir / "config.json").is_file()
                             else "{}").get("endpoint"):
            assert proc.poll() is None and time.monotonic() < deadline, out.read_text()[-3000:]
            time.sleep(0.1)
        endpoint, auth = json.loads((run_dir / "config.json").read_text())["endpoint"], run_dir / "zenoh-auth"
        assert stat.S_IMODE(auth.stat().st_mode) == 0o600
        # The run's own session gets in (the endpoint is live) and sees the learner at work.
        with bus.session_scope(bus.make_config(connect=[endpoint], auth_file=auth), retry_for=60) as insider:
            stats = bus.Latest.subscribe(insider, keys.learner_stats(run))
            assert stats.wait(keys.learner_stats(run), timeout=120), "no learner stats"
            stats.close()
        deadline, children = time.monotonic() + 120, children_of(proc.pid)
        while {role for _, role in children} < {"learner", "referee", "worker"}:  # the workers start last
            assert proc.poll() is None and time.monotonic() < deadline, children
            time.sleep(0.1)
            children = children_of(proc.pid)
        for pid, _role in children:  # what `ps` shows every user
            assert password(auth).encode() not in Path(f"/proc/{pid}/cmdline").read_bytes()
        intrude(run, endpoint, EnvSpec.from_env_id("AppleCollect-v1"), tmp_path)
        proc.wait(240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    assert proc.returncode == 0, out.read_text()[-3000:]
    log = (run_dir / "logs" / "learner.log").read_text(errors="replace")
    assert REFUSED_NONE in log and REFUSED_WRONG in log, log[-3000:]  # whom it refused, in the learner's log
    assert not auth.exists()  # the part is over: nobody joins it any more
    transport = json.loads((run_dir / "transport.json").read_text())
    assert transport["rejected"] == {} and transport["lost"] == 0, transport  # nothing of it even arrived
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS)
    record = _record(run_dir)
    assert record["summary"]["exact"] is True
    _equals_reference(record, ref)
    assert processes_of(run) == []
