"""Which code produced a result: the commit and whether code (not a ledger) was modified."""

from __future__ import annotations

import subprocess
from pathlib import Path

from mam_lab.provenance import code_version, commit_label


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


def test_a_grid_writing_its_ledger_leaves_the_code_clean_and_a_code_change_is_named(tmp_path: Path) -> None:
    repo = tmp_path / "clone"
    (repo / "services").mkdir(parents=True)
    (repo / "docs" / "results" / "grid" / "runs").mkdir(parents=True)
    (repo / "services" / "learner.py").write_text("x = 1\n")
    manifest = repo / "docs" / "results" / "grid" / "runs" / "experiment.json"
    manifest.write_text("{}\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    head = _git(repo, "rev-parse", "HEAD")
    assert code_version(repo) == {"commit": head, "dirty": False, "modified": []}

    manifest.write_text('{"argv": ["--stop-by", "00:05"]}\n')  # what `mam experiment` writes as it starts
    assert code_version(repo) == {"commit": head, "dirty": False, "modified": []}

    (repo / "services" / "learner.py").write_text("x = 2\n")
    code = code_version(repo)
    assert code["dirty"] and code["modified"] == ["services/learner.py"]
    assert commit_label({"commit": head, **code}) == head[:12] + "+modified"


def test_the_label_of_a_record_counts_only_code_changes() -> None:
    commit = "d043ddd53a5f578848c421741638eafde8f46da2"
    ledger_only = {"commit": commit, "dirty": True, "modified": ["docs/results/evidence-b/runs/experiment.json"]}
    assert commit_label(ledger_only) == "d043ddd53a5f"
    assert commit_label({"commit": commit, "dirty": True, "modified": ["mam_core/agent.py"]}) == "d043ddd53a5f+modified"
    assert commit_label({"commit": commit, "dirty": True}) == "d043ddd53a5f+modified"  # an old record: its flag
    assert commit_label({"commit": None}) == "unknown"
