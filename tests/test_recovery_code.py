"""Issue 38, item 7 end to end: `mam run --resume --allow-other-code` continues a run that ran other
library versions, says so, and the run records `exact: false` with the differences (a real `mam
run`, stopped with SIGINT, resumed)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.e2e import ROOT, processes_of, unique_run
from tests.test_recovery_holes import ENV, apple, iterations, start, wait_until


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_forced_resume_onto_other_library_versions_ends_not_exact_naming_them(tmp_path: Path) -> None:
    run, run_dir, out = unique_run("other-code"), tmp_path / "run", tmp_path / "mam.out"
    proc = start(run_dir, *apple(1500, eliminate_at=900, compete_every=300, eval_every=300), "--checkpoint-seconds",
                 "2", "--run", run, "--run-dir", str(run_dir), out=out)
    try:
        wait_until(lambda: iterations(run_dir) >= 300 and list((run_dir / "checkpoints").glob("manifest-*.json")),
                   180, "iteration 300 and a checkpoint", proc, out)
        proc.send_signal(signal.SIGINT)  # Ctrl-C: the learner checkpoints, `mam run` exits 130
        assert proc.wait(60) == 130, out.read_text(errors="replace")[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    record = json.loads((run_dir / "code.json").read_text())
    now = record["versions"]["numpy"]
    record["versions"]["numpy"] = "0.0.1"  # the run's first part ran another numpy
    (run_dir / "code.json").write_text(json.dumps(record))
    cmd = [sys.executable, "-m", "services.cli", "run", "--resume", str(run_dir)]
    refused = subprocess.run(cmd, cwd=ROOT, env=ENV, text=True, capture_output=True, timeout=120)
    said = " ".join(refused.stderr.replace("│", " ").split())  # rich's box: its borders break the lines
    assert refused.returncode == 2 and "numpy 0.0.1 (the run's) vs" in said, refused.stderr[-2000:]
    got = subprocess.run([*cmd, "--allow-other-code"], cwd=ROOT, env=ENV, text=True, capture_output=True,
                         timeout=300)
    text = " ".join(got.stdout.split())
    assert got.returncode == 0, got.stdout[-3000:] + got.stderr[-3000:]
    assert f"resuming with other code (--allow-other-code): numpy 0.0.1 (the run's) vs {now} (this code)" in text
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exact"] is False and summary["parts"] == 2, summary
    assert "resumed with other code" in summary["inexact"] and "numpy 0.0.1" in summary["inexact"], summary
    forced = json.loads((run_dir / "code.json").read_text())["forced"]
    assert [f["part"] for f in forced] == [2], forced
    time.sleep(0.5)
    assert processes_of(run) == []
