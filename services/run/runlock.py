"""One run per run directory and per run name (docs/RELIABILITY.md, "Faults beyond kills", the row
"two runs with one name or one run directory").

A run directory is locked by the processes that own it, with `fcntl.flock` on lock files in it
(held for the process's lifetime; the kernel releases them when it dies, even by SIGKILL):

    RUN_DIR/run.lock       `mam run` (the launcher); its children carry its token in MAM_RUN_LOCK
    RUN_DIR/learner.lock   the learner of the run (launched or split)
    RUN_DIR/referee.lock   the referee of the run (launched or split)
    EXP_DIR/experiment.lock   `mam experiment`, for the whole grid (`lock_experiment`)

`mam run` takes run.lock and refuses a directory whose learner or referee lock is held (a split
run lives there). A learner or referee takes its own lock and refuses a directory whose run.lock
is held by a `mam run` that is not its parent: the launcher writes a random token into run.lock
and passes it to its children in the environment (LOCK_ENV). A split learner and a split
referee may share a directory (the runbook does); a second of either is refused.

One `mam experiment` per experiment directory: a second one would take the first one's runs in
flight for stopped ones, and redo (delete) them when they refuse it. The grid also leaves alone a
run directory some process holds (`in_use`: a `mam run` started there by hand).

A second learner for a run name that is live on the same Zenoh network is refused too
(`refuse_live_learner`: the liveliness tokens mam/<run>/alive/learner/*).

Every refusal happens before the process writes anything but the lock file, with a message
naming the directory (or run) and the holder (pid, host, role, since when).
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
import uuid
from pathlib import Path
from typing import Any, Callable

RUN_LOCK = "run.lock"
EXPERIMENT_LOCK = "experiment.lock"
LOCK_ENV = "MAM_RUN_LOCK"  # the launcher's token, in its children's environment
EXIT_REFUSED = 73  # a role refused to start (its run directory or run name is in use)
LEASE_S = 12.0  # how long a learner token may linger after its process froze (Zenoh's lease is 10 s)
ORPHAN_WAIT_S = 60.0  # how long `mam run` waits for the children of a dead `mam run` of its directory to stop


class RunInUse(Exception):
    """The run directory or the run name is in use by another live process."""


def role_lock(role: str) -> str:
    return f"{role}.lock"


ROLE_LOCKS = (role_lock("learner"), role_lock("referee"))


class DirLock:
    """An flock held on RUN_DIR/<name> until `release` (or the process's death)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path, self.fd = path, fd
        self.token = ""

    def write(self, info: dict[str, Any]) -> None:
        data = json.dumps(info).encode()
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, data, 0)

    def release(self) -> None:
        if self.fd >= 0:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = -1

    def __enter__(self) -> "DirLock":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


def _try_lock(path: Path) -> DirLock | None:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    return DirLock(path, fd)


def holder(path: Path) -> dict[str, Any]:
    """What the holder of a lock wrote into it ({} if nothing yet)."""
    for _ in range(20):  # the holder writes just after it locks
        try:
            data = json.loads(path.read_text() or "{}")
        except (OSError, ValueError):
            data = {}
        if data:
            return data if isinstance(data, dict) else {}
        time.sleep(0.05)
    return {}


def describe(info: dict[str, Any]) -> str:
    if not info:
        return "another process"
    since = time.strftime("%H:%M:%S", time.localtime(info["started"])) if "started" in info else "?"
    of = "grid" if info.get("role") == "mam experiment" else "run"
    return f"{info.get('role', '?')} of {of} {info.get('run', '?')!r} (pid {info.get('pid', '?')} on " \
           f"{info.get('host', '?')}, since {since})"


def _info(role: str, run: str, token: str = "", launcher: str = "") -> dict[str, Any]:
    info = {"role": role, "run": run, "pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
    if token:
        info["token"] = token
    if launcher:  # the token of the `mam run` that started this learner or referee
        info["launcher"] = launcher
    return info


def _held(path: Path) -> bool:
    """True if someone holds the lock at `path` (probed without keeping it)."""
    if not path.exists():
        return False
    probe = _try_lock(path)
    if probe is None:
        return True
    probe.release()
    return False


def lock_run(run_dir: Path, run: str, orphan_wait_s: float = ORPHAN_WAIT_S,
             waiting: Callable[[str], None] | None = None) -> DirLock:
    """`mam run`'s lock on RUN_DIR (run.lock, with a token for its children); RunInUse if a
    `mam run`, a learner or a referee already lives there. A learner or referee started by a
    `mam run` that has died (killed: its children got SIGTERM and are checkpointing) is waited
    for, up to `orphan_wait_s`, and `waiting` told whom once."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / RUN_LOCK
    lock = _try_lock(path)
    if lock is None:
        raise RunInUse(f"run directory {run_dir} is in use by {describe(holder(path))}: refusing to start "
                       "(one run per directory; pass another --run-dir or --run)")
    deadline = time.monotonic() + orphan_wait_s
    while (orphans := [n for n in ROLE_LOCKS if _held(run_dir / n) and holder(run_dir / n).get("launcher")]) \
            and time.monotonic() < deadline:
        if waiting is not None:
            waiting(f"waiting for the stopping {describe(holder(run_dir / orphans[0]))} (its `mam run` was killed)")
            waiting = None
        time.sleep(0.2)
    who = in_use(run_dir, ROLE_LOCKS)
    if who is not None:
        lock.release()
        raise RunInUse(f"run directory {run_dir} is in use by {who}: refusing to start (one run per directory; "
                       "pass another --run-dir or --run)")
    lock.token = uuid.uuid4().hex
    lock.write(_info("mam run", run, lock.token))
    return lock


def in_use(run_dir: Path, names: tuple[str, ...] = (RUN_LOCK, *ROLE_LOCKS)) -> str | None:
    """Who holds one of RUN_DIR's locks `names` (a `mam run`, a learner or a referee), described;
    None if nobody does (or RUN_DIR does not exist)."""
    for name in names:
        if _held(run_dir / name):
            return describe(holder(run_dir / name))
    return None


def lock_experiment(exp_dir: Path, name: str) -> DirLock:
    """`mam experiment`'s lock on EXP_DIR (experiment.lock); RunInUse if another one holds it."""
    exp_dir.mkdir(parents=True, exist_ok=True)
    path = exp_dir / EXPERIMENT_LOCK
    lock = _try_lock(path)
    if lock is None:
        raise RunInUse(f"experiment directory {exp_dir} is in use by {describe(holder(path))}: refusing to start "
                       "(one `mam experiment` per directory; wait for it, or stop it with Ctrl-C: its runs "
                       "continue from their checkpoints when the grid runs again)")
    lock.write(_info("mam experiment", name))
    return lock


def lock_role(run_dir: Path, role: str, run: str) -> DirLock:
    """A learner's or referee's lock on RUN_DIR; RunInUse if another one of that role lives there,
    or a `mam run` that did not start this process owns the directory."""
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / role_lock(role)
    lock = _try_lock(path)
    if lock is None:
        raise RunInUse(f"run directory {run_dir} already has a live {role}: {describe(holder(path))}; refusing to "
                       "start a second one")
    run_path = run_dir / RUN_LOCK
    if _held(run_path):
        owner = holder(run_path)
        if not owner.get("token") or owner.get("token") != os.environ.get(LOCK_ENV):
            lock.release()
            raise RunInUse(f"run directory {run_dir} is owned by {describe(owner)}: refusing to start a {role} "
                           "there (use another --run-dir)")
    lock.write(_info(role, run, launcher=os.environ.get(LOCK_ENV, "")))
    return lock


def live_learners(session: Any, run: str, timeout: float = 2.0) -> list[str]:
    """Ids of the learners of `run` whose liveliness token is up on this Zenoh network."""
    from services.messaging import keys

    found = []
    for reply in session.liveliness().get(keys.alive_all(run, "learner"), timeout=timeout):
        try:
            found.append(keys.parse_alive(str(reply.ok.key_expr))[1])
        except (ValueError, AttributeError, TypeError):
            continue
    return found


def refuse_live_learner(session: Any, run: str, lease_s: float = LEASE_S) -> None:
    """RunInUse if a learner of `run` is live on the network this session reaches. A token that
    goes away within `lease_s` (a killed or frozen predecessor whose lease runs out) is no
    refusal."""
    deadline = time.monotonic() + lease_s
    while True:
        live = live_learners(session, run)
        if not live:
            return
        if time.monotonic() > deadline:
            raise RunInUse(f"run {run!r} already has a live learner on this Zenoh network ({', '.join(live)}): "
                           "refusing to start a second one (pick another --run name)")
        time.sleep(1.0)
