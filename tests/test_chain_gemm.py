"""mam_core's own GEMM kernels (portable arithmetic's default, mam_core/chain_gemm.c): every element is
one FMA chain over k in order, from +0, so the AVX-512, AVX2 and plain C kernels, any blocking,
orientation, layout, member sharing and thread count give the same bits, and those bits are the
definition computed exactly here, in rationals."""

from __future__ import annotations

import os
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest
import torch

from mam_core import arithmetic, gemm
from tests.e2e import ROOT

AVX512 = gemm._Chain(3).isa == 3  # what this CPU can run (asking for more gives the best it has)


@pytest.fixture(autouse=True)
def one_thread():
    gemm.set_threads(1)
    yield
    gemm.set_threads(1)


def fma32(a: np.float32, b: np.float32, c: np.float32) -> np.float32:
    """a·b + c rounded once to float32, to nearest, ties to even: exact, in rationals."""
    exact = Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c))
    near = np.float32(float(exact))  # within an ulp; the neighbours settle it
    best = min((np.nextafter(near, np.float32(-np.inf)), near, np.nextafter(near, np.float32(np.inf))),
               key=lambda f: (abs(Fraction(float(f)) - exact), int(np.float32(f).view(np.int32)) & 1))
    return np.float32(best) if best != 0 or exact != 0 else np.float32(0.0)  # an exact 0 is +0 (RN: -0 + +0)


def chain_by_definition(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    m, k = a.shape
    out = np.zeros((m, b.shape[1]), np.float32)
    for i in range(m):
        for j in range(b.shape[1]):
            acc = np.float32(0.0)
            for p in range(k):
                acc = fma32(a[i, p], b[p, j], acc)
            out[i, j] = acc
    return out


def operands(e: int, m: int, k: int, n: int, rng: np.random.Generator) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(a, b) of one product in the layouts the layers make: row- or column-major, a shared member."""
    a = torch.from_numpy(rng.standard_normal((e, m, k), dtype=np.float32))
    b = torch.from_numpy(rng.standard_normal((e, k, n), dtype=np.float32))
    shared = torch.from_numpy(rng.standard_normal((1, k, n), dtype=np.float32))
    return [(a, b), (a.mT.contiguous().mT, b), (a, b.mT.contiguous().mT), (a.mT.contiguous().mT, shared),
            (a, shared.mT.contiguous().mT.expand(e, -1, -1))]


def bits(x: torch.Tensor) -> np.ndarray:
    return x.numpy().view(np.int32)


def test_every_kernel_computes_the_definition_exactly() -> None:
    """Small products, every kernel, against the chain computed in rationals: shapes that leave
    partial tiles on both sides, a single row or column (the one-row kernel, the transposed
    orientation), k = 1, and signs that cancel to zero."""
    rng = np.random.default_rng(0)
    for m, k, n in [(7, 9, 5), (1, 13, 40), (33, 6, 1), (3, 1, 17), (13, 11, 35)]:
        a = rng.standard_normal((m, k)).astype(np.float32)
        b = rng.standard_normal((k, n)).astype(np.float32)
        a[0, :] = 0.0  # products of zeros and of -0: +0 from the first FMA
        b[:, 0] = -b[:, 0] if n > 1 else b[:, 0]
        want = chain_by_definition(a, b)
        for isa in (1, 2, 3):
            got = gemm._Chain(isa).bmm(torch.from_numpy(a)[None], torch.from_numpy(b)[None])[0]
            assert np.array_equal(bits(got), want.view(np.int32)), (isa, m, k, n)


def test_the_kernels_agree_bit_for_bit_in_every_layout() -> None:
    """AVX-512 (where the CPU has it), AVX2 and plain C, in every layout and shape the layers
    make, K longer than a block (the chain carried across blocks) and more rows than a block."""
    if not AVX512:
        pytest.skip("no AVX-512 on this CPU: the AVX2 and plain C kernels are still compared below")
    kernels = [gemm._Chain(isa) for isa in (3, 2, 1)]
    rng = np.random.default_rng(1)
    for e, m, k, n in [(2, 256, 23, 256), (1, 256, 256, 1), (2, 1, 256, 256), (3, 100, 300, 70),
                       (1, 130, 520, 33), (2, 5, 7, 3)]:
        for a, b in operands(e, m, k, n, rng):
            fast, avx2, plain = (bits(kernel.bmm(a, b)) for kernel in kernels)
            assert np.array_equal(fast, avx2) and np.array_equal(fast, plain), (e, m, k, n)
            torch.testing.assert_close(kernels[0].bmm(a, b).double(), torch.bmm(a.double(), b.double()
                                                                                .expand(e, -1, -1)),
                                       rtol=1e-5, atol=1e-4)


def test_avx2_and_plain_c_agree_bit_for_bit() -> None:
    avx2, plain = gemm._Chain(2), gemm._Chain(1)
    rng = np.random.default_rng(2)
    for e, m, k, n in [(2, 64, 300, 48), (1, 40, 17, 1), (3, 9, 33, 70)]:
        for a, b in operands(e, m, k, n, rng):
            assert np.array_equal(bits(avx2.bmm(a, b)), bits(plain.bmm(a, b))), (e, m, k, n)


def test_the_same_bits_over_any_number_of_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Members, or the columns of one member, cut over 1-3 threads: the same bits."""
    monkeypatch.setattr(gemm, "_chain", lambda: kernel)
    kernel = gemm._Chain()
    rng = np.random.default_rng(3)
    for e, m, k, n in [(1, 256, 256, 256), (3, 128, 128, 128), (2, 256, 17, 256)]:
        for a, b in operands(e, m, k, n, rng):
            results = []
            for threads in (1, 2, 3):
                gemm.set_threads(threads)
                results.append(bits(gemm.bmm(a, b)))  # the set threads reach the kernels
            assert np.array_equal(results[0], results[1]) and np.array_equal(results[0], results[2])


def learner_digest(env: dict[str, str]) -> str:
    """A few MA-TD3 updates (the layers' forward and backward products) in a fresh process."""
    code = ("import hashlib, mam_core; from mam_core import arithmetic, gemm; from tests.test_gemm import trained; "
            "assert arithmetic.status()['gemm'] == 'chain', arithmetic.status(); "
            "p = trained(int(__import__('os').environ.get('T', '1')), 'ma-td3', updates=3); "
            "print(hashlib.sha256(b''.join(p[n].tobytes() for n in sorted(p))).hexdigest())")
    base = {k: v for k, v in os.environ.items() if k not in arithmetic.PINS}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={**base, arithmetic.ARITHMETIC_ENV: "portable", arithmetic.GEMM_ENV: "chain", **env})
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_a_learner_s_updates_have_the_same_bits_under_every_kernel_and_thread_count() -> None:
    fast = learner_digest({gemm._Chain.ISA_ENV: "3", "T": "1"})
    assert learner_digest({gemm._Chain.ISA_ENV: "2", "T": "2"}) == fast
    assert learner_digest({gemm._Chain.ISA_ENV: "1", "T": "1"}) == fast


def test_a_fresh_machine_builds_them_once_and_computes_the_same_bits(tmp_path) -> None:
    """An empty cache (a fresh machine): the first process builds the library there with the
    compiler, and its products are this process's bit for bit; a second process reuses the build."""
    code = ("import sys, numpy as np, mam_core, torch; from mam_core import gemm; k = gemm._Chain(); "
            "a = torch.from_numpy(np.random.default_rng(7).standard_normal((2, 70, 300), dtype=np.float32)); "
            "sys.stdout.buffer.write(k.bmm(a, a.mT).numpy().tobytes())")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path)}
    first = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, timeout=120, env=env)
    assert first.returncode == 0, first.stderr[-2000:]
    built = list((tmp_path / "mam").glob("chain-*.so"))
    assert len(built) == 1
    made = built[0].stat().st_mtime_ns
    again = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, timeout=120, env=env)
    assert again.stdout == first.stdout and built[0].stat().st_mtime_ns == made
    a = torch.from_numpy(np.random.default_rng(7).standard_normal((2, 70, 300), dtype=np.float32))
    assert first.stdout == gemm._Chain().bmm(a, a.mT).numpy().tobytes()


def test_no_compiler_is_a_clear_error(tmp_path) -> None:
    code = "from mam_core import gemm; gemm._Chain()"
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path), "TMPDIR": str(tmp_path), "CC": str(tmp_path / "no-cc")}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode != 0 and "portable arithmetic needs a C compiler" in out.stderr, out.stderr[-2000:]
    assert "--arithmetic native" in out.stderr


def test_a_learner_that_cannot_build_them_stops_with_one_configuration_error(tmp_path) -> None:
    """`mam-learner` where no C compiler is found: exit 78 (EXIT_CONFIG, which `mam run` does not
    restart) after one line that says what is missing and what else would do."""
    from services.run.preflight import CONFIG_ERROR, EXIT_CONFIG

    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path), "TMPDIR": str(tmp_path), "CC": str(tmp_path / "no-cc"),
           "PYTHONWARNINGS": "ignore"}
    out = subprocess.run([sys.executable, "-m", "services.roles.learner", "--env", "Pendulum-v1", "--algo", "td3",
                          "--steps", "1000",
                          "--run", "no-compiler", "--run-dir", str(tmp_path / "run"), "--listen", "tcp/127.0.0.1:0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    lines = [line for line in (out.stdout + out.stderr).splitlines() if CONFIG_ERROR in line]
    assert out.returncode == EXIT_CONFIG and len(lines) == 1, out.stdout[-2000:] + out.stderr[-2000:]
    assert "portable arithmetic needs a C compiler" in lines[0] and "--arithmetic native" in lines[0]
