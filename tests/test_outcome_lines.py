"""What `mam run` prints at the end (issue 29): the progress bar's last line agrees with the done
line, "no elimination in this budget" instead of "survivor None", a MuJoCo return beside a random
policy's, and the referee's log in one unit."""

import os
import re
import subprocess
import sys
from pathlib import Path

from services.run.options import build_run_config
from services.run.progress import RANDOM_POLICY_RETURNS, done_text, outcome_text
from tests.e2e import ROOT, unique_run

ENV = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore")


def test_a_run_without_an_elimination_says_so():
    cfg = build_run_config({"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 400}, None)
    text = done_text(cfg, {"launcher_wall_time_s": 159.0, "final_returns": [1.0, 2.0, None], "survivor": None},
                     92.4)  # the budget reached 92.4 s after the launcher started
    assert text.endswith("final returns [1.00, 2.00, —], no elimination in this budget"), text
    assert "budget reached at 0:01:32" in text and "None" not in text
    single = build_run_config({"env": "AppleCollect-v1", "algo": "ddpg", "steps": 400}, None)
    text = done_text(single, {"launcher_wall_time_s": 9.0, "final_returns": [1.0], "survivor": 0}, None)
    assert "survivor" not in text and "elimination" not in text  # one actor: nothing to eliminate


def test_a_mujoco_outcome_names_the_random_policy_return():
    cfg = build_run_config({"env": "Hopper-v5", "algo": "ma-td3", "steps": 1000}, None)
    text = outcome_text(cfg, {"final_returns": [None, 1234.56], "survivor": 1})
    mean, std = RANDOM_POLICY_RETURNS["Hopper-v5"]
    assert text == (f"survivor 1: mean return 1,234.6; a uniform random policy scores {mean:,.1f} ± {std:,.1f} "
                    "on Hopper-v5 (docs/RESULTS.md, \"Reference returns\")")
    assert "Reference returns" in (ROOT / "docs" / "RESULTS.md").read_text()
    for env in RANDOM_POLICY_RETURNS:  # every reference is recorded in the docs with its figure
        assert f"| {env} |" in (ROOT / "docs" / "RESULTS.md").read_text(), env


def test_the_last_progress_line_agrees_with_the_done_line_and_the_referee_logs_one_unit(tmp_path: Path):
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", "--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", "400",
         "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300", "--hidden", "16,16",
         "--batch-size", "16", "--eval-episodes", "2", "--eval-every", "100", "--run", unique_run("outcome"),
         "--run-dir", str(run_dir), "--no-plot"], cwd=ROOT, env=ENV, text=True, capture_output=True, timeout=600)
    out = proc.stdout
    assert proc.returncode == 0, out + proc.stderr
    bar = [line for line in out.splitlines() if line.startswith("transitions ")][-1]
    done = next(line for line in out.splitlines() if line.startswith("done in "))
    reached = re.search(r"budget reached at (\d+:\d\d:\d\d)", done)
    assert reached and reached.group(1) in bar, (bar, done)
    assert "transitions/s" not in bar and "upd/s" not in bar and bar.rstrip().endswith("done"), bar
    assert re.search(r"survivor \d", done) and "None" not in done, done
    log = (run_dir / "logs" / "referee.log").read_text()
    points = re.findall(r"(?:eval|allocation \(\w+\)) at ([^:]+):", log)
    assert points and all(re.fullmatch(r"iteration [\d,]+ \([\d,]+ transitions\)", p) for p in points), points


def test_a_resumed_run_s_done_line_says_which_clock_is_which():
    """After a resume the wall time counts both parts, the bar's clock only the last: the line says so."""
    cfg = build_run_config({"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 400}, None)
    text = done_text(cfg, {"launcher_wall_time_s": 100.0, "final_returns": [1.0], "survivor": 0, "parts": 2}, 54.0)
    assert text.startswith("[bold green]done[/] in 100 s over 2 parts (this part reached the budget 0:00:54 after "
                           "it started"), text
    assert "budget reached at" not in text
