"""Learner incarnations cannot deadlock the run (issue: a learner killed before its first
checkpoint hung the run forever): weights carry the learner's incarnation, workers and the
referee prefer a new incarnation's copy of a version, rows acted with a dead incarnation's
weights are accepted, and workers step on from the new learner's iteration."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mam_core.config import resolve
from mam_core.policy import EnvSpec, NumpyActors, params_digest, read_policy_file
from mam_core.reference import run_reference
from services.messaging.codec import TransitionBatch, TransitionSpec
from services.roles.lockstep import SlotStage, WeightsHistory
from services.roles.outbox import PublishedDigests
from services.run.rundir import read_jsonl
from tests.e2e import ROOT, unique_run

SPEC = EnvSpec(3, 2, (1.0, 1.0))
HIDDEN = (4,)


def test_a_new_learner_incarnations_copy_of_a_version_replaces_the_dead_ones():
    """Versions are the plan's, so a restarted learner publishes the same version numbers again,
    with its own parameters: a role keeps the successor's copy once the stats name it, and a
    late or cached message of the dead learner never replaces it."""
    shapes = NumpyActors(1, SPEC, HIDDEN).shapes
    history = WeightsHistory(1)

    def params(value: float) -> dict[str, np.ndarray]:
        return {name: np.full(shape, value, np.float32) for name, shape in shapes.items()}

    assert history.add(0, 40, params(1.0), "old", prefer="old")
    assert history.add(0, 40, params(2.0), "new", prefer="new")
    assert history.source(0, 40) == "new" and float(history.get(0, 40)["w0"][0, 0]) == 2.0
    assert not history.add(0, 40, params(3.0), "old", prefer="new")
    assert float(history.get(0, 40)["w0"][0, 0]) == 2.0


def _batch(worker: str, incarnation: str, seq: int, iteration: int, rows: int, resend: bool = False):
    z = np.zeros
    return TransitionBatch(worker, incarnation, seq, 0, 0, z((rows, 3), np.float32), z((rows, 2), np.float32),
                           z(rows, np.float32), z((rows, 3), np.float32), z(rows, np.bool_), resend=resend,
                           iteration=iteration, slot=0)


def test_the_stage_tells_a_resend_from_a_slot_that_stepped_iterations_again():
    """Rows of iterations the slot already has: a resend to a restarted learner is skipped
    quietly; the same worker stepping them anew (its env then is elsewhere) ends exactness."""
    stage = SlotStage(1)
    assert stage.add(_batch("w0", "a", 0, 1, 4)) == (True, "", 0)
    assert stage.add(_batch("w0", "a", 0, 1, 4, resend=True)) == (False, "", 4)
    assert stage.add(_batch("w0", "a", 1, 5, 2)) == (True, "", 0)
    staged, why, skipped = stage.add(_batch("w0", "a", 2, 6, 3))
    assert staged and skipped == 1 and why == "slot 0 stepped iterations 6..6 again (w0 went back to where a " \
                                              "restarted learner stood)"
    assert stage.end == [9]
    # A batch of the owner past the slot's next iteration waits for its resend (not staged, nothing
    # counted); a new owner's fills the gap and says the rows were lost.
    assert stage.add(_batch("w0", "a", 9, 12, 2)) == (False, "", 0) and stage.end == [9]
    staged, why, _ = stage.add(_batch("w0", "b", 0, 12, 2))
    assert staged and why == "slot 0 lost iterations 9..11 (rows lost in flight)" and stage.end == [11]


def test_a_held_version_carries_the_digest_a_batch_reports():
    """The worker's copy of a version and the batches acted with it carry `params_digest`; the
    learner compares it with its own (services/roles/outbox.py: foreign_weights)."""
    shapes = NumpyActors(1, SPEC, HIDDEN).shapes
    history = WeightsHistory(1)
    one = {name: np.full(shape, 1.0, np.float32) for name, shape in shapes.items()}
    history.add(0, 3, one, "L1")
    assert history.digest(0, 3) == params_digest(one) != params_digest({**one, "w0": one["w0"] * 2})
    batch = dataclasses.replace(_batch("w0", "a", 0, 1, 2), policy_digest=history.digest(0, 3))
    assert TransitionBatch.from_bytes(batch.to_bytes(), TransitionSpec(3, 2, 1)).policy_digest == params_digest(one)


def test_published_digests_go_through_the_checkpoint_and_name_foreign_weights():
    """With lag B > 0 a restarted learner gets rows acted with versions its predecessor published
    before the checkpoint: the checkpoint carries their digests, so those rows are checked too."""
    shapes = NumpyActors(1, SPEC, HIDDEN).shapes
    one = {name: np.full(shape, 1.0, np.float32) for name, shape in shapes.items()}
    other = {**one, "w0": one["w0"] * 2}
    published = PublishedDigests()
    for version in range(5):
        published.record(0, version, one if version != 3 else other)
    published.record(1, 2, one)  # an eliminated actor's last version
    published.prune(4, [True, False])  # slots act with version >= 4 of the live actor from now on
    assert sorted(published.known) == [(0, 3), (0, 4), (1, 2)]
    restored = PublishedDigests.from_json(published.to_json())
    assert restored.known == published.known

    def acted(actor: int, version: int, params: dict) -> TransitionBatch:
        return dataclasses.replace(_batch("w0", "a", 0, 9, 2), actor=actor, version=version,
                                   policy_digest=params_digest(params), policy_from="L1")

    assert restored.foreign(acted(0, 3, other)) == ""
    assert restored.foreign(acted(0, 3, one)) == ("slot 0 acted at iteration 9 with actor 0's version 3 of "
                                                  "learner L1, not this learner's")
    assert restored.foreign(acted(1, 2, other)) != ""
    assert restored.foreign(acted(0, 1, other)) == ""  # pruned: not known here, trusted
    with pytest.raises(ValueError, match="actor, version, digest"):
        PublishedDigests.from_json('[[0, 1]]')


@pytest.mark.slow
def test_a_learner_killed_without_a_checkpoint_and_three_more_times_the_run_finishes(tmp_path: Path) -> None:
    """The first kill also deletes the checkpoints, so the launcher starts a fresh learner at
    iteration 0 while the workers are hundreds of iterations on (they step on from the new
    learner's iteration; what is missing is filled by the rows that come); three more kills
    resume from checkpoints. The run goes on in lock-step and finishes its budget: equal to the
    reference where the workers still held every row the fresh learner needed, else not exact."""
    run_dir, name = tmp_path / "kills", unique_run("kills")
    steps = 6000
    args = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(steps), "--workers", "2", "--actors", "2",
            "--schedule", "equal-data", "--start-steps", "500", "--compete-every", "2000", "--eliminate-at", "4000",
            "--eval-episodes", "2", "--hidden", "16,16", "--batch-size", "16", "--seed", "1",
            "--checkpoint-seconds", "2", "--run", name, "--run-dir", str(run_dir), "--no-plot"]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "run", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)

    def learner_pid() -> int | None:
        pattern = f"services.roles.learner .*{run_dir}"
        out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout
        return int(out.split()[0]) if out.split() else None

    def updates() -> int:
        path = run_dir / "learner.jsonl"
        rows = read_jsonl(path) if path.is_file() else []
        return rows[-1]["updates"] if rows else 0

    try:
        for kill, at_updates in enumerate((300, 900, 1500, 2500)):
            deadline = time.monotonic() + 180
            while updates() < at_updates and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.2)
            pid = learner_pid()
            assert pid is not None and proc.poll() is None, proc.stdout.read() if proc.poll() is not None else ""
            os.kill(pid, signal.SIGKILL)
            if kill == 0:  # no checkpoint: the launcher starts a fresh learner, versions from 0
                time.sleep(0.3)
                shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)
            time.sleep(3.0)
        out, _ = proc.communicate(timeout=400)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] == steps and summary["restarts"]["learner"] == 4, summary
    if summary["exact"]:  # the workers still held every row since iteration 1: the fresh learner recomputed them
        cfg = resolve("ma-ddpg", workers=2, actors=2, schedule="equal-data", start_steps=500, compete_every=2000,
                      eliminate_at=4000, eval_episodes=2, hidden=(16, 16), batch_size=16, seed=1)
        ref = run_reference("AppleCollect-v1", cfg, steps)
        _, params = read_policy_file(run_dir / "checkpoints" / "policy.npz")
        assert all(np.array_equal(a[n], b[n]) for a, b in zip(params, ref.policy) for n in a)
    else:  # the fresh learner missed the rows its predecessor's checkpoint had acknowledged
        assert "lost iterations" in summary["inexact"], summary
