"""`mam-worker --slot 0,1,2`: several slots in one worker process (services/roles/worker_group.py,
`WorkerGroup`); the runs themselves are in tests/test_exact.py (lag 2, and a killed process)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import typer

from services.roles.worker_group import parse_slots, slot_ids
from services.run.cluster import slots_note
from tests.e2e import ROOT


def test_slots_are_single_lists_and_ranges_each_once():
    assert parse_slots("3") == [3]
    assert parse_slots("0,1,2") == [0, 1, 2]
    assert parse_slots("4-6,1") == [4, 5, 6, 1]
    for bad in ("", "a", "1,,2", "-1", "2-", "1-2-3", "0,0", "0-2,1", "3-1"):
        with pytest.raises(typer.BadParameter):
            parse_slots(bad)


def test_each_slot_gets_its_own_worker_id():
    assert slot_ids("w0,w1", [0, 1]) == ["w0", "w1"]
    assert slot_ids("b7", [7]) == ["b7"]
    one, = slot_ids(None, [0])
    assert "-s" not in one
    assert [i.rsplit("-", 1)[1] for i in slot_ids(None, [2, 5])] == ["s2", "s5"]
    with pytest.raises(typer.BadParameter, match="names 1 worker"):
        slot_ids("w0", [0, 1])
    with pytest.raises(typer.BadParameter, match="its own worker id"):
        slot_ids("w0,w0", [0, 1])
    with pytest.raises(typer.BadParameter):
        slot_ids("w0,bad/id", [0, 1])


def test_the_worker_command_refuses_bad_slots_before_connecting():
    out = subprocess.run([sys.executable, "-m", "services.roles.worker", "--run", "r", "--slot", "0,0",
                          "--connect", "tcp/127.0.0.1:9"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "slot 0 is named twice" in out.stdout + out.stderr
    out = subprocess.run([sys.executable, "-m", "services.roles.worker", "--run", "r", "--slot", "0,1", "--id", "w0",
                          "--connect", "tcp/127.0.0.1:9"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "give one id a slot" in out.stdout + out.stderr


def test_a_run_refuses_fewer_than_one_slot_a_worker(tmp_path):
    out = subprocess.run([sys.executable, "-m", "services.cli", "run", "--env", "Pendulum-v1", "--algo", "td3",
                          "--steps", "10", "--slots-per-worker", "0", "--run-dir", str(tmp_path / "r"), "--no-plot"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "slots_per_worker must be >= 1" in out.stdout + out.stderr
    assert not (tmp_path / "r" / "logs").exists()  # refused before any process started


def test_mam_run_suggests_several_slots_a_process_where_processes_outnumber_the_cores():
    note = slots_note(6, 1, 2)
    assert note is not None and note.startswith("6 worker processes on 2 core(s): --slots-per-worker 3 steps the 6 "
                                                "slots in 2 ")
    assert slots_note(5, 1, 2) is not None and "--slots-per-worker 3 steps the 5 slots in 2 " in slots_note(5, 1, 2)
    assert slots_note(3, 1, 2) is None  # fewer than twice the cores: no note
    assert slots_note(6, 3, 2) is None  # already packed
    assert slots_note(16, 1, 16) is None
