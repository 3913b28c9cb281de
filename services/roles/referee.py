"""`mam-referee`: evaluates the actors and decides which actor each worker slot runs (Eq. 8).

It follows the run's plan (mam_core/algorithm1.py, `events()`): each competition evaluates the
live actors over `eval_episodes` deterministic episodes on the version it judges (sent by the
learner on `weights/<k>/eval`), recomputes P_k (Eq. 8) and draws the slot -> actor allocation
with the run's allocation stream; at C it eliminates all but the best actor; curve points and
the final evaluation follow the updates. After each evaluation its state (the allocation
stream's included) goes to `referee_state.json`, so a restarted referee goes on exactly.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import typer

import mam_core.envs  # noqa: F401
from mam_core.algorithm1 import Algorithm1, Purpose
from mam_core.config import AlgoConfig
from mam_core.evaluation import evaluate_policy
from mam_core.obsolescence import Obsolescence, best_actors, competition_returns, counts, obsolescence_for
from mam_core.policy import EnvSpec, NumpyActors
from mam_core.seeding import evaluation_seed, stream
from services.messaging import bus, keys
from services.messaging.codec import Allocation, Eval, LearnerStats, MessageError
from services.roles import role, tb
from services.roles.lockstep import WeightsHistory
from services.run import config, options, rundir
from services.run.config import RunConfig
from services.run.rundir import JsonlWriter, write_json

log = logging.getLogger("mam.referee")

STATE_FILE = rundir.REFEREE_STATE
HEARTBEAT_S = 2.0  # the current allocation is re-published this often


@dataclass
class RefereeState:
    """What a restarted referee needs to go on exactly where its predecessor stood; saved to
    referee_state.json after each evaluation is logged and its decision published."""

    obsolescence: Obsolescence  # P, the live actors, the survivor
    rng: np.random.Generator  # the allocation stream: slot draws and the tie-break at C (mam_core.seeding)
    events_done: int = 0  # evaluations of plan.events() done (and logged)
    decision: tuple[int, dict[str, int]] | None = None  # the latest allocation: (iteration, slots)
    previous: tuple[int, dict[str, int]] | None = None  # the one before it
    final_row: tuple[int, list[float | None], int, list[int]] | None = None  # the final evaluation
    wall_before: float = 0.0  # seconds of the run before this incarnation

    @classmethod
    def fresh(cls, algo: AlgoConfig, steps: int) -> RefereeState:
        return cls(obsolescence_for(algo, steps), stream(algo.seed, "allocation"))

    def save(self, path: Path, wall: float) -> None:
        write_json(path, {
            "schedule": self.obsolescence.to_dict(), "rng": self.rng.bit_generator.state,
            "events_done": self.events_done, "decision": self.decision, "previous": self.previous,
            "final_row": self.final_row, "wall_s": round(wall, 3)}, durable=True)

    @classmethod
    def load(cls, path: Path, algo: AlgoConfig, steps: int) -> RefereeState | None:
        """The saved state; None without one, or for an unreadable one (the evaluations start again)."""
        if not path.is_file():
            return None
        state = cls.fresh(algo, steps)
        try:
            data = json.loads(path.read_text())
            state.obsolescence = Obsolescence.from_dict(data["schedule"])  # the file's key since the start
            state.rng.bit_generator.state = data["rng"]
            state.events_done = int(data["events_done"])
            state.decision = _decision(data.get("decision"))
            state.previous = _decision(data.get("previous"))
            final = data.get("final_row")
            state.final_row = None if final is None else (int(final[0]), list(final[1]), int(final[2]),
                                                          [int(v) for v in final[3]])
            state.wall_before = float(data.get("wall_s", 0.0))
        except (ValueError, KeyError, TypeError, IndexError) as e:
            log.warning("ignoring unreadable %s (the run's evaluations start again): %s", path, e)
            return None
        return state


class Referee:
    def __init__(self, cfg: RunConfig, session: Any, run_dir: Path) -> None:
        self.cfg = cfg
        self.algo = cfg.algo
        self.session = session
        self.run_dir = run_dir
        self.id = f"{socket.gethostname()}-{os.getpid()}"
        self.rejects = bus.RejectLog(log, "message")
        self.spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
        self.actors = NumpyActors(self.algo.actors, self.spec, self.algo.hidden, self.algo.family.policy_kind)
        self.shapes = self.actors.shapes
        self.plan = Algorithm1.for_run(self.algo, cfg.steps)  # the events, in order
        self.stats: LearnerStats | None = None
        self.seq = 0
        self.stop_requested = False
        self.started = time.monotonic()
        loaded = RefereeState.load(run_dir / STATE_FILE, self.algo, cfg.steps)
        self.resumed = loaded is not None
        self.state = loaded or RefereeState.fresh(self.algo, cfg.steps)
        if loaded is not None:
            ob = loaded.obsolescence
            log.info("recovered referee state: %d of %d evaluations done, round %d, P %s, survivor %s",
                     loaded.events_done, len(self.plan.events()), ob.round, ob.probabilities.round(3).tolist(),
                     ob.survivor)

    def wall(self) -> float:
        return self.state.wall_before + time.monotonic() - self.started

    def drop_rows_done_again(self) -> None:
        """Drop the eval.jsonl and allocation.jsonl rows a predecessor logged past the state this
        referee starts from, which it logs again: those of an evaluation the predecessor did not
        finish, or, with no state saved (killed before its first evaluation was saved), all of them,
        the initial allocation's row included (a fresh referee logs it again)."""
        keep_logs(self.run_dir / rundir.EVAL, self.state.events_done)
        keep_logs(self.run_dir / rundir.ALLOCATION,
                  1 + self.plan.competitions_among(self.state.events_done) if self.resumed else 0)

    # -- wiring -------------------------------------------------------------------------------
    def serve(self) -> None:
        run, s = self.cfg.run, self.session
        self.alloc_pub = bus.declare_latest_publisher(s, keys.allocation(run))
        self.eval_pub = bus.declare_latest_publisher(s, keys.eval(run))
        # The versions each evaluation judges, in order (before the first allocation).
        self.snapshots = bus.Inbox.subscribe(s, keys.eval_weights_all(run), maxsize=1024,
                                            screen=role.weights_screen(self.shapes, self.algo.actors, self.rejects))
        self.stats_sub = bus.Latest.subscribe(s, keys.learner_stats(run))
        self.done = bus.Latest.subscribe(s, keys.done(run))
        self.workers = bus.watch_alive(s, run, "worker")
        self.learners = bus.watch_alive(s, run, "learner")  # at the end: gone once it has the final report
        self.token = bus.declare_alive(s, run, "referee", self.id)
        self.report = role.RoleReport(s, run, "referee", self.id)
        self.board = tb.RunBoard(self.run_dir, "referee")  # RUN_DIR/tb/referee: the JSONL rows' scalars
        self.drop_rows_done_again()
        self.alloc_log = self.board.tee(JsonlWriter(self.run_dir / rundir.ALLOCATION), tb.allocation_scalars)
        self.eval_log = self.board.tee(JsonlWriter(self.run_dir / rundir.EVAL), tb.eval_scalars)
        try:
            self._loop()
        finally:
            self.token.undeclare()
            for sub in (self.snapshots, self.stats_sub, self.done, self.workers, self.learners):
                sub.close()
            self.alloc_log.close()
            self.eval_log.close()
            self.board.close()

    def _loop(self) -> None:
        """Each evaluation of the plan in order, on the actors it judges; each competition's
        allocation tagged with its iteration; then, after the learner's done, the summary."""
        plan = self.plan
        history = WeightsHistory(self.algo.actors)
        if self.state.decision is None:
            self.publish_allocation(0, "initial", None)
        else:
            self.put_allocation("recovered")
        for index, purpose in plan.events()[self.state.events_done:]:
            it = plan.iteration(index)
            competes = purpose.competes
            version = plan.judged_version(index, purpose)
            live = [k for k in range(self.algo.actors) if self.state.obsolescence.live[k]]
            while not all(history.has(k, version) for k in live):
                if not self.wait(history):
                    return
            for k in live:
                self.actors.load_member(k, history.get(k, version))
            versions = [version if k in live else -1 for k in range(self.algo.actors)]
            seed = evaluation_seed(self.algo.seed, purpose, it.evaluation_index(purpose))
            means = self.evaluate(it, seed, purpose, versions, it.updates[0] if competes else it.updates[1])
            if competes:  # lines 15-20: Eq. 8 or the survivor; the slots draw for iteration index+1+B on
                self.state.obsolescence.record_evaluation(it.units[1], competition_returns(means), rng=self.state.rng)
                self.publish_allocation(index, purpose.value, competition_returns(means).tolist())
            if it.last:  # the final evaluation: curve point or not, it is the run's last
                self.state.final_row = (it.transitions[1], means, seed, versions)
            self.state.events_done += 1
            self.state.save(self.run_dir / STATE_FILE, self.wall())
            history.forget_below(version)
        while not self.stop_requested:  # the learner's done, then the summary
            self.refresh()
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                self.write_summary(*self.state.final_row)
                return
            self.heartbeat()
            self.stats_sub.wait_fresh(timeout=0.1)

    def wait(self, history: WeightsHistory) -> bool:
        """Take the snapshots that arrived; heartbeats meanwhile. False when stopping."""
        item = self.snapshots.get(timeout=0.05)
        current = self.stats.incarnation if self.stats is not None else ""
        for item in ([item] if item is not None else []) + self.snapshots.drain():
            try:
                w = role.decoded_weights(item, self.shapes, self.algo.actors)
            except MessageError as e:
                self.rejects.reject(keys.parse_last(item.key), e)
                continue
            history.add(w.actor, w.version, w.params, w.incarnation, prefer=current)
        self.refresh()
        self.publish_report()
        self.heartbeat()
        return not self.stop_requested

    def heartbeat(self) -> None:
        if time.monotonic() - self.last_publish > HEARTBEAT_S:
            self.alloc_pub.put(self.last_allocation)  # the same decision again: late joiners, lost samples
            self.last_publish = time.monotonic()

    def publish_allocation(self, index: int, reason: str, returns: list[float] | None) -> None:
        """The slots w0..w{M-1} drawn with the run's allocation stream, tagged with the iteration
        that decided them (they apply from iteration index+1+B), with the decision before."""
        st = self.state
        drawn = st.obsolescence.allocation(self.algo.workers, st.rng)[:self.plan.slot_width(index)]
        st.previous, st.decision = st.decision, (index, {keys.slot_name(i): int(k) for i, k in enumerate(drawn)})
        slots = st.decision[1]
        i_k = counts(slots, self.algo.actors).astype(int).tolist()
        it = self.plan.iteration(index) if index else None
        best = best_actors(returns, None) if returns is not None else []
        self.alloc_log.write({"t": round(self.wall(), 3), "round": st.obsolescence.round,
                              "env_steps": it.transitions[1] if it else 0, "iterations": it.units[1] if it else 0,
                              "updates": it.updates[0] if it else 0,
                              "decided_at": it.transitions[1] if it else 0, "decided_at_iteration": index,
                              "applies_from_iteration": self.plan.applies_from(index),
                              "returns": returns, "tie": best if len(best) > 1 else None,
                              "probabilities": [float(p) for p in st.obsolescence.probabilities], "counts": i_k,
                              "slots": dict(slots), "eliminated": [bool(e) for e in st.obsolescence.eliminated],
                              "survivor": st.obsolescence.survivor, "reason": reason})
        self.put_allocation(reason, returns)
        at = role.at_text(self.plan.schedule.paper, it.units[1] if it else 0, it.transitions[1] if it else 0)
        log.info("allocation (%s) at %s: from iteration %d, P=%s I=%s", reason, at,
                 self.plan.applies_from(index), np.round(st.obsolescence.probabilities, 3).tolist(), i_k)

    def put_allocation(self, reason: str, returns: list[float] | None = None) -> None:
        index, slots = self.state.decision
        ob = self.state.obsolescence
        it = self.plan.iteration(index) if index else None
        msg = Allocation(ob.round, it.transitions[1] if it else 0, None if returns is None else tuple(returns),
                         tuple(float(p) for p in ob.probabilities),
                         tuple(counts(slots, self.algo.actors).astype(int).tolist()), dict(slots),
                         tuple(bool(e) for e in ob.eliminated), ob.survivor, reason,
                         iteration=index, previous=self.state.previous)
        self.last_allocation = msg.to_bytes(self.id, self._next_seq())
        self.alloc_pub.put(self.last_allocation)
        self.last_publish = time.monotonic()

    def refresh(self) -> None:
        stats = role.fresh_learner_stats(self.stats_sub, self.cfg.run, self.rejects)
        if stats is not None:
            self.stats = stats

    # -- evaluation -----------------------------------------------------------------------------
    def evaluate(self, it: Any, seed: int, purpose: Purpose, versions: list[int], updates: int) -> list[float | None]:
        """Deterministic returns of each live actor on the episodes of `seed` (eval.jsonl row,
        `eval` topic)."""
        returns: list[list[float]] = []
        for k in range(self.algo.actors):
            if versions[k] < 0:
                returns.append([])
                continue
            r = evaluate_policy(self.actors.policy(k), self.cfg.env_id, self.algo.eval_episodes, seed=seed,
                                env_kwargs=self.cfg.env_kwargs)
            returns.append([float(x) for x in r])
        means = [float(np.mean(r)) if r else None for r in returns]
        steps = it.transitions[1]
        msg = Eval(self.state.events_done + 1, steps, tuple(tuple(r) for r in returns), tuple(means), tuple(versions))
        self.eval_pub.put(msg.to_bytes(self.id, self._next_seq()))
        self.eval_log.write({"t": round(self.wall(), 3), "round": self.state.events_done + 1, "env_steps": steps,
                             "iterations": it.units[1], "updates": updates, "purpose": purpose.value, "seed": seed,
                             "returns": returns, "mean": means, "versions": versions, "bias": None})
        log.info("%s eval at %s: %s", purpose, role.at_text(self.plan.schedule.paper, it.units[1], steps),
                 [None if m is None else round(m, 2) for m in means])
        return means

    def publish_report(self, final: bool = False) -> None:
        """The referee's counters on mam/<run>/stats/referee-<id> (rejections are visible there):
        the evaluations done (the learner re-sends what the next one needs) and, once the
        summary is written, `final` (the learner waits for it)."""
        fields = {"round": self.state.obsolescence.round, "events": self.state.events_done,
                  "rejected": self.rejects.counts()}
        if final:
            fields["final"] = True
        self.report.publish(fields, seq=self._next_seq, force=final)

    def write_summary(self, steps: int, means: list[float | None], seed: int, versions: list[int]) -> None:
        """summary.json: the final evaluation (`mam eval` reproduces it from `final_eval`)."""
        survivor = self.state.obsolescence.survivor
        if survivor is None and any(m is not None for m in means):
            survivor = None if self.algo.actors > 1 else 0
        write_json(self.run_dir / rundir.SUMMARY, {
            "run": self.cfg.run, "env_id": self.cfg.env_id, "algo": self.algo.algo,
            "final_returns": means, "survivor": survivor, "env_steps": steps,
            "iterations": self.plan.schedule.units_at(steps), "schedule": self.algo.schedule,
            "final_eval": {"seed": seed, "episodes": self.algo.eval_episodes,
                           "versions": versions},  # `mam eval` reproduces it from these
            "lag": self.plan.lag,
            "exact": bool(self.stats.exact) if self.stats else False,
            "inexact": self.stats.inexact if self.stats else "",
            "updates": self.stats.updates if self.stats else 0,
            "wall_time_s": round(self.wall(), 2),
            "rounds": self.state.obsolescence.round, "probabilities": self.state.obsolescence.probabilities.tolist(),
            "rejected": self.rejects.counts()})
        # The learner stays up until it sees this (a restarted referee still needs its caches), and
        # leaves when it has: repeat (the last put before close can be lost) until then, 3 times at most.
        for _ in range(3):
            self.publish_report(final=True)
            if self.learners.wait_for(lambda live: not live, timeout=0.1):
                break

    def _next_seq(self) -> int:
        self.seq += 1
        return self.seq


def _decision(raw: Any) -> tuple[int, dict[str, int]] | None:
    """A saved (iteration, slots) decision."""
    if raw is None:
        return None
    index, slots = raw
    return int(index), {str(w): int(k) for w, k in slots.items()}


def keep_logs(path: Path, rows: int) -> None:
    """Keep the first `rows` lines of a JSONL log (what a restarted referee's state covers)."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines(keepends=True)
    if len(lines) > rows:
        path.write_text("".join(lines[:rows]))


def main(run: str, conf: Any, run_dir: Path) -> None:
    role.serve_role("referee", conf, lambda cfg, session: Referee(cfg, session, run_dir), run=run, run_dir=run_dir,
                    log=log)


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags)
def referee_command(
    run: options.Run = None, connect: options.Connect = None, listen: options.Listen = None,
    zenoh_config: options.ZenohConfig = None, run_dir: options.RunDir = None,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="debug logging"),
) -> None:
    """Run the referee of a run: evaluation rounds, P_k, slot allocation, elimination."""
    role.setup_logging(verbose)
    if not run:
        raise typer.BadParameter("--run NAME is required")
    config.check_run_name(run)
    main(run, role.client_config(connect, listen, zenoh_config), run_dir or Path("runs") / run)


cli = app  # the `mam-referee` entry point


if __name__ == "__main__":
    cli()
