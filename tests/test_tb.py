"""TensorBoard event files: the JSONL rows' scalars, read back with TensorBoard's own reader."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from services.roles import tb
from services.run.rundir import JsonlWriter, read_jsonl
from tests.e2e import ROOT


def scalars(logdir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar series in a TensorBoard log directory: tag -> [(step, value)]."""
    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_rows_become_scalars_at_their_env_steps(tmp_path: Path):
    board = tb.RunBoard(tmp_path, "learner")
    log = board.tee(JsonlWriter(tmp_path / "learner.jsonl"), tb.learner_scalars)
    log.write({"env_steps": 100, "updates": 50, "utd": 0.5, "updates_per_s": 40.0, "transitions_per_s": 80.0,
               "buffer": 100, "loss/critic": 1.5, "q/actor0": -2.0, "q/actor1": float("nan"), "live": [True, True]})
    log.write({"env_steps": 200, "updates": 150, "utd": 0.75, "updates_per_s": 41.0, "transitions_per_s": 79.0,
               "buffer": 200, "loss/critic": 1.25, "loss/actor": 0.5, "q/actor0": -1.0, "q/actor1": -3.0,
               "iterations": 7, "train_return": -4.5})
    bias = board.tee(JsonlWriter(tmp_path / "bias.jsonl"), tb.bias_scalars)
    bias.write({"env_steps": 200, "bias": {"actor": 1, "q_estimate": 2.0, "q_true": 1.0, "bias": 1.0,
                                           "bias_rate": 1.0}})
    log.close()
    bias.close()
    board.close()
    assert len(read_jsonl(tmp_path / "learner.jsonl")) == 2  # the JSONL rows are written as they were
    got = scalars(tmp_path / "tb" / "learner")
    assert got["loss/critic"] == [(100, 1.5), (200, 1.25)] and got["loss/actor"] == [(200, 0.5)]
    assert got["q/actor0"] == [(100, -2.0), (200, -1.0)] and got["q/actor1"] == [(200, -3.0)]  # NaN skipped
    assert got["learner/replay_size"] == [(100, 100.0), (200, 200.0)]
    assert got["learner/utd"] == [(100, 0.5), (200, 0.75)] and got["learner/updates_per_s"][1] == (200, 41.0)
    assert got["learner/iterations"] == [(200, 7.0)] and got["learner/train_return"] == [(200, -4.5)]
    assert got["bias/rate/actor1"] == [(200, 1.0)] and got["bias/q_true/actor1"] == [(200, 1.0)]


def test_referee_rows(tmp_path: Path):
    board = tb.RunBoard(tmp_path, "referee")
    board.row({"env_steps": 400, "returns": [[1.0, 3.0], [], [5.0]], "mean": [2.0, None, 5.0]}, tb.eval_scalars)
    board.row({"env_steps": 400, "round": 1, "probabilities": [0.2, 0.3, 0.5], "counts": [1, 0, 2],
               "eliminated": [False, False, False], "survivor": None}, tb.allocation_scalars)
    board.row({"env_steps": 800, "round": 2, "probabilities": [0.0, 0.0, 1.0], "counts": [0, 0, 3],
               "eliminated": [True, True, False], "survivor": 2}, tb.allocation_scalars)
    board.close()
    got = scalars(tmp_path / "tb" / "referee")
    assert got["eval/return/actor0"] == [(400, 2.0)] and got["eval/return_std/actor0"] == [(400, 1.0)]
    assert "eval/return/actor1" not in got and got["eval/return/actor2"] == [(400, 5.0)]
    assert got["allocation/P/actor2"] == [(400, 0.5), (800, 1.0)]
    assert got["allocation/I/actor0"] == [(400, 1.0), (800, 0.0)]
    assert got["allocation/survivor"] == [(400, -1.0), (800, 2.0)]
    assert got["allocation/eliminated/actor0"] == [(400, 0.0), (800, 1.0)]
    assert got["allocation/round"] == [(400, 1.0), (800, 2.0)]


def test_a_board_that_cannot_write_never_stops_the_role(tmp_path: Path):
    blocker = tmp_path / "tb"
    blocker.write_text("a file where the directory should be")
    board = tb.RunBoard(tmp_path, "learner")
    assert not board.enabled
    board.scalars(1, {"x": 1.0})  # nothing happens
    board.close()


def test_the_referee_writes_event_files_without_importing_torch(tmp_path: Path):
    code = ("import sys, services.roles.referee; from services.roles import tb; "
            f"b = tb.RunBoard({str(tmp_path)!r}, 'referee'); b.scalars(3, {{'eval/return/actor0': 1.0}}); b.close(); "
            "print(b.logdir.is_dir(), sorted(m for m in sys.modules if m.split('.')[0] == 'torch')[:3])")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True []", out.stdout + out.stderr
    assert scalars(tmp_path / "tb" / "referee") == {"eval/return/actor0": [(3, 1.0)]}
