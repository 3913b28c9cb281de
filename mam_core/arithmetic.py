"""Portable arithmetic: the same seed gives the same run on any x86-64 CPU with AVX2.

The libraries mam computes with pick their kernels by the CPU they find, and another kernel
sums floats in another order:

- torch's GEMMs, and its tanh, run in MKL, whose kernel depends on the CPU's instruction sets
  and cache sizes. MKL's conditional numerical reproducibility (`MKL_CBWR`) fixes the branch;
  COMPATIBLE is the one branch MKL honours on Intel and AMD CPUs alike (AVX2 and the others are
  "available only for Intel processors": on AMD MKL falls back to AUTO without a word).
- torch's own kernels are compiled for several instruction sets and chosen at import
  (`ATEN_CPU_CAPABILITY`); `torch.randn` changes between the default and the AVX2 build.
- NumPy dispatches some ufuncs by CPU: `np.exp` of float64 has other bits under AVX-512 than
  under AVX2. `NPY_DISABLE_CPU_FEATURES` keeps it to its AVX2 (X86_V3) loops.
- NumPy's OpenBLAS picks a kernel per CPU model: pinned to its Haswell (AVX2) kernels for what
  calls BLAS outside the actors (AppleCollect's distances, an env's own numpy).
- The workers' and the referee's actors call no BLAS at all: `mam_core.policy.dense` sums in a
  fixed order.

Each library reads its variable once, when it loads (MKL at its first call), so `pin()` runs
before numpy or torch is imported: `mam_core/__init__.py` calls it, and `services` and
`mam_lab` import `mam_core` first, so every command and `python -m` entry point (and the test
suite, through tests/conftest.py) pins before anything else loads. A process that imported
numpy or torch before mam is machine-bound: `status()` says so, with a warning.

`MAM_ARITHMETIC=native` (`--arithmetic native`) leaves the libraries to choose, for speed;
that run reruns only on the machine, and in the environment, where it ran. This module imports
nothing but the standard library.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import warnings
from typing import Any

ARITHMETIC_ENV = "MAM_ARITHMETIC"
ARITHMETICS = ("portable", "native")
# The learner's GEMMs under portable arithmetic: mam_core's own kernels (the default: one FMA chain
# an element, mam_core/chain_gemm.c); "openblas": NumPy's OpenBLAS pinned to its Haswell kernels
# (the default from 08c3077 until the chain kernels: other bits, to rerun the records of those
# commits); "mkl": MKL's COMPATIBLE branch (the default before 08c3077; other bits again)
GEMM_ENV = "MAM_PORTABLE_GEMM"
GEMMS = {"chain": "chain", "openblas": "openblas-haswell", "mkl": "mkl-compatible"}  # GEMM_ENV: status["gemm"]

# NumPy names its AVX-512 dispatch targets X86_V4, AVX512_ICL, AVX512_SPR (2.4 and later) or
# AVX512F, AVX512_SKX, ... (earlier): names a NumPy does not know are ignored (an ImportWarning).
_NUMPY_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL"

PINS: dict[str, str] = {
    "MKL_CBWR": "COMPATIBLE",
    "ATEN_CPU_CAPABILITY": "avx2",
    "NPY_DISABLE_CPU_FEATURES": _NUMPY_AVX512,
    "OPENBLAS_CORETYPE": "Haswell",
    "OPENBLAS_NUM_THREADS": "1",
    "OPENBLAS_L2_SIZE": "1024",
}
# Not a pin (no bits depend on it), set unless the environment sets it: how long OpenBLAS's
# threads spin for the next call before they sleep, 2^16 cycles (mam_core/gemm.py, `_Batch`:
# the learner's GEMMs over its threads; a longer spin burns the core the workers need).
SPEED = {"OPENBLAS_THREAD_TIMEOUT": "16"}

# Where a pinned process starts another, the child inherits its pins and cannot tell them from
# values its user exported (a `mam run --arithmetic native` started by a pinned program kept MKL's
# COMPATIBLE branch as the user's choice: docs/PERFORMANCE.md, "A native side that was not native").
# So a process that pins passes on, in this variable, the values it found (JSON), and a process
# that finds a variable still at the pinned value with this beside it takes the value passed on.
FOUND_ENV = "MAM_ARITHMETIC_FOUND"
_NAMES = (*PINS, *SPEED, "NPY_ENABLE_CPU_FEATURES")  # what pin() sets or removes

_status: dict[str, Any] = {}
_before: dict[str, str | None] = {}  # the variables as the user set them (`_found`), before pin() set them


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity), at least 1. Standard library only:
    the launcher, which never imports torch, asks it too."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def cpu_has_avx2() -> bool:
    """An x86-64 CPU with AVX2 and FMA (Linux: /proc/cpuinfo), the machines the pins cover."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return {"avx2", "fma"} <= flags
    except OSError:
        pass
    return False


def _pinned(name: str) -> str | None:
    """The value `pin()` leaves in the environment for `name` (None: removed)."""
    return PINS.get(name, SPEED.get(name))


def _found() -> dict[str, str | None]:
    """The variables of `_NAMES` as the user set them: as this process found them, but for a value
    still at what a pinning ancestor set, which is taken as what that ancestor found (FOUND_ENV)."""
    found = {k: os.environ.get(k) for k in _NAMES}
    try:
        passed = json.loads(os.environ.get(FOUND_ENV) or "{}")
    except ValueError:
        passed = {}
    if isinstance(passed, dict):
        for k in _NAMES:
            if k in passed and isinstance(passed[k], (str, type(None))) and found[k] == _pinned(k):
                found[k] = passed[k]
    return found


def _restore(values: dict[str, str | None], env: Any = os.environ) -> None:
    """Set (or remove, for None) each variable of `values` in `env`."""
    for k, v in values.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v


def pin() -> dict[str, Any]:
    """Set the pins of `PINS` in os.environ (over any value already there) unless the
    arithmetic is native; return `status()`. Idempotent: the first call decides."""
    if _status:
        return dict(_status)
    mode = os.environ.get(ARITHMETIC_ENV, "portable") or "portable"
    if mode not in ARITHMETICS:
        raise ValueError(f"{ARITHMETIC_ENV}={mode!r}: choose one of {', '.join(ARITHMETICS)}")
    late = [m for m in ("numpy", "torch") if m in sys.modules]
    why = ""
    _before.update(_found())
    if mode == "native":
        why = "native arithmetic: the libraries choose their kernels for this CPU"
        _restore(_before)  # an ancestor's pins are not the user's: the machine's own kernels
        os.environ.pop(FOUND_ENV, None)
    elif not cpu_has_avx2():
        why = f"not an x86-64 CPU with AVX2 and FMA ({platform.machine()}): nothing pinned"
    else:
        os.environ[FOUND_ENV] = json.dumps(_before, sort_keys=True)  # for the processes this one starts
        os.environ.update(PINS)
        for k, v in SPEED.items():
            os.environ.setdefault(k, v)
        os.environ.pop("NPY_ENABLE_CPU_FEATURES", None)  # NumPy refuses to start with both set
        if late:
            why = (f"{' and '.join(late)} imported before mam pinned the arithmetic: this process keeps the "
                   "kernels it loaded (import mam_core before numpy and torch)")
            warnings.warn(f"mam: {why}; results may differ from other machines", RuntimeWarning, stacklevel=2)
    _status.update(arithmetic=mode, portable=not why, machine_bound=why,
                   pins={k: os.environ.get(k, "") for k in PINS})
    return dict(_status)


def unpinned_environ() -> dict[str, str]:
    """os.environ as it was before `pin()` set the pins: for a child that must choose its own
    kernels (a yardstick that is not mam)."""
    pin()
    env = dict(os.environ)
    _restore(_before, env)
    env.pop(ARITHMETIC_ENV, None)
    env.pop(FOUND_ENV, None)
    return env


def portable_gemm() -> bool:
    """Do the learner's float32 GEMMs run in `mam_core.gemm`? Under portable arithmetic, in
    mam_core's own kernels ("chain", the default) or NumPy's pinned OpenBLAS (GEMM_ENV=openblas,
    where NumPy's BLAS is OpenBLAS: else an error); else torch's (MKL COMPATIBLE under portable
    arithmetic with GEMM_ENV=mkl; the machine's own kernels under native)."""
    if "gemm" not in _status:
        pin()
        asked = os.environ.get(GEMM_ENV, "") or "chain"
        if asked not in GEMMS:
            raise ValueError(f"{GEMM_ENV}={asked!r}: give one of {', '.join(GEMMS)}")
        if asked == "openblas" and _status["portable"] and not _numpy_blas_is_openblas():
            raise ValueError(f"{GEMM_ENV}=openblas: this NumPy's BLAS is not OpenBLAS")
        _status["gemm"] = GEMMS[asked] if _status["portable"] else "native"
    return _status["gemm"] in ("chain", "openblas-haswell")


def _numpy_blas_is_openblas() -> bool:
    try:
        import numpy as np

        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
    except Exception:  # noqa: BLE001 - an unusual NumPy: the fallback kernels
        return False
    return "openblas" in str(blas.get("name", "")).lower() and "openblas" in str(
        blas.get("openblas configuration", "openblas")).lower()


def status() -> dict[str, Any]:
    """{"arithmetic": "portable" | "native", "portable": bool, "machine_bound": "" or why not,
    "pins": the variables as this process set them}."""
    return pin()


def for_children(arithmetic: str) -> None:
    """Make the processes this one starts from now on compute with `arithmetic` (`mam run`'s
    roles): MAM_ARITHMETIC for their `pin()`, and for native the variables as they were before
    this process pinned them (the children must not inherit this process's pins)."""
    if arithmetic not in ARITHMETICS:
        raise ValueError(f"arithmetic must be one of {', '.join(ARITHMETICS)}, not {arithmetic!r}")
    pin()
    os.environ[ARITHMETIC_ENV] = arithmetic
    if arithmetic == "native":
        _restore(_before)
        os.environ.pop(FOUND_ENV, None)
