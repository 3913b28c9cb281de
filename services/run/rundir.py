"""The names of the files and folders of a run directory (and of an experiment directory).

One place for every name a process writes and a reader (plots, reports, the lab, `mam eval`)
looks for, so a rename is one edit. Plain string constants: importing this module costs nothing.

    RUN_DIR/config.json            the run's configuration (RunConfig.to_dict)
    RUN_DIR/summary.json           written by the referee when the run is done
    RUN_DIR/transport.json         the learner's transport counters at the end
    RUN_DIR/referee_state.json     the referee's state, for a restarted referee
    RUN_DIR/code.json              the code and library versions the run ran (services/run/codecheck.py)
    RUN_DIR/learner_epoch.json     the epoch of the run's latest learner incarnation (fencing)
    RUN_DIR/learner.jsonl          learner metrics (one row per log interval)
    RUN_DIR/eval.jsonl             evaluations (one row per evaluation point)
    RUN_DIR/allocation.jsonl       allocation rounds (I_k, P_k)
    RUN_DIR/bias.jsonl             Eq. 17 bias measurements (runs with --bias-every)
    RUN_DIR/checkpoints/learner.pt the learner's checkpoint; checkpoints/replay/ its replay chunks;
    RUN_DIR/checkpoints/policy.npz the exported policy (mam_core.policy.POLICY_FILE); both are links
                                   to the newest generation's learner-<g>.pt and policy-<g>.npz,
                                   which manifest-<g>.json verifies (services/roles/checkpoint.py)
    RUN_DIR/run.lock, learner.lock, referee.lock   who owns the directory (services/run/runlock.py)
    RUN_DIR/logs/<role>.log        each process's output (`mam run`)
    RUN_DIR/workers/               per-worker batch logs and end records
    RUN_DIR/plots/                 `mam plot` PNGs
    RUN_DIR/tb/                    TensorBoard event files
    RUN_DIR/launch.json, launcher.log, record.json   a run of a `mam experiment` grid
    RUN_DIR/launcher.json          `mam run`'s parts, restarts and wall time so far (RunParts)
    RUN_DIR/zenoh-auth             mode 0600: the per-run secret of a live `mam run` part (services/run/secret.py)

    EXP_DIR/experiment.json, report.md, figures/, failures/   a `mam experiment` directory
    EXP_DIR/experiment.lock        the `mam experiment` working there (services/run/runlock.py)

`read_json` and `read_jsonl` read them, for the plots, the reports and the lab alike: a file
that is missing, unreadable or (for JSONL) a row that is half written reads as nothing.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# --- a run directory ---------------------------------------------------------------------------
CONFIG = "config.json"
SUMMARY = "summary.json"
TRANSPORT = "transport.json"
REFEREE_STATE = "referee_state.json"
LEARNER_EPOCH = "learner_epoch.json"  # the learner's starts so far: each incarnation's epoch (fencing)
CODE = "code.json"  # the code fingerprint and library versions the run ran (services/run/codecheck.py)
LEARNER_LOG = "learner.jsonl"
EVAL = "eval.jsonl"
ALLOCATION = "allocation.jsonl"
BIAS = "bias.jsonl"
CHECKPOINTS = "checkpoints"
LEARNER_CHECKPOINT = "learner.pt"  # in CHECKPOINTS
REPLAY = "replay"  # in CHECKPOINTS: the replay buffer's chunk log
MANIFEST_GLOB = "manifest-*.json"  # in CHECKPOINTS: one per verified checkpoint generation
LOGS = "logs"
WORKERS = "workers"
PLOTS = "plots"
TB = "tb"
CHAOS = "chaos.json"  # `mam chaos`'s result
RUN_SECRET = "zenoh-auth"  # mode 0600, while a `mam run` part lives: who may join its Zenoh session

# --- a run of a `mam experiment` grid ------------------------------------------------------------
LAUNCH = "launch.json"  # what the run process is to do (written by the grid)
LAUNCHER_LOG = "launcher.log"  # the run process's stdout and stderr
RECORD = "record.json"  # which code ran it; in the ledger, written last: marks a finished run
TRAIN_RETURNS = "train_returns.jsonl"  # in the ledger: learner.jsonl's training-episode returns, every one

# --- an experiment directory (and a ledger) ----------------------------------------------------
EXPERIMENT = "experiment.json"
REPORT = "report.md"
FIGURES = "figures"
FAILURES = "failures"


def env_dirname(env: str) -> str:
    """An env id as a directory name (EXP_DIR/<env>/<variant>/seed<k>, figure names)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", env)


def has_checkpoint(run_dir: Path | str) -> bool:
    """A checkpoint generation is on disk (its manifest; services/roles/checkpoint.py verifies it)."""
    return any((Path(run_dir) / CHECKPOINTS).glob(MANIFEST_GLOB))


def role_log(role: str) -> str:
    """LOGS/<role>.log, relative to the run directory."""
    return f"{LOGS}/{role}.log"


# --- reading ---------------------------------------------------------------------------------


def read_json(path: Path | str) -> dict[str, Any]:
    """A JSON object file as a dict; {} when it is missing, unreadable or not an object."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):  # ValueError: JSONDecodeError, UnicodeDecodeError
        return {}
    return data if isinstance(data, dict) else {}


def read_jsonl(path: Path | str) -> list[dict[str, Any]]:
    """Rows of a JSONL file; blank, partial (a live run's last line) or corrupt lines are skipped.

    A missing file gives []. Only JSON objects count as rows.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return []
    lines = text.splitlines()
    last = max((i for i, line in enumerate(lines) if line.strip()), default=-1)
    rows: list[dict[str, Any]] = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if i != last:  # a trailing partial line is expected while a run is live; others are not
                log.warning("%s:%d: skipping corrupt line", path, i + 1)
            continue
        if isinstance(row, dict):
            rows.append(row)
    return rows


def write_json(path: Path, data: Any, durable: bool = False) -> None:
    """Atomic write: a reader never sees half a file. `durable`: on disk once this returns (fsync
    of the file before the rename, of the directory after it), for a state a restarted role goes
    on from (the referee's): after a power cut it is the new file or the old one, never empty."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(json.dumps(data, indent=2, sort_keys=True))
        if durable:
            f.flush()
            os.fsync(f.fileno())
    os.replace(tmp, path)
    if durable:
        try:
            fd = os.open(path.parent, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError:  # some file systems refuse a directory fsync
            pass
        finally:
            os.close(fd)


class JsonlWriter:
    """Append-only JSON lines, flushed per row so a crash loses at most one line."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(path, "a", buffering=1)

    def write(self, row: dict[str, Any]) -> None:
        self._f.write(json.dumps(row, allow_nan=True) + "\n")

    def close(self) -> None:
        self._f.close()


def free_bytes(path: Path) -> int:
    try:
        return shutil.disk_usage(path).free
    except OSError:
        return 1 << 62


def disk_free(path: Path) -> str:
    n = free_bytes(path)
    return f"{n / (1 << 20):.1f} MiB" if n >= 1 << 20 else f"{n / 1024:.1f} KiB"


def last_line(path: Path, needle: str) -> str:
    """The last line of a log holding `needle` ("" if none, or unreadable)."""
    try:
        with open(path, "rb") as f:
            f.seek(max(f.seek(0, 2) - 65536, 0))
            lines = [ln for ln in f.read().decode(errors="replace").splitlines() if needle in ln]
    except OSError:
        return ""
    return lines[-1].strip()[-400:] if lines else ""


LAUNCHER_STATE = "launcher.json"  # RUN_DIR/launcher.json: parts, restarts and wall time so far


def earlier_parts(run_dir: Path) -> dict[str, Any]:
    """What the earlier parts of a resumed run took (RUN_DIR/launcher.json; none: a fresh run)."""
    try:
        data = json.loads((run_dir / LAUNCHER_STATE).read_text())
        return {"parts": int(data["parts"]), "restarts": {str(r): int(n) for r, n in data["restarts"].items()},
                "wall_s": float(data["wall_s"])}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {"parts": 0, "restarts": {}, "wall_s": 0.0}


PARTS_EVERY_S = 5.0  # how often a running part rewrites RUN_DIR/launcher.json


@dataclass
class RunParts:
    """RUN_DIR/launcher.json: how many parts a run has had (a resumed run has several), the
    restarts of each role and the wall time over all of them. `supervise` saves it when `due`, every
    PARTS_EVERY_S while a part runs, so a part killed with everything (SIGKILL, a reboot, a session's
    end) still counts its restarts and time up to then."""

    run_dir: Path
    before: dict[str, Any]  # rundir.earlier_parts: what the earlier parts took
    started: float = field(default_factory=time.monotonic)
    saved_at: float = 0.0

    def totals(self, restarts: dict[str, int]) -> dict[str, Any]:
        earlier = self.before["restarts"]
        return {"parts": self.before["parts"] + 1,
                "restarts": {r: restarts.get(r, 0) + earlier.get(r, 0) for r in {**earlier, **restarts}},
                "wall_s": round(self.before["wall_s"] + time.monotonic() - self.started, 2)}

    def save(self, restarts: dict[str, int]) -> dict[str, Any]:
        state = self.totals(restarts)
        with contextlib.suppress(OSError):  # a full disk stops the run elsewhere; this record can wait
            write_json(self.run_dir / LAUNCHER_STATE, state)
        self.saved_at = time.monotonic()
        return state

    def due(self) -> bool:
        return time.monotonic() - self.saved_at >= PARTS_EVERY_S
