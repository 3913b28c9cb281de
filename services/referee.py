"""`mam-referee`: evaluates the actors and decides which actor each worker slot runs (Eq. 8).

Every A env steps (read from the learner's stats) it evaluates each live actor over
`eval_episodes` deterministic episodes, recomputes P_k (Eq. 8), draws a new slot -> actor
allocation over the live workers and publishes `allocation` and `eval`. At C it eliminates all
but the best actor. When a worker joins or leaves it re-allocates at once with the current P.
After elimination (or without obsolescence) it keeps evaluating every `eval_every` steps for
learning curves. Its state is saved to `referee_state.json` so a restarted referee goes on.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

import mam_core.envs  # noqa: F401
from mam_core.algorithm1 import Algorithm1
from mam_core.evaluation import evaluate_policy
from mam_core.obsolescence import Obsolescence, best_actors, competition_returns, counts, obsolescence_for
from mam_core.policy import EnvSpec, NumpyActors, Policy
from mam_core.schedule import Schedule
from mam_core.seeding import evaluation_seed, stream
from services import bus, keys, options, role, rundir, tb
from services.codec import Allocation, Eval, LearnerStats, MessageError, Weights
from services.exact import WeightsHistory
from services.options import JsonlWriter, RunConfig, write_json

log = logging.getLogger("mam.referee")

STATE_FILE = rundir.REFEREE_STATE
HEARTBEAT_S = 2.0  # the current allocation is re-published this often


class Referee:
    def __init__(self, cfg: RunConfig, session: Any, run_dir: Path) -> None:
        self.cfg = cfg
        self.algo = cfg.algo
        self.session = session
        self.run_dir = run_dir
        self.id = f"{socket.gethostname()}-{os.getpid()}"
        self.rejects = bus.RejectLog(log, "message")
        self.spec = EnvSpec.from_env_id(cfg.env_id, cfg.env_kwargs)
        self.follower = role.WeightsFollower.for_algo(self.algo, self.spec, self.rejects)
        self.actors = self.follower.actors  # acting only: no torch
        self.versions = self.follower.versions
        self.schedule: Obsolescence = obsolescence_for(self.algo, cfg.steps)  # counts schedule steps (units)
        self.clock = Schedule.for_run(self.algo, cfg.steps)  # transitions <-> iterations
        self.rng = stream(self.algo.seed, "allocation")  # slot draws and the tie-break at C (mam_core.seeding)
        self.plan = Algorithm1.for_run(self.algo, cfg.steps)
        self.exact = cfg.collection == "exact"
        self.last_eval: dict[str, Any] | None = None  # exact mode: the final evaluation's row
        self.slots: dict[str, int] = {}
        self.drawn_over: set[str] = set()  # the live workers the current slots were drawn for
        self.eval_round = 0
        self.decided_at = 0  # transitions at the evaluation behind the current P
        self.next_curve_eval = self.algo.eval_every
        self.stats: LearnerStats | None = None
        self.seq = 0
        self.stop_requested = False
        self.started = time.monotonic()
        self._load_state()

    # -- state (recovery after a restart) -----------------------------------------------------
    def _load_state(self) -> None:
        path = self.run_dir / STATE_FILE
        if not path.is_file():
            return
        try:
            data = json.loads(path.read_text())
            self.schedule = Obsolescence.from_dict(data["schedule"])
            self.slots = {str(w): int(k) for w, k in data["slots"].items()}
            self.eval_round = int(data["eval_round"])
            self.next_curve_eval = int(data["next_curve_eval"])
            self.decided_at = int(data.get("decided_at", 0))
            self.exact = False  # a restarted referee: the run is no longer exact (services/exact.py)
            log.info("recovered referee state: round %d, P %s, survivor %s", self.schedule.round,
                     self.schedule.probabilities.round(3).tolist(), self.schedule.survivor)
        except (ValueError, KeyError, TypeError) as e:
            log.warning("ignoring unreadable %s: %s", path, e)

    def _save_state(self) -> None:
        write_json(self.run_dir / STATE_FILE, {
            "schedule": self.schedule.to_dict(), "slots": self.slots, "eval_round": self.eval_round,
            "next_curve_eval": self.next_curve_eval, "decided_at": self.decided_at})

    # -- wiring -------------------------------------------------------------------------------
    def serve(self) -> None:
        run, s = self.cfg.run, self.session
        self.alloc_pub = bus.declare_latest_publisher(s, keys.allocation(run))
        self.eval_pub = bus.declare_latest_publisher(s, keys.eval(run))
        self.weights = bus.Latest.subscribe(s, keys.weights_all(run), screen=self.follower.admits)
        # exact mode: the versions each evaluation needs, in order (before the first allocation)
        self.snapshots = bus.Inbox.subscribe(s, keys.eval_weights_all(run), maxsize=1024,
                                            screen=self.follower.admits)
        self.stats_sub = bus.Latest.subscribe(s, keys.learner_stats(run))
        self.done = bus.Latest.subscribe(s, keys.done(run))
        self.workers = bus.watch_alive(s, run, "worker")
        self.token = bus.declare_alive(s, run, "referee", self.id)
        self.report = role.RoleReport(s, run, "referee", self.id)
        self.board = tb.RunBoard(self.run_dir, "referee")  # RUN_DIR/tb/referee: the JSONL rows' scalars
        self.alloc_log = self.board.tee(JsonlWriter(self.run_dir / rundir.ALLOCATION), tb.allocation_scalars)
        self.eval_log = self.board.tee(JsonlWriter(self.run_dir / rundir.EVAL), tb.eval_scalars)
        try:
            self._loop()
        finally:
            self.token.undeclare()
            for sub in (self.weights, self.snapshots, self.stats_sub, self.done, self.workers):
                sub.close()
            self.alloc_log.close()
            self.eval_log.close()
            self.board.close()

    def _loop(self) -> None:
        if self.exact:
            if self._exact_loop():
                return
            log.warning("the run is no longer exact: %s; allocating asynchronously",
                        self.stats.inexact if self.stats else "?")
        self.publish_allocation("initial" if not self.slots else "recovered", returns=None)
        while not self.stop_requested:
            self.refresh()
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                self.final_evaluation()
                return
            if set(self.workers.live()) != self.drawn_over:  # (with one slot after C, slots ⊂ workers)
                self.publish_allocation("workers-changed", returns=None)
            steps = self.stats.env_steps if self.stats else 0
            units = self.clock.units_at(steps)  # iterations (paper) or transitions (equal-data)
            if self.schedule.due_elimination(units) or self.schedule.due_round(units):
                self.compete(steps)
            elif units >= self.next_curve_eval and units >= self.algo.start_steps:
                self.evaluate(steps, evaluation_seed(self.algo.seed, "curve", units // self.algo.eval_every), "curve")
                self.next_curve_eval = (units // self.algo.eval_every + 1) * self.algo.eval_every
                self._save_state()
            else:
                if time.monotonic() - self.last_publish > HEARTBEAT_S:
                    self.alloc_pub.put(self.last_allocation)  # heartbeat: the same decision again
                    self.last_publish = time.monotonic()
                self.stats_sub.wait_fresh(timeout=0.1)

    # -- exact mode: the plan's evaluations on the versions it names (services/exact.py) ----------
    def _exact_loop(self) -> bool:
        """Each evaluation of the plan in order, on the actors it must see; each competition's
        allocation tagged with its iteration. True when the run is done (summary written) or
        stopped; False when it stopped being exact (the caller goes on asynchronously)."""
        plan = self.plan
        history = WeightsHistory(self.algo.actors)
        scratch = NumpyActors(self.algo.actors, self.spec, self.algo.hidden, self.algo.stochastic)
        self.exact_decision: tuple[int, dict[str, int]] | None = None
        self.publish_exact_allocation(0, "initial", None)
        for index, purpose in plan.events():
            it = plan.iteration(index)
            competes = purpose in ("round", "elimination")
            version = plan.version_for(index) if competes else plan.version_after(index)
            live = [k for k in range(self.algo.actors) if self.schedule.live[k]]
            while not all(history.has(k, version) for k in live):
                if not self.wait_exact(history):
                    return self.stop_requested
            for k in live:
                scratch.load_member(k, history.get(k, version))
            versions = [version if k in live else -1 for k in range(self.algo.actors)]
            seed = evaluation_seed(self.algo.seed, purpose, it.round if purpose == "round" else it.curve)
            means = self.evaluate(it.transitions[1], seed, purpose, scratch, versions, it.units[1],
                                  it.updates[0] if competes else it.updates[1])
            if competes:  # lines 15-20: Eq. 8 or the survivor; the slots draw for iteration index+1 on
                self.schedule.record_evaluation(it.units[1], competition_returns(means), rng=self.rng)
                self.decided_at = it.transitions[1]
                self.publish_exact_allocation(index, purpose, competition_returns(means).tolist())
            else:
                self.next_curve_eval = (it.units[1] // self.algo.eval_every + 1) * self.algo.eval_every
            self._save_state()
            history.forget_below(version)
            if it.last:  # the final evaluation: curve point or not, it is the run's last
                self.final_row = (it.transitions[1], means, seed, versions)
        while not self.stop_requested:  # the learner's done, then the summary
            self.refresh()
            self.publish_report()
            if bus.run_is_done(self.done, self.cfg.run, self.rejects):
                steps, means, seed, versions = self.final_row
                self.write_summary(steps, means, seed, versions)
                return True
            if self.stats is not None and not self.stats.exact:
                return False
            self.stats_sub.wait_fresh(timeout=0.1)
        return True

    def wait_exact(self, history: WeightsHistory) -> bool:
        """Take the snapshots that arrived; heartbeats meanwhile. False when the run is no
        longer exact or the referee is stopping."""
        item = self.snapshots.get(timeout=0.05)
        items = ([item] if item is not None else []) + self.snapshots.drain()
        for item in items:
            try:
                w = Weights.from_bytes(item.payload, self.follower.shapes, self.algo.actors)
            except MessageError as e:
                self.rejects.reject(keys.parse_last(item.key), e)
                continue
            history.add(w.actor, w.version, w.params)
        self.refresh()
        self.publish_report()
        if time.monotonic() - self.last_publish > HEARTBEAT_S:
            self.alloc_pub.put(self.last_allocation)
            self.last_publish = time.monotonic()
        inexact = self.stats is not None and not self.stats.exact and bool(self.stats.inexact)
        return not (inexact or self.stop_requested)

    def publish_exact_allocation(self, index: int, reason: str, returns: list[float] | None) -> None:
        """The slots w0..w{M-1} drawn with the run's allocation stream, tagged with the iteration
        that decided them (they apply from the next one), with the decision before."""
        m = self.algo.workers
        drawn = self.schedule.allocation(m, self.rng)
        if self.schedule.survivor is not None and self.algo.single_env:
            drawn = drawn[:1]  # the survivor runs slot 0 (I_e = 1)
        self.slots = {keys.slot_name(i): int(k) for i, k in enumerate(drawn)}
        previous, self.exact_decision = self.exact_decision, (index, dict(self.slots))
        i_k = counts(self.slots, self.algo.actors).astype(int).tolist()
        msg = Allocation(self.schedule.round, self.decided_at, None if returns is None else tuple(returns),
                         tuple(float(p) for p in self.schedule.probabilities), tuple(i_k), dict(self.slots),
                         tuple(bool(e) for e in self.schedule.eliminated), self.schedule.survivor, reason,
                         iteration=index, previous=previous)
        self.last_allocation = msg.to_bytes(self.id, self._next_seq())
        self.alloc_pub.put(self.last_allocation)
        self.last_publish = time.monotonic()
        self.drawn_over = set(self.workers.live())
        it = self.plan.iteration(index) if index else None
        best = best_actors(returns, None) if returns is not None else []
        self.alloc_log.write({"t": round(time.monotonic() - self.started, 3), "round": self.schedule.round,
                              "env_steps": it.transitions[1] if it else 0, "iterations": it.units[1] if it else 0,
                              "updates": it.updates[0] if it else 0, "decided_at": self.decided_at,
                              "decided_at_iteration": index, "returns": returns,
                              "tie": best if len(best) > 1 else None,
                              "probabilities": [float(p) for p in self.schedule.probabilities], "counts": i_k,
                              "slots": dict(self.slots), "eliminated": [bool(e) for e in self.schedule.eliminated],
                              "survivor": self.schedule.survivor, "reason": reason})
        log.info("allocation (%s) at iteration %d: P=%s I=%s", reason, index,
                 np.round(self.schedule.probabilities, 3).tolist(), i_k)

    def refresh(self) -> None:
        self.follower.follow(self.weights, self.stats)
        item = self.stats_sub.fresh().get(keys.learner_stats(self.cfg.run))
        if item is not None:
            try:
                self.stats = LearnerStats.from_bytes(item.payload)
            except MessageError as e:
                self.rejects.reject("learner", e)

    # -- evaluation and competition -------------------------------------------------------------
    def policy(self, k: int) -> Policy:
        return self.actors.policy(k)

    def evaluate(self, steps: int, seed: int, purpose: str, actors: NumpyActors | None = None,
                 versions: list[int] | None = None, iterations: int | None = None,
                 updates: int | None = None) -> list[float | None]:
        """Deterministic returns of each live actor on the episodes of `seed` (eval.jsonl row,
        `eval` topic). `purpose`: round, elimination, curve or final (mam_core.seeding)."""
        live = self.schedule.live
        actors = actors or self.actors
        versions = list(self.versions) if versions is None else versions
        returns: list[list[float]] = []
        for k in range(self.algo.actors):
            if not live[k] or versions[k] < 0:
                returns.append([])
                continue
            r = evaluate_policy(actors.policy(k), self.cfg.env_id, self.algo.eval_episodes, seed=seed,
                                env_kwargs=self.cfg.env_kwargs)
            returns.append([float(x) for x in r])
        means = [float(np.mean(r)) if r else None for r in returns]
        self.eval_round += 1
        msg = Eval(self.eval_round, steps, tuple(tuple(r) for r in returns), tuple(means), tuple(versions))
        self.eval_pub.put(msg.to_bytes(self.id, self._next_seq()))
        row = {"t": round(time.monotonic() - self.started, 3), "round": self.eval_round,
               "env_steps": steps, "iterations": self.clock.units_at(steps) if iterations is None else iterations,
               "updates": (self.stats.updates if self.stats else 0) if updates is None else updates,
               "purpose": purpose, "seed": seed, "returns": returns, "mean": means, "versions": versions,
               "bias": None}
        self.eval_log.write(row)
        self.last_eval = row
        log.info("%s eval at %d steps: %s", purpose, steps, [None if m is None else round(m, 2) for m in means])
        return means

    def compete(self, steps: int) -> None:
        """One obsolescence round (Eq. 8), or the elimination at C."""
        units = self.clock.units_at(steps)
        eliminating = self.schedule.due_elimination(units)
        purpose = "elimination" if eliminating else "round"
        seed = evaluation_seed(self.algo.seed, purpose, units // self.algo.compete_every)
        means = self.evaluate(steps, seed, purpose)
        returns = competition_returns(means)  # no return: the lowest seen, never favoured
        best = best_actors(returns, self.schedule.live)
        self.schedule.record_evaluation(units, returns, rng=self.rng)  # a tie at C: the seeded rng picks
        self.decided_at = steps
        reason = "elimination" if eliminating else "round"
        self.publish_allocation(reason, returns=returns.tolist(), redraw=True, tie=best if len(best) > 1 else None)
        self.next_curve_eval = (units // self.algo.eval_every + 1) * self.algo.eval_every
        self._save_state()

    def publish_allocation(self, reason: str, returns: list[float] | None, redraw: bool = False,
                           tie: list[int] | None = None) -> None:
        """Slots keep their actor unless `redraw`; new workers draw with the current P. `tie`:
        the actors that shared the best return in this round (recorded in allocation.jsonl)."""
        live_workers = sorted(self.workers.live())
        self.drawn_over = set(live_workers)
        if redraw or self.schedule.survivor is not None or not self.schedule.enabled:
            self.slots = dict(self.schedule.allocation(live_workers, self.rng)) if live_workers else {}
        else:
            kept = {w: k for w, k in self.slots.items() if w in live_workers and self.schedule.live[k]}
            new = [w for w in live_workers if w not in kept]
            if new:
                kept.update(self.schedule.allocation(new, self.rng))
            self.slots = kept
        if self.schedule.survivor is not None and self.algo.single_env and self.slots:
            first = sorted(self.slots)[0]
            self.slots = {first: self.schedule.survivor}
        i_k = counts(self.slots, self.algo.actors).astype(int).tolist()
        steps = self.decided_at  # when the current P was decided (the learner's round barrier reads it)
        msg = Allocation(self.schedule.round, steps, None if returns is None else tuple(returns),
                         tuple(float(p) for p in self.schedule.probabilities), tuple(i_k), dict(self.slots),
                         tuple(bool(e) for e in self.schedule.eliminated), self.schedule.survivor, reason)
        self.last_allocation = msg.to_bytes(self.id, self._next_seq())
        self.alloc_pub.put(self.last_allocation)
        self.last_publish = time.monotonic()
        now_steps = self.stats.env_steps if self.stats else steps
        self.alloc_log.write({"t": round(time.monotonic() - self.started, 3), "round": self.schedule.round,
                              "env_steps": max(now_steps, steps),
                              "iterations": self.clock.units_at(max(now_steps, steps)),
                              "updates": self.stats.updates if self.stats else 0,
                              "decided_at": steps, "returns": returns, "tie": tie,
                              "probabilities": [float(p) for p in self.schedule.probabilities], "counts": i_k,
                              "slots": dict(self.slots), "eliminated": [bool(e) for e in self.schedule.eliminated],
                              "survivor": self.schedule.survivor, "reason": reason})
        log.info("allocation (%s) round %d: P=%s I=%s", reason, self.schedule.round,
                 np.round(self.schedule.probabilities, 3).tolist(), i_k)

    def publish_report(self, final: bool = False) -> None:
        """The referee's counters on mam/<run>/stats/referee-<id> (rejections are visible there);
        `final` once the final evaluation is written (the learner waits for it)."""
        fields = {"round": self.schedule.round, "rejected": self.rejects.counts()}
        if final:
            fields["final"] = True
        self.report.publish(fields, seq=self._next_seq, force=final)

    def final_evaluation(self) -> None:
        """After the learner's `done`: evaluate the final weights and write summary.json."""
        time.sleep(0.5)  # the final weights are published just before done
        self.refresh()
        steps = self.stats.env_steps if self.stats else 0
        seed = evaluation_seed(self.algo.seed, "final")
        means = self.evaluate(steps, seed, "final")
        self.write_summary(steps, means, seed, list(self.versions))

    def write_summary(self, steps: int, means: list[float | None], seed: int, versions: list[int]) -> None:
        """summary.json: the final evaluation (`mam eval` reproduces it from `final_eval`)."""
        survivor = self.schedule.survivor
        if survivor is None and any(m is not None for m in means):
            survivor = None if self.algo.actors > 1 else 0
        write_json(self.run_dir / rundir.SUMMARY, {
            "run": self.cfg.run, "env_id": self.cfg.env_id, "algo": self.algo.algo,
            "final_returns": means, "survivor": survivor, "env_steps": steps,
            "iterations": self.clock.units_at(steps), "schedule": self.algo.schedule,
            "final_eval": {"seed": seed, "episodes": self.algo.eval_episodes,
                           "versions": versions},  # `mam eval` reproduces it from these
            "collection": self.cfg.collection,
            "exact": bool(self.stats.exact) if self.stats else False,
            "inexact": self.stats.inexact if self.stats else "",
            "updates": self.stats.updates if self.stats else 0,
            "wall_time_s": round(time.monotonic() - self.started, 2),
            "rounds": self.schedule.round, "probabilities": self.schedule.probabilities.tolist(),
            "rejected": self.rejects.counts()})
        # The learner stays up until it sees this (a restarted referee still needs its caches).
        for _ in range(3):  # the last put before close can be lost
            self.publish_report(final=True)
            time.sleep(0.1)

    def _next_seq(self) -> int:
        self.seq += 1
        return self.seq


def main(run: str, conf: Any, run_dir: Path) -> None:
    from services import runlock

    try:  # one referee per run directory, none in a directory another `mam run` owns
        lock = runlock.lock_role(run_dir, "referee", run)
    except runlock.RunInUse as e:
        log.error("%s", e)
        raise SystemExit(runlock.EXIT_REFUSED) from None
    with lock, bus.session_scope(conf, retry_for=30.0) as session:
        cfg = role.fetch_config(session, run, bus.RejectLog(log, "config"))
        referee = Referee(cfg, session, run_dir)
        role.stop_on_signals(referee)
        referee.serve()


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
    options.check_run_name(run)
    main(run, role.client_config(connect, listen, zenoh_config), run_dir or Path("runs") / run)


cli = app  # the `mam-referee` entry point


if __name__ == "__main__":
    cli()
