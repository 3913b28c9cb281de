"""`mam-learner`: replay buffer, all K actors and n·K critics, checkpoints.

One loop, Algorithm 1's iterations in lock-step (mam_core/algorithm1.py, services/roles/lockstep.py):
stage the workers' transitions per slot, insert iteration i's rows in slot order, make its
updates (the referee's elimination where the plan places it), publish weights when they change
and the snapshots the referee judges, stats a few times a second, checkpoint
(services/roles/checkpoint.py), and end the run with the plan's last iteration. Its state is a
`LearnerState` (services/roles/learner_state.py) that its helpers take: learner_files.py, outbox.py.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import torch
import typer

from mam_core import arithmetic, gemm, optim_start
from mam_core.agent import EnvSpec, MultiActorAgent, pick_device
from mam_core.algorithm1 import Algorithm1
from mam_core.pacing import CheckpointRule
from mam_core.replay import ReplayBuffer, ReplayLog
from services.messaging import bus, keys
from services.messaging.codec import Allocation, Done, MessageError, TransitionSpec
from services.roles import learner_files, role, tb
from services.roles.checkpoint import (
    EXIT_CORRUPT,
    CheckpointCorrupt,
    exit_on_write_error,
    load_checkpoint,
    replay_dir,
)
from services.roles.intake import Intake
from services.roles.learner_state import LearnerState, LogRates
from services.roles.lockstep import SlotStage
from services.roles.outbox import Outbox, Watches
from services.run import announce, cpu, options, preflight, rundir, runlock
from services.run.binding import SlotBinding
from services.run.config import RunConfig
from services.run.rundir import JsonlWriter, write_json

log = logging.getLogger("mam.learner")

STATS_PERIOD_S = 0.1  # stats this often while updating; four times as often while waiting for data
LOG_PERIOD_S = 1.0
HEARTBEAT_S = 2.0  # config re-published this often
LEAVE_WITHIN_S = 20.0  # after the run's last file: the most its teardown may take (role.leave_within)
STOP_GRACE_S = 2.0  # a stop after updates made ahead of an iteration's rows waits this long for them
INBOX_STAGE_AHEAD = 1024  # more queued after an iteration: all staged at once (a resend of thousands of batches)


class Learner:
    def __init__(self, cfg: RunConfig, session: Any, run_dir: Path, resume: dict[str, Any] | None = None) -> None:
        self.cfg, self.algo, self.session, self.run_dir = cfg, cfg.algo, session, run_dir
        self.id = f"{socket.gethostname()}-{os.getpid()}"
        # raised durably at every start; roles follow the highest epoch; a learner that sees a higher one stops
        self.epoch = learner_files.next_epoch(run_dir)
        self.incarnation = f"e{self.epoch}-{uuid.uuid4().hex[:12]}"
        self.spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
        self.device = pick_device(self.algo.device)
        torch.manual_seed(self.algo.seed)
        threads = gemm.use_learner_threads(cfg.learner_threads)  # mam_core/gemm.py
        arith = arithmetic.status()  # what this process computes with: the log says it (benches check it)
        log.info("arithmetic %s, GEMMs %s, %s%s", arith["arithmetic"], arith["gemm"], threads,
                 f"; machine-bound: {arith['machine_bound']}" if arith["machine_bound"] else "")
        optim_start.defer_dynamo_import()  # building the agent imports nothing: its config goes out ~1 s sooner
        agent = MultiActorAgent(self.algo, self.spec, self.device)
        plan = Algorithm1.for_run(self.algo, cfg.steps)  # every "when" of the run
        buffer = ReplayBuffer(plan.replay_capacity(self.algo.buffer_size), self.spec.obs_dim, self.spec.act_dim,
                              self.device, self.algo.seed)
        spec = TransitionSpec(self.spec.obs_dim, self.spec.act_dim, self.algo.actors, max_rows=4096,
                              max_action=max(self.spec.max_action))
        max_message = spec.max_rows * (2 * self.spec.obs_dim + self.spec.act_dim + 2) * 4 + (1 << 16)
        intake = Intake(buffer, spec, max_message, SlotBinding(cfg.slot_binding))
        intake.incarnation = self.incarnation
        replay_log = ReplayLog(replay_dir(run_dir)) if cfg.save_replay else None
        checkpoints = CheckpointRule(cfg.checkpoint_every, cfg.checkpoint_rows, cfg.checkpoint_seconds)
        # What the checkpoint saves and the helpers (learner_files.py, outbox.py) take: learner_state.py
        self.state = LearnerState(plan, agent, buffer, replay_log, intake, checkpoints)
        self.agent, self.plan, self.buffer, self.intake = agent, plan, buffer, intake
        self.progress = self.state.progress  # (restored in place)
        self.stop_requested = False
        self.mid_iteration = False  # half an iteration (stopped in the elimination's wait)
        if resume is not None:
            learner_files.restore(self.state, resume, run_dir, self.algo)

    @property
    def iteration(self) -> int:
        """Iterations whose updates are done."""
        return self.progress.iteration

    @property
    def inexact(self) -> str:
        """Why the run is not exact ("" while it is)."""
        return self.progress.inexact

    def serve(self) -> None:
        run, s = self.cfg.run, self.session
        self.token = bus.declare_alive(s, run, "learner", self.id)
        # A worker or referee that comes up (a start, a restart) gets what it may have missed as soon as
        # the loop waits, not a heartbeat later: it subscribes before it declares its token.
        self.joined = threading.Event()
        workers, referees = (bus.watch_alive(s, run, r, on_change=self.on_role_change) for r in ("worker", "referee"))
        self.allocation = bus.Latest.subscribe(s, keys.allocation(run))
        self.watches = Watches(workers, referees, bus.Latest(late_join=False).subscribe(
            s, keys.role_stats_all(run, "referee")))  # the referee's `events` and `final`
        self.rivals = bus.Latest(late_join=False).subscribe(s, keys.learner_stats(run))  # a higher epoch: stale
        self.inbox = bus.Inbox(maxsize=8192).subscribe(s, keys.transitions_all(run))
        self.episode_queries = bus.Answers(s, keys.episode_all(run))
        self.out = Outbox(s, self.cfg, self.state, self.id, self.incarnation, self.watches)
        self.board = tb.RunBoard(self.run_dir, "learner")  # RUN_DIR/tb/learner: the JSONL rows' scalars
        self.log_writer = self.board.tee(JsonlWriter(self.run_dir / rundir.LEARNER_LOG), tb.learner_scalars)
        self.bias_writer = (self.board.tee(JsonlWriter(self.run_dir / rundir.BIAS), tb.bias_scalars)
                            if self.cfg.bias_every else None)
        self.out.config()
        self.worker_count = announce.WorkerCount(s, self.cfg, log)  # a split-role run short of M workers warns
        try:
            self._loop()
        finally:
            self.worker_count.close()
            w = self.watches
            for closable in (self.inbox, self.episode_queries, self.allocation, w.referee_reports, self.rivals,
                             w.workers, w.referees, self.log_writer, self.bias_writer, self.board):
                if closable is not None:
                    closable.close()

    # -- the loop: Algorithm 1's iterations in lock-step ------------------------------------------
    def _loop(self) -> None:
        """Iterations of the plan: iteration i's rows in slot order, then its updates."""
        plan, p, stage = self.plan, self.progress, self.state.stage
        self.out.restore(self.state.carried)  # lag B > 0, a referee behind the checkpoint
        self.out.weights(all_actors=True)
        self.state.checkpoints.mark(self.agent.updates, p.env_steps, time.monotonic())
        self.checkpoint()  # at once: a learner killed early resumes from here
        self.stats_due, self.heartbeat, self.log_row = map(role.Every, (STATS_PERIOD_S, HEARTBEAT_S, LOG_PERIOD_S))
        self.state.rates = LogRates((p.env_steps, self.agent.updates, time.monotonic()))
        self.out.snapshots_after(p.iteration)
        while not self.stop_requested:
            index = p.iteration + 1
            if index > plan.iterations:
                self.finish()
                return
            it = plan.iteration(index)
            versions = list(self.agent.versions)  # before its updates (the intake's lag counters)
            early = None if stage.ready(index, it.slots) else plan.updates_ahead(it, self.agent, self.buffer,
                                                                                    self.apply_elimination)
            p.ahead = early.made if early is not None else 0  # made before the rows are in
            waited = time.perf_counter()
            while not stage.ready(index, it.slots) and not (  # line 9; a stop after updates ahead: STOP_GRACE_S
                    self.stop_requested and (not p.ahead or time.perf_counter() - waited > STOP_GRACE_S)):
                self.receive(stage, timeout=0.002)
                p.awaiting = tuple(stage.missing(index, it.slots))
                self.idle_duties(f"iteration {index}'s rows from slots {list(p.awaiting)}", waited)
            p.awaiting = ()
            p.wait_s += time.perf_counter() - waited
            if not stage.ready(index, it.slots):  # stopped
                break
            rows, sources, used = stage.take(index, it.slots)
            self.intake.insert(rows, sources)
            p.env_steps += len(it.slots)
            for batch, _ in sources:
                if why := self.state.digests.foreign(batch):  # a row acted with weights this learner never made
                    p.break_exact(why)
            self.state.episodes.inserted(index, it.slots, sources)
            for batch in used:
                if self.intake.admit(batch):
                    self.intake.count(batch, versions)
            if early is None:
                metrics = plan.run_updates(it, self.agent, self.sample, self.apply_elimination)
            else:  # those that would sample the rows, now that they are in
                metrics = plan.rest_of(it, early, self.agent, self.buffer, self.apply_elimination)
            p.metrics, p.ahead = metrics or p.metrics, 0
            if it.eliminate and p.survivor is None:  # stopped in the elimination's wait: half an iteration
                self.mid_iteration = True
                break
            p.iteration = index
            if plan.weights_change(index):
                self.out.weights()
            self.out.snapshots_after(index)
            bias = plan.crossing(index, self.cfg.bias_every)
            if bias is not None:
                learner_files.measure_bias(self.state, self.cfg, self.bias_writer, bias)
            now = time.monotonic()
            if self.stats_due.due(now):
                self.out.stats()
            if self.log_row.due(now):
                learner_files.write_log(self.state, self.log_writer, now)
            if self.heartbeat.due(now):
                self.out.config()
                self.out.remind_referee()
                learner_files.fence(self.rivals, self.incarnation, self.cfg.run)
            if self.state.checkpoints.due(self.agent.updates, p.env_steps, now):
                self.checkpoint()
            if self.inbox.qsize() > INBOX_STAGE_AHEAD:  # a resend of thousands of batches: staged before the
                self.receive(stage, timeout=0.0, max_items=self.inbox.qsize())  # inbox sheds any of it
        # Stopped by a signal: keep a usable checkpoint (of the last whole iteration); the run is not done.
        if not self.mid_iteration:  # (a row's counts are those of whole iterations)
            learner_files.write_log(self.state, self.log_writer)
        if not self.mid_iteration and not p.ahead:  # (a checkpoint would hold updates without their rows)
            self.checkpoint()

    def checkpoint(self) -> None:
        learner_files.checkpoint(self.state, self.cfg, self.run_dir, self.out.kept())

    def on_role_change(self, _role: str, _id: str, alive: bool) -> None:
        """(On Zenoh's thread.) A role came up: `idle_duties` resends."""
        if alive:
            self.joined.set()

    def sample(self) -> Any:  # `agent.sampler`: on a GPU, indices staged for the CUDA graphs
        return self.agent.sampler(self.buffer, self.algo.batch_size)()

    def idle_duties(self, awaited: str, since: float, between_iterations: bool = True) -> None:
        """While the loop waits: stats, config and log rows; after HEARTBEAT_S, what a role may
        have missed once more; every `stall_timeout`, a line saying what is awaited. Inside an
        iteration (its rows in, its updates not all made) no learner.jsonl row: a row's counts
        are those of whole iterations."""
        now = time.monotonic()
        if self.stats_due.due(now, STATS_PERIOD_S / 4):
            self.out.stats()
        if self.joined.is_set():
            self.joined.clear()
            self.out.resend()
        if self.heartbeat.due(now):
            self.out.config()
            learner_files.fence(self.rivals, self.incarnation, self.cfg.run)
            if time.perf_counter() - since > HEARTBEAT_S:  # late: something may be lost
                self.out.resend()
        if between_iterations and self.log_row.due(now):
            learner_files.write_log(self.state, self.log_writer, now)
        limit, waited = self.cfg.stall_timeout, time.perf_counter() - since
        if limit > 0 and waited > limit and now - getattr(self, "_stall_note", 0.0) > limit:
            self._stall_note = now
            log.warning("waiting %.0f s for %s; %d workers live, referee %s", waited, awaited,
                        len(self.watches.workers.live()), "live" if self.watches.referees.live() else "gone")

    def receive(self, stage: SlotStage, timeout: float, max_items: int = 256) -> None:
        """Stage what arrived; follow the referee."""
        p = self.progress
        items = self.inbox.drain(max_items=max_items)
        if not items and timeout > 0:
            item = self.inbox.get(timeout=timeout)
            items = [item] if item is not None else []
        for item in items:
            batch = self.intake.validate(item, self.agent.versions)
            if batch is None:
                continue
            if stage.holds(batch):
                continue  # a resend of a batch still staged: it is counted once, when it is used
            staged, why, trimmed = stage.add(batch)
            if not staged and not why and not trimmed:  # held back (SlotStage.add): its rows come again
                continue
            for reason in (why, *batch.inexact_reasons(self.cfg.env_id)):
                p.break_exact(reason)
            new = staged or self.intake.admit(batch)  # not staged: the tracker sees it now (redundant, or new)
            if trimmed and new:  # rows of iterations the slot has: skipped, but for those in the replay already
                rest = trimmed - min(trimmed, self.intake.own_rows(batch))
                if rest:
                    self.intake.skip(batch, rest)
        self.episode_queries.poll(lambda key, _: self.state.episodes.reply(key, stage, self.buffer, self.id,
                                                                           self.out.next_seq))
        self.follow_allocation()
        if not p.referee_seen and self.watches.referees.live():
            p.referee_seen = True  # (finish() names a referee that never came)

    def apply_elimination(self) -> None:
        """The referee's survivor at C (it evaluates the actors after iteration C-1 while C's rows come in)."""
        since, p = time.perf_counter(), self.progress
        p.awaiting = (-1,)
        while p.decided_survivor is None and not self.stop_requested:
            self.follow_allocation()
            self.idle_duties("the referee's elimination", since, between_iterations=False)
            self.allocation.wait_fresh(timeout=0.05)
        p.awaiting = ()
        if p.decided_survivor is None:
            return  # stopping: the checkpoint is of the iteration before
        p.survivor = p.decided_survivor
        self.agent.eliminate(p.survivor)
        log.info("eliminated all actors but %d at iteration %d", p.survivor, self.plan.elimination)

    def follow_allocation(self) -> None:
        """The survivor, once the referee has decided it (applied where the plan places it)."""
        item = self.allocation.fresh().get(keys.allocation(self.cfg.run))
        if item is None:
            return
        try:
            alloc = Allocation.from_bytes(item.payload, self.algo.actors)
        except MessageError as e:
            self.state.allocation_rejects.reject("allocation", e)
            return
        if alloc.survivor is not None:
            self.progress.decided_survivor = alloc.survivor

    def finish(self) -> None:
        """Budget reached: final weights, checkpoint, then tell everyone until they have left."""
        self.worker_count.close()  # the workers leave now: no warning about their count
        self.out.weights(all_actors=True)
        learner_files.write_log(self.state, self.log_writer)
        self.checkpoint()
        self.out.stats(done=True)
        msg = Done("budget", self.progress.env_steps, self.agent.updates)
        deadline = time.monotonic() + 10.0
        while True:  # the last put before close can be lost: repeat until the workers have gone (tokens vanish)
            self.out.done(msg.to_bytes(self.id, self.out.next_seq()))
            self.out.stats(done=True)
            if not self.watches.workers.live() or time.monotonic() > deadline:
                break
            learner_files.count_late(self.intake, self.agent.versions, self.inbox.drain())
            time.sleep(0.1)
        self.inbox.close()
        learner_files.count_late(self.intake, self.agent.versions, self.inbox.drain())
        self.out.wait_for_referee(msg, lambda: self.stop_requested)
        learner_files.write_transport(self.state, self.run_dir, self.inbox.dropped)
        role.leave_within(LEAVE_WITHIN_S, "the learner")  # the run is done and recorded: nothing left to lose


def main(cfg: RunConfig, conf: Any, run_dir: Path, resume: bool = False) -> None:
    def build(cfg: RunConfig, session: Any) -> Learner:
        try:
            state = load_checkpoint(run_dir) if resume else None
        except CheckpointCorrupt as e:  # every generation is damaged: nothing to resume from
            log.error("stopping: %s", e)
            raise SystemExit(EXIT_CORRUPT) from None
        problem = preflight.gemm_problem(state.get("gemm"), arithmetic.status()["gemm"]) if state else ""
        if problem:
            log.error("%s %s", preflight.CONFIG_ERROR, problem)
            raise SystemExit(preflight.EXIT_CONFIG)
        if state is not None:  # this part's endpoint (`mam run` gave it a new port): a later restart listens there
            cfg = RunConfig.from_dict({**json.loads(state["config"]), "steps": cfg.steps,
                                       **({"endpoint": cfg.endpoint} if cfg.endpoint else {})})
        try:
            runlock.refuse_live_learner(session, cfg.run)
        except runlock.RunInUse as e:
            log.error("%s", e)
            raise SystemExit(runlock.EXIT_REFUSED) from None
        write_json(run_dir / rundir.CONFIG, cfg.to_dict())
        return Learner(cfg, session, run_dir, state)

    with exit_on_write_error(run_dir):  # a full disk: one line naming the path, exit EXIT_WRITE_ERROR
        role.serve_role("learner", conf, build, run=cfg.run, run_dir=run_dir, cfg=cfg, log=log)


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
    cpu.check_precision(cfg)
    preflight.require_device(cfg.algo.device, log)  # a device torch does not see: exit 78 (EXIT_CONFIG), one line
    preflight.require_gemm(log)  # portable GEMM kernels that cannot be built here (no C compiler): likewise
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
    role.exit_finished()  # its files are closed: skip torch's teardown, which `mam run` would wait for


cli = app  # the `mam-learner` entry point


if __name__ == "__main__":
    cli()
