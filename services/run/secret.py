"""The per-run secret that closes a local run (`mam run`) to every process but its own.

At the start of each part `mam run` writes a fresh random password to RUN_DIR/zenoh-auth: one
`mam:<password>` line, mode 0600 (Zenoh's user-password dictionary format). Its children find the
file through their environment (bus.AUTH_ENV), never on their command line, which `ps` shows to
every user. Every session opened with it presents the password, and the learner, which listens,
admits only sessions that present it (bus.make_config): a process without it cannot connect, so
it can neither publish a batch nor answer an episode query. `mam watch --run NAME`, run by the
same user, reads the file from the run directory. The file goes when the part ends (one that
stops before it starts its children, on a write error, may leave it: the next part replaces it).

It keeps out other users and processes that cannot read the run directory's file; a process of
the same Unix user can read the file (docs/DESIGN-DECISIONS.md, "Who may join a local run").
"""

from __future__ import annotations

import contextlib
import os
import secrets
from pathlib import Path

from services.messaging import bus
from services.run import rundir

USER = "mam"


def create(run_dir: Path) -> Path:
    """A fresh secret for this part of the run, readable by this user alone; its path."""
    path = Path(run_dir) / rundir.RUN_SECRET
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(f"{USER}:{secrets.token_urlsafe(32)}\n")
    os.replace(tmp, path)  # a previous part's file is replaced whole: its processes cannot rejoin
    return path


def child_env(path: Path | None) -> dict[str, str]:
    """What a child of the run adds to its environment to join the run (nothing without a secret)."""
    return {bus.AUTH_ENV: str(path)} if path is not None else {}


def of_run(run_dir: Path | None) -> Path | None:
    """The secret of the run in `run_dir`, if it has one this process can read (the same user)."""
    if run_dir is None:
        return None
    path = Path(run_dir) / rundir.RUN_SECRET
    return path if path.is_file() and os.access(path, os.R_OK) else None


def remove(path: Path | None) -> None:
    """The part is over: nobody may join it any more."""
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()
