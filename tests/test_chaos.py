"""The chaos run: a `mam run` on MuJoCo while a driver SIGKILLs a random child every 20–40 s."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.chaos import chaos
from tests.e2e import processes_of, unique_run

pytestmark = pytest.mark.slow


def test_chaos_run_reaches_its_budget_with_every_transition_exactly_once(tmp_path: Path) -> None:
    run = unique_run("chaos")
    args = ["--env", "InvertedPendulum-v5", "--algo", "ma-td3", "--actors", "2", "--workers", "3",
            "--steps", "45000", "--hidden", "32,32", "--batch-size", "32", "--start-steps", "1000",
            "--compete-every", "4000", "--eliminate-at", "16000", "--eval-episodes", "3", "--seed", "3",
            "--checkpoint-seconds", "5", "--max-restarts", "10", "--run", run]
    figures = chaos(args, tmp_path / "run", kill_every=(20.0, 40.0), seed=11)
    assert figures["problems"] == [], figures
    assert figures["exit_status"] == 0 and figures["env_steps"] >= 45000
    # the last kill may hit a child that was finishing
    assert figures["kills"] >= 3 and figures["restarts_total"] >= figures["kills"] - 1
    assert figures["lost_rows"] == 0 and figures["duplicated_rows"] == 0
    assert figures["sent_rows"] == figures["replay_rows"] == figures["env_steps"] == figures["checkpoint_replay_rows"]
    assert processes_of(run) == []
