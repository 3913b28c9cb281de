"""What the learner writes and reads back (services/roles/learner.py): its checkpoints and
the counters they carry, learner.jsonl rows, and the Eq. 17 rows of bias.jsonl."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from mam_core.evaluation import estimation_bias
from mam_core.seeding import bias_seed
from services.messaging.codec import LearnerStats, MessageError
from services.roles import role
from services.roles.checkpoint import save_checkpoint
from services.roles.outbox import PublishedDigests
from services.run import codecheck, rundir, runlock
from services.run.rundir import write_json

if TYPE_CHECKING:
    from services.roles.learner import Learner

log = logging.getLogger("mam.learner")


def checkpoint(lr: Learner) -> None:
    started = time.monotonic()
    counters = {"env_steps": lr.env_steps, "per_worker": json.dumps(lr.intake.tracker.per_sender()),
                "stream_rows": json.dumps(lr.intake.stream_rows),
                "stream_skipped": json.dumps(lr.intake.stream_skipped),
                "stream_partial": json.dumps(lr.intake.stream_partial), "referee_seen": int(lr.referee_seen),
                "iteration": lr.iteration, "inexact": lr.inexact, "episodes": lr.episodes.to_json(),
                "digests": lr.digests.to_json(),
                "retired": json.dumps(sorted(lr.stage.retired | lr.retired) if lr.stage is not None
                                      else sorted(lr.retired)),
                "wall_s": round(lr.wall_before + time.monotonic() - lr.started, 3)}
    path = save_checkpoint(lr.run_dir, lr.agent, lr.buffer, counters, lr.cfg, lr.replay_log,
                           survivor=lr.survivor,  # with policy.npz, in a verified generation
                           extra={"kept_weights": kept_weights_state(lr.out.kept_weights()),
                                  "kept_snapshots": kept_weights_state(lr.out.kept_snapshots())})
    lr.checkpoints.mark(lr.agent.updates, lr.env_steps, time.monotonic())
    if lr.replay_log is not None:  # only now on disk: workers may drop what the previous one holds
        lr.acked, lr.acked_newest = lr.acked_newest, lr.intake.checkpointed_prefixes()
    log.info("checkpoint %s at iteration %d, %d updates, %d transitions (%.2f s)", path, lr.iteration,
             lr.agent.updates, lr.env_steps, time.monotonic() - started)



def next_epoch(run_dir: Path) -> int:
    """This learner's epoch: one more than the run's last (RUN_DIR/learner_epoch.json, written
    durably before the learner publishes anything)."""
    last = rundir.read_json(run_dir / rundir.LEARNER_EPOCH).get("epoch", 0)
    epoch = (last if isinstance(last, int) and last >= 0 else 0) + 1
    write_json(run_dir / rundir.LEARNER_EPOCH, {"epoch": epoch}, durable=True)
    return epoch


def fence(lr: Learner) -> None:
    """The stats of a learner of a higher epoch on this run's key: another took the run over while
    this one was frozen or cut off. Stop at once, exit 73, without a checkpoint (the run's state
    is that one's now)."""
    for item in lr.rivals.fresh().values():
        try:
            other = LearnerStats.from_bytes(item.payload).incarnation
        except MessageError:
            continue
        if role.learner_order(other) > role.learner_order(lr.incarnation):
            log.error("stopping: learner %s (a higher epoch) serves run %r: this one (%s) is stale", other,
                      lr.cfg.run, lr.incarnation)
            raise SystemExit(runlock.EXIT_REFUSED)


def count_late(lr: Learner, items: list) -> None:
    """Batches that arrive after the last iteration (a resend): counted, never inserted."""
    for item in items:
        batch = lr.intake.validate(item, lr.agent.versions)
        if batch is not None:
            lr.intake.admit(batch)


def write_transport(lr: Learner) -> None:
    """transport.json at the end: the counters `mam run`'s audit holds against the workers' logs."""
    tracker = lr.intake.tracker
    write_json(lr.run_dir / rundir.TRANSPORT, {
        "env_steps": lr.env_steps, "iterations": lr.iterations, "updates": lr.updates,
        "lost": tracker.lost, "duplicates": tracker.duplicates, "rejected": lr.rejected(),
        "recovered": tracker.recovered, "redundant": tracker.redundant,
        "replay_rows": lr.buffer.inserted if lr.replay_log is not None else None,
        "wall_s": round(lr.wall_before + time.monotonic() - lr.started, 3),
        **lr.intake.transport(),
        "inbox_dropped": lr.inbox.dropped})  # shed before decoding when the inbox overflowed
    log.info("done: %d transitions, %d updates, lost %d, duplicates %d, rejected %d, survivor %s, %s; the final "
             "returns: the referee's %s", lr.env_steps, lr.agent.updates, tracker.lost, tracker.duplicates,
             lr.intake.rejects.total, "-" if lr.survivor is None else lr.survivor,
             "exact" if not lr.inexact else f"not exact ({lr.inexact})", lr.run_dir / rundir.SUMMARY)


def kept_weights_state(kept: list[tuple[int, int, int, dict[str, np.ndarray]]]) -> list[list[Any]]:
    """The versions a slot may still act with (Outbox.kept_weights) as checkpoint entries:
    [plan version, actor, its version, {name: tensor}]."""
    return [[key, k, version, {name: torch.from_numpy(a) for name, a in params.items()}]
            for key, k, version, params in kept]


def kept_weights_from(rows: Any, shapes: dict[str, tuple[int, ...]], actors: int) \
        -> list[tuple[int, int, int, dict[str, np.ndarray]]]:
    """`kept_weights_state` read back, every entry checked (ValueError naming the first that is not
    an actor of this run's shapes)."""
    out = []
    for row in rows if isinstance(rows, list) else [rows]:
        if not (isinstance(row, list) and len(row) == 4 and all(isinstance(x, int) for x in row[:3])
                and isinstance(row[3], dict)):
            raise ValueError(f"checkpoint kept_weights: not [version, actor, version, params]: {type(row).__name__}")
        key, k, version, params = row
        got = {name: tuple(t.shape) for name, t in params.items() if isinstance(t, torch.Tensor)}
        if not 0 <= k < actors or got != {name: tuple(s) for name, s in shapes.items()}:
            raise ValueError(f"checkpoint kept_weights: actor {k} version {version} is not of this run's shapes")
        out.append((key, k, version, {name: t.numpy().astype(np.float32) for name, t in params.items()}))
    return out


def restore(lr: Learner, state: dict[str, Any]) -> None:
    lr.agent.load_state_dict(state["agent"])
    c = state["counters"]
    lr.env_steps = int(c["env_steps"])
    if "replay" in state:  # checkpoints written before the chunked replay log
        lr.buffer.load_state_dict(state["replay"])
    if "replay_log" in state and lr.replay_log is not None:
        meta = state["replay_log"]
        lr.replay_log.restore(lr.buffer, meta["manifest"], int(meta["inserted"]), json.loads(meta["rng"]))
        if lr.buffer.inserted != lr.env_steps:
            raise ValueError(f"checkpoint counts {lr.env_steps} transitions, its replay {lr.buffer.inserted}")
    lr.intake.stream_rows = {k: int(v) for k, v in json.loads(c.get("stream_rows", "{}")).items()}
    lr.intake.stream_skipped = {k: int(v) for k, v in json.loads(c.get("stream_skipped", "{}")).items()}
    lr.intake.stream_partial = {k: (int(v[0]), int(v[1])) for k, v in json.loads(c.get("stream_partial", "{}")).items()}
    # The run had a referee: a learner resumed at its budget waits for it (its final evaluation).
    lr.referee_seen = bool(int(c.get("referee_seen", 0)))
    # Sequence numbers go on from the checkpoint: a gap then counts what died with the old
    # learner, until the workers' resends fill it.
    lr.intake.tracker.restore(json.loads(c.get("per_worker", "{}")))
    if lr.replay_log is not None:  # just verified: its rows need not be kept twice
        lr.acked = lr.acked_newest = lr.intake.checkpointed_prefixes()
    lr.iteration = int(c["iteration"]) if "iteration" in c else lr.plan.iteration_at(lr.env_steps)
    lr.wall_before = float(c.get("wall_s", 0.0))
    lr.episodes.inserted_through = lr.iteration
    if "episodes" in c:
        lr.episodes.restore(str(c["episodes"]))
    if "digests" in c:  # what the dead learner published: rows acted with it are checked too (lag B > 0)
        lr.digests = PublishedDigests.from_json(str(c["digests"]))
    # Every stream and the staging point are in the checkpoint; the workers resend the rows after
    # it: the resumed learner recomputes the same updates (exact unless the run was inexact already).
    lr.inexact = str(c.get("inexact", ""))
    if not lr.inexact and (why := codecheck.inexact_reason(lr.run_dir)):  # resumed onto other code, forced
        lr.break_exact(why)
    if lr.env_steps > 0 and len(lr.buffer) == 0:  # --no-save-replay: nothing of the replay is on disk
        lr.break_exact(f"resumed at iteration {lr.iteration:,} with an empty replay buffer: the run keeps no replay "
                       f"(--no-save-replay), so the {lr.env_steps:,} transitions before it and the sampling "
                       "stream's state are gone")
    # Slot owners that lost their slot (a stale worker back from a pause): their batches stay refused.
    lr.retired = {(str(w), str(i)) for w, i in json.loads(c.get("retired", "[]"))}
    # The versions before its own that the workers' next iterations act with (lag B > 0).
    lr.kept_weights = kept_weights_from(state.get("kept_weights", []), lr.agent.actor_shapes(), lr.algo.actors)
    # ... and the snapshots of the evaluations the referee had not reported done (it may be behind)
    lr.kept_snapshots = kept_weights_from(state.get("kept_snapshots", []), lr.agent.actor_shapes(), lr.algo.actors)
    if lr.algo.lag > 0 and "kept_weights" not in state:
        log.warning("the checkpoint keeps no older actor versions (written before they were kept): at lag %d the "
                    "workers may wait for a version this learner cannot publish", lr.algo.lag)
    live = lr.agent.live_actors
    if sum(live) == 1 and lr.algo.actors > 1:
        lr.survivor = lr.decided_survivor = live.index(True)
    log.info("resumed at iteration %d: %d transitions, %d updates (replay rows: %d)", lr.iteration,
             lr.env_steps, lr.agent.updates, len(lr.buffer))



def write_log(lr: Learner, now: float | None = None) -> None:
    """One learner.jsonl row; with `now`, the rates since the previous such row first."""
    if now is not None:
        steps, updates, t = lr._rate_base
        dt = max(now - t, 1e-9)
        lr.rates = ((lr.env_steps - steps) / dt, (lr.updates - updates) / dt)
        lr._rate_base = (lr.env_steps, lr.updates, now)
    tracker = lr.intake.tracker
    row = {"t": round(time.monotonic() - lr.started, 3), "env_steps": lr.env_steps,
           "iterations": lr.iterations, "updates": lr.updates, "utd": lr.utd(),
           "transitions_per_s": round(lr.rates[0], 2), "updates_per_s": round(lr.rates[1], 2),
           "versions": list(lr.agent.versions), "live": lr.agent.live_actors,
           "lost": tracker.lost, "duplicates": tracker.duplicates,
           "rejected": lr.intake.rejects.total, "buffer": len(lr.buffer),
           "received": {w: t.received for w, t in lr.intake.workers.items()},
           "exact_wait_s": round(getattr(lr, "wait_s", 0.0), 3), "update_s": round(lr.agent.update_s, 3)}
    row.update(lr.metrics)
    if lr.intake.episode_returns:
        row["train_return"] = float(np.mean(lr.intake.episode_returns))
        row["train_episodes"] = len(lr.intake.episode_returns)
        lr.intake.episode_returns.clear()
    lr.log_writer.write(row)



def measure_bias(lr: Learner, point_index: int) -> None:
    """Eq. 17 for every live actor k at bias point j: Q_k1(s0, π_k(s0)) of the current critic
    against the discounted Monte-Carlo return of π_k from the same initial states
    (`bias_rollouts` rollouts, `seeding.bias_seed`). Training pauses meanwhile."""
    started = time.monotonic()
    point = point_index * lr.cfg.bias_every
    live = lr.agent.live_actors
    for k in (k for k, alive in enumerate(live) if alive):
        try:
            result = estimation_bias(lambda obs, k=k: lr.agent.act(obs, k),
                                     lambda obs, act, k=k: lr.agent.q_value(obs, act, k),
                                     lr.cfg.env_id, lr.cfg.bias_rollouts, lr.algo.gamma,
                                     bias_seed(lr.algo.seed, point_index), lr.cfg.env_kwargs,
                                     horizon=lr.cfg.bias_horizon)
        except Exception:  # a diagnostic never stops the training
            log.exception("bias measurement at %d failed (actor %d)", point, k)
            continue
        lr.bias_writer.write({"env_steps": lr.env_steps, "iterations": lr.iterations, "point": point,
                                "updates": lr.updates, "live": list(live),
                                "rollouts": lr.cfg.bias_rollouts, "bias": {"actor": k, **result}})
    log.info("bias at %d transitions measured in %.1f s", lr.env_steps, time.monotonic() - started)

