"""`--precision bf16` refuses to start where the CPU has no native bf16 GEMMs (16x slower there)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from services.run import cpu, options
from tests.e2e import ROOT

ZEN4 = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 9R14
flags\t\t: fpu vme sse sse2 avx avx2 avx512f avx512dq avx512bw avx512vl avx512_bf16 avx512_vnni
"""
SKYLAKE = """processor\t: 0
model name\t: Intel(R) Xeon(R) Platinum 8175M CPU @ 2.50GHz
flags\t\t: fpu vme sse sse2 avx avx2 avx512f avx512dq avx512bw avx512vl avx512_vnni
"""
SAPPHIRE = "flags\t\t: fpu avx512f avx512bw amx_bf16 amx_tile amx_int8\n"
GRAVITON3 = "processor\t: 0\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics bf16 i8mm sve\n"
GRAVITON2 = "processor\t: 0\nFeatures\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics\n"


@pytest.mark.parametrize("cpuinfo, native", [(ZEN4, True), (SAPPHIRE, True), (GRAVITON3, True),
                                             (SKYLAKE, False), (GRAVITON2, False), ("", False)])
def test_native_bf16_from_cpuinfo(cpuinfo: str, native: bool) -> None:
    assert cpu.native_bf16_cpu(cpuinfo) is native


def cfg(precision: str = "bf16"):
    return options.build_run_config(dict(env="Pendulum-v1", algo="td3", steps=100, device="cpu",
                                         precision=precision), None)


def test_check_precision(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    old, new = tmp_path / "skylake", tmp_path / "zen4"
    old.write_text(SKYLAKE)
    new.write_text(ZEN4)
    monkeypatch.delenv(cpu.ALLOW_SLOW_BF16, raising=False)
    monkeypatch.setenv(cpu.CPUINFO, str(old))
    with pytest.raises(typer.BadParameter, match="no native bf16"):
        cpu.check_precision(cfg())
    cpu.check_precision(cfg("fp32"))  # fp32 always starts
    monkeypatch.setenv(cpu.ALLOW_SLOW_BF16, "1")
    cpu.check_precision(cfg())  # the override
    monkeypatch.delenv(cpu.ALLOW_SLOW_BF16)
    monkeypatch.setenv(cpu.CPUINFO, str(new))
    cpu.check_precision(cfg())


@pytest.mark.parametrize("command", [["services.cli", "run"], ["services.roles.learner"]])
def test_mam_run_and_the_learner_refuse_bf16_without_native_support(tmp_path: Path, command: list[str]) -> None:
    (tmp_path / "cpuinfo").write_text(SKYLAKE)
    env = {k: v for k, v in os.environ.items() if k != cpu.ALLOW_SLOW_BF16}
    env.update({cpu.CPUINFO: str(tmp_path / "cpuinfo"), "COLUMNS": "200"})
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", *command, "--env", "Pendulum-v1", "--algo", "td3", "--steps", "100",
                           "--device", "cpu", "--precision", "bf16", "--run-dir", str(run_dir)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    text = " ".join((proc.stdout + proc.stderr).split())
    assert proc.returncode == 2, text
    assert "no native bf16" in text and "--precision fp32" in text and cpu.ALLOW_SLOW_BF16 in text
    assert not run_dir.exists()  # nothing started
