"""Configuration errors stop at once, with the reason on the terminal; restarts are for faults.

Real processes: `mam run` and `mam learner` as a user starts them, and `run_local` with a
learner child that meets a device torch does not see (services/run/preflight.py).
"""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mam_core.config import resolve
from services.run.preflight import EXIT_CONFIG, ConfigError, check_run_dir, cuda_problem
from tests.e2e import ROOT, unique_run

ENV = dict(os.environ, COLUMNS="200", PYTHONWARNINGS="ignore")
APPLE = ["--env", "AppleCollect-v1", "--steps", "300", "--hidden", "16,16", "--no-plot"]
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a host where torch sees no CUDA device")


def _mam(*args: str, timeout: float = 60) -> tuple[subprocess.CompletedProcess, float]:
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=ROOT, env=ENV, text=True,
                          capture_output=True, timeout=timeout, stdin=subprocess.DEVNULL)
    return proc, time.monotonic() - started


@no_cuda
def test_mam_run_device_cuda_on_a_cpu_host_stops_at_once_with_the_reason(tmp_path: Path):
    run_dir = tmp_path / "run"
    proc, took = _mam("run", *APPLE, "--device", "cuda", "--run", unique_run("cfg"), "--run-dir", str(run_dir))
    assert proc.returncode != 0 and took < 10, (proc.returncode, took, proc.stdout, proc.stderr)
    assert "torch on this host sees no CUDA device" in proc.stderr, proc.stderr
    assert "restart" not in proc.stdout + proc.stderr
    assert not (run_dir / "logs").exists()  # no child was started


@no_cuda
def test_cuda_n_is_a_device_and_names_the_missing_gpu(tmp_path: Path):
    assert resolve("ma-td3", device="cuda:1").device == "cuda:1"
    with pytest.raises(ValueError, match="cuda:N"):
        resolve("ma-td3", device="gpu")
    proc, _ = _mam("run", *APPLE, "--device", "cuda:1", "--run-dir", str(tmp_path / "run"))
    assert proc.returncode == 2 and "--device cuda:1 asked for" in proc.stderr, proc.stderr
    text = cuda_problem("cuda:2", True, 2)
    assert "torch sees 2 CUDA devices (cuda:0 to cuda:1)" in text and "CUDA_VISIBLE_DEVICES" in text
    assert cuda_problem("cuda:1", True, 2) == "" and cuda_problem("cpu", False, 0) == ""


def test_a_run_directory_that_is_a_file_is_refused_before_any_process(tmp_path: Path):
    (tmp_path / "taken").write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        check_run_dir(tmp_path / "taken")
    proc, _ = _mam("run", *APPLE, "--device", "cpu", "--run-dir", str(tmp_path / "taken"))
    assert proc.returncode == 2 and "is a file, not a directory" in proc.stderr, proc.stderr


@no_cuda
def test_a_role_with_a_configuration_error_exits_78_after_one_line(tmp_path: Path):
    proc, _ = _mam("learner", *APPLE[:-1], "--device", "cuda", "--run", unique_run("cfg"),
                   "--listen", "tcp/127.0.0.1:0", "--run-dir", str(tmp_path / "run"))
    assert proc.returncode == EXIT_CONFIG, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "configuration error:" in ln]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr


@no_cuda
def test_the_launcher_does_not_restart_a_child_that_exits_with_a_configuration_error(tmp_path: Path):
    """A learner that meets the error after `mam run`'s checks (here: run_local called directly,
    as `mam experiment` does) stops the run at once; the reason is on stderr, no restart."""
    run_dir = tmp_path / "run"
    script = (
        "import sys\n"
        "from services.run.launcher import run_local\n"
        "from services.run.options import build_run_config\n"
        f"cfg = build_run_config({{'env': 'AppleCollect-v1', 'steps': 300, 'hidden': '16,16', 'device': 'cuda', "
        f"'run': {unique_run('cfg')!r}}}, None)\n"
        f"summary = run_local(cfg, __import__('pathlib').Path({str(run_dir)!r}), plot=False)\n"
        "sys.exit(0 if summary else 1)\n")
    started = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=ENV, text=True, capture_output=True,
                          timeout=120)
    took = time.monotonic() - started
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    assert "learner stopped on a configuration error: --device cuda asked for" in proc.stderr, proc.stderr
    assert "restart" not in proc.stdout.replace("not restarted", ""), proc.stdout
    assert "--- mam run:" not in (run_dir / "logs" / "learner.log").read_text()  # no restart banner
    assert took < 60, took


@no_cuda
def test_mam_experiment_checks_the_device_once_before_any_run(tmp_path: Path):
    proc, took = _mam("experiment", "--exp-dir", str(tmp_path / "exp"), "--envs", "AppleCollect-v1", "--algos",
                      "ddpg", "--steps", "100", "--device", "cuda", "--no-ledger")
    assert proc.returncode == 2 and "torch on this host sees no CUDA device" in proc.stderr, proc.stderr
    assert not (tmp_path / "exp").exists()


def test_an_unknown_env_id_or_env_kwargs_stop_mam_run_before_any_process(tmp_path: Path):
    for args, reason in ((["--env", "NoSuch-v9"], "doesn't exist"),
                         (["--env", "AppleCollect-v1", "--env-kwargs", '{"nope": 1}'], "unexpected keyword argument")):
        proc, took = _mam("run", *args, "--steps", "100", "--run-dir", str(tmp_path / "run"))
        assert proc.returncode == 2 and reason in proc.stderr and took < 30, (took, proc.stderr)
        assert not (tmp_path / "run").exists()
