"""Which code and which libraries produced a result: the git commit of the code that runs (with a
dirty flag) and the versions of the libraries that change results or figures. One `versions()`
for the experiment records and the bench.
"""

from __future__ import annotations

import platform
import subprocess
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]  # the code that runs (a checkout: mam_lab/ beside services/)

# label -> distribution. Results: MuJoCo trajectories differ across releases, and so on.
RESULT_LIBRARIES: dict[str, str] = {"mam": "mam", "torch": "torch", "numpy": "numpy", "gymnasium": "gymnasium",
                                    "mujoco": "mujoco", "eclipse-zenoh": "eclipse-zenoh"}


RESULTS_DIR = "docs/results/"  # the ledgers: data a grid writes (its experiment.json too), not code


def code_changes(modified: list[str]) -> list[str]:
    """The modified tracked files that are code: a grid writing its own ledger leaves the code clean."""
    return [path for path in modified if not path.startswith(RESULTS_DIR)]


def code_version(root: Path | None = None) -> dict[str, Any]:
    """The commit of the code that runs: {"commit": full hash or None, "dirty": tracked files
    other than the ledgers (`code_changes`) modified, "modified": [those files]}."""
    root = root or ROOT
    out: dict[str, Any] = {"commit": None, "dirty": False, "modified": []}
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        if head.returncode != 0 or not head.stdout.strip():
            return out
        out["commit"] = head.stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                 capture_output=True, text=True, timeout=20)
        if changed.returncode == 0:
            out["modified"] = code_changes([line[3:] for line in changed.stdout.splitlines() if line.strip()])
            out["dirty"] = bool(out["modified"])
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def code_fingerprint(root: Path | None = None) -> str:
    """The commit and, for a tree with modified code, a hash of its diff against the commit: two
    equal fingerprints ran the same code ("" when it cannot be told: no git)."""
    import hashlib

    code = code_version(root)
    if not code["commit"]:
        return ""
    if not code["dirty"]:
        return code["commit"]
    try:
        diff = subprocess.run(["git", "diff", "HEAD", "--", *code["modified"]], cwd=root or ROOT, capture_output=True,
                              timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return ""
    return f"{code['commit']}+{hashlib.sha256(diff).hexdigest()[:16]}"


def run_code() -> dict[str, Any]:
    """What a run records of the code it runs (RUN_DIR/code.json, services/run/codecheck.py): the
    fingerprint ("" without git) and the versions of the libraries behind results."""
    return {"format": 1, "fingerprint": code_fingerprint(ROOT), "versions": versions(commit=False)}


def commit_label(record: Mapping[str, Any]) -> str:
    """"abc1234" or "abc1234+modified" (a dirty tree) or "unknown"."""
    commit = record.get("commit")
    if not isinstance(commit, str) or not commit:
        return "unknown"
    modified = record.get("modified")
    dirty = bool(code_changes(modified)) if isinstance(modified, list) else bool(record.get("dirty"))
    return commit[:12] + ("+modified" if dirty else "")


def versions(libraries: Mapping[str, str] = RESULT_LIBRARIES, *, missing: str | None = None,
             commit: bool = True) -> dict[str, str]:
    """{"python": ..., label: version of each distribution of `libraries`}; a distribution that is
    not installed is left out, or reported as `missing`. With `commit`, "git": the short commit of
    the code that runs, "+modified(files)" when tracked files are modified."""
    out = {"python": platform.python_version()}
    for label, dist in libraries.items():
        try:
            out[label] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            if missing is not None:
                out[label] = missing
    if commit:
        code = code_version(ROOT)
        if code["commit"]:
            out["git"] = code["commit"][:7]
            if code["dirty"]:  # tracked files modified: say so
                out["git"] += "+modified(" + ",".join(code["modified"]) + ")"
    return out
