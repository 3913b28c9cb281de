"""CPU features the run depends on: whether `--precision bf16` has native bf16 GEMMs here."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from services.run.config import RunConfig

ALLOW_SLOW_BF16 = "MAM_ALLOW_SLOW_BF16"  # set to 1: run --precision bf16 even without native bf16 GEMMs
CPUINFO = "MAM_CPUINFO"  # read this file instead of /proc/cpuinfo (tests; a CPU you plan to run on)
BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")  # x86 AVX512-BF16, x86 AMX, aarch64 BF16


def cpu_flags(cpuinfo: str | None = None) -> set[str]:
    """The CPU feature flags of /proc/cpuinfo (x86 `flags`, aarch64 `Features`); empty if unknown."""
    if cpuinfo is None:
        try:
            cpuinfo = Path(os.environ.get(CPUINFO) or "/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return set()
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip().lower() in ("flags", "features"):
            flags.update(value.split())
    return flags


def native_bf16_cpu(cpuinfo: str | None = None) -> bool:
    """True if this CPU computes bf16 GEMMs natively (AVX512-BF16, AMX-BF16 or Arm BF16).

    Without them oneDNN emulates bf16 with fp32 conversions: the K=2 update measured 16×
    slower than in fp32 on such a CPU (docs/PERFORMANCE.md).
    """
    return bool(cpu_flags(cpuinfo) & set(BF16_CPU_FLAGS))


def check_precision(cfg: RunConfig) -> None:
    """Refuse `--precision bf16` where it would only be slower (typer.BadParameter).

    A CPU learner needs native bf16 GEMMs, a CUDA learner a GPU with bf16 support. The
    environment variable MAM_ALLOW_SLOW_BF16=1 runs it anyway (to measure it, or in tests).
    """
    if cfg.algo.precision != "bf16" or os.environ.get(ALLOW_SLOW_BF16) == "1":
        return
    device = cfg.algo.device
    if device == "auto" or device.startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            if torch.cuda.is_bf16_supported():
                return
            raise typer.BadParameter(
                "--precision bf16: this GPU has no native bf16 support; use --precision fp32 "
                f"(or set {ALLOW_SLOW_BF16}=1 to run it anyway)")
    if native_bf16_cpu():
        return
    raise typer.BadParameter(
        "--precision bf16: this CPU has no native bf16 GEMMs (no avx512_bf16, amx_bf16 or Arm bf16 in "
        "/proc/cpuinfo), where bf16 updates run ~16x slower than fp32 instead of ~1.5x faster. "
        f"Use --precision fp32 (the default), or set {ALLOW_SLOW_BF16}=1 to run it anyway "
        "(docs/PERFORMANCE.md lists which CPUs benefit).")
