"""The messaging layer on real Zenoh sessions over loopback TCP.

Every test uses its own free port, explicit tcp/127.0.0.1 endpoints, multicast
scouting off (``make_config``), a unique run name, and closes its sessions.
The topology is the project's star: one listening peer (the learner's session),
everyone else a client connected to it.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
import time
import uuid
from contextlib import ExitStack

import numpy as np
import pytest
import zenoh

from services.messaging import bus, keys
from services.messaging.bus import (
    DUPLICATE,
    GAP,
    IN_ORDER,
    Inbox,
    Latest,
    Received,
    RejectLog,
    SequenceTracker,
    declare_alive,
    declare_latest_publisher,
    declare_reliable_publisher,
    make_config,
    open_session,
    watch_alive,
)
from services.messaging.codec import Allocation, MessageError, TransitionBatch, TransitionSpec, Weights


def unique_run() -> str:
    return f"test-{uuid.uuid4().hex[:10]}"


class Star:
    """A listening peer (the hub) plus clients connected to it; all closed at the end."""

    def __init__(self, stack: ExitStack) -> None:
        self._stack = stack
        self.endpoint = bus.loopback_endpoint(bus.free_tcp_port())
        self.hub = self._open(make_config(listen=[self.endpoint]))

    def _open(self, conf: zenoh.Config) -> zenoh.Session:
        session = open_session(conf)
        self._stack.callback(session.close)
        return session

    def client(self) -> zenoh.Session:
        return self._open(make_config(connect=[self.endpoint]))


@pytest.fixture
def star():
    with ExitStack() as stack:
        yield Star(stack)


def wait_until(predicate, timeout: float = 5.0, step: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


# --------------------------------------------------------------------------- transitions


OBS, ACT = 3, 1
SPEC = TransitionSpec(obs_dim=OBS, act_dim=ACT, n_actors=2, max_rows=16, max_action=1.0)


def publish_batches(session: zenoh.Session, run: str, worker: str, count: int, rows: int = 2) -> None:
    pub = declare_reliable_publisher(session, keys.transitions(run, worker))
    rng = np.random.default_rng(abs(hash(worker)) % 1000)
    obs = rng.standard_normal((rows, OBS)).astype(np.float32)
    act = rng.uniform(-1, 1, (rows, ACT)).astype(np.float32)
    rew = rng.standard_normal(rows).astype(np.float32)
    term = np.zeros(rows, bool)
    for seq in range(count):
        batch = TransitionBatch(worker, "inc0", seq, seq % 2, seq // 100, obs, act, rew, obs, term)
        pub.put(batch.to_bytes())
    pub.undeclare()


def test_20000_batches_none_lost_none_duplicated(star):
    """Two workers, 10k batches each, BLOCK + RELIABLE, a small inbox and a consumer that
    stalls now and then: every batch arrives exactly once, in order."""
    run = unique_run()
    per_worker, workers = 10_000, ("w0", "w1")
    inbox = Inbox.subscribe(star.hub, keys.transitions_all(run), maxsize=128, put_timeout=3.0)
    clients = [star.client() for _ in workers]
    time.sleep(0.2)  # let the subscription reach the clients before the first put

    t0 = time.perf_counter()
    threads = [threading.Thread(target=publish_batches, args=(c, run, w, per_worker))
               for c, w in zip(clients, workers)]
    for t in threads:
        t.start()

    tracker, rejects = SequenceTracker(), RejectLog()
    rows, total = 0, per_worker * len(workers)
    deadline = time.monotonic() + 25
    while tracker.received + tracker.duplicates < total and time.monotonic() < deadline:
        for item in inbox.drain(512) or ([x] if (x := inbox.get(timeout=0.1)) else []):
            try:
                batch = TransitionBatch.from_bytes(item.payload, SPEC)
            except MessageError as e:
                rejects.reject(keys.parse_last(item.key), e)
                continue
            assert keys.parse_last(item.key) == batch.worker
            tracker.observe(batch.worker, batch.incarnation, batch.batch_seq)
            rows += batch.rows
        if tracker.received in (2_000, 9_000):  # a slow consumer: backpressure, not loss
            time.sleep(0.3)
    elapsed = time.perf_counter() - t0
    for t in threads:
        t.join(timeout=10)

    assert rejects.total == 0, rejects.counts()
    assert inbox.dropped == 0
    assert tracker.lost == 0 and tracker.duplicates == 0
    assert tracker.received == total and rows == 2 * total
    for w in workers:
        assert tracker.expected(w, "inc0") == per_worker
        assert tracker.per_sender()[w]["last_seq"] == per_worker - 1
    inbox.close()
    print(f"\n{total} batches in {elapsed:.2f}s = {total / elapsed:,.0f} msg/s "
          f"(inbox waits: {inbox.waits})")


# --------------------------------------------------------------------------- late joiners


def weights_msg(k: int, version: int) -> bytes:
    params = {"w": np.full((2, OBS), version, np.float32)}
    return Weights(k, version, params, OBS, ACT, 1.0, (2,)).to_bytes("learner", version)


def allocation_msg(rnd: int) -> bytes:
    return Allocation(rnd, rnd * 10, None, (0.5, 0.5), (1, 0), {"w0": 0}, (False, False),
                      None, "test").to_bytes("referee", rnd)


def test_late_joiner_gets_latest_weights_and_allocation_within_1s(star):
    run = unique_run()
    # learner publishes from the hub, the referee from a client: both routes are covered
    weight_pubs = [declare_latest_publisher(star.hub, keys.weights(run, k)) for k in (0, 1)]
    referee = star.client()
    alloc_pub = declare_latest_publisher(referee, keys.allocation(run))
    for version in range(1, 6):
        for k, pub in enumerate(weight_pubs):
            pub.put(weights_msg(k, version * 10 + k))
        alloc_pub.put(allocation_msg(version))
    time.sleep(0.3)  # everything published long before the worker exists

    t0 = time.monotonic()
    worker = star.client()
    weights = Latest.subscribe(worker, keys.weights_all(run))
    alloc = Latest.subscribe(worker, keys.allocation(run))
    assert wait_until(lambda: len(weights.snapshot()) == 2 and alloc.get(keys.allocation(run)),
                      timeout=1.0)
    waited = time.monotonic() - t0
    got = {keys.parse_actor(k): Weights.from_bytes(r.payload).version
           for k, r in weights.snapshot().items()}
    assert got == {0: 50, 1: 51}
    assert Allocation.from_bytes(alloc.get(keys.allocation(run)).payload).round == 5
    print(f"\nlate joiner had weights + allocation after {waited * 1000:.0f} ms")

    # and it keeps following new publications; fresh() only returns what is new
    weights.fresh()
    weight_pubs[1].put(weights_msg(1, 61))
    assert wait_until(lambda: weights.get(keys.weights(run, 1)) is not None
                      and Weights.from_bytes(weights.get(keys.weights(run, 1)).payload).version == 61)
    assert list(weights.fresh()) == [keys.weights(run, 1)]
    assert weights.fresh() == {}


def test_a_junk_flood_on_a_weights_key_never_displaces_the_valid_weights(star):
    """A stranger floods a weights key with junk right after the learner's message: with the
    roles' screen the junk is rejected in the callback and counted, a `Latest` still holds the
    learner's weights and the `Inbox` (what a worker reads) queues only them; without a screen
    the junk wins."""
    from mam_core.policy import member_shapes
    from services.roles import role

    run = unique_run()
    rejects = RejectLog(None)
    shapes = member_shapes(OBS, (4,), ACT)
    screen = role.weights_screen(shapes, 1, rejects)
    params = {name: np.full(shape, 7.0, np.float32) for name, shape in shapes.items()}
    valid = Weights(0, 3, params, OBS, ACT, 1.0, (4,), "inc").to_bytes("learner", 1)
    worker = star.client()
    screened = Latest.subscribe(worker, keys.weights_all(run), screen=screen)
    plain = Latest.subscribe(worker, keys.weights_all(run))
    inbox = Inbox.subscribe(worker, keys.weights_all(run), maxsize=16, screen=screen)
    time.sleep(0.3)
    key = keys.weights(run, 0)
    learner, stranger = declare_latest_publisher(star.hub, key), star.client().declare_publisher(key)
    learner.put(valid)
    for _ in range(500):
        stranger.put(b"\x93junk")
    # each screened subscription (the Latest, the Inbox) rejects each junk message once
    assert wait_until(lambda: rejects.total == 1000 and plain.received == 501, timeout=10.0), rejects.counts()
    assert screened.get(key).payload == valid and screened.received == 1
    assert plain.get(key).payload == b"\x93junk"
    assert [item.payload for item in inbox.drain()] == [valid] and inbox.dropped == 0
    assert set(rejects.counts()) == {"not_msgpack"}


def test_subscriber_before_publisher_gets_its_first_value(star):
    run = unique_run()
    worker = star.client()
    latest = Latest.subscribe(worker, keys.weights_all(run))
    time.sleep(0.1)
    pub = declare_latest_publisher(star.hub, keys.weights(run, 0))
    pub.put(weights_msg(0, 1))
    assert latest.wait(keys.weights(run, 0), timeout=2.0)
    assert Weights.from_bytes(latest.get(keys.weights(run, 0)).payload).version == 1
    # a plain reliable publisher (stats) feeds a late-join Latest too, newest value wins
    stats = Latest.subscribe(worker, keys.stats_all(run))
    time.sleep(0.1)
    stats_pub = declare_reliable_publisher(star.hub, keys.learner_stats(run), express=True)
    for i in range(20):
        stats_pub.put(bytes([i]))
    assert wait_until(lambda: (r := stats.get(keys.learner_stats(run))) is not None
                      and r.payload == bytes([19]), timeout=2.0)


def test_stalled_consumer_drops_are_counted_and_the_link_survives(star):
    """A consumer that stops draining for 3 s while a worker keeps sending: after
    ``put_timeout`` the inbox drops (counted), so Zenoh's receive thread never stalls
    long enough for the publisher's BLOCK to close the transport. Every message is either
    received or counted as dropped, and the link still works afterwards. (Waiting
    ``put_timeout`` on every message instead killed this link within 3 s and lost
    thousands of messages uncounted.)"""
    run = unique_run()
    inbox = Inbox(maxsize=16, put_timeout=0.3).subscribe(star.hub, keys.transitions_all(run))
    client = star.client()
    time.sleep(0.2)
    pub = declare_reliable_publisher(client, keys.transitions(run, "w0"))
    sent, stop = [0], threading.Event()

    def produce():
        while not stop.is_set():
            pub.put(sent[0].to_bytes(8, "little"))
            sent[0] += 1
            time.sleep(0.0005)

    producer = threading.Thread(target=produce)
    producer.start()
    time.sleep(3.0)  # the consumer is stalled
    assert inbox.overflowing and inbox.dropped > 0 and inbox.waits == 1
    tracker, got = SequenceTracker(), 0
    for _ in range(50):  # the consumer resumes
        for item in inbox.drain():
            tracker.observe("w0", "i", int.from_bytes(item.payload, "little"))
            got += 1
        time.sleep(0.005)
    stop.set()
    producer.join()
    deadline = time.monotonic() + 5
    while got + inbox.dropped < sent[0] and time.monotonic() < deadline:
        for item in inbox.drain():
            tracker.observe("w0", "i", int.from_bytes(item.payload, "little"))
            got += 1
        time.sleep(0.01)
    assert got + inbox.dropped == sent[0]
    assert tracker.expected("w0", "i") == sent[0]  # the very last message arrived
    assert tracker.lost == inbox.dropped and tracker.duplicates == 0


# --------------------------------------------------------------------------- isolation


def test_two_runs_on_one_hub_never_cross(star):
    run_a, run_b = unique_run(), unique_run()
    pub_side, sub_side = star.client(), star.client()
    inbox_b = Inbox.subscribe(sub_side, f"mam/{run_b}/**")
    latest_b = Latest.subscribe(sub_side, keys.weights_all(run_b))
    inbox_a = Inbox.subscribe(sub_side, f"mam/{run_a}/**")
    plain_b = Latest(late_join=False).subscribe(sub_side, keys.weights_all(run_b))
    alive_b = watch_alive(sub_side, run_b)
    time.sleep(0.2)

    a_weights = declare_latest_publisher(pub_side, keys.weights(run_a, 0))
    a_weights.put(weights_msg(0, 1))
    a_trans = declare_reliable_publisher(pub_side, keys.transitions(run_a, "w0"))
    for _ in range(10):
        a_trans.put(b"for run a")
    token = declare_alive(pub_side, run_a, "worker", "w0")
    # a marker on run b proves run b's subscriptions are live
    declare_reliable_publisher(pub_side, keys.done(run_b)).put(b"marker")

    assert wait_until(lambda: inbox_a.qsize() >= 11)
    assert wait_until(lambda: inbox_b.qsize() >= 1)
    time.sleep(0.3)
    assert [r.key for r in inbox_b.drain()] == [keys.done(run_b)]
    assert latest_b.snapshot() == {} and plain_b.snapshot() == {}
    assert alive_b.live() == frozenset()
    assert all(r.key.startswith(f"mam/{run_a}/") for r in inbox_a.drain())
    token.undeclare()


# --------------------------------------------------------------------------- liveliness


def test_a_settled_watch_holds_every_token_already_up_at_its_first_look(star):
    """watch_alive's history comes on Zenoh's thread: a spare that judged from its first look saw
    no live worker and called a held slot orphaned (CI). With settle, the first look is complete; a
    query asked after the subscriber (the first fix) came back empty or partial one time in ten."""
    run = unique_run()
    owner = star.client()
    tokens = [declare_alive(owner, run, "worker", f"w{i}") for i in range(3)]
    gone = declare_alive(owner, run, "worker", "w9")
    gone.undeclare()
    # "already up" means the network holds them: declare_token returns before the hub has the
    # declaration, and a query racing it finds nothing. The hub's own view is the proof.
    with watch_alive(star.hub, run, "worker") as hub_view:
        assert hub_view.wait_for(lambda live: live == {"w0", "w1", "w2"}, timeout=5.0)
    for _ in range(8):  # a fresh process each time, as a spare starts: the first look is complete
        watcher = star.client()
        workers = watch_alive(watcher, run, "worker", settle=5.0)
        assert workers.settled and workers.live() == {"w0", "w1", "w2"}
        spares = watch_alive(watcher, run, "spare", settle=5.0)  # a second role on the same session
        assert spares.settled and spares.live() == frozenset()
        workers.close()
        spares.close()
    empty = unique_run()
    started = time.monotonic()
    nobody = watch_alive(star.client(), empty, "worker", settle=5.0)
    assert nobody.settled and nobody.live() == frozenset()
    assert time.monotonic() - started < 5.0  # nothing up: the query ends, the wait does not run out
    nobody.close()
    del tokens


def test_liveliness_appear_undeclare_and_session_close(star):
    run = unique_run()
    early = star.client()
    early_token = declare_alive(early, run, "referee", "r0")  # before anyone watches
    events: list[tuple[str, str, bool]] = []
    watcher = star.client()
    workers = watch_alive(watcher, run, "worker", on_change=lambda *e: events.append(e))
    everyone = watch_alive(watcher, run)
    assert everyone.wait_for(lambda ids: "r0" in ids, timeout=2.0)  # history: already up
    assert ("referee", "r0") in everyone.members()

    w0 = star.client()
    token = declare_alive(w0, run, "worker", "w0")
    assert workers.wait_for(lambda ids: ids == {"w0"}, timeout=2.0)
    token.undeclare()
    assert workers.wait_for(lambda ids: not ids, timeout=2.0)

    w1 = open_session(make_config(connect=[star.endpoint]))
    w1_token = declare_alive(w1, run, "worker", "w1")  # noqa: F841 - dropping it undeclares
    assert workers.wait_for(lambda ids: ids == {"w1"}, timeout=2.0)
    w1.close()  # owner goes away without undeclaring
    assert workers.wait_for(lambda ids: not ids, timeout=2.0)
    assert events == [("worker", "w0", True), ("worker", "w0", False),
                      ("worker", "w1", True), ("worker", "w1", False)]
    assert everyone.wait_for(lambda ids: ids == {"r0"}, timeout=2.0)
    early_token.undeclare()
    workers.close()
    everyone.close()


# --------------------------------------------------------------------------- config & sessions


def test_make_config_modes_and_endpoints(tmp_path):
    conf = make_config(connect=["tcp/127.0.0.1:1"])
    assert "client" in conf.get_json("mode")
    assert "tcp/127.0.0.1:1" in conf.get_json("connect/endpoints")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("scouting/gossip/enabled") == "false"
    assert "router" in make_config(listen=["tcp/127.0.0.1:2"]).get_json("mode")  # the hub of a star
    assert "router" in make_config(listen=["tcp/127.0.0.1:2"], mode="router").get_json("mode")
    with pytest.raises(ValueError):
        make_config(mode="server")
    f = tmp_path / "zenoh.json5"
    f.write_text('{ mode: "client", scouting: { multicast: { enabled: true } } }\n')
    conf = make_config(config_file=f, connect=["tcp/127.0.0.1:3"])
    assert "client" in conf.get_json("mode")
    assert conf.get_json("scouting/multicast/enabled") == "true"  # the file decides
    assert "tcp/127.0.0.1:3" in conf.get_json("connect/endpoints")


def test_client_fails_fast_then_retries_until_the_hub_is_up():
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    t0 = time.monotonic()
    with pytest.raises(zenoh.ZError):
        open_session(make_config(connect=[endpoint]))
    assert time.monotonic() - t0 < 2.0

    hub: list[zenoh.Session] = []
    timer = threading.Timer(0.3, lambda: hub.append(open_session(make_config(listen=[endpoint]))))
    timer.start()
    try:
        with bus.session_scope(make_config(connect=[endpoint]), retry_for=5.0) as client:
            assert not client.is_closed()
        assert client.is_closed()
    finally:
        timer.join()
        for s in hub:
            s.close()


# --------------------------------------------------------------------------- helpers without zenoh


def test_inbox_backpressure_then_drop_is_counted(caplog):
    inbox = Inbox(maxsize=2, put_timeout=0.2)
    item = Received("k", b"x", None, 0.0)
    assert inbox.push(item) and inbox.push(item)
    threading.Timer(0.05, inbox.get).start()  # consumer frees a slot while push waits
    assert inbox.push(item) and inbox.waits == 1 and inbox.dropped == 0
    with caplog.at_level(logging.WARNING):
        t0 = time.monotonic()
        assert not inbox.push(item)
        assert 0.15 < time.monotonic() - t0 < 1.0
    assert inbox.dropped == 1 and "dropped 1" in caplog.text
    assert len(inbox.drain()) == 2 and inbox.get(timeout=0.01) is None
    assert inbox.push(item) and inbox.push(item)
    inbox.close()
    t0 = time.monotonic()
    assert not inbox.push(item)  # closed and full: gives up without waiting
    assert time.monotonic() - t0 < 0.1 and inbox.dropped == 2
    assert len(inbox.drain(1)) == 1 and inbox.qsize() == 1


def test_subscribe_twice_is_an_error(star):
    inbox = Inbox.subscribe(star.hub, "mam/x/transitions/*")
    with pytest.raises(RuntimeError):
        inbox.subscribe(star.hub, "mam/x/transitions/*")
    inbox.close()


def test_latest_keeps_newest_per_key():
    latest = Latest()
    for i in range(5):
        latest.put(Received("a", bytes([i]), None, 0.0))
    latest.put(Received("b", b"b", None, 0.0))
    assert latest.get("a").payload == b"\x04" and latest.wait("b", timeout=0)
    assert latest.wait_fresh(timeout=0) and latest.wait_fresh(timeout=0)  # not consumed
    assert set(latest.fresh()) == {"a", "b"} and latest.fresh() == {}
    assert not latest.wait("c", timeout=0.01) and not latest.wait_fresh(timeout=0.01)
    threading.Timer(0.05, latest.put, args=(Received("c", b"c", None, 0.0),)).start()
    assert latest.wait_fresh(timeout=2.0) and list(latest.fresh()) == ["c"]


def test_sequence_tracker():
    t = SequenceTracker()
    assert [t.observe("w0", "i0", s) for s in (0, 1, 2)] == [IN_ORDER] * 3
    assert t.observe("w0", "i0", 5) == GAP and t.lost == 2
    assert t.observe("w0", "i0", 4) == DUPLICATE and t.duplicates == 1
    assert t.observe("w0", "i1", 0) == IN_ORDER  # restarted worker: new count
    assert t.observe("w1", "i0", 1) == GAP and t.lost == 3
    assert t.received == 6 and t.expected("w0", "i0") == 6
    assert t.per_sender()["w0"] == {"received": 5, "lost": 2, "duplicates": 1,
                                    "last_seq": 0, "incarnation": "i1"}


def test_reject_log_counts_all_logs_once(caplog):
    rl = RejectLog(what="transition batch")
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            rl.reject("w0", MessageError("shape:obs", "(2, 4) != (2, 3)"))
        rl.reject("w1", MessageError("shape:obs"))
        rl.reject("w0", "too_large")
    assert rl.counts() == {"shape:obs": 4, "too_large": 1} and rl.total == 5
    assert len(caplog.records) == 3
    assert "w0" in caplog.records[0].getMessage() and "(2, 4)" in caplog.records[0].getMessage()


# --------------------------------------------------------------------------- keys


def test_keys_layout():
    run = "exp-1.a_b"
    assert keys.weights(run, 3) == "mam/exp-1.a_b/weights/3"
    assert keys.weights_all(run) == "mam/exp-1.a_b/weights/*"
    assert keys.transitions(run, "w0") == "mam/exp-1.a_b/transitions/w0"
    assert keys.transitions_all(run) == "mam/exp-1.a_b/transitions/*"
    assert keys.allocation(run) == "mam/exp-1.a_b/allocation"
    assert keys.eval(run) == "mam/exp-1.a_b/eval"
    assert keys.learner_stats(run) == "mam/exp-1.a_b/stats/learner"
    assert keys.stats_all(run) == "mam/exp-1.a_b/stats/*"
    assert keys.done(run) == "mam/exp-1.a_b/done"
    assert keys.config(run) == "mam/exp-1.a_b/config"
    assert keys.alive(run, "worker", "w0") == "mam/exp-1.a_b/alive/worker/w0"
    assert keys.alive_all(run) == "mam/exp-1.a_b/alive/*/*"
    assert keys.alive_all(run, "referee") == "mam/exp-1.a_b/alive/referee/*"
    assert keys.parse_alive("mam/r/alive/worker/w7") == ("worker", "w7")
    assert keys.parse_last("mam/r/transitions/w7") == "w7"
    assert keys.parse_actor("mam/r/weights/12") == 12
    for key in (keys.weights_all(run), keys.alive_all(run), keys.stats_all(run)):
        zenoh.KeyExpr(key)  # every pattern is a canonical Zenoh key expression


@pytest.mark.parametrize("bad", ["", "a/b", "*", "**", "a*", "$x", "a?", "a#b", "a b", "ü", 7, None,
                                 "x" * 129])
def test_keys_reject_bad_names(bad):
    with pytest.raises(ValueError):
        keys.allocation(bad)
    with pytest.raises(ValueError):
        keys.transitions("run", bad)
    with pytest.raises(ValueError):
        keys.alive("run", "worker", bad)


def test_keys_reject_bad_actor_and_foreign_keys():
    for k in (-1, True, 1.0, "0"):
        with pytest.raises(ValueError):
            keys.weights("run", k)
    for key in ("other/r/alive/worker/w0", "mam/r/alive/worker", "mam/r/weights/0/x/y"):
        with pytest.raises(ValueError):
            keys.parse_alive(key)
    for key in ("mam/r/weights/x", "mam/r/weights/01", "mam/r/weights/-1"):
        with pytest.raises(ValueError):
            keys.parse_actor(key)
    with pytest.raises(ValueError):
        keys.parse_last("other")


def test_sequence_tracker_resends_fill_gaps_exactly_once():
    from services.messaging.bus import RECOVERED, REDUNDANT

    t = SequenceTracker()
    assert [t.observe("w0", "i0", s) for s in (0, 1)] == [IN_ORDER] * 2
    assert t.observe("w0", "i0", 5) == GAP and t.lost == 3  # 2, 3, 4 died with a learner
    assert t.contiguous("w0") == ("i0", 1)  # what a checkpoint now may acknowledge
    # The worker resends everything after its acknowledged prefix, 2..5, flagged as resent.
    assert [t.observe("w0", "i0", s, resend=True) for s in (2, 3, 4, 5)] == [RECOVERED] * 3 + [REDUNDANT]
    assert (t.lost, t.recovered, t.redundant, t.duplicates) == (0, 3, 1, 0)
    assert t.contiguous("w0") == ("i0", 5)
    assert t.observe("w0", "i0", 3, resend=True) == REDUNDANT  # a hole is filled once only
    assert t.observe("w0", "i0", 3) == DUPLICATE  # not flagged: a real duplicate, as before
    # A checkpoint's per_sender() carries the holes: a resumed learner lets a resend fill them.
    t.observe("w0", "i0", 9)
    saved = t.per_sender()
    assert saved["w0"]["holes"] == [[6, 9]] and saved["w0"]["lost"] == 3
    resumed = SequenceTracker()
    resumed.restore(saved)
    assert resumed.lost == 3 and resumed.contiguous("w0") == ("i0", 5)
    assert [resumed.observe("w0", "i0", s, resend=True) for s in (6, 7, 8, 9, 10)] == \
        [RECOVERED] * 3 + [REDUNDANT, IN_ORDER]
    assert resumed.lost == 0 and resumed.expected("w0", "i0") == 11
    # A forged huge seq costs one interval, not memory per missing number.
    resumed.observe("w1", "i0", 2**62)
    assert resumed.per_sender()["w1"]["holes"] == [[0, 2**62]]


def test_a_client_waits_quietly_for_an_endpoint_that_is_not_up_yet_then_connects():
    """`mam run` starts every role at once: a client whose learner is still starting waits while the
    port refuses (no Zenoh warning a try), and connects once it listens; a port that never listens
    still ends in Zenoh's own error after `retry_for`."""
    endpoint = bus.loopback_endpoint(bus.free_tcp_port())
    assert bus.refused(make_config(connect=[endpoint]))
    assert not bus.refused(make_config(connect=["udp/127.0.0.1:1"]))  # another transport: Zenoh's to try
    code = ("import sys, time; from services.messaging import bus; bus.init_zenoh_log(); "
            f"s = bus.open_session(bus.make_config(connect=[{endpoint!r}]), retry_for=20.0); "
            "print('connected'); s.close()")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(1.5)  # ~15 tries of its own meanwhile
        assert child.poll() is None
        with open_session(make_config(listen=[endpoint])):
            out, err = child.communicate(timeout=30)
    finally:
        child.kill()
    assert child.returncode == 0 and "connected" in out, err
    assert "Unable to connect" not in out + err, out + err  # (Zenoh's log: on stdout)
    with pytest.raises(zenoh.ZError):
        open_session(make_config(connect=[bus.loopback_endpoint(bus.free_tcp_port())]), retry_for=0.3)
