"""The learner's outgoing messages: weights, the referee's snapshots, stats, config, done, and
what is re-sent to a role that may have missed it (services/roles/learner.py).

Weights go out when they change, every live actor on its latest-value key; the versions the
slots act with in the next B+1 iterations are kept for a re-send. The referee's snapshots go
once per version an evaluation judges (`Algorithm1.judged_after`), on a reliable key, and are kept
until the referee reports the evaluations that judge them done (its role stats' `events`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.messaging import bus, keys
from services.messaging.codec import Done, LearnerStats, MessageError, Weights, decode, encode
from services.roles.learner_state import Carried, KeptParams, LearnerState, PublishedDigests
from services.run.config import RunConfig

__all__ = ["Outbox", "PublishedDigests", "Watches"]  # PublishedDigests: its home is learner_state.py

log = logging.getLogger("mam.learner")

# After done: how long to wait for a referee that is gone (a restart: `mam run`'s backoff is up to
# 15 s, and a referee starting on a loaded box took more than 20 s in the chaos test) ...
REFEREE_GRACE_S = 60.0
REFEREE_WAIT_S = 240.0  # ... and at most, in all, for its final evaluation


@dataclass(frozen=True)
class Watches:
    """What the outbox follows of the other roles: their liveliness tokens, and the referee's role
    stats (the evaluations it reports done, `events`, and its `final` one)."""

    workers: bus.AliveWatch
    referees: bus.AliveWatch
    referee_reports: bus.Latest


class Outbox:
    """Publishes what `st` holds, as learner `sender` (of `incarnation`), on `cfg.run`'s keys."""

    def __init__(self, session: Any, cfg: RunConfig, st: LearnerState, sender: str, incarnation: str,
                 watches: Watches) -> None:
        self.cfg, self.st, self.sender, self.incarnation, self.watches = cfg, st, sender, incarnation, watches
        run, s, k = cfg.run, session, cfg.algo.actors
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
        self.referee_events = 0  # evaluations the referee reports done
        self.seq = 0

    def next_seq(self) -> int:
        self.seq += 1
        return self.seq

    def weights_message(self, k: int, version: int | None = None, params: dict[str, np.ndarray] | None = None) -> bytes:
        """Actor `k`'s weights message: its current parameters, or `params` as its `version`."""
        agent, spec = self.st.agent, self.st.agent.spec
        if params is None or version is None:
            version, params = agent.versions[k], agent.actor_params(k)
        self.st.digests.record(k, version, params)  # what it published (and its predecessor, from the checkpoint)
        return Weights(k, version, params, spec.obs_dim, spec.act_dim, max(spec.max_action),
                       tuple(self.cfg.algo.hidden), self.incarnation).to_bytes(self.sender, self.next_seq())

    def weights(self, all_actors: bool = False) -> None:
        """The live actors' weights (all with `all_actors`), kept while a slot may act with them."""
        agent, plan, after = self.st.agent, self.st.plan, self.st.progress.iteration  # iterations done
        msgs, params = [], []
        for k, alive in enumerate(agent.live_actors):
            if alive or all_actors:
                params.append((k, agent.versions[k], agent.actor_params(k)))
                msg = self.weights_message(k, *params[-1][1:])
                self.weights_pubs[k].put(msg)
                msgs.append((k, msg))
        self.recent_weights[plan.version_after(after)] = msgs
        self.recent_params[plan.version_after(after)] = params
        self.prune_weights()

    def prune_weights(self) -> None:
        """Forget the versions no slot acts with again (before the next iteration's)."""
        plan = self.st.plan
        needed = plan.version_for(min(self.st.progress.iteration + 1, plan.iterations))
        for old in [v for v in self.recent_weights if v < needed]:
            del self.recent_weights[old]
            self.recent_params.pop(old, None)
        self.st.digests.prune(needed, self.st.agent.live_actors)

    def restore(self, carried: Carried) -> None:
        """A resumed learner: what its predecessor's checkpoint kept, published again."""
        self.restore_weights(carried.kept_weights)
        self.restore_snapshots(carried.kept_snapshots)

    def kept(self) -> Carried:
        """What a checkpoint keeps for the next incarnation's `restore`."""
        return Carried(self.kept_weights(), self.kept_snapshots())

    def restore_weights(self, kept: list[KeptParams]) -> None:
        """A resumed learner: publish the versions its predecessor kept for the workers' next
        iterations (`kept_weights`, from the checkpoint), as its own messages, before its current
        one. Without them a run at lag B > 0 waits forever: a worker's first iteration after the
        resume acts with the version B iterations older than the learner's."""
        current = self.st.plan.version_after(self.st.progress.iteration)  # `weights` publishes that one
        for key, k, version, params in sorted(kept, key=lambda row: (row[0], row[1])):
            if key >= current:
                continue
            msg = self.weights_message(k, version, params)
            self.weights_pubs[k].put(msg)
            self.recent_weights.setdefault(key, []).append((k, msg))
            self.recent_params.setdefault(key, []).append((k, version, params))
        self.prune_weights()

    def kept_weights(self) -> list[KeptParams]:
        """(plan version, actor, its version, params) of every version a slot may still act with:
        kept in the checkpoint for `restore_weights`."""
        return [(key, k, version, params) for key, rows in sorted(self.recent_params.items())
                for k, version, params in rows]

    def snapshots_after(self, index: int) -> None:
        """The versions the referee's next evaluations judge, once each (`Algorithm1.judged_after`)."""
        agent = self.st.agent
        for version in sorted(self.st.plan.judged_after(index) - set(self.snapshots)):
            self.snapshot_params[version] = [(k, agent.versions[k], agent.actor_params(k))
                                             for k, alive in enumerate(agent.live_actors) if alive]
            self.snapshots[version] = [(k, self.weights_message(k, v, params))
                                       for k, v, params in self.snapshot_params[version]]
            for k, msg in self.snapshots[version]:
                self.snapshot_pubs[k].put(msg)

    def restore_snapshots(self, kept: list[KeptParams]) -> None:
        """A resumed learner: publish the snapshots its predecessor kept for evaluations the
        referee had not reported done (`kept_snapshots`, from the checkpoint). A referee behind
        the checkpoint (killed with the learner mid-evaluation, or slow) judges versions older
        than the resumed learner's, which only these hold."""
        for key, k, version, params in sorted(kept, key=lambda row: (row[0], row[1])):
            self.snapshot_params.setdefault(key, []).append((k, version, params))
            self.snapshots.setdefault(key, []).append((k, self.weights_message(k, version, params)))
            self.snapshot_pubs[k].put(self.snapshots[key][-1][1])

    def kept_snapshots(self) -> list[KeptParams]:
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
        plan = self.st.plan
        for item in self.watches.referee_reports.snapshot().values():
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
        self.config_pub.put(encode("config", {"config": self.cfg.to_dict()}, sender=self.sender, seq=self.next_seq()))

    def stats(self, done: bool = False) -> None:
        self.stats_pub.put(self.learner_stats(done).to_bytes(self.sender, self.next_seq()))

    def done(self, msg: bytes) -> None:
        self.done_pub.put(msg)

    def learner_stats(self, done: bool = False) -> LearnerStats:
        st, p, now = self.st, self.st.progress, time.monotonic()
        losses = {k.split("/", 1)[1]: v for k, v in p.metrics.items() if k.startswith("loss/")}
        q_means = [p.metrics.get(f"q/actor{k}", float("nan")) for k in range(self.cfg.algo.actors)]
        budget = st.plan.schedule.budget
        return LearnerStats(
            env_steps=p.env_steps, updates=st.updates(), accept_until=budget,
            utd=st.utd(), losses=losses, q_means=tuple(q_means), versions=tuple(st.agent.versions),
            per_worker=st.intake.counters(now, st.acks.acked), rejected=st.rejected(), done=done,
            live=tuple(st.agent.live_actors), workers=max(len(self.watches.workers.live()), st.intake.active(now)),
            steps=budget, incarnation=self.incarnation, exact=not p.inexact,
            iteration=p.iteration, inexact=p.inexact, awaiting=p.awaiting, slots_next=tuple(st.stage.end),
            owners=tuple(f"{o[0]}/{o[1]}" if o else "" for o in st.stage.owner))

    def wait_for_referee(self, msg: Done, stopping: Callable[[], bool]) -> None:
        """Stay up (repeating done) until the referee has written its final evaluation.

        A referee that dies now is restarted (`mam run`) and needs this learner's config,
        done notice and snapshots; so does one that has not come up yet (a run short enough to
        end while its referee still starts: the learner left, the referee found no one to
        connect to, and `mam run` waited for it). Waits until a referee reports `final`: up to
        REFEREE_GRACE_S without any referee alive, and at most REFEREE_WAIT_S in all.
        """
        deadline = time.monotonic() + REFEREE_WAIT_S
        gone_since: float | None = None
        last_put = 0.0
        while time.monotonic() < deadline and not stopping():
            if any(self._is_final(item) for item in self.watches.referee_reports.snapshot().values()):
                return
            now = time.monotonic()
            if self.watches.referees.live():
                gone_since = None
            elif gone_since is None:
                gone_since = now
            elif now - gone_since > REFEREE_GRACE_S:
                log.warning("no referee for %.0f s after done%s: not waiting for its final evaluation",
                            REFEREE_GRACE_S, "" if self.st.progress.referee_seen else " (none came in the run)")
                return
            if now - last_put >= 1.0:  # a restarted referee needs these (the caches serve them too)
                self.done(msg.to_bytes(self.sender, self.next_seq()))
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
