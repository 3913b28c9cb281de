"""`benchmarks/gpu.sh --dry-run`: the GPU machine's script, run here on CPU at tiny sizes.

The same steps as on the GPU (a venv over the base Python, the carried wheels offline, the project
with --no-deps, the learner bench grid, a time-boxed `mam run`, a time-boxed `mam experiment`), so
a GPU lease starts from a script that has run. Timings are not asserted (a shared CI box), only that
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
    assert {"logs/bench.json", "logs/e2e.json", "logs/experiment.json", "logs/setup.json"} <= names

    d = json.loads((out / "gpu.json").read_text())
    assert d["dry_run"] is True and d["device"] == "cpu"
    assert d["setup"]["torch"] and d["setup"]["packages"]["mujoco"] == "4.0.0"
    assert {"torch", "mujoco", "gymnasium", "zenoh"} <= set(d["versions"])

    bench = d["learner_bench"]
    assert bench["learner_ks"] == [1, 2, 3] and bench["learner_variants"] == "all"
    for name in ("k1", "k2", "k3", "k2_shared", "k3_shared", "k1_bf16", "k2_bf16", "k3_bf16", "k2_shared_bf16",
                 "k3_shared_bf16"):
        for key in ("updates_per_s", "vs_td3", "device_ms_per_update"):
            assert positive(bench[f"learner_halfcheetah_{name}_{key}"]), (name, key)

    run = d["e2e"]
    assert "--algo ma-td3" in run["command"] and "--workers 3" in run["command"]
    assert "--schedule paper" in run["command"] and "--device cpu" in run["command"]
    assert run["lost"] == 0 and run["train_seconds"] > 0 and 0.5 < run["utd"] < 1.5
    derived = d["derived"]
    for key in ("k2_vs_td3", "k2_bf16_vs_td3", "e2e_env_steps_per_s", "e2e_updates_per_s",
                "learner_update_share", "device_time_share", "grid_env_steps_per_s"):
        assert positive(derived[key]), (key, derived[key])
    # Paper schedule, M = 3: three transitions per iteration, one update each.
    assert 2.0 < derived["e2e_env_steps_per_s"] / derived["e2e_updates_per_s"] < 4.0
    # estimates from a tiny bench on a shared box: sane, not exact
    assert derived["learner_update_share"] < 5 and derived["device_time_share"] < 5
    assert derived["device_time_source"] == "process cpu time"
    if "--collection" in run["command"]:  # mam run has exact and async collection: both ran, in the same script
        assert "--collection exact" in run["command"] and d["e2e_async"]["lost"] == 0
        assert positive(derived["exact_vs_async"]) and 0 <= derived["learner_wait_share"] < 1.5
    assert set(d["goals"]) == {"k2_vs_td3 >= 0.95 (CUDA)", "e2e_env_steps_per_s >= 1000 (paper schedule)"}
    assert d["experiment"]["runs_started"] >= 1 and positive(d["experiment"]["grid_updates_per_s"])
    if d["wheels_check"] is not None:  # a Python 3.12 and the wheels were there
        assert d["wheels_check"]["ok"] and d["wheels_check"]["python"].startswith("3.12")
        assert d["wheels_check"]["versions"]["mujoco"] == "4.0.0"
    assert positive(d["timings_s"]["total"]) and d["timings_s"]["failed_steps"] == []
