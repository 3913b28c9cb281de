"""Portable arithmetic (mam_core/arithmetic.py): a seed computes the same run whatever kernels the
CPU and the environment would have chosen, here stood in for by the variables that choose them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import torch

from mam_core import arithmetic
from mam_core.config import resolve
from mam_core.policy import dense
from mam_core.reference import run_reference
from tests.e2e import ROOT, spawn, stop, unique_run
from tests.test_exact import APPLE, APPLE_STEPS, _record, _same_params

AVX2 = pytest.mark.skipif(not arithmetic.cpu_has_avx2(), reason="the pins cover x86-64 CPUs with AVX2 and FMA")

# `python -m mam_lab.numerics` + TINY_NUMERICS on any x86-64 machine with AVX2, with the package
# versions of pyproject.toml and the Makefile. A change of these digests is a change of results:
# docs/RESULTS.md says which ledger records were computed before it.
TINY_NUMERICS = ["--env", "HalfCheetah-v5", "--steps", "100", "--seed", "1", "--hidden", "16,16", "--batch-size", "16"]
EXPECTED_DIGESTS = {"paper": "3e3eb536e3ea1949", "equal-data": "11346d2a57da436c"}
# The learner's GEMMs in pinned OpenBLAS (MAM_PORTABLE_GEMM=openblas): the default's digest from
# 08c3077 until the chain kernels, still printed, so records of those commits can be rerun
OPENBLAS_DIGESTS = {"paper": "54d817ee4f322ab7", "equal-data": "f725b9b095f2b33e"}

# Stand-ins for other machines: the variables that make each library choose another kernel
# (OpenBLAS, ATen, MKL, NumPy), and masks that make MKL and glibc's libm (MuJoCo's sin, cos,
# exp) see a CPU without AVX-512.
KERNEL_CHOICES = [
    {},
    {"OPENBLAS_CORETYPE": "Haswell", "ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "AVX2", "MAM_GEMM_THREADS": "2",
     "MAM_CHAIN_ISA": "2"},
    {"OPENBLAS_CORETYPE": "SkylakeX", "ATEN_CPU_CAPABILITY": "avx2", "MKL_CBWR": "AUTO", "OPENBLAS_NUM_THREADS": "2",
     "OPENBLAS_L2_SIZE": "2048", "MAM_CHAIN_ISA": "1"},
    {"OPENBLAS_CORETYPE": "Zen", "ATEN_CPU_CAPABILITY": "default", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
     "NPY_ENABLE_CPU_FEATURES": "X86_V3", "MAM_GEMM_THREADS": "3",
     "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX512VL,-AVX512BW,-AVX512DQ,-AVX512CD"},
]
# MAM_CHAIN_ISA: the AVX2 and the plain C kernels of the default GEMMs, where this CPU would take AVX-512's
_CHOSEN = {k for choice in KERNEL_CHOICES for k in choice} | set(arithmetic.PINS) | {arithmetic.ARITHMETIC_ENV,
                                                                                   arithmetic.FOUND_ENV}


def _numerics(extra: dict[str, str]) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in _CHOSEN}
    out = subprocess.run([sys.executable, "-m", "mam_lab.numerics", *TINY_NUMERICS], cwd=ROOT, capture_output=True,
                         text=True, timeout=600, env=dict(env, PYTHONWARNINGS="ignore", **extra))
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_dense_sums_over_the_inputs_in_order_rounding_every_step() -> None:
    rng = np.random.default_rng(0)
    for batch, n_in, n_out in [(None, 17, 256), (1, 256, 256), (10, 256, 256), (10, 256, 6), (3, 5, 1)]:
        shape = (n_in,) if batch is None else (batch, n_in)
        x = rng.normal(size=shape).astype(np.float32)
        w = (rng.normal(size=(n_in, n_out)) / np.sqrt(n_in)).astype(np.float32)
        b = rng.normal(size=n_out).astype(np.float32)
        acc = x[..., 0:1] * w[0]  # float32 products and sums, one input after the other
        for i in range(1, n_in):
            acc = acc + x[..., i:i + 1] * w[i]
        got = dense(x, w, b)
        assert got.dtype == np.float32 and np.array_equal(got, acc + b), (batch, n_in, n_out)
        np.testing.assert_allclose(got, x @ w + b, rtol=1e-4, atol=1e-5)
        if batch:  # a row alone gets the bits it gets in a batch
            assert all(np.array_equal(dense(x[r], w, b), got[r]) for r in range(batch))


@AVX2
def test_the_suite_computes_with_the_pinned_arithmetic() -> None:
    state = arithmetic.status()
    assert state["arithmetic"] == "portable" and state["portable"], state
    assert {k: os.environ[k] for k in arithmetic.PINS} == arithmetic.PINS
    assert torch.backends.cpu.get_cpu_capability() == "AVX2"


@AVX2
def test_numpy_before_mam_is_machine_bound_and_native_pins_nothing() -> None:
    env = {k: v for k, v in os.environ.items() if k not in arithmetic.PINS and k != arithmetic.ARITHMETIC_ENV}
    code = ("import os, json, warnings; warnings.simplefilter('always'); {first}import mam_core\n"
            "from mam_core import arithmetic; s = arithmetic.status()\n"
            "print(json.dumps([s['portable'], s['machine_bound'], os.environ.get('MKL_CBWR')]))")

    def run(first: str, **extra: str) -> tuple[list, str]:
        r = subprocess.run([sys.executable, "-c", code.format(first=first)], cwd=ROOT, capture_output=True, text=True,
                           timeout=120, env=dict(env, **extra), check=True)
        return json.loads(r.stdout), r.stderr

    (portable, why, cbwr), err = run("")
    assert portable and why == "" and cbwr == "COMPATIBLE" and "machine-bound" not in err
    (portable, why, cbwr), err = run("import numpy; ")
    assert not portable and "numpy imported before mam" in why and "results may differ" in err
    (portable, why, cbwr), _ = run("", MAM_ARITHMETIC="native")
    assert not portable and why.startswith("native arithmetic") and cbwr is None


@AVX2
def test_the_numerics_digest_is_the_committed_one_whatever_kernels_the_machine_would_choose() -> None:
    """Each choice runs `python -m mam_lab.numerics` (two at a time); with native arithmetic two
    of the same choices give two digests, so the variables do reach the libraries."""
    native = [dict(KERNEL_CHOICES[0], MAM_ARITHMETIC="native"), dict(KERNEL_CHOICES[1], MAM_ARITHMETIC="native")]
    openblas = [dict(choice, MAM_PORTABLE_GEMM="openblas") for choice in KERNEL_CHOICES[:2]]
    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(_numerics, KERNEL_CHOICES + openblas + native))
    for choice, got in zip(KERNEL_CHOICES, results):
        assert got["arithmetic"] == "portable", got
        assert {s: got[s]["digest"] for s in EXPECTED_DIGESTS} == EXPECTED_DIGESTS, choice
    for choice, got in zip(openblas, results[len(KERNEL_CHOICES):]):
        assert got["arithmetic"] == "portable, GEMMs openblas-haswell", got
        assert {s: got[s]["digest"] for s in OPENBLAS_DIGESTS} == OPENBLAS_DIGESTS, choice
    a, b = results[len(KERNEL_CHOICES) + len(openblas):]
    assert a["arithmetic"].startswith("native") and a["paper"]["digest"] != b["paper"]["digest"]


@AVX2
def test_workers_with_other_kernels_than_the_learner_give_the_reference_run(tmp_path: Path) -> None:
    """A split-role exact run: the learner, the referee and each worker start with another
    machine's kernel choices (standing in for processes on other machines), and the run is
    still the one-process reference, bit for bit."""
    from services.messaging import bus

    run, endpoint, run_dir = unique_run("portable"), bus.loopback_endpoint(bus.free_tcp_port()), tmp_path / "run"
    flags = ["--env", "AppleCollect-v1", "--algo", "ma-ddpg", "--steps", str(APPLE_STEPS), "--workers", "5",
             "--actors", "3", "--start-steps", "100", "--compete-every", "100", "--eliminate-at", "300",
             "--eval-episodes", "2", "--eval-every", "100", "--hidden", "16,16", "--batch-size", "16", "--seed", "3"]
    learner = spawn("learner", *flags, "--run", run, "--listen", endpoint, "--run-dir", str(run_dir),
                    log=tmp_path / "learner.log", env=KERNEL_CHOICES[3])
    referee = spawn("referee", "--run", run, "--connect", endpoint, "--run-dir", str(run_dir),
                    log=tmp_path / "referee.log", env=KERNEL_CHOICES[2])
    workers = [spawn("worker", "--run", run, "--connect", endpoint, "--id", f"w{i}", "--slot", str(i), "--run-dir",
                     str(run_dir), log=tmp_path / f"w{i}.log", env=KERNEL_CHOICES[1 + i % 3]) for i in range(5)]
    try:
        deadline = time.monotonic() + 400
        while not (run_dir / "summary.json").is_file():
            assert time.monotonic() < deadline, "the run did not finish"
            assert learner.poll() in (None, 0), (tmp_path / "learner.log").read_text()[-3000:]
            time.sleep(0.5)
        for p in (*workers, referee, learner):
            p.wait(60)
            assert p.returncode == 0, f"{p.args} exited {p.returncode}"
    finally:
        stop(*workers, referee, learner)
    got = _record(run_dir)
    ref = run_reference("AppleCollect-v1", resolve("ma-ddpg", seed=3, **APPLE), APPLE_STEPS)
    assert got["summary"]["exact"] is True
    assert got["evals"] == [(e["iterations"], e["purpose"], e["returns"]) for e in ref.evaluations]
    assert got["summary"]["survivor"] == ref.survivor
    assert _same_params(got["params"], ref.policy)
    # A learner started by hand says the outcome it knows and where the referee's is (issue 40)
    done = [line for line in (tmp_path / "learner.log").read_text().splitlines() if " done: " in line]
    assert done and f"survivor {ref.survivor}, exact;" in done[-1] and "summary.json" in done[-1], done


def test_the_run_config_records_its_arithmetic(monkeypatch: pytest.MonkeyPatch) -> None:
    """config.json says which arithmetic a run computed with: native runs are machine-bound."""
    from services.run.config import RunConfig
    from services.run.options import build_run_config

    base = {"env": "AppleCollect-v1", "algo": "ma-ddpg", "steps": 100}
    monkeypatch.delenv(arithmetic.ARITHMETIC_ENV, raising=False)
    assert build_run_config(base, None).to_dict()["arithmetic"] == "portable"
    native = build_run_config(dict(base, arithmetic="native"), None)
    assert RunConfig.from_dict(native.to_dict()).arithmetic == "native"
    monkeypatch.setenv(arithmetic.ARITHMETIC_ENV, "native")  # a role started with native kernels says so
    assert build_run_config(base, None).arithmetic == "native"
    with pytest.raises(Exception, match="arithmetic must be one of portable, native"):
        build_run_config(dict(base, arithmetic="fast"), None)


@pytest.mark.slow
def test_a_native_run_reruns_on_its_machine_with_its_own_kernels(tmp_path: Path) -> None:
    """`mam run --arithmetic native`: the roles start without the pins `mam run` itself loaded
    with, so the run equals the reference computed by a native process on this machine."""
    env = {k: v for k, v in os.environ.items() if k not in arithmetic.PINS}  # as a user's shell has them
    run_dir = tmp_path / "native"
    subprocess.run([sys.executable, "-m", "services.cli", "run", "--env", "AppleCollect-v1", "--algo", "ma-ddpg",
                    "--steps", str(APPLE_STEPS), "--workers", "5", "--actors", "3", "--start-steps", "100",
                    "--compete-every", "100", "--eliminate-at", "300", "--eval-episodes", "2", "--eval-every", "100",
                    "--hidden", "16,16", "--batch-size", "16", "--seed", "3", "--run", unique_run("native"),
                    "--run-dir", str(run_dir), "--no-plot", "--arithmetic", "native"], cwd=ROOT, env=env,
                   capture_output=True, text=True, timeout=300, check=True)
    assert json.loads((run_dir / "config.json").read_text())["arithmetic"] == "native"
    assert "arithmetic native, GEMMs native, 1 torch thread" in (run_dir / "logs" / "learner.log").read_text()
    code = ("import sys, json; import mam_core; import torch; torch.set_num_threads(1); sys.path.insert(0, '.')\n"
            "from pathlib import Path\n"
            "from mam_core.config import resolve\nfrom mam_core.reference import run_reference\n"
            "from tests.test_exact import APPLE, APPLE_STEPS, _record, _same_params\n"
            "ref = run_reference('AppleCollect-v1', resolve('ma-ddpg', seed=3, **APPLE), APPLE_STEPS)\n"
            f"got = _record(Path({str(run_dir)!r}))\n"
            "print(json.dumps([_same_params(got['params'], ref.policy), "
            "got['evals'] == [(e['iterations'], e['purpose'], e['returns']) for e in ref.evaluations]]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env=dict(env, MAM_ARITHMETIC="native"), check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [True, True]


PINS_SEEN = ("import json, os, sys; from mam_core import arithmetic; arithmetic.for_children(sys.argv[1]); "
             "print(json.dumps({k: os.environ.get(k) for k in arithmetic.PINS}))")


def test_the_td3_bench_starts_each_side_from_the_users_environment() -> None:
    """`mam_lab.bench_td3` pins its own arithmetic as it imports mam_core; its `mam run
    --arithmetic native` side must still hand its roles the variables a user's shell has (here:
    this process's before it pinned), not the bench's pins, which native would keep as the
    user's (MKL's COMPATIBLE branch: the native side took 2.5x native's time in the records up to
    td3-1c047b8-intel). The portable side pins as always."""
    from mam_lab.bench_td3 import bench_sides

    sides, user = bench_sides(100, 50), arithmetic.unpinned_environ()
    for side, arith, want in (("mam-native", "native", {k: user.get(k) for k in arithmetic.PINS}),
                              ("mam", "portable", arithmetic.status()["pins"])):
        out = subprocess.run([sys.executable, "-c", PINS_SEEN, arith], cwd=ROOT, env=sides[side][1],
                             capture_output=True, text=True, timeout=120, check=True)
        assert json.loads(out.stdout) == want, side
    assert arithmetic.ARITHMETIC_ENV not in sides["mam"][1] and sides["loop"][1] == sides["mam"][1]


@AVX2
def test_a_process_started_by_a_pinned_one_still_computes_natively_under_native_arithmetic() -> None:
    """A child inherits its pinned parent's pins and could take them for its user's: `mam run
    --arithmetic native` started by a pinned program (a bench, `mam experiment`'s scheduler, a
    script that imported mam_core) computed in MKL's COMPATIBLE branch. The parent passes on what
    it found (FOUND_ENV): a native child, a native grandchild, and the roles a pinned child starts
    under native arithmetic see the user's variables; a portable one still pins."""
    user = arithmetic.unpinned_environ()
    want = {k: user.get(k) for k in arithmetic.PINS}
    inherited = dict(os.environ)  # this process is pinned (tests/conftest.py): what a child of it inherits
    assert {k: inherited[k] for k in arithmetic.PINS} == arithmetic.PINS and arithmetic.FOUND_ENV in inherited
    if want["MKL_CBWR"] == "COMPATIBLE":
        pytest.skip("this shell exports MKL_CBWR=COMPATIBLE itself: nothing tells the pins apart")

    def seen(code: str, *args: str, **extra: str) -> dict:
        out = subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True,
                             timeout=120, env=dict(inherited, **extra), check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])

    native = ("import json, os, mam_core, torch; from mam_core import arithmetic\n"
              "print(json.dumps(dict({k: os.environ.get(k) for k in arithmetic.PINS}, "
              "cap=torch.backends.cpu.get_cpu_capability())))")
    got = seen(native, MAM_ARITHMETIC="native")
    cap = got.pop("cap")
    assert got == want
    with open("/proc/cpuinfo") as f:
        if "avx512f" in f.read():  # the machine's own ATen kernels, not the pinned AVX2 ones
            assert cap.startswith("AVX512"), cap
    grandchild = ("import json, os, subprocess, sys, mam_core\n"
                  "env = dict(os.environ, MAM_ARITHMETIC='native')\n"
                  "print(subprocess.run([sys.executable, '-c', sys.argv[1]], env=env, capture_output=True, "
                  "text=True, check=True).stdout)")
    assert {k: v for k, v in seen(grandchild, native).items() if k != "cap"} == want
    assert seen(PINS_SEEN, "native") == want  # `mam run --arithmetic native` in a pinned child: its roles' view
    assert seen(PINS_SEEN, "portable") == arithmetic.PINS


MUJOCO_STEPS = """
import hashlib, json
import mam_core
import gymnasium as gym, numpy as np
out = {}
for env_id in ("HalfCheetah-v5", "Ant-v5", "Humanoid-v5"):
    env, rng, h = gym.make(env_id), np.random.default_rng(0), hashlib.sha256()
    env.reset(seed=0)
    for t in range(100):
        obs, _, term, trunc, _ = env.step(rng.uniform(-1, 1, env.action_space.shape) * env.action_space.high)
        h.update(obs.tobytes())
        if term or trunc:
            env.reset(seed=t)
    out[env_id] = h.hexdigest()
print(json.dumps(out))
"""


def glibc_without(features: list[str]) -> str:
    """GLIBC_TUNABLES that hide CPU features from glibc's choice of variants."""
    return "glibc.cpu.hwcaps=" + ",".join(f"-{f}" for f in features)


@AVX2
def test_mujoco_steps_do_not_depend_on_avx512_but_do_on_fma() -> None:
    """MuJoCo reads none of the pinned variables; what it takes from the CPU comes through glibc's
    libm (sin, cos, exp), whose variants glibc picks by CPU. Masking AVX-512 from glibc (a CPU
    with AVX2 only) leaves 100 random-action steps of three MuJoCo envs bit-identical; masking AVX2
    and FMA too (a CPU the guarantee does not cover) changes them: the check can fail."""
    pytest.importorskip("mujoco")

    def steps(tunables: str | None) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
        if tunables:
            env["GLIBC_TUNABLES"] = tunables
        r = subprocess.run([sys.executable, "-c", MUJOCO_STEPS], cwd=ROOT, capture_output=True, text=True,
                           timeout=300, env=env, check=True)
        return json.loads(r.stdout.strip().splitlines()[-1])

    avx512 = ["AVX512F", "AVX512VL", "AVX512BW", "AVX512DQ", "AVX512CD"]
    with ThreadPoolExecutor(2) as pool:
        native, no_avx512, no_fma = pool.map(steps, [None, glibc_without(avx512),
                                                     glibc_without(["AVX2", "FMA", *avx512])])
    assert no_avx512 == native
    assert any(no_fma[e] != native[e] for e in native), "masking AVX2 and FMA from glibc changed nothing"
