"""deploy/: certificates, Zenoh configs (TLS + access control), systemd units, and runs across hosts.

* fast: `deploy/make-certs.sh` output, every JSON5 config loads, the systemd units; a `mam router`
  with deploy/zenoh/router-tls.json5 on loopback, probed with real Zenoh sessions holding each
  role's certificate: no valid certificate, no session; each role may publish, subscribe and
  declare liveliness tokens and caches only where the access-control rules allow.
* slow: a whole run (learner + referee + router on "host A", two workers on "host B") over a
  veth pair between two network namespaces, with the plain TCP configs and with TLS + ACL.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
import zenoh

from mam_core.config import resolve
from mam_core.policy import read_policy_file
from mam_core.reference import run_reference
from services.messaging import bus, keys
from services.messaging.codec import decode
from services.roles import role
from tests.e2e import ROOT, assert_exactly_once, learner_iterations, load, stop, unique_run

DEPLOY = ROOT / "deploy"
ZENOH_DIR = DEPLOY / "zenoh"
ROLES = ("learner", "referee", "worker", "monitor")
CERTS_IN_CONFIGS = "/etc/mam/certs"

needs_openssl = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")


# --------------------------------------------------------------------------- helpers


def make_certs(directory: Path, *hosts: str) -> Path:
    subprocess.run(["bash", str(DEPLOY / "make-certs.sh"), str(directory), *hosts], check=True,
                   capture_output=True, text=True, timeout=60)
    return directory


def deploy_config(name: str, certs: Path, into: Path) -> Path:
    """A copy of deploy/zenoh/NAME whose certificate paths point at ``certs``."""
    text = (ZENOH_DIR / name).read_text()
    assert CERTS_IN_CONFIGS in text or "tls" not in name, name
    out = into / name
    out.write_text(text.replace(CERTS_IN_CONFIGS, str(certs)))
    return out


def spawn(args: list[str], log: Path, *, netns: str | None = None, env: dict | None = None) -> subprocess.Popen:
    """`python -m services.X ...`, optionally inside a network namespace (`ip netns exec` execs it,
    so the Popen pid is the Python process itself and SIGTERM reaches it)."""
    prefix = ["ip", "netns", "exec", netns] if netns else []
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as out:
        return subprocess.Popen([*prefix, sys.executable, "-m", *args], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True,
                                env={**os.environ, "PYTHONWARNINGS": "ignore", **(env or {})})


def client_config(certs: Path, role: str | None, endpoint: str, tmp: Path, **tls_overrides) -> zenoh.Config:
    """The deploy config of ``role``; role None: the worker's without a client certificate (it
    still trusts the CA, so only the router's demand for a certificate can refuse it)."""
    path = deploy_config(f"{role or 'worker'}-tls.json5", certs, tmp)
    conf = bus.make_config(connect=[endpoint], config_file=path)
    if role is None:
        conf.insert_json5("transport/link/tls/connect_certificate", "null")
        conf.insert_json5("transport/link/tls/connect_private_key", "null")
        conf.insert_json5("transport/link/tls/enable_mtls", "false")
    for k, v in tls_overrides.items():
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(v))
    return conf


def read_unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A systemd unit as {section: {key: [values]}} (keys such as EnvironmentFile repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
        else:
            key, _, value = line.partition("=")
            current.setdefault(key.strip(), []).append(value.strip())
    return sections


# --------------------------------------------------------------------------- files


@needs_openssl
def test_make_certs_makes_a_ca_and_one_certificate_per_role(tmp_path: Path) -> None:
    certs = make_certs(tmp_path / "certs", "10.9.8.7", "mam-router.example.org")
    for name in ("router", *ROLES):
        pem = certs / f"{name}.pem"
        subprocess.run(["openssl", "verify", "-CAfile", str(certs / "ca.pem"), str(pem)], check=True,
                       capture_output=True)
        subject = subprocess.run(["openssl", "x509", "-in", str(pem), "-noout", "-subject"], check=True,
                                 capture_output=True, text=True).stdout
        assert re.search(rf"CN\s*=\s*{name}\b", subject), subject
        assert oct((certs / f"{name}.key").stat().st_mode & 0o777) == "0o600"
    text = subprocess.run(["openssl", "x509", "-in", str(certs / "router.pem"), "-noout", "-ext", "subjectAltName"],
                          check=True, capture_output=True, text=True).stdout
    for name in ("localhost", "127.0.0.1", "10.9.8.7", "mam-router.example.org"):
        assert name in text
    # A second call reuses the CA: certificates made later still chain to the shipped ca.pem.
    ca = (certs / "ca.pem").read_bytes()
    make_certs(certs)
    assert (certs / "ca.pem").read_bytes() == ca


def test_every_deploy_config_loads() -> None:
    files = sorted(ZENOH_DIR.glob("*.json5"))
    assert {f.name for f in files} >= {f"{r}{t}.json5" for r in ("router", *ROLES) for t in ("", "-tls")}
    for f in files:
        conf = bus.make_config(config_file=f)
        mode = json.loads(conf.get_json("mode"))
        assert mode == ("router" if f.name.startswith("router") else "client"), f.name
        assert json.loads(conf.get_json("timestamping/enabled")) is True  # the advanced publishers need it
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
        if "-tls" in f.name:
            tls = json.loads(conf.get_json("transport/link/tls"))
            assert tls["enable_mtls"] is True and tls["root_ca_certificate"].startswith(CERTS_IN_CONFIGS)
            assert json.loads(conf.get_json("transport/link/protocols")) == ["tls"]
    acl = json.loads(bus.make_config(config_file=ZENOH_DIR / "router-tls.json5").get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {cn for s in acl["subjects"] for cn in s["cert_common_names"]} == set(ROLES)


def test_systemd_units_use_the_environment_file() -> None:
    units = {p.name: p for p in (DEPLOY / "systemd").glob("*.service")}
    assert set(units) >= {"mam-router.service", "mam-learner@.service", "mam-worker@.service",
                          "mam-referee@.service"}
    env_example = (DEPLOY / "systemd" / "mam.env").read_text()
    defined = set(re.findall(r"^([A-Z_]+)=", env_example, re.M))
    for name, path in units.items():
        service = read_unit(path)["Service"]
        assert "/etc/mam/mam.env" in service["EnvironmentFile"], name
        (command,) = service["ExecStart"]
        role = name.removeprefix("mam-").split("@")[0].split(".")[0]
        role = {"spare": "worker"}.get(role, role)  # mam-spare.service: `mam-worker --spare`
        assert (f"mam-{role}" in command) or (f"mam {role}" in command), command
        assert "--zenoh-config" in command and ("--connect" in command or "--listen" in command)
        used = set(re.findall(r"\$\{?([A-Z_]+)\}?", command))
        assert used <= defined, (name, used - defined)


# --------------------------------------------------------------------------- TLS + access control


@pytest.fixture(scope="module")
def tls_router(tmp_path_factory):
    """`mam router --zenoh-config router-tls.json5` on a free loopback port; yields (certs, endpoint, tmp)."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    tmp = tmp_path_factory.mktemp("tls")
    certs = make_certs(tmp / "certs")
    config = deploy_config("router-tls.json5", certs, tmp)
    endpoint = f"tls/127.0.0.1:{bus.free_tcp_port()}"
    router = spawn(["services.roles.router", "--zenoh-config", str(config), "--listen", endpoint], tmp / "router.log")
    try:
        conf = client_config(certs, "monitor", endpoint, tmp)
        with bus.session_scope(conf, retry_for=30):
            pass
        yield certs, endpoint, tmp
    finally:
        stop(router)


def test_the_router_says_where_it_listens(tls_router) -> None:
    """A router started by hand names its endpoint in its log (issue 40's newcomer list)."""
    _, endpoint, tmp = tls_router
    deadline = time.monotonic() + 20  # the line follows the session's start, which a client may beat
    while f"listening on {endpoint}" not in (tmp / "router.log").read_text():
        assert time.monotonic() < deadline, (tmp / "router.log").read_text()[-2000:]
        time.sleep(0.2)


@pytest.mark.parametrize("case, router_says", [
    ("no client certificate", "peer sent no certificates"),
    ("certificate of another CA", "invalid peer certificate: UnknownIssuer"),
    ("plain tcp", "received corrupt message of type InvalidContentType"),
])
def test_a_client_without_a_valid_certificate_cannot_connect(tls_router, tmp_path: Path, case: str,
                                                             router_says: str) -> None:
    certs, endpoint, tmp = tls_router
    if case == "no client certificate":
        conf = client_config(certs, None, endpoint, tmp_path)
    elif case == "certificate of another CA":  # same CN "worker", another CA
        rogue = make_certs(tmp_path / "rogue")
        conf = client_config(certs, "worker", endpoint, tmp_path,
                             connect_certificate=str(rogue / "worker.pem"),
                             connect_private_key=str(rogue / "worker.key"))
    else:
        conf = bus.make_config(connect=[endpoint.replace("tls/", "tcp/")], config_file=ZENOH_DIR / "worker.json5")
    log = tmp / "router.log"
    seen_before = log.read_text(errors="replace").count(router_says)
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError):
        bus.open_session(conf).close()
    assert time.monotonic() - t0 < 10
    # The router refused it, and says why in its log (the lines docs/DEPLOY.md's table quotes).
    deadline = time.monotonic() + 5
    while log.read_text(errors="replace").count(router_says) == seen_before:
        assert time.monotonic() < deadline, log.read_text(errors="replace")[-2000:]
        time.sleep(0.05)


def test_check_connection_reports_connected_or_why_not(tls_router, tmp_path: Path) -> None:
    certs, endpoint, tmp = tls_router
    script = [sys.executable, str(DEPLOY / "check-connection.py"), "--connect", endpoint, "--zenoh-config"]
    ok = subprocess.run([*script, str(deploy_config("monitor-tls.json5", certs, tmp_path)), "--run", "nobody-here"],
                        capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "connected to" in ok.stdout and "no liveliness token" in ok.stdout, ok
    rogue = make_certs(tmp_path / "rogue")
    bad = subprocess.run([*script, str(deploy_config("monitor-tls.json5", rogue, tmp_path / "rogue"))],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "NOT CONNECTED" in bad.stderr
    assert "invalid peer certificate" in bad.stdout  # Zenoh's own reason, not just "Unable to connect"


# publisher role, key under mam/<run>/, subscriber role, delivered?
PUBLICATIONS = [
    ("learner", "weights/0", "referee", True),
    ("learner", "weights/0", "worker", True),
    ("worker", "weights/0", "referee", False),   # only the learner publishes weights
    ("referee", "weights/0", "worker", False),
    ("learner", "weights/0", "monitor", False),  # a monitor may not even subscribe to weights
    ("worker", "transitions/w0", "learner", True),
    ("monitor", "transitions/m0", "learner", False),  # monitors only subscribe
    ("referee", "allocation", "learner", True),
    ("referee", "allocation", "worker", True),
    ("worker", "allocation", "learner", False),  # only the referee publishes allocation and eval
    ("monitor", "allocation", "worker", False),
    ("learner", "allocation", "monitor", False),
    ("referee", "eval", "monitor", True),
    ("worker", "eval", "monitor", False),
    ("learner", "config", "referee", True),
    ("worker", "config", "referee", False),
    ("learner", "done", "worker", True),
    ("worker", "done", "referee", False),
]


@pytest.fixture
def role_sessions(tls_router):
    certs, endpoint, tmp = tls_router
    sessions = {}
    try:
        for role in ROLES:
            sessions[role] = bus.open_session(client_config(certs, role, endpoint, tmp), retry_for=10)
        yield sessions
    finally:
        for s in sessions.values():
            s.close()


def test_each_role_publishes_only_what_the_acl_allows(role_sessions) -> None:
    run = unique_run("acl")
    got: dict[tuple[str, str], set[bytes]] = {}
    lock = threading.Lock()

    def recorder(receiver: str, key: str):
        def on_sample(sample: zenoh.Sample) -> None:
            with lock:
                got.setdefault((receiver, key), set()).add(sample.payload.to_bytes())
        return on_sample

    subs = [role_sessions[rx].declare_subscriber(f"mam/{run}/{key}", recorder(rx, key))
            for rx, key in sorted({(rx, key) for _, key, rx, _ in PUBLICATIONS})]
    pubs = {(tx, key): bus.declare_reliable_publisher(role_sessions[tx], f"mam/{run}/{key}")
            for tx, key in sorted({(tx, key) for tx, key, _, _ in PUBLICATIONS})}
    expected = {(rx, key, tx.encode()) for tx, key, rx, ok in PUBLICATIONS if ok}

    def delivered() -> set[tuple[str, str, bytes]]:
        with lock:
            return {(rx, key, p) for (rx, key), payloads in got.items() for p in payloads}

    # Publish every (role, key) until every allowed one arrived, then half a second more:
    # the refused ones had every chance (subscriptions were in place) and must never show up.
    deadline = time.monotonic() + 15
    while not expected <= delivered() and time.monotonic() < deadline:
        for (tx, _), pub in pubs.items():
            pub.put(tx.encode())
        time.sleep(0.05)
    for _ in range(10):
        for (tx, _), pub in pubs.items():
            pub.put(tx.encode())
        time.sleep(0.05)
    for s in [*subs, *pubs.values()]:
        s.undeclare()
    seen = delivered()
    assert expected - seen == set(), "allowed publications that never arrived"
    refused = {(rx, key, tx.encode()) for tx, key, rx, ok in PUBLICATIONS if not ok}
    assert seen & refused == set(), "publications the ACL should have refused"


def test_only_the_learner_answers_a_workers_episode_query(role_sessions, tls_router) -> None:
    """A worker taking a slot over asks `mam/<run>/episode/w<i>` (services/roles/takeover.py): the
    learner's queryable answers it through the TLS router; another worker's or the referee's does
    not. (The asker is a second worker session: a session's own queryable answers it locally.)"""
    certs, endpoint, tmp = tls_router
    asker = bus.open_session(client_config(certs, "worker", endpoint, tmp), retry_for=10)
    run = unique_run("acl-episode")
    key = keys.episode(run, 1)
    answers = {role: bus.Answers(role_sessions[role], keys.episode_all(run)) for role in ("learner", "worker",
                                                                                         "referee")}
    got: list[bytes] = []

    def ask() -> None:  # every reply to each query (zenoh's default: one per queryable that matches)
        for _ in range(6):
            for reply in asker.get(key, timeout=1.0):
                if reply.ok is not None:
                    got.append(reply.ok.payload.to_bytes())

    thread = threading.Thread(target=ask)
    thread.start()
    deadline = time.monotonic() + 12
    while thread.is_alive() and time.monotonic() < deadline:
        for name, a in answers.items():
            a.poll(lambda _key, _payload, name=name: name.encode())
        time.sleep(0.02)
    thread.join(15)
    for a in answers.values():
        a.close()
    asker.close()
    assert got and set(got) == {b"learner"}, got


def test_liveliness_tokens_and_late_joiner_caches_follow_the_roles(role_sessions) -> None:
    run = unique_run("acl-live")
    s = role_sessions
    # Liveliness: each role announces only itself; a worker cannot pose as the learner.
    tokens = [s["worker"].liveliness().declare_token(keys.alive(run, "worker", "w0")),
              s["worker"].liveliness().declare_token(keys.alive(run, "learner", "fake")),
              s["worker"].liveliness().declare_token(keys.alive(run, "referee", "fake")),
              s["learner"].liveliness().declare_token(keys.alive(run, "learner", "l0")),
              s["monitor"].liveliness().declare_token(keys.alive(run, "referee", "m0"))]
    # Late-joiner caches (advanced publishers): only the learner's weights are served.
    real = bus.declare_latest_publisher(s["learner"], keys.weights(run, 0))
    fake = bus.declare_latest_publisher(s["worker"], keys.weights(run, 1))
    real.put(b"real")
    fake.put(b"fake")
    time.sleep(0.5)
    try:
        watches = {watcher: bus.watch_alive(s[watcher], run) for watcher in ("referee", "monitor")}
        late = bus.Latest.subscribe(s["referee"], keys.weights_all(run))
        assert late.wait(keys.weights(run, 0), timeout=10), "the learner's cached weights never arrived"
        for watcher, watch in watches.items():
            assert watch.wait_for(lambda live: {"w0", "l0"} <= live, timeout=10), (watcher, watch.members())
        time.sleep(0.5)
        assert late.get(keys.weights(run, 0)).payload == b"real"
        assert late.get(keys.weights(run, 1)) is None
        assert watches["referee"].members() == {("worker", "w0"), ("learner", "l0")}
        # (a session sees its own tokens locally, without the router: the monitor's fake one)
        assert watches["monitor"].members() == {("worker", "w0"), ("learner", "l0"), ("referee", "m0")}
        late.close()
        for watch in watches.values():
            watch.close()
    finally:
        for t in tokens:
            t.undeclare()
        real.undeclare()
        fake.undeclare()


def test_a_spare_with_the_worker_certificate_sees_the_workers_and_the_other_spares(tls_router) -> None:
    """`mam-worker --spare` runs with the worker's certificate: it may announce itself under
    alive/spare/* and read the workers' tokens and reports (which slot each live worker holds)."""
    certs, endpoint, tmp = tls_router
    run = unique_run("acl-spare")
    with bus.session_scope(client_config(certs, "worker", endpoint, tmp), retry_for=10) as worker, \
            bus.session_scope(client_config(certs, "worker", endpoint, tmp), retry_for=10) as spare, \
            bus.session_scope(client_config(certs, "worker", endpoint, tmp), retry_for=10) as other:
        tokens = [bus.declare_alive(worker, run, "worker", "w0"), bus.declare_alive(other, run, keys.SPARE, "s1")]
        reports = bus.Latest(late_join=False).subscribe(spare, keys.role_stats_all(run, "worker"))
        workers, spares = bus.watch_alive(spare, run, "worker"), bus.watch_alive(spare, run, keys.SPARE)
        report = role.RoleReport(worker, run, "worker", "w0", every_s=0.0)
        try:
            assert workers.wait_for(lambda live: live == {"w0"}, timeout=10), workers.members()
            assert spares.wait_for(lambda live: live == {"s1"}, timeout=10), spares.members()
            deadline = time.monotonic() + 10
            while reports.get(keys.role_stats(run, "worker", "w0")) is None and time.monotonic() < deadline:
                report.publish({"slot": 0}, seq=0)
                time.sleep(0.1)
            item = reports.get(keys.role_stats(run, "worker", "w0"))
            assert item is not None, "a worker's report never reached the spare"
            assert decode(item.payload)["slot"] == 0
        finally:
            for closable in (reports, workers, spares):
                closable.close()
            for t in tokens:
                t.undeclare()


# --------------------------------------------------------------------------- across hosts


class Netns:
    """Two network namespaces joined by a veth pair: "host A" 10.123.0.1, "host B" 10.123.0.2.

    The addresses exist only inside the namespaces, so nothing on the machine's own network is
    touched, and concurrent test runs do not collide (each has its own namespaces).
    """

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:6]
        self.a, self.b = f"mam-a-{tag}", f"mam-b-{tag}"
        self.veth_a, self.veth_b = f"mva{tag}", f"mvb{tag}"
        self.addr_a, self.addr_b = "10.123.0.1", "10.123.0.2"

    @staticmethod
    def ip(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)

    def up(self) -> None:
        steps = [
            ("netns", "add", self.a), ("netns", "add", self.b),
            ("link", "add", self.veth_a, "type", "veth", "peer", "name", self.veth_b),
            ("link", "set", self.veth_a, "netns", self.a), ("link", "set", self.veth_b, "netns", self.b),
            ("-n", self.a, "addr", "add", f"{self.addr_a}/24", "dev", self.veth_a),
            ("-n", self.b, "addr", "add", f"{self.addr_b}/24", "dev", self.veth_b),
            ("-n", self.a, "link", "set", "lo", "up"), ("-n", self.b, "link", "set", "lo", "up"),
            ("-n", self.a, "link", "set", self.veth_a, "up"), ("-n", self.b, "link", "set", self.veth_b, "up"),
        ]
        for step in steps:
            r = self.ip(*step)
            if r.returncode != 0:
                raise RuntimeError(f"ip {' '.join(step)}: {r.stderr.strip()}")
        r = subprocess.run(["ip", "netns", "exec", self.a, "true"], capture_output=True, text=True, timeout=20)
        if r.returncode != 0:
            raise RuntimeError(f"ip netns exec: {r.stderr.strip()}")
        ping = subprocess.run(["ip", "netns", "exec", self.b, "ping", "-c", "1", "-W", "5", self.addr_a],
                              capture_output=True, text=True, timeout=30) if shutil.which("ping") else None
        if ping is not None and ping.returncode != 0:
            raise RuntimeError(f"no route from B to A: {ping.stdout}{ping.stderr}")

    def bytes_over_veth(self) -> int:
        stats = json.loads(self.ip("-n", self.b, "-s", "-j", "link", "show", self.veth_b).stdout)[0]["stats64"]
        return stats["rx"]["bytes"] + stats["tx"]["bytes"]

    def down(self) -> None:
        for ns in (self.a, self.b):  # deleting a namespace destroys its end of the veth pair, and so both
            self.ip("netns", "del", ns)


@pytest.fixture
def two_hosts():
    if os.geteuid() != 0:
        pytest.skip("needs root: creates network namespaces and a veth pair")
    if shutil.which("ip") is None:
        pytest.skip("needs iproute2 (`ip netns`)")
    hosts = Netns()
    try:
        hosts.up()
    except (RuntimeError, OSError, subprocess.TimeoutExpired) as e:
        hosts.down()
        pytest.skip(f"`ip netns` / veth unavailable here: {e}")
    try:
        yield hosts
    finally:
        hosts.down()


STEPS, WORKERS = 1500, 2
RUN_FLAGS = ["--env", "AppleCollect-v0", "--algo", "ma-ddpg", "--schedule", "equal-data", "--steps", str(STEPS),
             "--workers", str(WORKERS),
             "--hidden", "32,32", "--batch-size", "32", "--start-steps", "300", "--compete-every", "500",
             "--eliminate-at", "1000", "--eval-episodes", "3", "--seed", "3"]
ACL_TRACE = {"RUST_LOG": "warn,zenoh::net::routing::interceptor=trace"}


@pytest.mark.slow
@pytest.mark.parametrize("transport,lag", [("tcp", 2), ("tls", 0)])
def test_a_run_across_two_hosts_through_a_router(two_hosts: Netns, tmp_path: Path, transport: str, lag: int) -> None:
    """Host A: `mam router` + learner + referee; host B: two workers that reach A over the veth.
    Over tcp with `--lag 2` (workers two iterations ahead), over TLS at lag 0. Over tcp, worker b1
    is SIGKILLed mid-run and a replacement `mam-worker --slot 1` on host A takes slot 1 over."""
    hosts, run, run_dir = two_hosts, unique_run(f"netns-{transport}"), tmp_path / "run"
    suffix = "-tls" if transport == "tls" else ""
    certs = make_certs(tmp_path / "certs", hosts.addr_a) if transport == "tls" else tmp_path
    conf = {name: str(deploy_config(f"{name}{suffix}.json5", certs, tmp_path)) for name in ("router", *ROLES)}
    port = 7447  # each namespace has its own ports
    on_a, from_b = f"{transport}/127.0.0.1:{port}", f"{transport}/{hosts.addr_a}:{port}"
    logs = tmp_path / "logs"
    router = spawn(["services.roles.router", "--zenoh-config", conf["router"],
                    "--listen", f"{transport}/0.0.0.0:{port}"],
                   logs / "router.log", netns=hosts.a, env=ACL_TRACE if transport == "tls" else None)
    procs = [router]
    before = hosts.bytes_over_veth()
    try:
        time.sleep(1.0)
        learner = spawn(["services.roles.learner", *RUN_FLAGS, "--lag", str(lag), "--run", run, "--connect", on_a,
                         "--zenoh-config", conf["learner"], "--run-dir", str(run_dir)], logs / "learner.log",
                        netns=hosts.a)
        referee = spawn(["services.roles.referee", "--run", run, "--connect", on_a, "--zenoh-config", conf["referee"],
                         "--run-dir", str(run_dir)], logs / "referee.log", netns=hosts.a)
        workers = [spawn(["services.roles.worker", "--run", run, "--connect", from_b, "--zenoh-config", conf["worker"],
                          "--id", f"b{i}", "--slot", str(i), "--run-dir", str(run_dir)], logs / f"worker-b{i}.log",
                         netns=hosts.b) for i in range(WORKERS)]
        procs += [learner, referee, *workers]
        if transport == "tcp":  # b1 dies on host B; a1 takes its slot over from host A
            deadline = time.monotonic() + 120
            while learner_iterations(run_dir) < 200 and time.monotonic() < deadline:
                time.sleep(0.2)
            workers[1].kill()
            workers[1].wait()
            workers[1] = spawn(["services.roles.worker", "--run", run, "--connect", on_a, "--zenoh-config",
                                conf["worker"], "--id", "a1", "--slot", "1", "--run-dir", str(run_dir)],
                               logs / "worker-a1.log", netns=hosts.a)
            procs.append(workers[1])
        try:
            assert learner.wait(timeout=300) == 0, (logs / "learner.log").read_text()[-3000:]
            for p in (*workers, referee):
                assert p.wait(timeout=60) == 0
        except subprocess.TimeoutExpired:
            tails = {p.name: p.read_text()[-1500:] for p in logs.glob("*.log")}
            raise AssertionError(f"the run did not finish: {tails}")
    finally:
        stop(*reversed(procs))
    result = load(run_dir)
    t = result["transport"]
    if transport == "tcp":  # b1 was killed (it wrote no report); a1 rebuilt slot 1 (services/roles/takeover.py)
        assert {w["worker"] for w in result["workers"]} == {"b0", "a1"}
        assert t["duplicates"] == 0 and t["rejected"] == {} and sum(t["rows_per_stream"].values()) == STEPS
        assert "every observation equal" in (logs / "worker-a1.log").read_text()
    else:
        assert_exactly_once(result)
        assert t["lost"] == 0 and {w["worker"] for w in result["workers"]} == {f"b{i}" for i in range(WORKERS)}
    assert t["duplicates"] == 0 and t["env_steps"] == STEPS
    assert all(w["sent_rows"] > 0 for w in result["workers"])  # both hosts' workers contributed
    assert result["summary"]["survivor"] == result["allocation"][-1]["survivor"]
    # Exact mode (the default) across hosts: the one-process Algorithm 1, bit for bit.
    assert result["summary"]["exact"] is True, result["summary"]
    torch.set_num_threads(1)
    ref = run_reference("AppleCollect-v0", resolve("ma-ddpg", schedule="equal-data", workers=WORKERS, hidden=(32, 32),
                                                   batch_size=32, start_steps=300, compete_every=500,
                                                   eliminate_at=1000, eval_episodes=3, seed=3, lag=lag), STEPS)
    assert [e["returns"] for e in result["eval"]] == [e["returns"] for e in ref.evaluations]
    assert result["summary"]["survivor"] == ref.survivor
    _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
    assert all(np.array_equal(params[k][n], ref.policy[k][n]) for k in range(len(ref.policy)) for n in ref.policy[k])
    # The workers' traffic really crossed the virtual wire (measured: 150-190 kB for this run).
    assert hosts.bytes_over_veth() - before > 50_000
    if transport == "tls":  # the ACL allowed everything the real system does: not one message refused
        log = re.sub(r"\x1b\[[0-9;]*m", "", (logs / "router.log").read_text(errors="replace"))
        # The router knew each client by its certificate, the workers by the veth they came in on.
        assert f"Interface({hosts.veth_a})+CertCommonName(worker)" in log
        assert "Interface(lo)+CertCommonName(learner)" in log and "Interface(lo)+CertCommonName(referee)" in log
        assert log.count("Msg intercepted") == 0, [line for line in log.splitlines() if "unauthorized" in line][:5]
