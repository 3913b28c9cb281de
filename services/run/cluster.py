"""The child processes of one `mam run` on this box, supervised (`LocalCluster`).

`LocalCluster` starts the learner, the referee and the M workers with `subprocess` (Zenoh sessions
do not survive `fork`), each logging to RUN_DIR/logs/<role>.log; restarts one that dies, with
backoff, the learner with `--resume` (`RestartPolicy`); watches for a stall (`check_stall`) and
stops them all, the learner first (`stop`). The launcher (launcher.py) runs the loop around it.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from services.messaging.codec import LearnerStats
from services.run import preflight, rundir, runlock, secret
from services.run.config import RunConfig
from services.run.errors import RoleKeepsDying, RunStalled, RunStopped, describe_exit
from services.run.rundir import disk_free, free_bytes, last_line

STOP_GRACE_S = 15.0
EXIT_WRITE_ERROR = 75  # the learner could not write its checkpoint (services/roles/checkpoint.py, same value)
EXIT_CORRUPT = 65  # no checkpoint generation verifies (services/roles/checkpoint.py, same value)
EXIT_CONFIG = preflight.EXIT_CONFIG  # 78: a configuration error (a device torch does not see); never restarted
LOW_DISK_BYTES = 1 << 20  # a child that dies with less than this free in the run directory: the disk is full
MAX_STALL_ACTIONS = 2  # watchdog restarts in a row without progress; one more stall stops the run
STARTUP_GRACE_S = 60.0  # the watchdog's limit until a (re)started learner's first stats arrive, if longer
# `mam experiment --parallel`: the cores of a run's learner ("0,1"); its referee and workers float
LEARNER_CPUS_ENV = "MAM_LEARNER_CPUS"
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Runs in the child before exec: SIGTERM it if the launcher dies (even by SIGKILL)."""
    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _child_setup(role: str) -> Callable[[], None]:
    """What a child runs before exec: die with the launcher; the learner also takes the cores
    named in LEARNER_CPUS_ENV (set by `mam experiment --parallel`: P runs' learners, where the
    CPU goes, do not fight, while the light referee and workers use whatever core is free —
    measured faster than pinning whole runs, docs/PERFORMANCE.md)."""
    cpus = os.environ.get(LEARNER_CPUS_ENV, "") if role == "learner" else ""
    cores = {int(c) for c in cpus.split(",") if c.strip().isdigit()}

    def setup() -> None:
        die_with_parent()
        if cores:
            try:
                os.sched_setaffinity(0, cores)
            except OSError:
                pass

    return setup


def slots_note(workers: int, slots_per_worker: int, cores: int) -> str | None:
    """A note for `mam run` when its worker processes outnumber the cores twice over and more:
    several slots a process cost less there (docs/PERFORMANCE.md)."""
    processes = math.ceil(workers / slots_per_worker)
    if cores < 1 or processes < 2 * cores:
        return None
    n = math.ceil(workers / cores)
    return (f"{processes} worker processes on {cores} core(s): --slots-per-worker {n} steps the {workers} slots in "
            f"{math.ceil(workers / n)} (one loop each; 0.85x the wall time of a 6-slot run on 2 cores, the same run: "
            "docs/PERFORMANCE.md)")


@dataclass
class RestartPolicy:
    """When and how often `mam run` restarts a child that died.

    A child that exits abnormally is started again after a backoff (backoff_s, doubling with
    each recent restart, at most backoff_max_s). More than `max_restarts` restarts of the
    same child within `window_s` seconds stop the run.
    """

    max_restarts: int = 5
    window_s: float = 300.0
    backoff_s: float = 1.0
    backoff_max_s: float = 15.0

    def __post_init__(self) -> None:
        if self.max_restarts < 0 or self.window_s <= 0:
            raise ValueError("max_restarts must be >= 0 and the restart window > 0")


@dataclass
class Child:
    role: str
    proc: subprocess.Popen
    log: Path
    args: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.monotonic)


@dataclass
class LocalCluster:
    """Child processes of one local run, supervised; `stop()` leaves nothing running.

    `children` holds the current incarnation of every role (learner, referee, worker-i);
    `supervise()` restarts those that died (see RestartPolicy) until the run is done or stopping.
    """

    cfg: RunConfig
    run_dir: Path
    endpoint: str
    children: list[Child] = field(default_factory=list)
    policy: RestartPolicy = field(default_factory=RestartPolicy)
    console: Console | None = None
    restarts: dict[str, list[float]] = field(default_factory=dict)  # role -> restart times
    cancelled: dict[str, int] = field(default_factory=dict)  # role -> restarts not made: the run finished first
    pending: dict[str, tuple[float, Child]] = field(default_factory=dict)  # role -> (due, dead child)
    stopping: bool = False
    done: bool = False  # the learner reported the budget reached
    lock_token: str = ""  # run.lock's token (services/run/runlock.py): lets the children into the run directory
    secret_file: Path | None = None  # RUN_DIR/zenoh-auth (services/run/secret.py): lets the children into its session
    # The stall watchdog (`check_stall`): the learner's last stats and when progress was last seen
    last_stats: LearnerStats | None = None
    last_stats_at: float | None = None
    progress: tuple[int, int] = (-1, -1)  # (env_steps, updates)
    progress_at: float = field(default_factory=time.monotonic)
    stall_actions: int = 0  # watchdog restarts since progress was last seen
    started_at: float = field(default_factory=time.monotonic)  # the launcher's start: the bar's clock
    done_at: float | None = None  # when the learner reported the budget reached
    parts: rundir.RunParts | None = None  # launcher.json, kept up to date by supervise
    waits: dict[str, str] = field(default_factory=dict)  # worker role -> what it waits for (its reports)

    def spawn(self, role: str, args: list[str]) -> Child:
        log_path = self.run_dir / rundir.LOGS / f"{role}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, **({runlock.LOCK_ENV: self.lock_token} if self.lock_token else {}),
                   **secret.child_env(self.secret_file))  # never on argv: `ps` shows that to every user
        with open(log_path, "ab") as out:
            proc = subprocess.Popen([sys.executable, "-m", f"services.roles.{role.split('-')[0]}", *args],
                                    stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, preexec_fn=_child_setup(role), env=env)
        child = Child(role, proc, log_path, list(args))
        self.children = [c for c in self.children if c.role != role] + [child]
        if role == "learner":  # its start-up counts as progress for the watchdog
            self.progress_at, self.last_stats_at = time.monotonic(), None
        return child

    def learner_args(self) -> list[str]:
        rd = str(self.run_dir)
        if rundir.has_checkpoint(self.run_dir):  # a verified generation's manifest; none: start afresh
            # Its endpoint is in config.json: it listens where the clients reconnect.
            return ["--resume", rd]
        return ["--run-config", str(self.run_dir / rundir.CONFIG), "--listen", self.endpoint, "--run-dir", rd]

    def start(self) -> None:
        """Every role at once: a worker imports its modules and makes its env while the learner
        imports torch, then connects as soon as the learner listens. Nothing is stepped early: a
        worker steps an iteration only once the referee's allocation covers it (lock-step)."""
        run, rd = self.cfg.run, str(self.run_dir)
        self.spawn("learner", self.learner_args())
        self.spawn("referee", ["--run", run, "--connect", self.endpoint, "--run-dir", rd])
        m, n = self.cfg.algo.workers, self.cfg.slots_per_worker
        for first in range(0, m, n):  # a process a slot, or `slots_per_worker` slots in one loop (worker.py)
            slots = range(first, min(first + n, m))
            self.spawn(self.slot_role(first), ["--run", run, "--connect", self.endpoint,
                                               "--id", ",".join(f"w{i}" for i in slots),
                                               "--slot", ",".join(map(str, slots)), "--run-dir", rd])

    def slot_role(self, slot: int) -> str:
        """The child that steps `slot`: worker-<its first slot>."""
        return f"worker-{slot - slot % self.cfg.slots_per_worker}"

    def child(self, role: str) -> Child | None:
        return next((c for c in self.children if c.role == role), None)

    def finished(self) -> bool:
        """The learner has written its last checkpoint and transport.json and exited 0."""
        learner = self.child("learner")
        return (learner is not None and learner.proc.poll() == 0 and "learner" not in self.pending
                and (self.run_dir / rundir.TRANSPORT).is_file())

    def needs_restart(self, c: Child) -> bool:
        rc = c.proc.returncode
        if self.stopping or rc is None:
            return False
        if c.role != "learner" and self.finished():  # nothing left for it to do
            return False
        if c.role == "learner":  # exits 0 only when done (or stopped by the launcher)
            return rc != 0 or not (self.run_dir / rundir.TRANSPORT).is_file()
        if rc == 0 or rc == -signal.SIGTERM:
            return False
        if c.role == "referee":
            return not (self.run_dir / rundir.SUMMARY).is_file()
        return not self.done  # a worker after done has nothing left to do

    def supervise(self) -> None:
        """Restart children that died (after their backoff), and act on a stall (check_stall).
        Raises RunStopped (RoleKeepsDying, RunStalled, a fatal exit)."""
        now = time.monotonic()
        if self.parts is not None and self.parts.due():
            self.parts.save(self.restart_counts())
        self.check_stall(now)
        for c in list(self.children):
            if c.role in self.pending or c.proc.poll() is None or not self.needs_restart(c):
                continue
            self.fatal_exit(c)
            recent = [t for t in self.restarts.get(c.role, []) if now - t <= self.policy.window_s]
            if len(recent) >= self.policy.max_restarts:
                raise RoleKeepsDying(c, len(recent), self.policy.window_s)
            delay = min(self.policy.backoff_s * 2 ** len(recent), self.policy.backoff_max_s)
            self.pending[c.role] = (now + delay, c)
            self._print(f"[yellow]{c.role} exited with {describe_exit(c.proc.returncode)}[/] after "
                        f"{now - c.started:.0f} s: restarting in {delay:.1f} s (see {c.log})")
        for role, (due, dead) in list(self.pending.items()):
            if now < due or self.stopping:
                continue
            del self.pending[role]
            if not self.needs_restart(dead):  # e.g. the run finished meanwhile
                self.cancelled[role] = self.cancelled.get(role, 0) + 1
                continue
            self.restarts.setdefault(role, []).append(now)
            try:
                with open(dead.log, "ab") as out:
                    out.write(f"\n--- mam run: {role} exited with {describe_exit(dead.proc.returncode)}; "
                              f"restart {len(self.restarts[role])} ---\n".encode())
            except OSError as e:  # a full disk: say so, do not crash
                self._print(f"[red]cannot write to {dead.log}: {e.strerror or e} ({disk_free(self.run_dir)} free)[/]")
            args = self.learner_args() if role == "learner" else dead.args
            try:
                new = self.spawn(role, args)
            except OSError as e:
                raise RunStopped(f"cannot restart {role}: {e} ({disk_free(self.run_dir)} free in {self.run_dir})") \
                    from None
            what = " (resuming from its checkpoint)" if role == "learner" and "--resume" in args else ""
            self._print(f"[yellow]restarted[/] {role}{what}: pid {new.proc.pid}, "
                        f"restart {len(self.restarts[role])} of this run")

    def fatal_exit(self, c: Child) -> None:
        """RunStopped for an exit that a restart cannot mend: the learner cannot write its
        checkpoint (EXIT_WRITE_ERROR), a child refused the run directory, the disk is full, a
        configuration error (EXIT_CONFIG: its one-line reason is the message)."""
        rc = c.proc.returncode
        if rc == EXIT_CONFIG:
            line = last_line(c.log, preflight.CONFIG_ERROR)
            reason = line[line.index(preflight.CONFIG_ERROR):] if line else "configuration error"
            raise RunStopped(f"{c.role} stopped on a {reason} (not restarted; see {c.log})")
        if rc == EXIT_WRITE_ERROR or (rc != 0 and free_bytes(self.run_dir) < LOW_DISK_BYTES):
            line = last_line(c.log, "stopping:")
            raise RunStopped(f"{c.role} cannot write to {self.run_dir} ({disk_free(self.run_dir)} free there)"
                             f"{': ' + line if line else ''}; the last verified checkpoint is intact; see {c.log}")
        if c.role == "learner" and rc == EXIT_CORRUPT:
            line = last_line(c.log, "stopping:")
            raise RunStopped(f"the learner cannot resume: {line or 'no checkpoint generation verifies'}; see {c.log}")
        if rc == runlock.EXIT_REFUSED:
            line = last_line(c.log, "refusing")
            raise RunStopped(f"{c.role} refused to start{': ' + line if line else ''}; see {c.log}")

    def observe(self, st: LearnerStats) -> None:
        """The learner's stats, for the stall watchdog."""
        self.last_stats, self.last_stats_at = st, (now := time.monotonic())
        if (st.env_steps, st.updates) != self.progress:
            self.progress, self.progress_at, self.stall_actions = (st.env_steps, st.updates), now, 0

    def check_stall(self, now: float) -> None:
        """The watchdog: no new transition and no new update for `stall_timeout` seconds. It prints
        what each side waits for and SIGKILLs the stuck child (supervise restarts it, the learner with
        --resume); after MAX_STALL_ACTIONS such restarts without progress RunStalled stops the run."""
        limit = self.cfg.stall_timeout
        if self.last_stats_at is None and limit > 0:  # a learner starting up (torch, a resume) gets longer
            limit = max(limit, STARTUP_GRACE_S)
        if limit <= 0 or self.done or self.stopping or self.pending or now - self.progress_at < limit:
            return
        diagnosis, victims = self.diagnose(now)
        if self.stall_actions >= MAX_STALL_ACTIONS or not victims:
            raise RunStalled(f"the run is stalled: {diagnosis}"
                             + (f"; {self.stall_actions} watchdog restarts did not help" if self.stall_actions else ""))
        self.stall_actions += 1
        self._print(f"[red]stalled[/]: {diagnosis}: restarting {', '.join(c.role for c in victims)}")
        for c in victims:
            if c.proc.poll() is None:
                c.proc.kill()  # SIGKILL also ends a frozen (SIGSTOPped) process
        self.progress_at = now  # a full period for the restarted children

    def diagnose(self, now: float) -> tuple[str, list[Child]]:
        """What the run waits for (from the learner's last stats) and the children to restart."""
        limit = self.cfg.stall_timeout
        learner, referee = self.child("learner"), self.child("referee")
        workers = [c for c in self.children if c.role.startswith("worker") and c.proc.poll() is None]
        st, age = self.last_stats, (now - self.last_stats_at) if self.last_stats_at is not None else None
        head = f"no new transition or update for {now - self.progress_at:.0f} s"
        ref = "referee " + ("running" if referee is not None and referee.proc.poll() is None else "down")
        if st is None or age is None or age > limit:
            seen = "never" if age is None else f"not for {age:.0f} s"
            return (f"{head}; learner stats: {seen} (the learner is frozen, blocked or cut off); {ref}",
                    [learner] if learner is not None and learner.proc.poll() is None else [])
        facts = (f"learner at iteration {st.iteration:,} ({st.env_steps:,} transitions, {st.updates:,} updates), "
                 f"versions {list(st.versions)}, {st.workers} workers, rejected {dict(st.rejected) or 'none'}, {ref}")
        if -1 in st.awaiting:
            return (f"{head}; {facts}: waiting for the referee's elimination decision",
                    [referee] if referee is not None and referee.proc.poll() is None else [learner])
        if st.awaiting:
            slots = [a for a in st.awaiting if a >= 0]
            stuck = [c for c in workers if c.role in {self.slot_role(i) for i in slots}]
            text, blamed = waited_on(stuck, self.waits, learner, referee)  # what their workers wait for
            return (f"{head}; {facts}: waiting for iteration {st.iteration + 1:,}'s transitions from slots {slots}"
                    f"{text}", blamed or stuck or workers)
        return f"{head}; {facts}: the learner waits for nothing and does not update", [learner]

    def restart_counts(self) -> dict[str, int]:
        return {c.role: len(self.restarts.get(c.role, [])) for c in self.children}

    def _print(self, text: str) -> None:
        (self.console or Console()).print(text)

    def failed(self) -> list[Child]:
        """Children that exited with an error."""
        return [c for c in self.children if c.proc.poll() not in (None, 0)]

    def running(self) -> list[Child]:
        return [c for c in self.children if c.proc.poll() is None]

    def wait(self, timeout: float, supervise: bool = False) -> bool:
        deadline = time.monotonic() + timeout
        while (self.running() or (supervise and self.pending)) and time.monotonic() < deadline:
            if supervise:
                self.supervise()
            time.sleep(0.1)
        return not self.running()

    def stop(self, grace: float = STOP_GRACE_S) -> None:
        """SIGTERM the learner, the others once it has left (it checkpoints, and the rows of updates
        it made ahead come from the workers), then SIGKILL what is still up after `grace`.
        Nothing is restarted from now on."""
        self.stopping = True
        for role in self.pending:  # waiting out their backoff when the run ended
            self.cancelled[role] = self.cancelled.get(role, 0) + 1
        self.pending.clear()
        for first in (True, False):
            for c in self.running():
                if (c.role == "learner") == first:
                    c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace
            while first and any(c.role == "learner" for c in self.running()) and time.monotonic() < deadline:
                time.sleep(0.05)
        if not self.wait(grace):
            for c in self.running():
                c.proc.kill()
            self.wait(5.0)


def waited_on(stuck: list[Child], waits: dict[str, str], learner: Child | None,
              referee: Child | None) -> tuple[str, list[Child]]:
    """What the workers of the awaited slots say they wait for (their reports' `waits`), as text
    for the stall diagnosis, and the children to restart for it: the learner when each waits for
    weights (a version the learner does not publish; restarted, it publishes the versions its
    checkpoint keeps), the referee when each waits for an allocation, else none (the workers)."""
    said = [(c.role, waits[c.role]) for c in stuck if waits.get(c.role)]
    if not stuck or len(said) < len(stuck):
        return "", []
    text = "; " + ", ".join(f"{role} waits for {what}" for role, what in said)
    for child, what, why in ((learner, "actor ", "the learner does not publish it"),
                             (referee, "the allocation", "the referee has not decided it")):
        if child is not None and child.proc.poll() is None and all(w.startswith(what) for _, w in said):
            return f"{text} ({why})", [child]
    return text, []
