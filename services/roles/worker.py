"""`mam-worker`: one environment slot. Steps its slot's iterations of Algorithm 1, publishes transitions.
(Several slots in one process, stepped by one loop: services/roles/worker_group.py.)

The worker needs only `--run`, `--connect` and `--slot`: the env, K and the noise come from the
learner's config topic. It steps iteration i once it holds the allocation and the actor version
that apply to i (mam_core/algorithm1.py: with a lag B, up to B iterations ahead of the
learner), explores (Gaussian noise, or SAC's sampled actions; uniform random actions in the start phase), sends
transitions in small batches tagged with worker id, incarnation, slot, iteration, actor and
policy version, and exits when the run is done. Its state is a few dataclasses its helpers take
(services/roles/worker_state.py: the slot's position, the batch being built, what it knows of the learner).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from mam_core.algorithm1 import Algorithm1
from mam_core.envs import make_env  # registers AppleCollect-v0; imports `module:EnvId` modules
from mam_core.obsolescence import initial_allocation
from mam_core.policy import EnvSpec, NumpyActors
from mam_core.slot import SlotStreams, act, uniform
from services.messaging import bus, keys
from services.messaging.codec import Allocation, LearnerStats, MessageError, TransitionBatch
from services.roles import role, takeover, worker_group
from services.roles.kept import KeptBatches
from services.roles.lockstep import WeightsHistory
from services.roles.simulator import FAULTS, EnvFault, GuardedSimulator
from services.roles.worker_group import WaitFor, parse_slots, slot_ids
from services.roles.worker_report import WorkerReports
from services.roles.worker_state import LearnerWatch, PendingBatch, SlotState
from services.run import config, options, rundir
from services.run.config import RunConfig

log = logging.getLogger("mam.worker")

MAX_BATCH_AGE_S = 0.05  # a partial batch is sent after this long
STATUS_EVERY_S = 10.0
LOST_AFTER_S = 2.0  # the learner's stats still lack a row sent this long before them: the batch was lost
class Worker(GuardedSimulator, WorkerReports):
    def __init__(self, cfg: RunConfig, session: Any, worker_id: str, slot_index: int = 0,
                 run_dir: Path | None = None, wake: threading.Event | None = None,
                 decodes: role.Decodes | None = None) -> None:
        self.run_dir, self.cfg, self.algo, self.session, self.id = run_dir, cfg, cfg.algo, session, worker_id
        # several slots in one loop (WorkerGroup): any slot's subscriptions set `wake`, and they decode once (`decodes`)
        self.wake, self.decodes = wake, decodes
        role.refuse_unbound(cfg, worker_id, [slot_index], f"slot {slot_index}", log)
        self.incarnation = uuid.uuid4().hex[:12]
        self.rejects = bus.RejectLog(log, "message")
        self.env = make_env(cfg.env_id, cfg.env_kwargs)
        self.spec = EnvSpec.from_env(self.env)
        self.max_action = np.asarray(self.spec.max_action, np.float32)
        self.plan = Algorithm1.for_run(self.algo, cfg.steps)
        # The slot's streams (mam_core.slot): from --seed and the slot only. A worker taking the slot
        # over mid-run rebuilds them and the env from the slot's current episode (takeover.py).
        self.slot = slot_index
        streams = SlotStreams.for_slot(self.algo.seed, slot_index)
        # Simulator faults: the step is retried on a reset env, the fault counted (by kind).
        self.faults, self.env_remade = {kind: 0 for kind in FAULTS}, 0
        self.env.action_space.seed(streams.action_seed)
        self.slot_state = SlotState(streams, self.reset_env(seed=streams.episode_seed(1)))  # worker_state.py
        # Exactly once: batches the learner has not yet checkpointed are kept, and resent to its next
        # incarnation or when one was lost in flight (kept.py; bounded by cfg.resend_rows).
        self.kept = KeptBatches(cfg.save_replay, cfg.resend_rows)
        self.lost_checked = 0.0  # when the kept batches last went again for a lost one
        self.batch_log = None
        # numpy forwards, no torch in a worker: a one-row torch forward costs ~100 µs of dispatch
        # between env steps, this ~14 µs, and importing torch ~3 s and ~180 MB (docs/PERFORMANCE.md)
        self.actors = NumpyActors(self.algo.actors, self.spec, self.algo.hidden, self.algo.family.policy_kind)
        self.shapes = self.actors.shapes
        self.policies = [self.actors.policy(k) for k in range(self.algo.actors)]
        self.history = WeightsHistory(self.algo.actors, decodes)  # the versions the next B+1 iterations act with
        self.weights_held_max = 0  # the most versions held at once (reported: bounded by the lag, not the run)
        self.weights_received = 0  # weights messages received by closed subscriptions (reported with the open one's)
        self.loaded: list[tuple[int, str] | None] = [None] * self.algo.actors  # (version, incarnation) in `actors`
        self.actor = slot_index % self.algo.actors
        self.learner = LearnerWatch()  # its stats, and whether the slot is still this worker's
        self.batch_seq = self.sent_rows = 0
        self.flushed_at = 0.0  # when the last batch was put
        self.waits = ""  # what its next iteration waits for (weights, an allocation), "" while it steps
        self.last_note = 0.0
        self.stop_requested = False
        self.pending = PendingBatch.empty(cfg.send_batch, self.spec.obs_dim, self.spec.act_dim)

    # -- the loop -----------------------------------------------------------------------------
    def serve(self) -> None:
        """This slot alone: its passes, each wait as the pass asks (blocking)."""
        self.open()
        try:
            for wait in self.passes():
                if wait is not None:
                    wait()
        finally:
            self.close()

    def open(self) -> None:
        """Its publishers, subscriptions and liveliness token, and its batch log."""
        run, s, wake = self.cfg.run, self.session, self.wake
        self.pub = bus.declare_reliable_publisher(s, keys.transitions(run, self.id))
        self.report = role.RoleReport(s, run, "worker", self.id)
        self.weights = self.subscribe_weights()
        self.allocation = bus.Latest.subscribe(s, keys.allocation(run), wake=wake)
        self.stats_sub = bus.Latest.subscribe(s, keys.learner_stats(run), wake=wake)
        self.done = bus.Latest.subscribe(s, keys.done(run), wake=wake)
        self.token = bus.declare_alive(s, run, "worker", self.id)
        if self.run_dir is not None:  # one line per batch, before it is put: what a killed worker had sent
            path = self.run_dir / rundir.WORKERS / f"{self.id}-{self.incarnation}.batches"
            path.parent.mkdir(parents=True, exist_ok=True)
            self.batch_log = open(path, "a", buffering=1)
        log.info("worker %s (incarnation %s), slot %d, on %s, run %s", self.id, self.incarnation, self.slot,
                 self.cfg.env_id, run)

    def close(self) -> None:
        """What it has not sent goes (unless the slot is another's now), its report, and its declarations."""
        if not self.learner.lost_to:  # a stale owner's rows would be refused: none go
            self.flush()
        self.publish_report(force=True)
        self.write_report()
        if self.batch_log is not None:
            self.batch_log.close()
        self.token.undeclare()
        for sub in (self.weights, self.allocation, self.stats_sub, self.done):
            sub.close()

    def passes(self) -> Iterator[WaitFor | None]:
        """The slot's iterations of the plan, each once it holds the allocation and the actor
        version that apply to it (mam_core/algorithm1.py), until the learner says done. The
        first is the one after the learner's last: 1 in a fresh run, later for a replacement.
        Yields None after each step, and what to wait on where the slot cannot step (`serve`
        waits on it; a WorkerGroup waits for any of its slots' subscriptions instead)."""
        plan, name = self.plan, keys.slot_name(self.slot)
        # Iteration of a competition -> its slots. The initial allocation is the allocation stream's first
        # draw (the referee's too): computed here, so collection starts before the referee is up.
        first = initial_allocation(self.algo, self.cfg.steps)
        decisions = {0: {keys.slot_name(i): int(k) for i, k in enumerate(first)}}
        index: int | None = None  # the next iteration to step
        waiting_since = time.monotonic()
        while not self.stop_requested:
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                log.info("run is done after %d transitions from this worker", self.sent_rows)
                return
            self.refresh(decisions, index)
            lr = self.learner
            if lr.lost_to:  # a stale owner (takeover.follow_owner): it leaves
                self.pending.rows = 0
                return
            if index is not None:
                self.resend_lost(index)
            if index is not None and takeover.out_of_step(lr, self.slot, index, waiting_since, self.pending.rows,
                                                          self.flushed_at, self.kept):
                need = lr.stats.slots_next[self.slot]
                log.info("iteration %d: the restarted learner needs iteration %d of slot %d next; rebuilding the "
                         "slot there", index, need, self.slot)
                lr.synced_with = lr.stats.incarnation
                self.kept.forget_from(need)
                index, waiting_since = self.take_over(need), time.monotonic()
            if index is None:  # where the run stands: the learner's stats
                if lr.stats is None:
                    yield lambda: self.stats_sub.wait_fresh(timeout=0.1)
                    continue
                st = lr.stats
                index = st.slots_next[self.slot] if self.slot < len(st.slots_next) else st.iteration + 1
                lr.synced_with = st.incarnation
                if index > 1:
                    log.info("taking slot %d over at iteration %d", self.slot, index)
                    index = self.take_over(index)
            it = plan.iteration(index) if index <= plan.iterations else None
            if it is None or self.slot not in it.slots:
                self.flush()  # this slot's part of the run is over (the survivor runs slot 0 after C)
                yield lambda: self.done.wait_fresh(timeout=0.1)
                continue
            slots = decisions.get(plan.decision_for(index))
            actor = None if slots is None else slots.get(name)
            version = -1 if it.random else plan.version_for(index)
            if actor is None or (version >= 0 and not self.history.has(actor, version)):
                self.flush()
                self.waits = f"the allocation of iteration {plan.decision_for(index)}" if actor is None \
                    else f"actor {actor} at version {version}"  # its reports say it (the stall watchdog)
                if time.monotonic() - max(waiting_since, self.last_note) > STATUS_EVERY_S:
                    log.info("iteration %d waits for %s", index, self.waits)
                    self.last_note = time.monotonic()
                if actor is None:
                    yield lambda: self.allocation.wait_fresh(timeout=0.05)
                else:
                    yield lambda i=index: self.take_weights(self.weights.get(timeout=0.05), i)
                continue
            waiting_since, self.waits = time.monotonic(), ""
            self.step(index, it.random, actor, version)
            index += 1
            yield None

    def subscribe_weights(self) -> bus.Inbox:
        """Every version, in order (a slot acts with one of the last B+1): a queue, not the latest sample."""
        return bus.Inbox.subscribe(self.session, keys.weights_all(self.cfg.run), maxsize=1024,
                                   screen=role.weights_screen(self.shapes, self.algo.actors, self.rejects,
                                                              self.decodes),
                                   wake=self.wake)

    def close_weights(self) -> None:
        if not self.weights.closed:
            self.weights.close()
            self.weights_received += self.weights.received

    def take_over(self, index: int) -> int:
        """Rebuild the slot where the learner needs it next, iteration `index` (takeover.py); that iteration."""
        if self.weights.closed:  # the slot had stepped its last; a restarted learner needs earlier iterations
            self.weights = self.subscribe_weights()  # (the learner resends the versions it keeps)
        episode = takeover.ask_episode(self.session, self.cfg.run, self.slot, self.spec, self.done, self.rejects,
                                       lambda: self.stop_requested)
        if episode is None:
            return index
        self.slot_state = takeover.rebuild(self, episode, self.plan, self.algo.seed, self.slot,
                                           self.slot_state.inexact)
        return episode.next

    def take_weights(self, item: bus.Received | None, index: int | None) -> None:
        """Keep the versions this slot may still act with (none below iteration `index`'s)."""
        items = ([item] if item is not None else []) + self.weights.drain()
        if index is not None and index > self.plan.last_step(self.slot):  # stepped its last: needs no version
            self.history.clear()  # (slots 1..M-1 after the paper schedule's C: else it kept all, >10 GiB)
            self.close_weights()  # and receives none: decoding every version took 6.5% of a core a worker
            return
        oldest = self.plan.version_for(index) if index is not None and index <= self.plan.iterations else 0
        stats = self.learner.stats
        current = stats.incarnation if stats is not None else ""
        for item in items:
            try:
                w = role.decoded_weights(item, self.shapes, self.algo.actors)
            except MessageError as e:
                self.rejects.reject(keys.parse_last(item.key), e)
                continue
            if w.version >= oldest and role.plausible_version(w, stats) and \
                    role.learner_order(w.incarnation) >= self.learner.newest:  # not a stale learner's
                self.history.add(w.actor, w.version, w.params, w.incarnation, prefer=current, payload=item.payload)
        self.history.forget_below(oldest)
        self.weights_held_max = max(self.weights_held_max, self.history.held())

    def refresh(self, decisions: dict[int, dict[str, int]], index: int | None) -> None:
        """Weights, the referee's decisions (with the one before: none is missed), the learner's stats."""
        st = role.fresh_learner_stats(self.stats_sub, self.cfg.run, self.rejects, self.decodes)
        if st is not None and role.learner_order(st.incarnation) >= self.learner.newest:  # else a stale learner's
            self.learner.newest = role.learner_order(st.incarnation)
            self.learner.stats, self.learner.stats_at = st, time.monotonic()
            self.on_stats(st)
        self.take_weights(None, index)
        item = self.allocation.fresh().get(keys.allocation(self.cfg.run))
        if item is not None:
            try:
                alloc = Allocation.from_bytes(item.payload, self.algo.actors)
            except MessageError as e:
                self.rejects.reject("referee", e)
            else:
                if alloc.iteration is not None:
                    decisions[alloc.iteration] = dict(alloc.slots)
                    if alloc.previous is not None:
                        decisions.setdefault(alloc.previous[0], dict(alloc.previous[1]))

    def on_stats(self, st: LearnerStats) -> None:
        """Drop what the learner has checkpointed; on a new learner incarnation resend the rest;
        see whether another worker has taken this one's slot over (the slot's owner in the stats
        was this incarnation, and is another now: this one is stale)."""
        lr = self.learner
        takeover.follow_owner(lr, st, self.slot, self.id, self.incarnation)
        self.trim_acked(st)
        if st.incarnation != lr.incarnation:
            first = lr.incarnation is None
            lr.incarnation, lr.seen_at = st.incarnation, time.monotonic()
            if not first:
                self.kept.resend(self.pub, "the new learner")
                self.lost_checked = time.monotonic()
            log.info("learner %s is up at iteration %d", lr.incarnation or "?", st.iteration)

    def trim_acked(self, st: LearnerStats) -> None:
        mine = st.per_worker.get(self.id)
        if not mine or mine.acked_incarnation != self.incarnation or mine.acked_seq is None:
            return
        self.kept.acked(mine.acked_seq)

    def resend_lost(self, index: int) -> None:
        """The learner (the same incarnation) still waits for an iteration of this slot that a kept
        batch holds, in stats newer by LOST_AFTER_S than when the batch went: it was lost in
        flight; the kept batches from it on go again (kept.py)."""
        st, now = self.learner.stats, time.monotonic()
        if st is None or st.incarnation != self.learner.incarnation or self.slot not in st.awaiting or \
                self.slot >= len(st.slots_next):
            return
        need, since = st.slots_next[self.slot], max(self.flushed_at, self.lost_checked)
        if need < index and self.learner.stats_at - since > LOST_AFTER_S and self.kept.holds(need):
            self.lost_checked = now
            self.kept.resend(self.pub, f"the learner, which waits for iteration {need:,} of slot {self.slot}", need)

    def step(self, index: int, random_phase: bool, actor: int, version: int) -> None:
        """Iteration `index` of this slot: one transition (a simulator fault: counted, the env
        reset, the step retried; the run is then not the seed's, and the learner says so)."""
        self.actor, state, pending = actor, self.slot_state, self.pending
        policy_from = digest = ""
        if version >= 0:
            policy_from, digest = self.history.source(actor, version), self.history.digest(actor, version)
            if self.loaded[actor] != (version, policy_from):
                self.actors.load_member(actor, self.history.get(actor, version))
                self.loaded[actor] = (version, policy_from)
        if pending.acted_otherwise(actor, version, policy_from):
            self.flush()  # a batch carries one actor and one policy version (of one learner incarnation)
        while True:
            action = uniform(self.env) if random_phase else \
                act(self.policies[actor], state.obs, state.streams.noise, self.algo, self.max_action)
            try:
                next_obs, reward, terminated, truncated = self.env_step(action)
                break
            except EnvFault as fault:
                self.count_fault(fault)
                state.episode_return, state.first_row = 0.0, True
                state.obs = self.reset_env()
        pending.add(index, state.obs, action, reward, next_obs, terminated, episode_start=state.first_row,
                    actor=actor, version=version, policy_from=policy_from, digest=digest)
        state.first_row = False
        state.episode_return += reward
        if terminated or truncated:
            pending.returns.append(state.episode_return)
            state.episode_return, state.first_row = 0.0, True
            state.obs = self.reset_env(seed=state.streams.episode_seed(index + 1))  # the next episode's own seed
        else:
            state.obs = next_obs
        if pending.rows >= self.cfg.send_batch or time.monotonic() - pending.started > MAX_BATCH_AGE_S:
            self.flush()

    def flush(self) -> None:
        p = self.pending
        if p.rows == 0:
            return
        n = p.rows
        batch = TransitionBatch(self.id, self.incarnation, self.batch_seq, p.actor, p.version,
                                *p.arrays(copy=self.kept.keep),  # kept for a resend: the arrays are reused
                                tuple(p.returns) or None, iteration=p.iteration, slot=self.slot,
                                policy_from=p.policy_from, env_faults=sum(self.faults.values()),
                                episode_starts=tuple(p.starts), inexact=self.slot_state.inexact,
                                policy_digest=p.digest)
        if self.batch_log is not None:
            self.batch_log.write(f"{self.batch_seq} {n}\n")
        self.pub.put(batch.to_bytes())
        self.flushed_at = time.monotonic()
        self.kept.add(batch)
        self.batch_seq += 1
        self.sent_rows += n
        p.sent()


def main(run: str, conf: Any, ids: list[str], slots: list[int], run_dir: Path | None = None) -> None:
    """Serve `slots` as the workers `ids`: one `Worker`, or several in one loop (worker_group.py)."""
    worker_group.serve(run, conf, ids, slots, lambda cfg, session, wid, slot, wake, decodes: Worker(
        cfg, session, wid, slot, run_dir, wake, decodes))


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags)
def worker_command(
    run: options.Run = None, connect: options.Connect = None, listen: options.Listen = None,
    zenoh_config: options.ZenohConfig = None, spare: options.Spare = False, take_over_after: options.TakeOver = None,
    id: str = typer.Option(None, "--id", help="worker id (slot name); default HOST-PID; with several slots one "
                           "id a slot, comma-separated (default HOST-PID-sI)"),  # noqa: A002
    slot: Optional[str] = typer.Option(None, metavar="I[,J|I-J...]",
                                       help="slot index (0..M-1; default 0): the slot's random streams (from --seed) "
                                       "and its place in each iteration; several (0,1,2 or 0-2): this process steps "
                                       "them all in one loop, cheaper than a process each"),
    run_dir: Optional[Path] = typer.Option(None, "--run-dir", help="the run directory for this worker's batch log "
                                           "(workers/ID-INCARNATION.batches) and report; default: none, neither is "
                                           "kept", rich_help_panel=options.RUN_PANEL),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging"),
) -> None:
    """Run one environment slot of a run, or several in one loop (needs only --run and --connect)."""
    role.setup_logging(verbose)
    if not run:
        raise typer.BadParameter("--run NAME is required (the learner prints it and writes it to config.json)")
    config.check_run_name(run)
    slots = parse_slots(slot) if slot is not None else [0]
    ids = slot_ids(id, slots)
    from services.roles import spare as spares  # --spare: services/roles/spare.py (it refuses --slot)
    if not spares.served(spare, None if slot is None else slots[0], take_over_after, run, ids[0], run_dir, Worker,
                         connect, listen, zenoh_config):
        main(run, role.client_config(connect, listen, zenoh_config), ids, slots, run_dir)


cli = app  # the `mam-worker` entry point


if __name__ == "__main__":
    cli()
