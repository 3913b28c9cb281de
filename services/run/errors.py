"""How `mam run` stops: the launcher's exceptions, and an exit status in words."""

from __future__ import annotations

import signal
from typing import Any


class Interrupted(Exception):
    """SIGTERM / SIGINT reached the launcher."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class RunStopped(Exception):
    """The launcher stops the run (exit status 1) and says why."""


class RunStalled(RunStopped):
    """No progress for `stall_timeout` seconds, and restarting the stuck child did not help."""


class RoleKeepsDying(RunStopped):
    """A child (cluster.Child) died more often than the restart policy allows."""

    def __init__(self, child: Any, restarts: int, window_s: float) -> None:
        super().__init__(f"{child.role} keeps dying: exited with {describe_exit(child.proc.returncode)}, "
                         f"{restarts} restarts within {window_s:.0f} s; see {child.log}")
        self.child = child


def describe_exit(rc: int | None) -> str:
    if rc is None:
        return "nothing (running)"
    if rc < 0:
        try:
            return f"{rc} ({signal.Signals(-rc).name})"
        except ValueError:
            return str(rc)
    return str(rc)
