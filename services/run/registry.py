"""Where local runs listen: a small registry that `mam run` writes and `mam watch --run NAME` reads.

`mam run` listens on a free loopback port. It records the run's name, endpoint, run directory
and its own pid in `<registry>/<run>.json` while it runs (and removes the entry at the end),
where `<registry>` is `$MAM_RUNS_REGISTRY`, else `$XDG_RUNTIME_DIR/mam/runs`, else
`~/.cache/mam/runs`. An entry whose process is gone is stale and ignored. The run directory's
`config.json` (`endpoint`) says the same for a run started from the current directory.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from services.run import rundir
from services.run.rundir import write_json

REGISTRY_ENV = "MAM_RUNS_REGISTRY"


def registry_dir() -> Path:
    if os.environ.get(REGISTRY_ENV):
        return Path(os.environ[REGISTRY_ENV])
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isdir(runtime) and os.access(runtime, os.W_OK):
        return Path(runtime) / "mam" / "runs"
    return Path.home() / ".cache" / "mam" / "runs"


def register(run: str, endpoint: str, run_dir: Path) -> Path | None:
    """Record a live local run (best effort: a registry that cannot be written is skipped)."""
    path = registry_dir() / f"{run}.json"
    try:
        write_json(path, {"run": run, "endpoint": endpoint, "run_dir": str(Path(run_dir).resolve()),
                          "pid": os.getpid()})
    except OSError:
        return None
    return path


def unregister(run: str) -> None:
    path = registry_dir() / f"{run}.json"
    try:
        if json.loads(path.read_text()).get("pid") == os.getpid():
            path.unlink()
    except (OSError, ValueError):
        pass


def _alive(pid: Any) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def lookup(run: str, run_dir: Path | None = None) -> tuple[str, str, Path] | None:
    """(endpoint, where it was found, run directory) of a local run, or None: `run_dir`'s
    config.json if given, else a live registry entry, else ./runs/<run>/config.json."""
    if run_dir is not None:
        return _from_config(run, Path(run_dir) / rundir.CONFIG)
    entry = registry_dir() / f"{run}.json"
    try:
        data = json.loads(entry.read_text())
        if data.get("run") == run and _alive(data.get("pid")) and data.get("endpoint"):
            return str(data["endpoint"]), str(entry), Path(data.get("run_dir") or Path("runs") / run)
    except (OSError, ValueError, AttributeError, TypeError):
        pass
    return _from_config(run, Path("runs") / run / rundir.CONFIG)


def _from_config(run: str, path: Path) -> tuple[str, str, Path] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and data.get("run") == run and data.get("endpoint"):
        return str(data["endpoint"]), str(path), path.parent
    return None


def places(run: str, run_dir: Path | None = None) -> str:
    """Where `lookup` looks, for the waiting message."""
    if run_dir is not None:
        return str(Path(run_dir) / rundir.CONFIG)
    return f"{registry_dir() / (run + '.json')} and {Path('runs') / run / rundir.CONFIG}"
