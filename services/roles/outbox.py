"""The learner's outgoing messages: weights, the referee's snapshots, stats, config, done, and
what is re-sent to a role that may have missed it (services/roles/learner.py).

Weights go out when they change, every live actor on its latest-value key; the versions the
slots act with in the next B+1 iterations are kept for a re-send. The referee's snapshots go
once per version an evaluation judges (`Algorithm1.judged_after`), on a reliable key, and are kept
until the referee reports the evaluations that judge them done (its role stats' `events`).
"""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from mam_core.policy import params_digest
from services.messaging import bus, keys
from services.messaging.codec import Done, LearnerStats, MessageError, TransitionBatch, Weights, decode, encode

if TYPE_CHECKING:
    from services.roles.learner import Learner

log = logging.getLogger("mam.learner")

# After done: how long to wait for a referee that is gone (a restart: `mam run`'s backoff is up to
# 15 s, and a referee starting on a loaded box took more than 20 s in the chaos test) ...
REFEREE_GRACE_S = 60.0
REFEREE_WAIT_S = 240.0  # ... and at most, in all, for its final evaluation


class PublishedDigests:
    """`params_digest` of every actor version a slot may still act with, as this learner published
    it, to check the `policy_digest` a batch reports (`foreign`). Kept in the learner's checkpoint:
    with lag B > 0 a restarted learner receives rows acted with versions its predecessor published
    before the checkpoint, and checks those too."""

    def __init__(self, known: dict[tuple[int, int], str] | None = None) -> None:
        self.known: dict[tuple[int, int], str] = dict(known or {})  # (actor, version) -> digest

    def record(self, actor: int, version: int, params: dict) -> None:
        self.known[(actor, version)] = params_digest(params)

    def foreign(self, batch: TransitionBatch) -> str:
        """Why `batch`'s rows were acted with other weights than this learner's of their version
        (a dead incarnation's that computed otherwise), or "" (the same, or not known here)."""
        mine = self.known.get((batch.actor, batch.version)) if batch.version >= 0 else None
        if mine is None or batch.policy_digest == mine:  # (a batch without a digest is refused by the intake)
            return ""
        return (f"slot {batch.slot} acted at iteration {batch.iteration} with actor {batch.actor}'s version "
                f"{batch.version} of learner {batch.policy_from or '?'}, not this learner's")

    def prune(self, needed: int, live: list[bool]) -> None:
        """Forget live actors' versions older than `needed` - 1 (no slot acts with them again; an
        eliminated actor's last versions stay, a few entries)."""
        for key in [key for key in self.known if key[1] < needed - 1 and live[key[0]]]:
            del self.known[key]

    def to_json(self) -> str:
        return json.dumps([[a, v, d] for (a, v), d in sorted(self.known.items())])

    @classmethod
    def from_json(cls, text: str) -> PublishedDigests:
        rows = json.loads(text)
        if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 3 for r in rows):
            raise ValueError("published digests: not a list of [actor, version, digest]")
        return cls({(int(a), int(v)): str(d) for a, v, d in rows})


class Outbox:
    def __init__(self, learner: Learner) -> None:
        self.learner = learner
        run, s, k = learner.cfg.run, learner.session, learner.algo.actors
        self.config_pub = bus.declare_latest_publisher(s, keys.config(run), drop=True)  # heartbeats: never block
        self.weights_pubs = [bus.declare_latest_publisher(s, keys.weights(run, a)) for a in range(k)]
        self.stats_pub = bus.declare_latest_publisher(s, keys.learner_stats(run), drop=True)  # 10 Hz, latest only
        self.done_pub = bus.declare_latest_publisher(s, keys.done(run))
        self.snapshot_pubs = [bus.declare_reliable_publisher(s, keys.eval_weights(run, a)) for a in range(k)]
        self.recent_weights: dict[int, list[tuple[int, bytes]]] = {}  # version -> (actor, message)
        # ... and what those messages hold, for the checkpoint: a resumed learner at lag B > 0
        # publishes the B versions before its own too (the workers' next iterations act with them)
        self.recent_params: dict[int, list[tuple[int, int, dict[str, np.ndarray]]]] = {}  # -> (actor, version, params)
        self.snapshots: dict[int, list[tuple[int, bytes]]] = {}
        self.snapshot_params: dict[int, list[tuple[int, int, dict[str, np.ndarray]]]] = {}  # as recent_params
        self.digests = learner.digests  # what it published (and its predecessor, from the checkpoint)
        self.referee_events = 0  # evaluations the referee reports done
        self.seq = 0

    def next_seq(self) -> int:
        self.seq += 1
        return self.seq

    def weights_message(self, k: int, version: int | None = None, params: dict[str, np.ndarray] | None = None) -> bytes:
        """Actor `k`'s weights message: its current parameters, or `params` as its `version`."""
        lr = self.learner
        if params is None or version is None:
            version, params = lr.agent.versions[k], lr.agent.actor_params(k)
        self.digests.record(k, version, params)
        return Weights(k, version, params, lr.spec.obs_dim, lr.spec.act_dim,
                       max(lr.spec.max_action), tuple(lr.algo.hidden), lr.incarnation).to_bytes(lr.id, self.next_seq())

    def weights(self, all_actors: bool = False) -> None:
        """The live actors' weights (all with `all_actors`), kept while a slot may act with them."""
        lr, plan = self.learner, self.learner.plan
        msgs, params = [], []
        for k, alive in enumerate(lr.agent.live_actors):
            if alive or all_actors:
                params.append((k, lr.agent.versions[k], lr.agent.actor_params(k)))
                msg = self.weights_message(k, *params[-1][1:])
                self.weights_pubs[k].put(msg)
                msgs.append((k, msg))
        self.recent_weights[plan.version_after(lr.iteration)] = msgs
        self.recent_params[plan.version_after(lr.iteration)] = params
        self.prune_weights()

    def prune_weights(self) -> None:
        """Forget the versions no slot acts with again (before the next iteration's)."""
        lr, plan = self.learner, self.learner.plan
        needed = plan.version_for(min(lr.iteration + 1, plan.iterations))
        for old in [v for v in self.recent_weights if v < needed]:
            del self.recent_weights[old]
            self.recent_params.pop(old, None)
        self.digests.prune(needed, lr.agent.live_actors)

    def restore(self, weights: list[tuple[int, int, int, dict[str, np.ndarray]]],
                snapshots: list[tuple[int, int, int, dict[str, np.ndarray]]]) -> None:
        """A resumed learner: what its predecessor's checkpoint kept, published again."""
        self.restore_weights(weights)
        self.restore_snapshots(snapshots)

    def restore_weights(self, kept: list[tuple[int, int, int, dict[str, np.ndarray]]]) -> None:
        """A resumed learner: publish the versions its predecessor kept for the workers' next
        iterations (`kept_weights`, from the checkpoint), as its own messages, before its current
        one. Without them a run at lag B > 0 waits forever: a worker's first iteration after the
        resume acts with the version B iterations older than the learner's."""
        current = self.learner.plan.version_after(self.learner.iteration)  # `weights` publishes that one
        for key, k, version, params in sorted(kept, key=lambda row: (row[0], row[1])):
            if key >= current:
                continue
            msg = self.weights_message(k, version, params)
            self.weights_pubs[k].put(msg)
            self.recent_weights.setdefault(key, []).append((k, msg))
            self.recent_params.setdefault(key, []).append((k, version, params))
        self.prune_weights()

    def kept_weights(self) -> list[tuple[int, int, int, dict[str, np.ndarray]]]:
        """(plan version, actor, its version, params) of every version a slot may still act with:
        kept in the checkpoint for `restore_weights`."""
        return [(key, k, version, params) for key, rows in sorted(self.recent_params.items())
                for k, version, params in rows]

    def snapshots_after(self, index: int) -> None:
        """The versions the referee's next evaluations judge, once each (`Algorithm1.judged_after`)."""
        lr = self.learner
        for version in sorted(lr.plan.judged_after(index) - set(self.snapshots)):
            self.snapshot_params[version] = [(k, lr.agent.versions[k], lr.agent.actor_params(k))
                                             for k, alive in enumerate(lr.agent.live_actors) if alive]
            self.snapshots[version] = [(k, self.weights_message(k, v, params))
                                       for k, v, params in self.snapshot_params[version]]
            for k, msg in self.snapshots[version]:
                self.snapshot_pubs[k].put(msg)

    def restore_snapshots(self, kept: list[tuple[int, int, int, dict[str, np.ndarray]]]) -> None:
        """A resumed learner: publish the snapshots its predecessor kept for evaluations the
        referee had not reported done (`kept_snapshots`, from the checkpoint). A referee behind
        the checkpoint (killed with the learner mid-evaluation, or slow) judges versions older
        than the resumed learner's, which only these hold."""
        for key, k, version, params in sorted(kept, key=lambda row: (row[0], row[1])):
            self.snapshot_params.setdefault(key, []).append((k, version, params))
            self.snapshots.setdefault(key, []).append((k, self.weights_message(k, version, params)))
            self.snapshot_pubs[k].put(self.snapshots[key][-1][1])

    def kept_snapshots(self) -> list[tuple[int, int, int, dict[str, np.ndarray]]]:
        """(plan version, actor, its version, params) of every snapshot an evaluation the referee
        has not reported done judges: kept in the checkpoint for `restore_snapshots`."""
        self.pending_snapshots()
        return [(key, k, version, params) for key, rows in sorted(self.snapshot_params.items())
                for k, version, params in rows]

    def remind_referee(self) -> None:
        """On the heartbeat: the snapshots of the evaluations the referee has not reported done,
        again, when it reported none done since the previous heartbeat. A referee restarted with
        the learner (a resume) connects after their first put, and the learner may never wait
        long enough for `resend` (after C nothing waits for the referee)."""
        before = self.referee_events
        pending = self.pending_snapshots() & set(self.snapshots)
        if self.referee_events != before:
            return
        for version in sorted(pending):
            for k, msg in self.snapshots[version]:
                self.snapshot_pubs[k].put(msg)

    def pending_snapshots(self) -> set[int]:
        """The versions of the evaluations the referee has not reported done (its role stats'
        `events`); the snapshots before them are forgotten."""
        plan = self.learner.plan
        for item in self.learner.referee_reports.snapshot().values():
            try:
                self.referee_events = max(self.referee_events, int(decode(item.payload).get("events", 0)))
            except (MessageError, TypeError, ValueError):
                continue
        pending = {plan.judged_version(i, purpose) for i, purpose in plan.events()[self.referee_events:]}
        for old in [v for v in self.snapshots if v < min(pending, default=0)]:
            del self.snapshots[old]
            self.snapshot_params.pop(old, None)
        return pending

    def resend(self) -> None:
        """Once more what a late role may have missed: the weights of the versions the slots act
        with next, and the snapshots of the evaluations the referee has not reported done.
        Versions a role holds are not loaded again, so this changes nothing for a role that had them."""
        for version in sorted(self.recent_weights):
            for k, msg in self.recent_weights[version]:
                self.weights_pubs[k].put(msg)
        pending = self.pending_snapshots()
        for version in sorted(pending & set(self.snapshots)):
            for k, msg in self.snapshots[version]:
                self.snapshot_pubs[k].put(msg)

    def config(self) -> None:
        lr = self.learner
        self.config_pub.put(encode("config", {"config": lr.cfg.to_dict()}, sender=lr.id, seq=self.next_seq()))

    def stats(self, done: bool = False) -> None:
        self.stats_pub.put(self.learner_stats(done).to_bytes(self.learner.id, self.next_seq()))

    def done(self, msg: bytes) -> None:
        self.done_pub.put(msg)

    def learner_stats(self, done: bool = False) -> LearnerStats:
        lr, now = self.learner, time.monotonic()
        losses = {k.split("/", 1)[1]: v for k, v in lr.metrics.items() if k.startswith("loss/")}
        q_means = [lr.metrics.get(f"q/actor{k}", float("nan")) for k in range(lr.algo.actors)]
        return LearnerStats(
            env_steps=lr.env_steps, updates=lr.updates, accept_until=lr.schedule.budget,
            utd=lr.utd(), losses=losses, q_means=tuple(q_means), versions=tuple(lr.agent.versions),
            per_worker=lr.intake.counters(now, lr.acked), rejected=lr.rejected(), done=done,
            live=tuple(lr.agent.live_actors), workers=max(len(lr.workers.live()), lr.intake.active(now)),
            steps=lr.schedule.budget, incarnation=lr.incarnation, exact=not lr.inexact,
            iteration=lr.iteration, inexact=lr.inexact, awaiting=lr.awaiting,
            slots_next=tuple(lr.stage.end) if lr.stage is not None else (),
            owners=tuple(f"{o[0]}/{o[1]}" if o else "" for o in lr.stage.owner) if lr.stage is not None else ())

    def wait_for_referee(self, msg: Done) -> None:
        """Stay up (repeating done) until the referee has written its final evaluation.

        A referee that dies now is restarted (`mam run`) and needs this learner's config,
        done notice and snapshots. Waits while a referee was seen during the run and has not
        reported `final`: up to REFEREE_GRACE_S without any referee alive, and at most
        REFEREE_WAIT_S in all.
        """
        lr = self.learner
        if not lr.referee_seen:
            return
        deadline = time.monotonic() + REFEREE_WAIT_S
        gone_since: float | None = None
        last_put = 0.0
        while time.monotonic() < deadline and not lr.stop_requested:
            if any(self._is_final(item) for item in lr.referee_reports.snapshot().values()):
                return
            now = time.monotonic()
            if lr.referees.live():
                gone_since = None
            elif gone_since is None:
                gone_since = now
            elif now - gone_since > REFEREE_GRACE_S:
                log.warning("no referee for %.0f s after done: not waiting for its final evaluation",
                            REFEREE_GRACE_S)
                return
            if now - last_put >= 1.0:  # a restarted referee needs these (the caches serve them too)
                self.done(msg.to_bytes(lr.id, self.next_seq()))
                self.stats(done=True)
                self.config()
                self.resend()
                last_put = now
            time.sleep(0.1)
        log.warning("the referee did not report its final evaluation within %.0f s", REFEREE_WAIT_S)

    @staticmethod
    def _is_final(item: bus.Received) -> bool:
        try:
            return decode(item.payload).get("final") is True
        except MessageError:
            return False
