"""`mam-worker`: one environment slot. Runs the actor the allocation gives it, publishes transitions.

The worker needs only `--run` and `--connect`: the env, K and the noise come from the learner's
config topic. It keeps a CPU copy of every actor (refreshed from the weights topic), explores
with Gaussian noise (uniform random actions during the run's first `start_steps`), sends
transitions in small batches tagged with worker id, incarnation, actor and policy version,
pauses when the learner's credit is used up, and exits when the run is done.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import socket
import time
import uuid
from collections import deque
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from mam_core.algorithm1 import Algorithm1
from mam_core.envs import make_env  # registers AppleCollect-v0; imports `module:EnvId` modules
from mam_core.policy import EnvSpec
from mam_core.schedule import Schedule
from mam_core.slot import SlotStreams, act, uniform
from services import bus, keys, options, role, rundir
from services.codec import Allocation, LearnerStats, MessageError, TransitionBatch
from services.options import RunConfig, write_json

log = logging.getLogger("mam.worker")

MAX_BATCH_AGE_S = 0.05  # a partial batch is sent after this long
STATUS_EVERY_S = 10.0
ENV_RETRIES = 10  # consecutive failed resets before the env is made anew; as many again: the worker exits
FAULTS = ("step_exception", "reset_exception", "nonfinite_obs", "nonfinite_reward")


class EnvFault(Exception):
    """The simulator raised or returned something unusable (counted by kind)."""

    def __init__(self, kind: str, detail: str = "") -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


class Worker:
    def __init__(self, cfg: RunConfig, session: Any, worker_id: str, slot_index: int = 0,
                 run_dir: Path | None = None, generation: int = 0) -> None:
        self.run_dir = run_dir
        self.cfg = cfg
        self.algo = cfg.algo
        self.session = session
        self.id = worker_id
        self.incarnation = uuid.uuid4().hex[:12]
        self.rejects = bus.RejectLog(log, "message")
        self.env = make_env(cfg.env_id, cfg.env_kwargs)
        self.spec = EnvSpec.from_env(self.env)
        self.max_action = np.asarray(self.spec.max_action, np.float32)
        # The slot's streams (mam_core.seeding): from --seed, the slot and the restart generation only.
        self.slot = slot_index
        self.streams = SlotStreams.for_slot(self.algo.seed, slot_index, generation)
        self.rng = self.streams.noise
        self.exact = cfg.collection == "exact" and generation == 0
        # Simulator faults: the episode is dropped, the env reset, the fault counted (by kind).
        self.faults = {kind: 0 for kind in FAULTS}
        self.dropped_rows = 0  # unsent rows of faulty episodes
        self.dropped_episodes = 0
        self.env_remade = 0
        self.env.action_space.seed(self.streams.action_seed)
        self.obs = self.reset_env(seed=self.streams.reset_seed)
        # Exactly once across a learner restart: batches the learner has not yet checkpointed
        # are kept and resent to its next incarnation (bounded by cfg.resend_rows).
        self.retain = cfg.save_replay
        self.unacked: deque[TransitionBatch] = deque()
        self.unacked_rows = 0
        self.unacked_dropped_rows = 0  # over the bound: not kept (if then lost, a counted gap)
        self.resent_rows = 0
        self.resends = 0
        self.put_rows = 0  # rows put on the wire, resends included (in-flight accounting)
        self.batch_log = None
        # numpy forwards, no torch in a worker: a one-row torch forward costs ~100 µs of dispatch
        # between env steps, this ~14 µs, and importing torch ~3 s and ~180 MB (docs/PERFORMANCE.md)
        self.follower = role.WeightsFollower.for_algo(self.algo, self.spec, self.rejects)
        self.actors = self.follower.actors
        self.policies = [self.actors.policy(k) for k in range(self.algo.actors)]
        self.versions = self.follower.versions  # -1: no weights yet
        self.actor = slot_index % self.algo.actors  # until the first allocation arrives
        self.idle = False  # after the elimination with one environment slot, and this is not it
        self.random_until = Schedule.for_run(self.algo, cfg.steps).random_until  # transitions
        self.stats: LearnerStats | None = None
        self.batch_seq = 0
        self.sent_rows = 0
        self.sent_base = 0  # sent_rows when the current learner incarnation appeared
        self.learner_incarnation: str | None = None
        self.episode_return = 0.0
        self.finished_returns: list[float] = []
        self.stop_requested = False
        self.last_note = 0.0
        self._reset_pending()

    def _reset_pending(self) -> None:
        n, o, a = self.cfg.send_batch, self.spec.obs_dim, self.spec.act_dim
        self.p_obs = np.empty((n, o), np.float32)
        self.p_action = np.empty((n, a), np.float32)
        self.p_reward = np.empty(n, np.float32)
        self.p_next = np.empty((n, o), np.float32)
        self.p_term = np.empty(n, np.bool_)
        self.p_n = 0
        self.p_episode = 0  # pending rows before this index belong to finished episodes
        self.p_actor = -1
        self.p_version = -1
        self.p_iteration = -1  # exact mode: the iteration of the first pending row
        self.p_from = ""  # the learner incarnation of the pending rows' weights
        self.p_started = time.monotonic()

    # -- the loop -----------------------------------------------------------------------------
    def serve(self) -> None:
        run, s = self.cfg.run, self.session
        self.pub = bus.declare_reliable_publisher(s, keys.transitions(run, self.id))
        self.report = role.RoleReport(s, run, "worker", self.id)
        self.weights = bus.Latest.subscribe(s, keys.weights_all(run), screen=self.follower.admits)
        self.allocation = bus.Latest.subscribe(s, keys.allocation(run))
        self.stats_sub = bus.Latest.subscribe(s, keys.learner_stats(run))
        self.done = bus.Latest.subscribe(s, keys.done(run))
        self.token = bus.declare_alive(s, run, "worker", self.id)
        if self.run_dir is not None:  # one line per batch, before it is put: what a killed worker had sent
            path = self.run_dir / rundir.WORKERS / f"{self.id}-{self.incarnation}.batches"
            path.parent.mkdir(parents=True, exist_ok=True)
            self.batch_log = open(path, "a", buffering=1)
        log.info("worker %s (incarnation %s) on %s, run %s", self.id, self.incarnation, self.cfg.env_id, run)
        try:
            self._loop()
        finally:
            self.flush()
            self.publish_report(force=True)
            self.write_report()
            if self.batch_log is not None:
                self.batch_log.close()
            self.token.undeclare()
            for sub in (self.weights, self.allocation, self.stats_sub, self.done):
                sub.close()

    def _loop(self) -> None:
        if self.exact:
            if self._exact_loop():
                return
            self.exact = False
            self.flush()
            log.info("the run is no longer exact: collecting asynchronously")
        idle_since: float | None = None
        last_status = stall_note = time.monotonic()
        while not self.stop_requested:
            if time.monotonic() - last_status > STATUS_EVERY_S:
                st = self.stats
                link = "" if role.connected(self.session) is not False else \
                    "; no link to any router or peer: the router or the learner's host is gone"
                log.info("sent %d rows, actor %d, weights %s, learner at %s/%s%s", self.sent_rows, self.actor,
                         self.versions, st.env_steps if st else "?", st.accept_until if st else "?", link)
                last_status = time.monotonic()
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                log.info("run is done after %d transitions from this worker", self.sent_rows)
                return
            self.refresh()
            if self.idle or not self.may_send():
                self.flush()
                idle_since = idle_since or time.monotonic()
                limit, now = self.cfg.stall_timeout, time.monotonic()
                if 0 < limit < now - idle_since and now - stall_note > limit:  # the split role's stall note
                    stall_note, st = now, self.stats
                    log.warning("paused for %.0f s: %s", now - idle_since, "no learner stats" if st is None else
                                "idle after the elimination" if self.idle else
                                f"credit used up (learner at {st.env_steps}, accept_until {st.accept_until}, "
                                f"{self.in_flight()} rows of mine not yet counted)")
                self.stats_sub.wait_fresh(timeout=0.05)  # pause (rate limiter or no learner): no spinning
                continue
            idle_since = None
            random_phase = self.in_random_phase()
            if not random_phase and self.versions[self.actor] < 0:
                if time.monotonic() - self.last_note > 5.0:
                    log.info("waiting for the weights of actor %d", self.actor)
                    self.last_note = time.monotonic()
                self.weights.wait_fresh(timeout=0.05)  # weights for our actor not here yet
                continue
            self.step(random_phase)

    # -- exact mode: iteration by iteration (services/exact.py) ---------------------------------
    def _exact_loop(self) -> bool:
        """Step this slot's iterations of the plan as soon as the allocation and the weights
        they need are here. True when the run is done (or stopped), False when it is no
        longer exact (the caller collects asynchronously from here)."""
        plan = Algorithm1.for_run(self.algo, self.cfg.steps)
        name = keys.slot_name(self.slot)
        decisions: dict[int, dict[str, int]] = {}  # iteration of a competition -> its slots
        index, need = 1, 0  # the next iteration to step; the decision that applies to it
        waiting_since = time.monotonic()
        while not self.stop_requested:
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                log.info("run is done after %d transitions from this worker", self.sent_rows)
                return True
            if not self.refresh_exact(decisions):
                return False
            it = plan.iteration(index) if index <= plan.iterations else None
            if it is None or self.slot not in it.slots:
                self.flush()  # this slot's part of the run is over (the survivor runs slot 0 after C)
                self.done.wait_fresh(timeout=0.1)
                continue
            slots = decisions.get(need)
            actor = None if slots is None else slots.get(name)
            version = -1 if it.random else plan.version_for(index)
            if actor is None or (version >= 0 and self.versions[actor] < version):
                self.flush()
                if time.monotonic() - waiting_since > STATUS_EVERY_S:
                    log.info("iteration %d waits for %s", index, "the allocation of iteration %d" % need
                             if actor is None else f"actor {actor} at version {version} (have {self.versions[actor]})")
                    waiting_since = time.monotonic()
                (self.allocation if actor is None else self.weights).wait_fresh(timeout=0.05)
                continue
            waiting_since = time.monotonic()
            self.actor = actor
            if self.p_n and (actor != self.p_actor or version != self.p_version):
                self.flush()
            if self.p_n == 0:
                self.p_iteration = index
            self.step(it.random)
            if it.competes:  # the allocation it draws applies from the next iteration on
                need = index
                decisions = {i: s for i, s in decisions.items() if i >= need}
            index += 1
        return True

    def refresh_exact(self, decisions: dict[int, dict[str, int]]) -> bool:
        """Weights, the referee's decisions (with the one before: none is missed), the learner's
        stats. False when the run stopped being exact (a restarted role)."""
        self.follower.follow(self.weights, self.stats)
        item = self.allocation.fresh().get(keys.allocation(self.cfg.run))
        if item is not None:
            try:
                alloc = Allocation.from_bytes(item.payload, self.algo.actors)
            except MessageError as e:
                self.rejects.reject("referee", e)
            else:
                if alloc.iteration is None:
                    return False  # a restarted referee allocates asynchronously
                decisions[alloc.iteration] = dict(alloc.slots)
                if alloc.previous is not None:
                    decisions.setdefault(alloc.previous[0], dict(alloc.previous[1]))
        item = self.stats_sub.fresh().get(keys.learner_stats(self.cfg.run))
        if item is not None:
            try:
                st = LearnerStats.from_bytes(item.payload)
            except MessageError as e:
                self.rejects.reject("learner", e)
            else:
                restarted = self.learner_incarnation is not None and st.incarnation != self.learner_incarnation
                self.stats = st
                self.on_stats(st)
                if restarted or not st.exact:
                    return False
        return True

    def publish_report(self, force: bool = False) -> None:
        """This worker's counters on mam/<run>/stats/worker-<id> (rejections are visible there)."""
        self.report.publish({"incarnation": self.incarnation, "sent_rows": self.sent_rows, "batches": self.batch_seq,
                             "actor": self.actor, "rejected": self.rejects.counts(), **self.fault_counters()},
                            seq=self.batch_seq, force=force)

    def write_report(self) -> None:
        """What this incarnation sent (compared with the learner's transport.json in tests)."""
        if self.run_dir is None:
            return
        write_json(self.run_dir / rundir.WORKERS / f"{self.id}-{self.incarnation}.json", {
            "worker": self.id, "incarnation": self.incarnation, "sent_rows": self.sent_rows,
            "batches": self.batch_seq, "rejected": self.rejects.counts(), **self.fault_counters()})

    def fault_counters(self) -> dict[str, Any]:
        """Simulator faults and resends (role_stats topic and workers/*.json)."""
        return {"env_faults": dict(self.faults), "dropped_rows": self.dropped_rows,
                "dropped_episodes": self.dropped_episodes, "env_remade": self.env_remade,
                "resent_rows": self.resent_rows, "resends": self.resends, "unacked_rows": self.unacked_rows,
                "unacked_dropped_rows": self.unacked_dropped_rows}

    def refresh(self) -> None:
        self.follower.follow(self.weights, self.stats)
        item = self.allocation.fresh().get(keys.allocation(self.cfg.run))
        if item is not None:
            try:
                alloc = Allocation.from_bytes(item.payload, self.algo.actors)
                if self.id in alloc.slots:
                    self.actor = alloc.slots[self.id]
                elif alloc.survivor is not None:
                    self.actor = alloc.survivor
                # The survivor runs one environment (I_e = 1): the other slots wait.
                self.idle = alloc.survivor is not None and self.algo.single_env and self.id not in alloc.slots
            except MessageError as e:
                self.rejects.reject("referee", e)
        item = self.stats_sub.fresh().get(keys.learner_stats(self.cfg.run))
        if item is not None:
            try:
                self.stats = LearnerStats.from_bytes(item.payload)
            except MessageError as e:
                self.rejects.reject("learner", e)
            else:
                self.on_stats(self.stats)

    def on_stats(self, st: LearnerStats) -> None:
        """Drop what the learner has checkpointed; on a new learner incarnation resend the rest."""
        self.trim_acked(st)
        if st.incarnation != self.learner_incarnation:
            first = self.learner_incarnation is None
            self.learner_incarnation = st.incarnation
            self.sent_base = self.put_rows  # a new learner: the in-flight count starts again
            if self.unacked and not first:
                self.resend()
            log.info("learner %s is up: sending again", self.learner_incarnation or "?")

    def trim_acked(self, st: LearnerStats) -> None:
        mine = st.per_worker.get(self.id)
        if not mine or mine.acked_incarnation != self.incarnation or mine.acked_seq is None:
            return
        acked = mine.acked_seq
        while self.unacked and self.unacked[0].batch_seq <= acked:
            self.unacked_rows -= self.unacked.popleft().rows

    def resend(self) -> None:
        """Every kept batch again, in order, flagged: the learner keeps those it has not got."""
        n = 0
        for batch in self.unacked:
            self.pub.put(dataclasses.replace(batch, resend=True).to_bytes())
            n += batch.rows
        self.resent_rows += n
        self.resends += 1
        self.put_rows += n
        log.info("resent %d rows in %d batches (seq %d..%d) to the new learner", n, len(self.unacked),
                 self.unacked[0].batch_seq, self.unacked[-1].batch_seq)

    def in_flight(self) -> int:
        """Rows put for the current learner incarnation that it has not reported yet.

        A restarted learner (new incarnation) starts the count again: what was sent to the old
        one was received by it, is resent (kept batches), or died with it.
        """
        if self.stats is None:
            return self.put_rows - self.sent_base
        mine = self.stats.per_worker.get(self.id)
        seen = 0
        if mine and mine.incarnation == self.incarnation:
            seen = (mine.incarnation_rows or 0) + (mine.redundant_rows or 0) + (mine.rejected_rows or 0)
        return max(self.put_rows - self.sent_base - seen, 0)

    def may_send(self) -> bool:
        """Rate limiter: keep this worker's unreported rows within its share of the learner's credit."""
        st = self.stats
        if st is None or st.done:
            return False
        room = st.accept_until - st.env_steps
        share = max(room // max(st.workers, 1), 1) if room > 0 else 0
        mine = st.per_worker.get(self.id)
        if not mine or mine.incarnation != self.incarnation:
            # Not yet counted among the learner's workers: one batch in flight until it is.
            share = min(share, self.cfg.send_batch)
        return self.in_flight() + self.p_n < share

    def in_random_phase(self) -> bool:
        st = self.stats
        return st is None or st.env_steps + self.in_flight() < self.random_until

    def step(self, random_phase: bool) -> None:
        if random_phase:
            action, actor, version = uniform(self.env), self.actor, -1
        else:
            actor, version = self.actor, self.versions[self.actor]
            action = act(self.policies[actor], self.obs, self.rng, self.algo, self.max_action)
        policy_from = self.follower.incarnations[actor] if version >= 0 else ""
        if self.p_n and (actor != self.p_actor or version != self.p_version or policy_from != self.p_from):
            self.flush()  # a batch carries one actor and one policy version (of one learner incarnation)
        try:
            next_obs, reward, terminated, truncated = self.env_step(action)
        except EnvFault as fault:
            self.env_fault(fault)
            return
        i = self.p_n
        self.p_obs[i] = self.obs
        self.p_action[i] = action
        self.p_reward[i] = reward
        self.p_next[i] = next_obs
        self.p_term[i] = terminated  # truncation is not terminal: the target still bootstraps
        self.p_actor, self.p_version, self.p_from = actor, version, policy_from
        if self.p_n == 0:
            self.p_started = time.monotonic()
        self.p_n += 1
        self.episode_return += reward
        if terminated or truncated:
            self.finished_returns.append(self.episode_return)
            self.episode_return = 0.0
            self.p_episode = self.p_n
            self.obs = self.reset_env()
        else:
            self.obs = next_obs
        if self.p_n >= self.cfg.send_batch or time.monotonic() - self.p_started > MAX_BATCH_AGE_S:
            self.flush()

    # -- the simulator, guarded ------------------------------------------------------------------
    def env_step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        """env.step, or EnvFault if it raises or returns a non-finite observation or reward."""
        try:
            next_obs, reward, terminated, truncated, _ = self.env.step(action)
            next_obs = np.asarray(next_obs, np.float32)
            reward = float(reward)
        except Exception as e:  # anything the simulator throws: this episode is lost, not the worker
            raise EnvFault("step_exception", f"{type(e).__name__}: {e}") from e
        if next_obs.shape != (self.spec.obs_dim,) or not np.isfinite(next_obs).all():
            raise EnvFault("nonfinite_obs", f"shape {next_obs.shape}")
        if not math.isfinite(reward):
            raise EnvFault("nonfinite_reward", repr(reward))
        return next_obs, reward, bool(terminated), bool(truncated)

    def reset_env(self, seed: int | None = None) -> np.ndarray:
        """A finite first observation: retries a failing reset, then makes the env anew,
        and gives up (the worker exits, its supervisor restarts it) if that fails too."""
        for attempt in range(2 * ENV_RETRIES):
            if attempt == ENV_RETRIES:
                log.warning("env reset failed %d times in a row: making %s anew", ENV_RETRIES, self.cfg.env_id)
                try:
                    self.env.close()
                except Exception:
                    pass
                self.env = make_env(self.cfg.env_id, self.cfg.env_kwargs)
                self.env_remade += 1
            try:
                obs, _ = self.env.reset(seed=seed) if seed is not None and attempt == 0 else self.env.reset()
                obs = np.asarray(obs, np.float32)
            except Exception as e:
                self.count_fault(EnvFault("reset_exception", f"{type(e).__name__}: {e}"))
                continue
            if obs.shape != (self.spec.obs_dim,) or not np.isfinite(obs).all():
                self.count_fault(EnvFault("nonfinite_obs", "after reset"))
                continue
            return obs
        raise RuntimeError(f"{self.cfg.env_id}: no usable reset in {2 * ENV_RETRIES} tries")

    def count_fault(self, fault: EnvFault) -> None:
        self.faults[fault.kind] += 1
        if self.faults[fault.kind] <= 3 or self.faults[fault.kind] % 100 == 0:
            log.warning("env fault %s (%d so far): %s", fault.kind, self.faults[fault.kind], fault.detail[:300])

    def env_fault(self, fault: EnvFault) -> None:
        """Drop the episode's rows that are not sent yet, reset, go on."""
        self.count_fault(fault)
        self.dropped_rows += self.p_n - self.p_episode
        self.dropped_episodes += 1
        self.p_n = self.p_episode
        self.episode_return = 0.0
        self.obs = self.reset_env()

    def flush(self) -> None:
        if self.p_n == 0:
            return
        n = self.p_n
        rows = (self.p_obs[:n], self.p_action[:n], self.p_reward[:n], self.p_next[:n], self.p_term[:n])
        if self.retain:  # kept for a resend: the pending arrays are reused
            rows = tuple(a.copy() for a in rows)
        batch = TransitionBatch(self.id, self.incarnation, self.batch_seq, self.p_actor, self.p_version,
                                *rows, tuple(self.finished_returns) or None,
                                iteration=self.p_iteration if self.exact else -1, slot=self.slot if self.exact else -1,
                                policy_from=self.p_from)
        if self.batch_log is not None:
            self.batch_log.write(f"{self.batch_seq} {n}\n")
        self.pub.put(batch.to_bytes())
        if self.retain:
            self.unacked.append(batch)
            self.unacked_rows += n
            while self.unacked_rows > self.cfg.resend_rows and len(self.unacked) > 1:
                dropped = self.unacked.popleft()
                self.unacked_rows -= dropped.rows
                self.unacked_dropped_rows += dropped.rows
        self.batch_seq += 1
        self.sent_rows += n
        self.put_rows += n
        self.finished_returns = []
        self.p_n = 0
        self.p_episode = 0


def main(run: str, conf: Any, worker_id: str, slot_index: int = 0, run_dir: Path | None = None,
         generation: int = 0) -> None:
    with bus.session_scope(conf, retry_for=30.0) as session:
        cfg = role.fetch_config(session, run, bus.RejectLog(log, "config"))
        worker = Worker(cfg, session, worker_id, slot_index, run_dir, generation)
        role.stop_on_signals(worker)
        worker.serve()


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags)
def worker_command(
    run: options.Run = None, connect: options.Connect = None, listen: options.Listen = None,
    zenoh_config: options.ZenohConfig = None,
    id: str = typer.Option(None, "--id", help="worker id (slot name); default HOST-PID"),  # noqa: A002
    slot: int = typer.Option(0, help="slot index (0..M-1): the slot's random streams (from --seed) and, in exact "
                             "mode, its place in each iteration"),
    generation: int = typer.Option(0, help="restarts of this slot so far (the launcher counts them): a restarted "
                                   "worker draws fresh streams and collects asynchronously"),
    run_dir: Optional[Path] = typer.Option(None, "--run-dir", help="the run directory for this worker's batch log "
                                           "(workers/ID-INCARNATION.batches) and report; default: none, neither is "
                                           "kept", rich_help_panel=options.RUN_PANEL),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging"),
) -> None:
    """Run one environment slot of a run (needs only --run and --connect)."""
    role.setup_logging(verbose)
    if not run:
        raise typer.BadParameter("--run NAME is required (the learner prints it and writes it to config.json)")
    options.check_run_name(run)
    worker_id = id or f"{socket.gethostname()}-{os.getpid()}"
    keys.check_name(worker_id, "worker id")
    main(run, role.client_config(connect, listen, zenoh_config), worker_id, slot, run_dir, generation)


cli = app  # the `mam-worker` entry point


if __name__ == "__main__":
    cli()
