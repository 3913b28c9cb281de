"""One run of a `mam experiment` grid as its own process: `python -m mam_lab.experiment_run RUN_DIR`.

`mam experiment` writes RUN_DIR/launch.json and starts this module once per run, with stdout and
stderr going to RUN_DIR/launcher.log. Its learner is pinned to the cores it was given (the
referee and workers float), then it trains the run with
`services.run.launcher.run_local` (the same as `mam run`). Its exit status is the run's outcome:

    0    finished (summary.json written)
    130  interrupted (SIGINT or SIGTERM: the launcher stopped every process of the run)
    1    failed (a process of the run failed, or anything else went wrong; see launcher.log)

launch.json: {"config": RunConfig dict, "cores": [core ids] or null, "plot": bool}.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import traceback
from pathlib import Path
from typing import Any

from services.run import rundir

FINISHED, FAILED, INTERRUPTED = 0, 1, 130
LAUNCH_FILE = rundir.LAUNCH


class _Stop(Exception):
    """SIGTERM before the launcher took over signal handling."""


def _on_term(signum: int, _frame: Any) -> None:
    raise _Stop(signal.Signals(signum).name)


def pin(cores: Any) -> list[int] | None:
    """Restrict this process (and what it starts) to `cores`; None or [] leaves the affinity alone."""
    if not cores:
        return None
    wanted = {int(c) for c in cores}
    os.sched_setaffinity(0, wanted)
    return sorted(os.sched_getaffinity(0))


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGTERM, _on_term)
    if len(argv) != 1:
        print("usage: python -m mam_lab.experiment_run RUN_DIR", file=sys.stderr)
        return FAILED
    run_dir = Path(argv[0])
    stops: tuple[type[BaseException], ...] = (KeyboardInterrupt, _Stop)
    try:
        spec = json.loads((run_dir / LAUNCH_FILE).read_text())
        from services.run.cluster import LEARNER_CPUS_ENV

        cores = spec.get("cores")
        if cores:  # the learner, where a run spends its CPU, gets the run's cores; the rest float
            os.environ[LEARNER_CPUS_ENV] = ",".join(str(int(c)) for c in cores)
            print(f"pinned to cores {sorted(int(c) for c in cores)} (the learner; referee and workers float)",
                  flush=True)
        from rich.console import Console

        from services.run.config import RunConfig
        from services.run.errors import Interrupted
        from services.run.launcher import run_local

        stops = (*stops, Interrupted)  # a signal while the launcher starts its processes

        cfg = RunConfig.from_dict(spec["config"])
        console = Console(file=sys.stdout, width=120, force_terminal=False, color_system=None)
        outcome: dict[str, Any] = {}
        from mam_lab.provenance import run_code

        summary = run_local(cfg, run_dir, console=console, plot=bool(spec.get("plot", False)), outcome=outcome,
                            code=run_code())  # RUN_DIR/code.json: a continue compares its library versions
    except BaseException as e:  # noqa: BLE001 - the exit status is the only report
        if isinstance(e, stops):
            print(f"interrupted ({type(e).__name__})", flush=True)
            return INTERRUPTED
        traceback.print_exc()
        return FAILED
    finally:
        sys.stdout.flush()
    if outcome.get("interrupted"):
        return INTERRUPTED
    return FINISHED if summary and (run_dir / rundir.SUMMARY).is_file() else FAILED


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
