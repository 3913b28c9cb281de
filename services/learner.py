"""`mam-learner`: replay buffer, all K actors and n·K critics, the rate limiter, checkpoints.

One loop: drain transitions into the replay buffer (services/intake.py), run as many updates as
the schedule allows, publish weights every `sync_every` updates and stats (with the rate
limiter's credit, mam_core/pacing.py) a few times a second, follow the referee's rounds and
elimination, checkpoint (services/checkpoint.py), and end the run at `--steps`.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
import uuid
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch
import typer

from mam_core.agent import EnvSpec, MultiActorAgent, pick_device
from mam_core.algorithm1 import Algorithm1
from mam_core.evaluation import estimation_bias
from mam_core.pacing import CheckpointRule, Pacer
from mam_core.replay import ReplayBuffer, ReplayLog
from mam_core.schedule import Schedule
from services import announce, bus, keys, options, role, rundir, runlock, tb
from services.checkpoint import (
    EXIT_CORRUPT,
    CheckpointCorrupt,
    exit_on_write_error,
    load_checkpoint,
    replay_dir,
    save_checkpoint,
)
from services.codec import Allocation, Done, LearnerStats, MessageError, TransitionSpec, Weights, decode, encode
from services.exact import ExactnessLost, SlotStage, snapshot_versions
from services.intake import Intake
from services.options import JsonlWriter, RunConfig, write_json

log = logging.getLogger("mam.learner")

STATS_PERIOD_S = 0.1  # stats this often while updating; four times as often while waiting for data
LOG_PERIOD_S = 1.0
HEARTBEAT_S = 2.0  # config re-published this often
# After done: how long to wait for a referee that is gone (a restart: `mam run`'s backoff is up to
# 15 s, and a referee starting on a loaded box took more than 20 s in the chaos test) ...
REFEREE_GRACE_S = 60.0
REFEREE_WAIT_S = 240.0  # ... and at most, in all, for its final evaluation


class Learner:
    def __init__(self, cfg: RunConfig, session: Any, run_dir: Path, resume: dict[str, Any] | None = None) -> None:
        self.cfg, self.algo, self.session, self.run_dir = cfg, cfg.algo, session, run_dir
        self.id = f"{socket.gethostname()}-{os.getpid()}"
        self.incarnation = uuid.uuid4().hex[:12]
        self.spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
        self.device = pick_device(self.algo.device)
        torch.manual_seed(self.algo.seed)
        if cfg.learner_threads > 0:
            torch.set_num_threads(cfg.learner_threads)
        self.agent = MultiActorAgent(self.algo, self.spec, self.device)
        self.schedule = Schedule.for_run(self.algo, cfg.steps)  # iterations (paper) or transitions
        self.plan = Algorithm1.for_run(self.algo, cfg.steps)  # Algorithm 1's control flow (exact mode)
        # Exact mode: lock-step with the plan until a restart breaks it (services/exact.py).
        self.exact = cfg.collection == "exact"
        self.inexact = "the learner restarted from its checkpoint" if self.exact and resume is not None else ""
        self.exact = self.exact and resume is None
        self.iteration = 0  # exact mode: iterations whose updates are done
        self.decided_survivor: int | None = None  # exact mode: the referee's choice at C, applied by the plan
        capacity = min(self.algo.buffer_size, self.schedule.budget + cfg.tolerance)
        if self.exact:  # what mam_core.reference allocates
            capacity = min(self.algo.buffer_size, max(self.schedule.budget, self.algo.batch_size))
        self.buffer = ReplayBuffer(capacity, self.spec.obs_dim, self.spec.act_dim, self.device, self.algo.seed)
        spec = TransitionSpec(self.spec.obs_dim, self.spec.act_dim, self.algo.actors, max_rows=4096,
                              max_action=max(self.spec.max_action))
        max_message = spec.max_rows * (2 * self.spec.obs_dim + self.spec.act_dim + 2) * 4 + (1 << 16)
        self.intake = Intake(self.buffer, spec, max_message)
        self.intake.incarnation = self.incarnation
        self.replay_log = ReplayLog(replay_dir(run_dir)) if cfg.save_replay else None
        # Per worker: (incarnation, seq) such that all its batches up to seq are in the checkpoint
        # generation before the newest (with the replay). Workers keep the batches after it and
        # resend them to a restarted learner (exactly once, with the intake de-duplicating). One
        # generation late: when the newest fails to verify at a resume, the learner falls back to
        # the previous one, and the rows after that are still with the workers.
        self.acked: dict[str, tuple[str, int]] = {}
        self.acked_newest: dict[str, tuple[str, int]] = {}  # the same for the newest generation
        self.referee_seen = False
        self.other_rejects = bus.RejectLog(log, "message")  # allocation topic
        self.metrics: dict[str, float] = {}
        self.env_steps = 0  # transitions received into the buffer (the schedule maps them to iterations)
        self.survivor: int | None = None
        self.checkpoints = CheckpointRule(cfg.checkpoint_every, cfg.checkpoint_rows, cfg.checkpoint_seconds)
        self.started = time.monotonic()
        self.stop_requested = False
        if resume is not None:
            self._restore(resume)
        self.pacer = Pacer(self.schedule, cfg.tolerance, cfg.bias_every, self.env_steps)
        if self.survivor is not None:
            self.pacer.eliminated = True

    def _restore(self, state: dict[str, Any]) -> None:
        self.agent.load_state_dict(state["agent"])
        c = state["counters"]
        self.env_steps = int(c["env_steps"])
        if "replay" in state:  # checkpoints written before the chunked replay log
            self.buffer.load_state_dict(state["replay"])
        if "replay_log" in state and self.replay_log is not None:
            meta = state["replay_log"]
            self.replay_log.restore(self.buffer, meta["manifest"], int(meta["inserted"]), json.loads(meta["rng"]))
            if self.buffer.inserted != self.env_steps:
                raise ValueError(f"checkpoint counts {self.env_steps} transitions, its replay {self.buffer.inserted}")
        self.intake.stream_rows = {k: int(v) for k, v in json.loads(c.get("stream_rows", "{}")).items()}
        # The run had a referee: a learner resumed at its budget waits for it (its final evaluation)
        # though none is alive yet, e.g. while `mam run` restarts it.
        self.referee_seen = bool(int(c.get("referee_seen", 0)))
        # Sequence numbers go on from the checkpoint: a gap then counts what died with the old
        # learner, until the workers' resends fill it.
        self.intake.tracker.restore(json.loads(c.get("per_worker", "{}")))
        if self.replay_log is not None:  # just verified: its rows need not be kept twice
            self.acked = self.acked_newest = self.intake.checkpointed_prefixes()
        # Policy versions jump past anything the dead incarnation can have published after this
        # checkpoint (at most checkpoint_every updates, one actor step per policy_delay of them).
        # Otherwise workers keep its newer-numbered weights, tag their transitions with versions
        # this learner has not reached, and those are rejected as future versions: a stall.
        jump = self.cfg.checkpoint_every // self.algo.policy_delay + 2
        self.agent.versions = [v + jump for v in self.agent.versions]
        live = self.agent.live_actors
        if sum(live) == 1 and self.algo.actors > 1:
            self.survivor = live.index(True)
        log.info("resumed at %d transitions, %d updates (replay rows: %d)", self.env_steps, self.agent.updates,
                 len(self.buffer))

    def serve(self) -> None:
        run, s = self.cfg.run, self.session
        self.config_pub = bus.declare_latest_publisher(s, keys.config(run), drop=True)  # heartbeats: never block
        self.weights_pubs = [bus.declare_latest_publisher(s, keys.weights(run, k)) for k in range(self.algo.actors)]
        self.stats_pub = bus.declare_latest_publisher(s, keys.learner_stats(run), drop=True)  # 10 Hz, latest only
        self.done_pub = bus.declare_latest_publisher(s, keys.done(run))
        self.token = bus.declare_alive(s, run, "learner", self.id)
        self.workers = bus.watch_alive(s, run, "worker")
        self.referees = bus.watch_alive(s, run, "referee")
        self.allocation = bus.Latest.subscribe(s, keys.allocation(run))
        self.inbox = bus.Inbox(maxsize=8192).subscribe(s, keys.transitions_all(run))
        self.snapshot_pubs = [bus.declare_reliable_publisher(s, keys.eval_weights(run, k))
                              for k in range(self.algo.actors)]
        self.snapshots_sent: set[int] = set()
        # The snapshot messages of the latest evaluations, re-sent with the current weights while
        # an iteration's rows are late (`resend_exact`): a sample lost or overwritten on its key
        # (a Latest subscriber keeps one per key) must not leave a lock-step run waiting forever.
        self.recent_snapshots: deque[tuple[int, bytes]] = deque(maxlen=4 * max(self.algo.actors, 1))
        self.board = tb.RunBoard(self.run_dir, "learner")  # RUN_DIR/tb/learner: the JSONL rows' scalars
        self.log_writer = self.board.tee(JsonlWriter(self.run_dir / rundir.LEARNER_LOG), tb.learner_scalars)
        self.bias_writer = (self.board.tee(JsonlWriter(self.run_dir / rundir.BIAS), tb.bias_scalars)
                            if self.cfg.bias_every else None)
        self.seq = 0
        self.publish_config()
        try:
            self._loop()
        finally:
            for closable in (self.inbox, self.allocation, self.workers, self.referees, self.log_writer,
                             self.bias_writer, self.board):
                if closable is not None:
                    closable.close()

    # -- the loop: receive, ingest, step the schedule, update, publish ----------------------------
    def _loop(self) -> None:
        if self.exact:
            if self._exact_loop():
                return  # done, or stopped
            log.warning("the run is no longer exact: %s; collection goes on asynchronously", self.inexact)
        self.publish_weights(all_actors=True)
        self.checkpoints.mark(self.agent.updates, self.env_steps, time.monotonic())
        if self.env_steps == 0:  # at once, and again when the random phase ends: a learner killed early resumes
            self.checkpoint()
        random_phase_checkpoint = self.env_steps < self.schedule.random_until
        self._progress, self._progress_at, self._stall_logged = (-1, -1), time.monotonic(), 0.0
        sync = role.Every(self.cfg.sync_every, start=self.agent.updates)  # counts updates
        stats, heartbeat, log_row = role.Every(STATS_PERIOD_S), role.Every(HEARTBEAT_S), role.Every(LOG_PERIOD_S)
        self.rates, self._rate_base = (0.0, 0.0), (self.env_steps, self.agent.updates, time.monotonic())
        while not self.stop_requested:
            self.ingest(self.inbox.drain(max_items=256))
            self.follow_allocation()
            if self.pacer.bias_due(self.env_steps, self.agent.updates):
                self.measure_bias()  # the critic as trained on the point's transitions
            budget_done = self.env_steps >= self.schedule.budget
            ran = self.run_updates(deadline=time.monotonic() + 0.02)
            if sync.due(self.agent.updates):
                self.publish_weights()
            now = time.monotonic()
            if stats.due(now, STATS_PERIOD_S if ran else STATS_PERIOD_S / 4):
                self.publish_stats()
            if heartbeat.due(now):  # late joiners also get it from the cache
                self.publish_config()
            if log_row.due(now):
                self.write_log(now)
            if self.checkpoints.due(self.agent.updates, self.env_steps, now):
                self.checkpoint()
            elif random_phase_checkpoint and self.env_steps >= self.schedule.random_until:
                random_phase_checkpoint = False
                self.checkpoint()
            self.watch_stall(now)
            if not self.referee_seen and self.referees.live():
                self.referee_seen = True
            if budget_done and self.agent.updates >= self.updates_allowed():
                self.finish()
                return
            if ran == 0:
                item = self.inbox.get(timeout=0.005)  # learner ahead of collection: wait for data
                if item is not None:
                    self.ingest([item])
        # Stopped by a signal: keep a usable checkpoint; the run is not done.
        self.write_log()
        self.checkpoint()

    def watch_stall(self, now: float) -> None:
        """The split learner's stall watchdog: no transition and no update for `stall_timeout`
        seconds logs what it waits for (once per period); `mam run` acts on stalls itself."""
        progress = (self.env_steps, self.agent.updates)
        if progress != self._progress:
            self._progress, self._progress_at = progress, now
            return
        limit = self.cfg.stall_timeout
        if limit <= 0 or now - self._progress_at < limit or now - self._stall_logged < limit:
            return
        self._stall_logged = now
        until, barrier, referee = self.accept_until(), self.pacer.barrier(), bool(self.referees.live())
        if until > self.env_steps:
            waits = f"transitions: credit open to {until}, {len(self.workers.live())} workers live"
        elif barrier is not None and referee and until >= barrier:
            waits = f"the referee's allocation for the round at {barrier} transitions (credit at the barrier)"
        else:
            waits = f"updates: credit used up at {until} (updates allowed {self.updates_allowed()})"
        log.warning("stalled for %.0f s at %d transitions, %d updates: waiting for %s; versions %s, referee %s, "
                    "rejected %s", now - self._progress_at, self.env_steps, self.agent.updates, waits,
                    list(self.agent.versions), "live" if referee else "gone", self.rejected() or "none")

    def ingest(self, items: list[bus.Received]) -> None:
        self.env_steps += self.intake.ingest(items, self.agent.versions)

    def updates_allowed(self) -> int:
        """Rate limiter: utd updates per schedule step (iteration or transition) past the start."""
        if len(self.buffer) < self.algo.batch_size:
            return 0
        return self.schedule.updates_allowed(self.env_steps)

    def accept_until(self) -> int:
        """The credit (mam_core/pacing.py): `tolerance` ahead of the updates, and no further than
        the next round while a referee is live and has not published it."""
        return self.pacer.accept_until(self.agent.updates, referee_live=bool(self.referees.live()))

    def run_updates(self, deadline: float) -> int:
        ran = 0
        allowed = self.updates_allowed()
        while self.agent.updates < allowed:
            self.metrics = self.agent.update(self.buffer.sample(self.algo.batch_size, self.agent.batch_groups))
            ran += 1
            if time.monotonic() > deadline:
                break
        return ran

    def follow_allocation(self) -> None:
        """Lift the round barrier once the referee has published the round; train only the
        survivor once it has eliminated the others (Sec. 3.1.1)."""
        item = self.allocation.fresh().get(keys.allocation(self.cfg.run))
        if item is None:
            return
        try:
            alloc = Allocation.from_bytes(item.payload, self.algo.actors)
        except MessageError as e:
            self.other_rejects.reject("allocation", e)
            return
        self.pacer.on_allocation(alloc.round, alloc.env_steps, alloc.survivor)
        if self.exact:
            if alloc.iteration is None:
                self.break_exact("the referee allocates asynchronously (it restarted)")
            elif alloc.survivor is not None:
                self.decided_survivor = alloc.survivor  # applied where Algorithm 1 places it
            return
        if alloc.survivor is not None and self.survivor is None:
            self.survivor = alloc.survivor
            self.agent.eliminate(alloc.survivor)
            log.info("eliminated all actors but %d at %d transitions", alloc.survivor, self.env_steps)
            self.publish_weights(all_actors=True)

    # -- publishing -------------------------------------------------------------------------------
    def publish_weights(self, all_actors: bool = False) -> None:
        live = self.agent.live_actors
        for k in range(self.algo.actors):
            if live[k] or all_actors:
                msg = Weights(k, self.agent.versions[k], self.agent.actor_params(k), self.spec.obs_dim,
                              self.spec.act_dim, max(self.spec.max_action), tuple(self.algo.hidden),
                              self.incarnation)
                self.weights_pubs[k].put(msg.to_bytes(self.id, self._next_seq()))

    def _next_seq(self) -> int:
        self.seq += 1
        return self.seq

    def stats(self, done: bool = False) -> LearnerStats:
        now = time.monotonic()
        losses = {k.split("/", 1)[1]: v for k, v in self.metrics.items() if k.startswith("loss/")}
        q_means = [self.metrics.get(f"q/actor{k}", float("nan")) for k in range(self.algo.actors)]
        return LearnerStats(
            env_steps=self.env_steps, updates=self.agent.updates, accept_until=self.accept_until(),
            utd=self.utd(), losses=losses, q_means=tuple(q_means), versions=tuple(self.agent.versions),
            per_worker=self.intake.counters(now, self.acked), rejected=self.rejected(), done=done,
            live=tuple(self.agent.live_actors), workers=max(len(self.workers.live()), self.intake.active(now)),
            steps=self.schedule.budget, incarnation=self.incarnation, exact=self.exact, iteration=self.iteration,
            inexact=self.inexact)

    @property
    def iterations(self) -> int:
        """Schedule steps done: Algorithm 1's iterations (paper) or transitions (equal-data)."""
        return self.schedule.units_at(self.env_steps)

    def utd(self) -> float:
        """Updates per schedule step past the start (per iteration or per transition)."""
        consumed = max(self.iterations - self.algo.start_steps, 0)
        return self.agent.updates / consumed if consumed else 0.0

    def rejected(self) -> dict[str, int]:
        """Rejection counts by reason: transitions by reason, the allocation topic as allocation:<reason>."""
        out = dict(self.intake.rejects.counts())
        out.update({f"allocation:{r}": n for r, n in self.other_rejects.counts().items()})
        return out

    def publish_config(self) -> None:
        self.config_pub.put(encode("config", {"config": self.cfg.to_dict()}, sender=self.id, seq=self._next_seq()))

    def publish_stats(self, done: bool = False) -> None:
        self.stats_pub.put(self.stats(done).to_bytes(self.id, self._next_seq()))

    def write_log(self, now: float | None = None) -> None:
        """One learner.jsonl row; with `now`, the rates since the previous such row first."""
        if now is not None:
            steps, updates, t = self._rate_base
            dt = max(now - t, 1e-9)
            self.rates = ((self.env_steps - steps) / dt, (self.agent.updates - updates) / dt)
            self._rate_base = (self.env_steps, self.agent.updates, now)
        tracker = self.intake.tracker
        row = {"t": round(time.monotonic() - self.started, 3), "env_steps": self.env_steps,
               "iterations": self.iterations, "updates": self.agent.updates, "utd": self.utd(),
               "transitions_per_s": round(self.rates[0], 2), "updates_per_s": round(self.rates[1], 2),
               "versions": list(self.agent.versions), "live": self.agent.live_actors,
               "lost": tracker.lost, "duplicates": tracker.duplicates,
               "rejected": self.intake.rejects.total, "buffer": len(self.buffer),
               "received": {w: t.received for w, t in self.intake.workers.items()}}
        row.update(self.metrics)
        if self.exact:
            row["exact_wait_s"] = round(getattr(self, "exact_wait_s", 0.0), 3)
        if self.intake.episode_returns:
            row["train_return"] = float(np.mean(self.intake.episode_returns))
            self.intake.episode_returns.clear()
        self.log_writer.write(row)

    def measure_bias(self) -> None:
        """Eq. 17 for every live actor k: Q_k1(s0, π_k(s0)) of the current critic against the
        discounted Monte-Carlo return of π_k from the same initial states (`bias_rollouts`
        rollouts, seeded by the point so every variant of a seed starts from the same states).
        Training pauses meanwhile; the rate limiter holds the workers."""
        point = self.pacer.take_bias_point(self.env_steps)
        started = time.monotonic()
        live = self.agent.live_actors
        seed = 1_000_003 * (self.algo.seed + 1) + point // self.cfg.bias_every * 1_009
        for k in (k for k, alive in enumerate(live) if alive):
            try:
                result = estimation_bias(lambda obs, k=k: self.agent.act(obs, k),
                                         lambda obs, act, k=k: self.agent.q_value(obs, act, k),
                                         self.cfg.env_id, self.cfg.bias_rollouts, self.algo.gamma, seed,
                                         self.cfg.env_kwargs, horizon=self.cfg.bias_horizon)
            except Exception:  # a diagnostic never stops the training
                log.exception("bias measurement at %d transitions failed (actor %d)", point, k)
                continue
            self.bias_writer.write({"env_steps": self.env_steps, "iterations": self.iterations, "point": point,
                                    "updates": self.agent.updates,
                                    "live": list(live), "rollouts": self.cfg.bias_rollouts,
                                    "bias": {"actor": k, **result}})
        log.info("bias at %d transitions measured in %.1f s", self.env_steps, time.monotonic() - started)

    def checkpoint(self) -> None:
        started = time.monotonic()
        counters = {"env_steps": self.env_steps, "per_worker": json.dumps(self.intake.tracker.per_sender()),
                    "stream_rows": json.dumps(self.intake.stream_rows), "referee_seen": int(self.referee_seen)}
        path = save_checkpoint(self.run_dir, self.agent, self.buffer, counters, self.cfg, self.replay_log,
                               survivor=self.survivor)  # with policy.npz, in a verified generation
        self.checkpoints.mark(self.agent.updates, self.env_steps, time.monotonic())
        if self.replay_log is not None:  # only now on disk: workers may drop what the previous one holds
            self.acked, self.acked_newest = self.acked_newest, self.intake.checkpointed_prefixes()
        log.info("checkpoint %s at %d updates, %d transitions (%.2f s)", path, self.agent.updates, self.env_steps,
                 time.monotonic() - started)

    # -- exact mode: Algorithm 1 in lock-step (services/exact.py) --------------------------------
    def _exact_loop(self) -> bool:
        """Iterations 1..N of the plan: rows in slot order, then the iteration's updates. True
        when the run finished (or was stopped); False when exactness broke (go asynchronous)."""
        plan, stage = self.plan, SlotStage(self.algo.workers)
        self.publish_weights(all_actors=True)
        self.checkpoints.mark(self.agent.updates, self.env_steps, time.monotonic())
        self.checkpoint()  # at once: a learner killed early resumes (asynchronously) from here
        stats, heartbeat, log_row = role.Every(STATS_PERIOD_S), role.Every(HEARTBEAT_S), role.Every(LOG_PERIOD_S)
        self.rates, self._rate_base = (0.0, 0.0), (self.env_steps, self.agent.updates, time.monotonic())
        self.workers_seen: set[str] = set()
        self.workers_were_live: set[str] = set()
        self.referee_id: str | None = None
        self.exact_wait_s = 0.0  # seconds the loop waited for an iteration's rows (learner.jsonl: where time goes)
        self.unstaged: list[bus.Received] = []  # what arrived with the batch that ended exactness
        try:
            while not self.stop_requested:
                index = self.iteration + 1
                if index > plan.iterations:
                    self.finish()
                    return True
                it = plan.iteration(index)
                waited = time.perf_counter()
                while not stage.ready(index, it.slots):  # line 9: the iteration's transitions
                    self.receive_exact(stage, timeout=0.002)
                    now = time.monotonic()
                    if stats.due(now, STATS_PERIOD_S / 4):
                        self.publish_stats()
                    if heartbeat.due(now):
                        self.publish_config()
                        if time.perf_counter() - waited > HEARTBEAT_S:  # late: something may be lost
                            self.resend_exact()
                    if log_row.due(now):
                        self.write_log(now)
                    if self.stop_requested:
                        break
                self.exact_wait_s += time.perf_counter() - waited
                if self.stop_requested:
                    break
                if index == 1:
                    self.publish_snapshots(0)  # the referee is subscribed: workers have its allocation
                rows, used = stage.take(index, it.slots)
                self.buffer.add_batch(rows["obs"], rows["action"], rows["reward"], rows["next_obs"],
                                      rows["terminated"], actor=rows["actor"], version=rows["version"])
                self.env_steps += len(it.slots)
                for batch in used:
                    self.intake.admit(batch)
                    self.intake.count(batch, self.agent.versions)
                self.exact_updates(it)
                self.iteration = index
                if plan.weights_change(index):
                    self.publish_weights()
                self.publish_snapshots(index)
                if self.pacer.bias_due(self.env_steps, self.agent.updates):
                    self.measure_bias()
                now = time.monotonic()
                if stats.due(now):
                    self.publish_stats()
                if log_row.due(now):
                    self.write_log(now)
                if heartbeat.due(now):
                    self.publish_config()
                if self.checkpoints.due(self.agent.updates, self.env_steps, now):
                    self.checkpoint()
        except ExactnessLost as e:
            self.inexact = str(e)
            self.exact = False
            self.insert_leftovers(stage)
            self.ingest(self.unstaged)
            self.publish_stats()
            return False
        self.write_log()
        self.checkpoint()
        return True

    def receive_exact(self, stage: SlotStage, timeout: float) -> None:
        """Stage what arrived; watch for what ends exactness (a role gone or restarted)."""
        items = self.inbox.drain(max_items=256)
        if not items:
            item = self.inbox.get(timeout=timeout)
            items = [item] if item is not None else []
        for n, item in enumerate(items):
            batch = self.intake.validate(item, self.agent.versions)
            if batch is None:
                continue
            try:
                stage.add(batch)
            except ExactnessLost:
                self.unstaged = items[n:]  # this batch and what came after it: ingested asynchronously
                raise
            self.workers_seen.add(batch.worker)
        self.follow_allocation()
        if self.inexact:
            raise ExactnessLost(self.inexact)
        live = self.workers.live()
        self.workers_were_live |= live  # a first batch can arrive before its sender's token: not "gone"
        gone = sorted((self.workers_seen & self.workers_were_live) - set(live))
        if gone:
            raise ExactnessLost(f"worker {gone[0]} left before the end of the run")
        referees = self.referees.live()
        if self.referee_id is None and len(referees) == 1:
            self.referee_id = next(iter(referees))
            self.referee_seen = True  # finish() waits for its final evaluation
        elif self.referee_id is not None and self.referee_id not in referees:
            raise ExactnessLost(f"referee {self.referee_id} left before the end of the run")

    def break_exact(self, why: str) -> None:
        """Exactness ends here (the caller's loop raises ExactnessLost)."""
        if self.exact and not self.inexact:
            self.inexact = why

    def insert_leftovers(self, stage: SlotStage) -> None:
        """Going asynchronous: what was staged goes into the buffer as it is, counted once."""
        for batch, used in stage.leftovers():
            rest = slice(used, batch.rows)
            self.buffer.add_batch(batch.obs[rest], batch.action[rest], batch.reward[rest], batch.next_obs[rest],
                                  batch.terminated[rest], actor=batch.actor, version=batch.version)
            self.env_steps += batch.rows - used
            if self.intake.admit(batch):
                self.intake.count(batch, self.agent.versions)

    def exact_updates(self, it: Any) -> None:
        """Iteration `it`'s updates (lines 11-24): one mini-batch per actor each; at C the
        elimination comes right before the first actor phase (or after the updates)."""
        at = self.plan.elimination_update() if it.eliminate else None
        for _ in range(it.updates[0], it.updates[1]):
            batch = self.buffer.sample(self.algo.batch_size, self.agent.batch_groups)
            metrics = self.agent.update_critics(batch)
            if self.agent.actor_phase_due:
                if self.agent.updates == at:
                    self.apply_elimination()
                metrics.update(self.agent.update_actors(batch))
            self.metrics = metrics
        if it.eliminate and at is None:
            self.apply_elimination()

    def apply_elimination(self) -> None:
        """The referee's survivor (waits for its decision at C: it evaluates the actors as they
        acted in iteration C, while this iteration's rows come in)."""
        heartbeat = role.Every(HEARTBEAT_S)
        while self.decided_survivor is None:
            self.follow_allocation()
            if self.inexact:
                raise ExactnessLost(self.inexact)
            if self.stop_requested:
                raise ExactnessLost("stopped while waiting for the elimination")
            if heartbeat.due():
                self.publish_stats()
                self.publish_config()
                self.resend_exact()  # the referee may have missed the snapshot it decides on
            self.allocation.wait_fresh(timeout=0.05)
        self.survivor = self.decided_survivor
        self.agent.eliminate(self.survivor)
        self.pacer.eliminated = True
        log.info("eliminated all actors but %d at iteration %d", self.survivor, self.plan.elimination)

    def publish_snapshots(self, index: int) -> None:
        """The versions the referee's next evaluations need, once each (`snapshot_versions`)."""
        for version in sorted(snapshot_versions(self.plan, index) - self.snapshots_sent):
            self.snapshots_sent.add(version)
            for k, alive in enumerate(self.agent.live_actors):
                if alive:
                    msg = Weights(k, self.agent.versions[k], self.agent.actor_params(k), self.spec.obs_dim,
                                  self.spec.act_dim, max(self.spec.max_action), tuple(self.algo.hidden),
                                  self.incarnation).to_bytes(self.id, self._next_seq())
                    self.snapshot_pubs[k].put(msg)
                    self.recent_snapshots.append((k, msg))

    def resend_exact(self) -> None:
        """The current weights and the latest snapshots once more (an iteration's rows are late:
        a worker or the referee may have missed them). Versions equal to what a role holds are
        not loaded again, so this changes nothing for a role that had them."""
        self.publish_weights()
        for k, msg in self.recent_snapshots:
            self.snapshot_pubs[k].put(msg)

    def finish(self) -> None:
        """Budget reached: final weights, checkpoint, then tell everyone until they have left."""
        if self.pacer.bias_reached(self.env_steps):
            self.measure_bias()  # a point at the budget itself: the loop leaves before checking it
        self.publish_weights(all_actors=True)
        self.write_log()
        self.checkpoint()
        self.publish_stats(done=True)
        msg = Done("budget", self.env_steps, self.agent.updates)
        deadline = time.monotonic() + 10.0
        # The last put before close can be lost: repeat until workers have gone (their tokens vanish).
        while True:
            self.done_pub.put(msg.to_bytes(self.id, self._next_seq()))
            self.publish_stats(done=True)
            if not self.workers.live() or time.monotonic() > deadline:
                break
            self.ingest(self.inbox.drain())  # what was sent before Done is counted, not left queued
            time.sleep(0.1)
        self.inbox.close()
        self.ingest(self.inbox.drain())
        self.checkpoint()  # with the rows that came in after done: the replay holds every counted row
        self.wait_for_referee(msg)
        tracker = self.intake.tracker
        write_json(self.run_dir / rundir.TRANSPORT, {
            "env_steps": self.env_steps, "iterations": self.iterations, "updates": self.agent.updates,
            "lost": tracker.lost, "duplicates": tracker.duplicates, "rejected": self.rejected(),
            "recovered": tracker.recovered, "redundant": tracker.redundant,
            "replay_rows": self.buffer.inserted if self.replay_log is not None else None,
            **self.intake.transport(),
            "inbox_dropped": self.inbox.dropped})  # shed before decoding when the inbox overflowed
        log.info("done: %d transitions, %d updates, lost %d, duplicates %d, rejected %d", self.env_steps,
                 self.agent.updates, tracker.lost, tracker.duplicates, self.intake.rejects.total)

    def wait_for_referee(self, msg: Done) -> None:
        """Stay up (repeating done) until the referee has written its final evaluation.

        A referee that dies now is restarted (`mam run`) and needs this learner's config,
        done notice and final weights. Waits while a referee was seen during the run and has
        not reported `final`: up to REFEREE_GRACE_S without any referee alive, and at most
        REFEREE_WAIT_S in all.
        """
        if not self.referee_seen:
            return
        sub = bus.Latest(late_join=False).subscribe(self.session, keys.role_stats_all(self.cfg.run, "referee"))
        deadline = time.monotonic() + REFEREE_WAIT_S
        gone_since: float | None = None
        last_put = 0.0
        try:
            while time.monotonic() < deadline and not self.stop_requested:
                if any(self._is_final(item) for item in sub.snapshot().values()):
                    return
                now = time.monotonic()
                if self.referees.live():
                    gone_since = None
                elif gone_since is None:
                    gone_since = now
                elif now - gone_since > REFEREE_GRACE_S:
                    log.warning("no referee for %.0f s after done: not waiting for its final evaluation",
                                REFEREE_GRACE_S)
                    return
                if now - last_put >= 1.0:  # a restarted referee needs these (the caches serve them too)
                    self.done_pub.put(msg.to_bytes(self.id, self._next_seq()))
                    self.publish_stats(done=True)
                    self.publish_config()
                    self.publish_weights(all_actors=True)
                    last_put = now
                time.sleep(0.1)
            log.warning("the referee did not report its final evaluation within %.0f s", REFEREE_WAIT_S)
        finally:
            sub.close()

    @staticmethod
    def _is_final(item: bus.Received) -> bool:
        try:
            return decode(item.payload).get("final") is True
        except MessageError:
            return False


def main(cfg: RunConfig, conf: Any, run_dir: Path, resume: bool = False) -> None:
    try:  # one learner per run directory and per run name: refused before anything is written
        lock = runlock.lock_role(run_dir, "learner", cfg.run)
    except runlock.RunInUse as e:
        log.error("%s", e)
        raise SystemExit(runlock.EXIT_REFUSED) from None
    with lock, exit_on_write_error(run_dir):  # a full disk: one line naming the path, exit EXIT_WRITE_ERROR
        try:
            state = load_checkpoint(run_dir) if resume else None
        except CheckpointCorrupt as e:  # every generation is damaged: nothing to resume from
            log.error("stopping: %s", e)
            raise SystemExit(EXIT_CORRUPT) from None
        if state is not None:
            cfg = RunConfig.from_dict({**json.loads(state["config"]), "steps": cfg.steps})
        with bus.session_scope(conf, retry_for=30.0) as session:  # a router may still be starting
            try:
                runlock.refuse_live_learner(session, cfg.run)
            except runlock.RunInUse as e:
                log.error("%s", e)
                raise SystemExit(runlock.EXIT_REFUSED) from None
            write_json(run_dir / rundir.CONFIG, cfg.to_dict())
            learner = Learner(cfg, session, run_dir, state)
            role.stop_on_signals(learner)
            workers = announce.WorkerCount(session, cfg, log)  # a split-role run short of M workers warns
            try:
                learner.serve()
            finally:
                workers.close()


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags)
@options.run_options()
def learner_command(
    run_opts: dict[str, Any], config: options.ConfigFile = None, connect: options.Connect = None,
    listen: options.Listen = None, zenoh_config: options.ZenohConfig = None, run_dir: options.RunDir = None,
    resume: Path = typer.Option(None, help="resume the run in this run directory from its checkpoint"),
    run_config: Path = typer.Option(None, help="a resolved config.json (written by `mam run`)"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging"),
) -> None:
    """Run the learner: replay buffer, K actors and n·K critics, weights and stats publisher."""
    role.setup_logging(verbose)
    if run_config is not None:
        cfg = RunConfig.from_dict(json.loads(run_config.read_text()))
    elif resume is not None:
        cfg = RunConfig.from_dict(json.loads((resume / rundir.CONFIG).read_text()))
    else:
        cfg = options.build_run_config(run_opts, config)
    steps = run_opts["steps"]
    if steps is not None and (run_config is not None or resume is not None):
        cfg = RunConfig.from_dict({**cfg.to_dict(), "steps": steps})
    options.check_precision(cfg)
    from services.preflight import require_device
    require_device(cfg.algo.device, log)  # a device torch does not see: exit 78 (EXIT_CONFIG) after one line
    if not listen and not connect and cfg.endpoint:
        listen = [cfg.endpoint]  # a resumed or launched learner comes back where its clients look
    listen = listen or ([] if connect or zenoh_config else [role.LISTEN_ALL])
    conf = bus.make_config(connect=connect, listen=listen, config_file=zenoh_config)
    if zenoh_config is None or "wait_before_close" not in zenoh_config.read_text():
        # A blocking put (weights, done) on a cut link holds the loop at most this long, then Zenoh
        # closes that transport (default 5 s; docs/ZENOH-NOTES.md, "Congestion").
        conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close", "1000000")
    announce.announce_learner(cfg, listen, connect, log)  # where it listens, what it waits for, budget notes
    directory = resume or run_dir or Path("runs") / cfg.run
    main(cfg, conf, directory, resume=resume is not None)


cli = app  # the `mam-learner` entry point


if __name__ == "__main__":
    cli()
