"""`mam chaos`: a `mam run` while a driver SIGKILLs one of its children at random every 20–40 s.

    mam chaos [--kill-every 20,40] [--chaos-seed 0] [--roles learner,referee,worker] [--kill-learner-early]
              [--out FILE] -- MAM RUN FLAGS

Runs `mam run MAM RUN FLAGS --no-plot` (a `--run-dir` is required), and until it exits kills a
random live child (the learner included) with SIGKILL after a uniformly drawn 20–40 s, once every
child is back from the previous kill and the learner has logged transitions since it. Then it
checks what `mam run` promises (docs/RELIABILITY.md): exit status 0, the budget reached,
every transition a worker sent in the replay exactly once over all incarnations (transport.json's
`audit`: lost and duplicated rows), the run directory complete, the final checkpoint and its
replay loadable, and the run still the seed's: `summary.json` says `exact: true` and every
array of the final policy equals the fault-free run's with the same seed (the one-process
reference, which a fault-free `mam run` equals bit for bit; `--no-compare` skips it). Prints
the figures as JSON and writes them to RUN_DIR/chaos.json (or --out). Exit status 0 if every
check passed.

`--kill-learner-early` adds four learner kills at fixed moments (EARLY_MOMENTS, reported in
`early_kills`): before its first checkpoint is on disk, at its first transitions, when the random
phase ends and half way through the budget — the window where a restarted learner once resumed
from nothing and the run hung (issue 20).
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import typer

from services.run import options, rundir

ROOT = Path(__file__).resolve().parents[1]
ROLES = ("learner", "referee", "worker")
# --kill-learner-early: (name, transitions the learner must have reached; None: before any checkpoint)
EARLY_MOMENTS = ("before the first checkpoint", "at the first transitions", "at the end of the random phase",
                 "half way")
RUN_FILES = (rundir.CONFIG, rundir.LEARNER_LOG, rundir.EVAL, rundir.ALLOCATION, rundir.SUMMARY, rundir.TRANSPORT,
             rundir.REFEREE_STATE, f"{rundir.CHECKPOINTS}/{rundir.LEARNER_CHECKPOINT}", rundir.role_log("learner"),
             rundir.role_log("referee"))


def children_of(pid: int) -> list[tuple[int, str]]:
    """(pid, role) of the live `services.roles.<role>` processes whose parent is `pid`."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            state = stat.rsplit(")", 1)[1].split()[0]
            if ppid != pid or state == "Z":
                continue
            args = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        for a in args:
            name = a.decode(errors="replace")
            if name.startswith("services.roles.") and name.rsplit(".", 1)[1] in ROLES:
                out.append((int(entry.name), name.rsplit(".", 1)[1]))
    return out


def verify(run_dir: Path, returncode: int) -> dict[str, Any]:
    """The figures of a finished (or failed) run and the list of checks that failed."""
    problems: list[str] = []
    figures: dict[str, Any] = {"exit_status": returncode}
    if returncode != 0:
        problems.append(f"mam run exited with {returncode}")
    missing = [name for name in RUN_FILES if not (run_dir / name).is_file()]
    if missing:
        problems.append(f"run directory incomplete: {missing}")
    cfg, summary, transport = ({} if not (run_dir / name).is_file() else json.loads((run_dir / name).read_text())
                               for name in (rundir.CONFIG, rundir.SUMMARY, rundir.TRANSPORT))
    audit = transport.get("audit", {})
    budget = cfg.get("steps", 0)
    figures.update(budget=budget, env_steps=transport.get("env_steps"), updates=transport.get("updates"),
                   restarts=summary.get("restarts"), restarts_total=summary.get("restarts_total"),
                   restarts_cancelled=sum((summary.get("restarts_cancelled") or {}).values()),
                   sent_rows=audit.get("sent_rows"), replay_rows=audit.get("replay_rows"),
                   skipped_rows=audit.get("skipped_rows", 0),
                   lost_rows=audit.get("lost_rows"), duplicated_rows=audit.get("duplicated_rows"),
                   worker_incarnations=audit.get("streams"), lost_batches=transport.get("lost"),
                   duplicate_batches=transport.get("duplicates"), recovered_batches=transport.get("recovered"),
                   redundant_batches=transport.get("redundant"), rejected=transport.get("rejected"),
                   wall_time_s=summary.get("launcher_wall_time_s"))
    if not transport.get("env_steps", 0) >= budget > 0:
        problems.append(f"budget not reached: {transport.get('env_steps')} of {budget}")
    if not audit:
        problems.append("no transport audit")
    else:
        if audit["lost_rows"] or audit["duplicated_rows"]:
            problems.append(f"{audit['lost_rows']} rows lost, {audit['duplicated_rows']} duplicated")
        if audit["streams_without_log"]:
            problems.append(f"streams without a worker log: {audit['streams_without_log']}")
        if not audit["sent_rows"] - audit.get("skipped_rows", 0) == audit["replay_rows"] == transport.get("env_steps"):
            problems.append("rows sent (less those skipped), rows in the replay and env_steps differ")
    try:
        import torch

        from mam_core.agent import EnvSpec, MultiActorAgent
        from mam_core.config import AlgoConfig
        from services.roles.checkpoint import load_checkpoint, load_replay

        state = load_checkpoint(run_dir)
        agent = MultiActorAgent(AlgoConfig.from_dict(cfg["algo"]), EnvSpec.from_env_id(cfg["env_id"]),
                                torch.device("cpu"))
        agent.load_state_dict(state["agent"])
        figures["checkpoint_updates"] = agent.updates
        if cfg.get("save_replay", True):
            figures["checkpoint_replay_rows"] = len(load_replay(run_dir, state=state))
            if figures["checkpoint_replay_rows"] != min(transport.get("env_steps", -1), cfg["algo"]["buffer_size"]):
                problems.append(f"the final replay holds {figures['checkpoint_replay_rows']} rows")
    except Exception as e:  # noqa: BLE001 - any failure to load is a finding
        problems.append(f"final checkpoint does not load: {type(e).__name__}: {e}")
    figures["problems"] = problems
    return figures


def compare_with_fault_free(run_dir: Path, figures: dict[str, Any]) -> None:
    """`exact` and `equal_to_fault_free` (with its wall time): the final policy against the
    one-process reference with the run's config and seed; a difference is a problem."""
    import numpy as np

    from mam_core import gemm
    from mam_core.policy import read_policy_file
    from mam_core.reference import run_reference
    from services.run.config import RunConfig

    summary = json.loads((run_dir / rundir.SUMMARY).read_text()) if (run_dir / rundir.SUMMARY).is_file() else {}
    figures["exact"], figures["inexact"] = summary.get("exact"), summary.get("inexact", "")
    if summary.get("exact") is not True:
        figures["problems"].append(f"the run is not exact: {summary.get('inexact') or 'summary.json says nothing'}")
    started = time.monotonic()
    try:
        cfg = RunConfig.from_dict(json.loads((run_dir / rundir.CONFIG).read_text()))
        gemm.use_learner_threads(cfg.learner_threads)  # the learner's arithmetic (mam_core/gemm.py)
        ref = run_reference(cfg.env_id, cfg.algo, cfg.steps, cfg.env_kwargs)
        _, params = read_policy_file(run_dir / rundir.CHECKPOINTS / "policy.npz")
    except Exception as e:  # noqa: BLE001 - a comparison that cannot be made is a finding
        figures["equal_to_fault_free"] = None
        figures["problems"].append(f"no comparison with the fault-free run: {type(e).__name__}: {e}")
        return
    equal = len(params) == len(ref.policy) and all(
        set(a) == set(b) and all(np.array_equal(a[n], b[n]) for n in a) for a, b in zip(params, ref.policy))
    figures["equal_to_fault_free"] = equal
    figures["fault_free_wall_time_s"] = round(time.monotonic() - started, 1)
    if not equal:
        figures["problems"].append("the final policy differs from the fault-free run's with the same seed")


def _early_thresholds(run_dir: Path) -> list[int | None]:
    """The transitions of EARLY_MOMENTS for the run in `run_dir` (its config.json)."""
    from mam_core.schedule import Schedule
    from services.run.config import RunConfig

    cfg = RunConfig.from_dict(json.loads((run_dir / rundir.CONFIG).read_text()))
    s = Schedule.for_run(cfg.algo, cfg.steps)
    return [None, 1, max(s.random_until, 2), max(s.budget // 2, s.random_until + 1)]


def _early_kill(proc: subprocess.Popen, run_dir: Path, moments: list[int | None], done: list[dict[str, Any]],
                started: float, log) -> None:
    """Kill the learner at the next of EARLY_MOMENTS once it is reached (one per call at most)."""
    i = len(done)
    if i >= len(moments):
        return
    learners = [pid for pid, role in children_of(proc.pid) if role == "learner"]
    if not learners or (done and learners[0] == done[-1].get("pid")):
        return
    # What this learner reached: the rows it wrote itself (after the previous kill), not its predecessor's.
    steps = _learner_steps(run_dir, done[-1]["log_bytes"] if done and "log_bytes" in done[-1] else 0)
    if moments[i] is None:  # the learner is up, and no checkpoint generation is on disk yet
        if rundir.has_checkpoint(run_dir):
            done.append({"moment": EARLY_MOMENTS[i], "missed": "a checkpoint was already on disk"})
            return
    elif steps < moments[i]:
        return
    try:
        os.kill(learners[0], signal.SIGKILL)
    except ProcessLookupError:
        return
    try:
        size = (run_dir / rundir.LEARNER_LOG).stat().st_size
    except OSError:
        size = 0
    done.append({"moment": EARLY_MOMENTS[i], "t": round(time.monotonic() - started, 1), "pid": learners[0],
                 "env_steps": steps, "checkpoint_on_disk": rundir.has_checkpoint(run_dir), "log_bytes": size})
    log(f"t={done[-1]['t']:7.1f} s  SIGKILL learner (pid {learners[0]}) {EARLY_MOMENTS[i]} (~{steps:,} env steps)")


def chaos(run_args: list[str], run_dir: Path, kill_every: tuple[float, float] = (20.0, 40.0), seed: int = 0,
          roles: tuple[str, ...] = ROLES, log=print, timeout: float = 7200.0,
          kill_learner_early: bool = False, compare: bool = True) -> dict[str, Any]:
    """Run `mam run` with kills; returns the figures (see `verify`) with the kills made."""
    rng = random.Random(seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    out_path = run_dir / "chaos-mam-run.out"
    env = dict(os.environ, COLUMNS="160", PYTHONWARNINGS="ignore")
    started = time.monotonic()
    kills: list[dict[str, Any]] = []
    early: list[dict[str, Any]] = []
    moments: list[int | None] | None = None
    seen, last_steps = 0, -1  # the most children seen alive at once; the learner's transitions at the last kill
    with open(out_path, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *run_args, "--run-dir", str(run_dir),
                                 "--no-plot"], cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    log(f"mam run started (pid {proc.pid}); its output: {out_path}")
    try:
        next_kill = time.monotonic() + rng.uniform(*kill_every)
        while proc.poll() is None:
            if time.monotonic() - started > timeout:
                raise TimeoutError(f"mam run still going after {timeout:.0f} s")
            if kill_learner_early and len(early) < len(EARLY_MOMENTS):
                if moments is None and (run_dir / rundir.CONFIG).is_file():
                    try:
                        moments = _early_thresholds(run_dir)
                    except (OSError, ValueError, KeyError):
                        moments = None
                if moments is not None:
                    _early_kill(proc, run_dir, moments, early, started, log)
                time.sleep(0.05)
                continue  # the random kills wait until the early ones are made
            if time.monotonic() < next_kill:
                time.sleep(0.2)
                continue
            live = children_of(proc.pid)
            seen = max(seen, len(live))
            steps = _learner_steps(run_dir)
            if len(live) < seen or steps <= last_steps:
                # Progress gate: the next kill waits until every child is back and the learner has logged
                # transitions since the previous one. Kills on a bare timer could outpace restarts on a
                # slow box (backoffs grow with each quick death) and keep the run from its budget.
                time.sleep(0.2)
                continue
            victims = [(pid, role) for pid, role in live if role in roles]
            if victims:
                pid, role = rng.choice(sorted(victims))
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue
                last_steps = steps
                kills.append({"t": round(time.monotonic() - started, 1), "role": role, "pid": pid, "env_steps": steps})
                log(f"t={kills[-1]['t']:7.1f} s  SIGKILL {role} (pid {pid}) at ~{steps:,} env steps")
            next_kill = time.monotonic() + rng.uniform(*kill_every)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(120)
    figures = verify(run_dir, proc.returncode)
    if compare:
        log("comparing the final policy with the fault-free run's (the one-process reference) ...")
        compare_with_fault_free(run_dir, figures)
    by_role: dict[str, int] = {}
    for k in kills:
        by_role[k["role"]] = by_role.get(k["role"], 0) + 1
    if kill_learner_early:
        made = [k for k in early if "missed" not in k]
        figures["early_kills"] = early
        if len(made) < len(EARLY_MOMENTS):
            figures["problems"].append(f"{len(made)} of {len(EARLY_MOMENTS)} early learner kills made "
                                       f"(the run ended or a moment was missed): {early}")
    figures.update(kills=len(kills), kills_by_role=by_role, kill_log=kills,
                   chaos_wall_time_s=round(time.monotonic() - started, 1), run_args=run_args)
    return figures


def _learner_steps(run_dir: Path, offset: int = 0) -> int:
    """env_steps of the last learner.jsonl row (of those after byte `offset`); 0 if none."""
    try:
        with open(run_dir / rundir.LEARNER_LOG, "rb") as f:
            f.seek(offset)
            lines = [ln for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
        return int(json.loads(lines[-1])["env_steps"]) if lines else 0
    except (OSError, ValueError, KeyError):
        return 0


app = typer.Typer(add_completion=False, help=__doc__)


@app.command(cls=options.PlainFlags, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def chaos_command(
    ctx: typer.Context,
    kill_every: str = typer.Option("20,40", help="seconds between kills, drawn uniformly from MIN,MAX"),
    seed: int = typer.Option(0, "--chaos-seed", help="seed of the kill schedule and of the victims"),
    roles: str = typer.Option(",".join(ROLES), help="roles that may be killed"),
    out: Path = typer.Option(None, help="write the figures here (default RUN_DIR/chaos.json)"),
    kill_learner_early: bool = typer.Option(False, "--kill-learner-early",
                                            help="first kill the learner before its first checkpoint, at its first "
                                                 "transitions, at the end of the random phase and half way"),
    compare: bool = typer.Option(True, "--compare/--no-compare",
                                 help="check the final policy against the fault-free run with the same seed (the "
                                      "one-process reference: as long again as a one-process run)"),
) -> None:
    """Kill random children of a `mam run` with SIGKILL and check that the run still finishes.

    Pass the `mam run` flags after these options, `--run-dir DIR` among them (required)."""
    args = list(ctx.args)
    if "--run-dir" not in args:
        raise typer.BadParameter("pass the mam run flags after the chaos flags, --run-dir DIR among them")
    i = args.index("--run-dir")
    run_dir = Path(args[i + 1])
    del args[i:i + 2]
    lo, hi = (float(x) for x in kill_every.split(","))
    figures = chaos(args, run_dir, (lo, hi), seed, tuple(r.strip() for r in roles.split(",") if r.strip()),
                    kill_learner_early=kill_learner_early, compare=compare)
    path = out or run_dir / rundir.CHAOS
    path.write_text(json.dumps(figures, indent=2))
    print(json.dumps({k: v for k, v in figures.items() if k != "kill_log"}, indent=2))
    if figures["problems"]:
        raise typer.Exit(1)


def cli() -> None:
    app()


if __name__ == "__main__":
    cli()
