"""`benchmarks/gpu.sh --dry-run`: the GPU machine's script, run here on CPU at tiny sizes.

The same steps as on the GPU (a venv over the base Python, the carried wheels offline, the project
with --no-deps, the learner bench, the graphs check, time-boxed `mam run`s at lag 0 and 2), so a
GPU lease starts from a script that has run. Timings are not asserted (a shared CI box), only that
every step ran and gave sane positive numbers in the one JSON.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def positive(x: object) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def test_gpu_script_dry_run(tmp_path: Path) -> None:
    out = tmp_path / "out"
    env = dict(os.environ, OUT=str(out), WORK=str(tmp_path / "work"), PYTHONUNBUFFERED="1")
    env.pop("DEVICE", None)
    proc = subprocess.run(["bash", "benchmarks/gpu.sh", "--dry-run"], cwd=ROOT, env=env, text=True,
                          capture_output=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    # What comes back from the device tool: at most 8 files; here 3.
    assert sorted(p.name for p in out.iterdir()) == ["gpu.json", "gpu.log", "logs.tar.gz"]
    with tarfile.open(out / "logs.tar.gz") as tar:
        names = set(tar.getnames())
    assert {"logs/bench.json", "logs/graphs_check.json", "logs/setup.json"} <= names
    assert {"logs/e2e-m2-lag0.json", "logs/e2e-m2-lag2.json"} <= names

    d = json.loads((out / "gpu.json").read_text())
    assert d["dry_run"] is True and d["device"] == "cpu"
    assert d["setup"]["torch"] and d["setup"]["packages"]["mujoco"] == "4.0.0"
    assert {"torch", "mujoco", "gymnasium", "zenoh"} <= set(d["versions"])

    bench = d["learner_bench"]
    assert bench["learner_ks"] == [1, 2] and bench["learner_variants"] == "default"
    for name in ("k1", "k2", "k2_shared", "k2_bf16"):
        for key in ("updates_per_s", "vs_td3", "device_ms_per_update"):
            assert positive(bench[f"learner_halfcheetah_{name}_{key}"]), (name, key)
    assert "learner_halfcheetah_k2_eager_updates_per_s" not in bench  # no CUDA graphs on a CPU: nothing to compare

    # On CPU the "graphed" agent takes the eager path: the same bits, no capture
    check = d["graphs_check"]
    assert check["graphs_vs_eager"] == {"max_abs_diff": 0.0, "equal_bits": True, "close": True}
    assert check["ma-td3_graphs_vs_eager"]["captures"] == 0 and check["same_seed"]["equal_bits"] is True

    runs = {r["tag"]: r for r in d["e2e"]}
    assert set(runs) == {"m2-lag0", "m2-lag2"} and [runs[t]["lag"] for t in sorted(runs)] == [0, 2]
    for run in runs.values():
        assert "--algo ma-td3" in run["command"] and "--workers 2" in run["command"]
        assert "--schedule paper" in run["command"] and "--device cpu" in run["command"]
        assert run["lost"] == 0 and run["train_seconds"] > 0 and 0.5 < run["utd"] < 1.5
        # Paper schedule, M = 2: two transitions per iteration, one update each.
        assert 1.5 < run["env_steps_per_s"] / run["updates_per_s"] < 2.5
        assert 0 <= run["learner_wait_share"] < 1.5
    derived = d["derived"]
    for key in ("k2_updates_per_s", "k2_vs_td3", "k2_bf16_vs_td3", "k2_device_busy_share", "learner_update_share"):
        assert positive(derived[key]), (key, derived[key])
    assert derived["device_time_source"] == "process cpu time"
    assert set(d["goals"]) == {"k2_updates_per_s >= 1500 (graphed, H200)", "k2_device_busy_share >= 0.5",
                               "e2e m3 lag2 env_steps_per_s >= 1000", "graphed == eager within tolerance (100 updates)",
                               "same seed, same policy bits (GPU)"}
    assert d["experiment"] is None  # the grid only with --experiment
    if d["wheels_check"] is not None:  # a Python 3.12 and the wheels were there
        assert d["wheels_check"]["ok"] and d["wheels_check"]["python"].startswith("3.12")
        assert d["wheels_check"]["versions"]["mujoco"] == "4.0.0"
    assert positive(d["timings_s"]["total"]) and d["timings_s"]["failed_steps"] == []
