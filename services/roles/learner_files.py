"""What the learner writes and reads back (services/roles/learner.py): checkpoints of its state
(`LearnerState`, learner_state.py) and their restore, learner.jsonl rows, transport.json, and the
Eq. 17 rows of bias.jsonl. Each function takes the state and what else it needs, not the learner."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mam_core import arithmetic
from mam_core.config import AlgoConfig
from mam_core.evaluation import estimation_bias
from mam_core.seeding import bias_seed
from services.messaging import bus
from services.messaging.codec import LearnerStats, MessageError
from services.roles import role
from services.roles.checkpoint import save_checkpoint
from services.roles.intake import Intake
from services.roles.learner_state import Carried, KeptParams, LearnerState
from services.run import codecheck, rundir, runlock
from services.run.config import RunConfig
from services.run.rundir import JsonlWriter, write_json

log = logging.getLogger("mam.learner")


def checkpoint(st: LearnerState, cfg: RunConfig, run_dir: Path, kept: Carried) -> Path:
    """A new checkpoint generation of `st`, with the versions and snapshots the outbox keeps
    (`kept`); the workers may then drop what the generation before it holds (`st.acks`)."""
    started, p = time.monotonic(), st.progress
    path = save_checkpoint(run_dir, st.agent, st.buffer, st.counters(), cfg, st.replay_log,
                           survivor=p.survivor,  # with policy.npz, in a verified generation
                           extra={"kept_weights": kept_weights_state(kept.kept_weights),
                                  "kept_snapshots": kept_weights_state(kept.kept_snapshots),
                                  "gemm": arithmetic.status().get("gemm", "")})  # preflight.gemm_problem
    st.checkpoints.mark(st.agent.updates, p.env_steps, time.monotonic())
    if st.replay_log is not None:  # only now on disk: workers may drop what the previous one holds
        st.acks.checkpointed(st.intake.checkpointed_prefixes())
    log.info("checkpoint %s at iteration %d, %d updates, %d transitions (%.2f s)", path, p.iteration,
             st.agent.updates, p.env_steps, time.monotonic() - started)
    return path


def next_epoch(run_dir: Path) -> int:
    """This learner's epoch: one more than the run's last (RUN_DIR/learner_epoch.json, written
    durably before the learner publishes anything)."""
    last = rundir.read_json(run_dir / rundir.LEARNER_EPOCH).get("epoch", 0)
    epoch = (last if isinstance(last, int) and last >= 0 else 0) + 1
    write_json(run_dir / rundir.LEARNER_EPOCH, {"epoch": epoch}, durable=True)
    return epoch


def fence(rivals: bus.Latest, incarnation: str, run: str) -> None:
    """The stats of a learner of a higher epoch on this run's key (`rivals`): another took the run
    over while this one (`incarnation`) was frozen or cut off. Stop at once, exit 73, without a
    checkpoint (the run's state is that one's now)."""
    for item in rivals.fresh().values():
        try:
            other = LearnerStats.from_bytes(item.payload).incarnation
        except MessageError:
            continue
        if role.learner_order(other) > role.learner_order(incarnation):
            log.error("stopping: learner %s (a higher epoch) serves run %r: this one (%s) is stale", other,
                      run, incarnation)
            raise SystemExit(runlock.EXIT_REFUSED)


def count_late(intake: Intake, versions: Sequence[int], items: list[bus.Received]) -> None:
    """Batches that arrive after the last iteration (a resend): counted, never inserted."""
    for item in items:
        batch = intake.validate(item, versions)
        if batch is not None:
            intake.admit(batch)


def write_transport(st: LearnerState, run_dir: Path, inbox_dropped: int) -> None:
    """transport.json at the end: the counters `mam run`'s audit holds against the workers' logs
    (`inbox_dropped`: batches shed before decoding when the inbox overflowed)."""
    p, tracker = st.progress, st.intake.tracker
    write_json(run_dir / rundir.TRANSPORT, {
        "env_steps": p.env_steps, "iterations": st.iterations(), "updates": st.updates(),
        "lost": tracker.lost, "duplicates": tracker.duplicates, "rejected": st.rejected(),
        "recovered": tracker.recovered, "redundant": tracker.redundant,
        "replay_rows": st.buffer.inserted if st.replay_log is not None else None,
        "wall_s": p.wall_s(),
        **st.intake.transport(),
        "inbox_dropped": inbox_dropped})
    log.info("done: %d transitions, %d updates, lost %d, duplicates %d, rejected %d, survivor %s, %s; the final "
             "returns: the referee's %s", p.env_steps, st.agent.updates, tracker.lost, tracker.duplicates,
             st.intake.rejects.total, "-" if p.survivor is None else p.survivor,
             "exact" if not p.inexact else f"not exact ({p.inexact})", run_dir / rundir.SUMMARY)


def kept_weights_state(kept: list[KeptParams]) -> list[list[Any]]:
    """The versions a slot may still act with (Outbox.kept_weights) as checkpoint entries:
    [plan version, actor, its version, {name: tensor}]."""
    return [[key, k, version, {name: torch.from_numpy(a) for name, a in params.items()}]
            for key, k, version, params in kept]


def kept_weights_from(rows: Any, shapes: dict[str, tuple[int, ...]], actors: int) -> list[KeptParams]:
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


def restore(st: LearnerState, saved: dict[str, Any], run_dir: Path, algo: AlgoConfig) -> None:
    """A resume: `st` as the checkpoint `saved` (load_checkpoint, verified) holds it."""
    p = st.progress
    st.agent.load_state_dict(saved["agent"])
    c = saved["counters"]
    p.env_steps = int(c["env_steps"])
    if "replay" in saved:  # checkpoints written before the chunked replay log
        st.buffer.load_state_dict(saved["replay"])
    if "replay_log" in saved and st.replay_log is not None:
        meta = saved["replay_log"]
        st.replay_log.restore(st.buffer, meta["manifest"], int(meta["inserted"]), json.loads(meta["rng"]))
        if st.buffer.inserted != p.env_steps:
            raise ValueError(f"checkpoint counts {p.env_steps} transitions, its replay {st.buffer.inserted}")
    st.restore_counters(c)
    if not p.inexact and (why := codecheck.inexact_reason(run_dir)):  # resumed onto other code, forced
        p.break_exact(why)
    if p.env_steps > 0 and len(st.buffer) == 0:  # --no-save-replay: nothing of the replay is on disk
        p.break_exact(f"resumed at iteration {p.iteration:,} with an empty replay buffer: the run keeps no replay "
                      f"(--no-save-replay), so the {p.env_steps:,} transitions before it and the sampling "
                      "stream's state are gone")
    # The versions before its own that the workers' next iterations act with (lag B > 0) ...
    shapes = st.agent.actor_shapes()
    st.carried = Carried(kept_weights_from(saved.get("kept_weights", []), shapes, algo.actors),
                         # ... and the snapshots of the evaluations the referee had not reported done
                         kept_weights_from(saved.get("kept_snapshots", []), shapes, algo.actors))
    if algo.lag > 0 and "kept_weights" not in saved:
        log.warning("the checkpoint keeps no older actor versions (written before they were kept): at lag %d the "
                    "workers may wait for a version this learner cannot publish", algo.lag)
    live = st.agent.live_actors
    if sum(live) == 1 and algo.actors > 1:
        p.survivor = p.decided_survivor = live.index(True)
    log.info("resumed at iteration %d: %d transitions, %d updates (replay rows: %d)", p.iteration,
             p.env_steps, st.agent.updates, len(st.buffer))


def write_log(st: LearnerState, writer: JsonlWriter, now: float | None = None) -> None:
    """One learner.jsonl row; with `now`, the rates since the previous such row first."""
    p, intake = st.progress, st.intake
    if now is not None:
        st.rates.advance(p.env_steps, st.updates(), now)
    tracker = intake.tracker
    row = {"t": round(time.monotonic() - p.started, 3), "env_steps": p.env_steps,
           "iterations": st.iterations(), "updates": st.updates(), "utd": st.utd(),
           "transitions_per_s": round(st.rates.per_s[0], 2), "updates_per_s": round(st.rates.per_s[1], 2),
           "versions": list(st.agent.versions), "live": st.agent.live_actors,
           "lost": tracker.lost, "duplicates": tracker.duplicates,
           "rejected": intake.rejects.total, "buffer": len(st.buffer),
           "received": {w: t.received for w, t in intake.workers.items()},
           "exact_wait_s": round(p.wait_s, 3), "update_s": round(st.agent.update_s, 3)}
    row.update(p.metrics)
    if intake.episode_returns:
        row["train_return"] = float(np.mean(intake.episode_returns))
        row["train_episodes"] = len(intake.episode_returns)
        intake.episode_returns.clear()
    writer.write(row)


def measure_bias(st: LearnerState, cfg: RunConfig, writer: JsonlWriter, point_index: int) -> None:
    """Eq. 17 for every live actor k at bias point j: Q_k1(s0, π_k(s0)) of the current critic
    against the discounted Monte-Carlo return of π_k from the same initial states
    (`bias_rollouts` rollouts, `seeding.bias_seed`). Training pauses meanwhile."""
    started, agent, p = time.monotonic(), st.agent, st.progress
    point = point_index * cfg.bias_every
    live = agent.live_actors
    for k in (k for k, alive in enumerate(live) if alive):
        try:
            result = estimation_bias(lambda obs, k=k: agent.act(obs, k),
                                     lambda obs, act, k=k: agent.q_value(obs, act, k),
                                     cfg.env_id, cfg.bias_rollouts, cfg.algo.gamma,
                                     bias_seed(cfg.algo.seed, point_index), cfg.env_kwargs,
                                     horizon=cfg.bias_horizon)
        except Exception:  # a diagnostic never stops the training
            log.exception("bias measurement at %d failed (actor %d)", point, k)
            continue
        writer.write({"env_steps": p.env_steps, "iterations": st.iterations(), "point": point,
                      "updates": st.updates(), "live": list(live),
                      "rollouts": cfg.bias_rollouts, "bias": {"actor": k, **result}})
    log.info("bias at %d transitions measured in %.1f s", p.env_steps, time.monotonic() - started)
