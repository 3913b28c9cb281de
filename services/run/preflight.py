"""Configuration errors: what `mam run` checks before it starts a process, and the exit status
of a role that finds one.

A configuration error (a device torch does not see, a run directory that cannot be written)
is not a fault: no restart mends it. `mam run` checks the device and the run directory here
before any child starts (the env id and env kwargs are checked when the config is built,
`services.run.options.check_env_id`), and a role that still meets one exits with EXIT_CONFIG
after one log line "configuration error: <reason>"; the launcher stops the run on that
status and prints the line instead of restarting the role (docs/RELIABILITY.md).

This module imports no torch: the launcher asks a short-lived `python -c` for the CUDA
devices, and only when --device names CUDA.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

from services.run import rundir

EXIT_CONFIG = 78  # a role's exit status on a configuration error (EX_CONFIG of sysexits.h)
CONFIG_ERROR = "configuration error:"  # the log line's prefix the launcher looks for
DEVICES = re.compile(r"auto|cpu|cuda(:\d+)?")  # what --device takes
PROBE_TIMEOUT_S = 120.0
_PROBE = "import torch; print(int(torch.cuda.is_available()), torch.cuda.device_count())"


class ConfigError(Exception):
    """A setting that cannot work on this host; the message is one line and says what to change."""


def cuda_problem(device: str, available: bool, count: int) -> str:
    """Why `device` cannot be used when torch reports CUDA `available` with `count` devices ("" if it can)."""
    if not DEVICES.fullmatch(device):
        return f"--device must be auto, cpu, cuda or cuda:N, not {device!r}"
    if not device.startswith("cuda"):
        return ""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    seen = f" (CUDA_VISIBLE_DEVICES={visible!r})" if visible is not None else ""
    if not available or count == 0:
        return (f"--device {device} asked for, but torch on this host sees no CUDA device{seen}; "
                "use --device cpu or auto, or a CUDA build of torch on a host with a GPU")
    index = int(device.partition(":")[2] or 0)
    if index >= count:
        return (f"--device {device} asked for, but torch sees {count} CUDA device{'s' if count > 1 else ''} "
                f"(cuda:0 to cuda:{count - 1}){seen}; CUDA_VISIBLE_DEVICES picks which GPUs torch sees, "
                "and renumbers them from 0")
    return ""


def check_device(device: str) -> None:
    """ConfigError unless torch on this host can use `device`. auto and cpu pass without torch;
    for cuda[:N] a child Python imports torch and counts the devices."""
    if device in ("auto", "cpu") or not DEVICES.fullmatch(device):
        problem = cuda_problem(device, False, 0)
    else:
        try:
            probe = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                                   timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL)
            available, count = (int(x) for x in probe.stdout.split()[-2:])
        except (OSError, ValueError, subprocess.TimeoutExpired) as e:
            raise ConfigError(f"--device {device}: cannot ask torch for its CUDA devices ({e})") from None
        problem = cuda_problem(device, bool(available), count)
    if problem:
        raise ConfigError(problem)


def device_problem_here(device: str) -> str:
    """`cuda_problem` with this process's torch (a role that imports torch anyway)."""
    if not device.startswith("cuda"):
        return cuda_problem(device, False, 0)
    import torch

    return cuda_problem(device, torch.cuda.is_available(), torch.cuda.device_count())


def require_device(device: str, log: logging.Logger) -> None:
    """In a role: exit EXIT_CONFIG with one log line if this host cannot use `device`."""
    problem = device_problem_here(device)
    if problem:
        log.error("%s %s", CONFIG_ERROR, problem)
        raise SystemExit(EXIT_CONFIG)


def require_gemm(log: logging.Logger) -> None:
    """In the learner: exit EXIT_CONFIG with one log line if the GEMM kernels of its arithmetic
    cannot be loaded here (portable arithmetic's are built with the C compiler at first use)."""
    from mam_core import gemm

    try:
        gemm.ready()
    except (RuntimeError, ValueError) as e:
        log.error("%s %s", CONFIG_ERROR, e)
        raise SystemExit(EXIT_CONFIG) from None


def gemm_problem(recorded: Any, current: str) -> str:
    """Why a learner computing its GEMMs with `current` (arithmetic.status()["gemm"]) must not
    resume a checkpoint whose learner computed with `recorded` ("" if it may: the same, or a
    checkpoint from before the kernels were recorded). The kernels are chosen by the environment
    (MAM_PORTABLE_GEMM), not by the run's config, so a resume from another shell could change
    them, and with them every float of the rest of the run."""
    from mam_core import arithmetic

    if not isinstance(recorded, str) or recorded == current:
        return ""
    asked = {"chain": f"{arithmetic.GEMM_ENV} unset", "openblas-haswell": f"{arithmetic.GEMM_ENV}=openblas",
             "mkl-compatible": f"{arithmetic.GEMM_ENV}=mkl"}
    how = asked.get(recorded, f"the GEMMs {recorded!r}")
    return (f"this run's learner computed its GEMMs with {recorded}, this one would with {current}, and the "
            f"rest of the run would not be the run: resume it with {how} in the environment")


def check_run_dir(run_dir: Path) -> None:
    """ConfigError unless `run_dir` is (or can be made) a directory this process can write to."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run directory {run_dir} is a file, not a directory; pass another --run-dir")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create run directory {run_dir}: {e.strerror or e}; pass another --run-dir") \
            from None
    if not os.access(run_dir, os.W_OK | os.X_OK):
        raise ConfigError(f"cannot write to run directory {run_dir} (permission denied); pass another --run-dir")


def held_run(run_dir: Path) -> str:
    """Why a new run cannot start in `run_dir` ("" if it can): a run's checkpoint is there (`mam run`
    would resume that run's learner under its own name and start the other roles under the new one).
    The caller holds the directory's run lock (services/run/launcher.py: `run_local`), so no other
    `mam run` lives there, and a learner or referee still stopping after its `mam run` was killed
    has been waited for."""
    if not rundir.has_checkpoint(run_dir):
        return ""
    try:
        name = json.loads((run_dir / rundir.CONFIG).read_text())["run"]
    except (OSError, ValueError, KeyError, TypeError):
        name = "another run"
    if (run_dir / rundir.SUMMARY).is_file():
        return f"run directory {run_dir} holds {name}, finished: pass another --run-dir for a new run"
    return (f"run directory {run_dir} holds {name}'s checkpoint: continue that run with "
            f"`mam run --resume {run_dir}`, or pass another --run-dir for a new one")
