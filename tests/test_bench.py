"""`mam bench` smoke tests: every piece runs at tiny sizes and reports finite, positive figures.

No timing is asserted (a shared CI box makes timings meaningless); only that the bench
runs end to end, as `python -m mam_lab.bench`, and prints its JSON object on the last line.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mam_lab.bench import PIECES, BenchSizes, meets, print_report, target_for

ROOT = Path(__file__).resolve().parents[1]


def start_bench(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="120")
    return subprocess.Popen([sys.executable, "-m", "mam_lab.bench", "--tiny", "--json", *args], cwd=ROOT, env=env,
                            text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def bench_json(proc: subprocess.Popen, timeout: float = 120) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out[-3000:] + err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def assert_positive(result: dict, keys: list[str]) -> None:
    for key in keys:
        assert key in result, key
        value = result[key]
        assert isinstance(value, (int, float)) and math.isfinite(value) and value > 0, (key, value)


def test_learner_transport_and_weights_pieces() -> None:
    result = bench_json(start_bench("--only", "learner,transport,weights"))
    assert result["device"] == "cpu" and result["torch_threads"] == 1
    assert {"torch", "zenoh", "mujoco", "gymnasium", "python"} <= set(result["versions"])
    assert_positive(result, [
        "learner_k2_vs_td3", "learner_k2_bf16_vs_td3", "learner_halfcheetah_k1_vs_td3",
        "learner_halfcheetah_td3_updates_per_s",
        "learner_halfcheetah_k2_updates_per_s", "learner_halfcheetah_k2_vs_td3_cpu_time",
        "learner_halfcheetah_k2_shared_vs_td3", "learner_halfcheetah_k2_per_actor_vs_shared",
        "learner_sac_k1_vs_sac", "learner_sac_k2_vs_sac", "learner_halfcheetah_sac_updates_per_s",
        "learner_halfcheetah_sac_k2_updates_per_s", "transport_transitions_per_s", "transport_bytes_per_transition",
        "weights_latency_p99_ms", "weights_latency_p50_ms", "weights_humanoid_p99_ms", "weights_halfcheetah_bytes"])
    assert result["transport_lost"] == 0 and result["transport_received"] == result["transport_expected"]
    # 17 + 17 obs floats, 6 action floats, a reward and a flag: at least 165 bytes per row on the wire.
    assert result["transport_bytes_per_transition"] >= (17 + 17 + 6 + 1) * 4


@pytest.mark.slow  # three runs start torch and MuJoCo: ~35 s, past the fast suite's budget
def test_end_to_end_and_collection_pieces() -> None:
    result = bench_json(start_bench("--only", "e2e,collection"), timeout=600)  # three runs start torch and MuJoCo
    assert_positive(result, ["e2e_vs_single_process", "e2e_bf16_vs_single_process", "e2e_single_process_s",
                             "e2e_mam_run_to_done_s", "e2e_mam_run_wall_s", "collection_steps_per_s_m4"])
    assert result["e2e_mam_run_startup_s"] <= result["e2e_mam_run_to_done_s"] <= result["e2e_mam_run_wall_s"]


def test_targets_and_report_rendering() -> None:
    assert target_for("learner_k2_vs_td3", "cpu") == ("ge", 0.8)
    assert target_for("learner_k2_vs_td3", "cuda:0") == ("ge", 0.95)
    assert meets("e2e_vs_single_process", 0.5) is True and meets("e2e_vs_single_process", 0.9) is False
    assert meets("collection_steps_per_s_m4", 1.0) is None and meets("weights_latency_p99_ms", math.nan) is None
    from rich.console import Console

    console = Console(record=True, width=120)
    print_report({"device": "cpu", "torch_threads": 1, "learner_k2_vs_td3": 0.61, "transport_lost": 0,
                  "profile_worker_us": {"env.step": 80.0}, "versions": {"torch": "x"}}, console)
    text = console.export_text()
    assert "0.61" in text and "not met" in text and "env.step" in text


def test_sizes_and_pieces() -> None:
    quick, full, tiny = BenchSizes.quick(), BenchSizes.full(), BenchSizes.tiny()
    assert full.learner_rounds * full.learner_updates > quick.learner_rounds * quick.learner_updates
    assert 4 in quick.collection_workers and 4 in full.collection_workers and 4 in tiny.collection_workers
    assert quick.weights_hidden == tiny.weights_hidden == (256, 256)
    assert set(PIECES) == {"learner", "e2e", "transport", "weights", "collection"}
    with pytest.raises(ValueError):
        from mam_lab.bench import run_bench

        run_bench(tiny, ("nope",))


@pytest.mark.parametrize("rows", [1, 8, 64])
def test_fast_layouts_compute_the_plain_mlp(rows: int) -> None:
    """Feature-major (many rows), row-major (few rows) and one-member 2-D paths, forward and
    gradients, against the member-by-member MLP written out."""
    import torch

    from mam_core.ensemble import CriticEnsemble

    g = torch.Generator().manual_seed(0)
    critic = CriticEnsemble(2, 2, 5, 3, (16, 16), g).double()
    obs, actions = torch.randn(rows, 5, dtype=torch.float64), torch.randn(4, rows, 3, dtype=torch.float64)

    def plain(member: int, a: torch.Tensor) -> torch.Tensor:
        x = torch.cat((obs, a), dim=-1)
        for i, (w, b) in enumerate(zip(critic.net.weights, critic.net.biases)):
            x = x @ w[member] + b[member, 0]
            x = torch.relu(x) if i < 2 else x
        return x[:, 0]

    q = critic(obs, actions)
    expected = torch.stack([plain(e, actions[e]) for e in range(4)])
    torch.testing.assert_close(q, expected)
    grads = torch.autograd.grad(q.sum(), list(critic.parameters()))
    expected_grads = torch.autograd.grad(expected.sum(), list(critic.parameters()))
    for got, want in zip(grads, expected_grads):
        torch.testing.assert_close(got, want)
    q1 = critic(obs, actions[1], members=slice(1, 2))  # one member: plain 2-D GEMMs
    torch.testing.assert_close(q1[0], plain(1, actions[1]))
    shared = critic(obs, actions[0])  # one action shared by every member
    torch.testing.assert_close(shared, torch.stack([plain(e, actions[0]) for e in range(4)]))


def test_learner_grid_of_variants_with_device_time() -> None:
    """`--ks 1,2,3 --variants all --device-time`: every K per actor and shared, fp32 and bf16,
    against the reference in the same rounds, with the device's busy time per update."""
    from mam_lab.bench_learner import variant_names

    names = variant_names((1, 2, 3), "all")
    assert names[:3] == ["k1", "k2", "k3"] and "k1_shared" not in names
    assert {"k1_bf16", "k2_shared", "k2_bf16", "k2_shared_bf16", "k3_shared", "k3_bf16", "k3_shared_bf16"} <= set(names)
    assert variant_names((1, 2, 3)) == ["k1", "k2", "k3", "k2_shared", "k2_bf16"]  # what `mam bench` timed before
    result = bench_json(start_bench("--only", "learner", "--ks", "1,2,3", "--variants", "all", "--device-time",
                                    "--rounds", "2", "--updates", "2", "--hidden", "16,16", "--batch-size", "16"))
    assert result["learner_ks"] == [1, 2, 3] and result["learner_variants"] == "all"
    assert result["sizes"]["hidden"] == [16, 16] and result["sizes"]["batch_size"] == 16
    assert result["learner_device_time_source"] == "process cpu time"
    keys = ["learner_k2_vs_td3", "learner_k2_bf16_vs_td3", "learner_halfcheetah_td3_device_ms_per_update"]
    for name in names:
        keys += [f"learner_halfcheetah_{name}_updates_per_s", f"learner_halfcheetah_{name}_vs_td3",
                 f"learner_halfcheetah_{name}_device_ms_per_update"]
    assert_positive(result, keys + ["learner_halfcheetah_k3_per_actor_vs_shared"])


def test_accel_switch() -> None:
    """The one switch for CUDA-only paths: a CPU device takes none of them (CPU runs unchanged),
    CUDA all of them; building one never initialises CUDA."""
    import numpy as np
    import torch

    from mam_core.accel import for_device
    from mam_core.replay import ReplayBuffer

    cpu, cuda = for_device("cpu"), for_device("cuda:0")
    assert (cpu.pin_memory, cpu.non_blocking, cpu.resident_replay, cpu.host_allocator_tuning) == (
        False, False, False, True)
    assert (cuda.pin_memory, cuda.non_blocking, cuda.resident_replay, cuda.host_allocator_tuning) == (
        True, True, True, False)
    assert cuda.cuda_graphs and not cpu.cuda_graphs and not for_device("meta").cuda_graphs
    assert for_device(torch.device("cpu")) is cpu and cpu.bf16_supported() is None and not cpu.cuda
    assert not for_device("meta").resident_replay and not for_device("meta").host_allocator_tuning
    buf = ReplayBuffer(64, 3, 2)
    assert buf.accel is cpu and not buf.resident
    buf.add_batch(np.ones((8, 3), np.float32), np.ones((8, 2), np.float32), np.ones(8, np.float32),
                  np.ones((8, 3), np.float32), np.zeros(8, bool))
    batch = buf.sample(4, groups=2)
    assert batch["obs"].shape == (2, 4, 3) and batch["obs"].device.type == "cpu" and not batch["obs"].is_pinned()


def test_the_arithmetic_bench_times_the_sides_asked_for_beside_native() -> None:
    """`python -m mam_lab.bench_arithmetic --sides S`: native (the reference) and S only, each a
    positive rate and a ratio; an unknown side is a usage error that lists the known ones."""
    env = dict(os.environ, PYTHONWARNINGS="ignore", COLUMNS="200")
    cmd = [sys.executable, "-m", "mam_lab.bench_arithmetic", "--rounds", "1", "--updates", "2", "--steps", "20"]
    out = subprocess.run([*cmd, "--sides", "portable-avx2"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    learner = sorted(k for k in result if k.startswith("learner_"))
    assert learner == sorted(f"learner_{algo}_{side}" for algo in ("td3", "ma-td3") for side in
                             ("native_updates_per_s", "portable-avx2_updates_per_s", "portable-avx2_vs_native"))
    assert_positive(result, learner)
    bad = subprocess.run([*cmd, "--sides", "portable,nope"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "unknown side(s) nope" in bad.stderr and "portable-openblas" in bad.stderr, \
        bad.stderr[-2000:]
