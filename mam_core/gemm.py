"""The learner's GEMMs under portable arithmetic: fast kernels whose bits do not depend on the CPU.

torch's CPU GEMMs run in MKL, whose only branch with the same bits on Intel and AMD is
COMPATIBLE (`MKL_CBWR`), about 3-6x slower than the machine's own kernels. Here every product of
the learner's layers (the forward one and both backward ones) runs in NumPy's OpenBLAS instead,
pinned so that the kernel, its blocking and its path are fixed (mam_core/arithmetic.py):

- `OPENBLAS_CORETYPE=Haswell`: the AVX2/FMA kernels on any x86-64 CPU with AVX2 (the dynamic
  build's table for that core, whatever the CPU is). FMA rounds once, by IEEE 754, on every vendor.
- The K-blocking (`SGEMM_DEFAULT_Q` of that table) is a constant; `OPENBLAS_L2_SIZE` pins the one
  parameter the library would read off the CPU (it only sizes older cores' row panels).
- `OPENBLAS_NUM_THREADS=1`: each call runs in the calling thread, so the library's own threading,
  which splits a product another way for another thread count, never runs.
- No call is a row-major N·N product: OpenBLAS takes its AVX-512 "direct" kernel for small
  row-major N·N products (α = 1, β = 0, what NumPy passes) on CPUs that have AVX-512 (a check of
  the CPU, not of the pinned core), and never when an operand is transposed. `bmm` computes such
  a product as (Bᵀ·Aᵀ)ᵀ, T·T, without a copy.

The second core: the members of an ensemble (K actors, n·K critics) are independent products. They
are always cut the same way, one member a call, and the calls spread over `threads()` Python
threads (NumPy drops the GIL in BLAS). A product of one member (TD3's actor) is always cut into
two calls on the two halves of its output's columns, whatever the thread count (a cut changes a
product's bits, so it depends on the shapes alone). Which thread computes a call does not change
its bits, so the learner's thread count is free (`set_threads`, `learner_threads`).

`tests/test_gemm.py` checks the products against float64, the bits against every thread count, and
that no call takes the row-major N·N form.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

_PARALLEL_MIN_FLOPS = 1 << 20  # below this a product runs in the calling thread (threads cost ~20 µs)
_MIN_HALF = 32  # a one-member product is cut in two column halves of at least this many columns
THREADS_ENV = "MAM_GEMM_THREADS"  # the threads a process starts with (default 1; `set_threads` changes it)
_pool: ThreadPoolExecutor | None = None
_threads = 1
_lock = threading.Lock()


def set_threads(n: int) -> None:
    """Spread the members' products over `n` threads (1: the calling thread only). Bits do not
    depend on it."""
    global _pool, _threads
    n = max(1, int(n))
    with _lock:
        if n == _threads:
            return
        if _pool is not None:
            _pool.shutdown(wait=True)
        _pool = ThreadPoolExecutor(n - 1, thread_name_prefix="mam-gemm") if n > 1 else None
        _threads = n


def threads() -> int:
    return _threads


def use_learner_threads(n: int) -> str:
    """A learner's threads (`--learner-threads`, RunConfig.learner_threads; 0: automatic). Under
    portable GEMMs torch keeps one thread (its reductions split by the thread count, which would
    change bits) and the GEMMs spread over n threads (0: every CPU this process may use); under
    torch's own GEMMs (native or the MKL fallback) torch gets n threads (0: one, as before: torch's
    OpenMP threads spin and contend with the workers on a small box).
    Returns what was set, for the log."""
    from mam_core import arithmetic

    if arithmetic.portable_gemm():
        torch.set_num_threads(1)
        set_threads(n if n > 0 else default_threads())
        return f"1 torch thread, GEMMs over {threads()} thread(s) (the same bits for any count)"
    torch.set_num_threads(n if n > 0 else 1)
    return f"{torch.get_num_threads()} torch thread(s)"


def _from_environment() -> None:
    try:
        n = int(os.environ.get(THREADS_ENV, "1"))
    except ValueError:
        raise ValueError(f"{THREADS_ENV}={os.environ[THREADS_ENV]!r}: give a number of threads") from None
    if n != 1:
        set_threads(n)


def default_threads() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _blasable(stride1: int, stride2: int, d2: int) -> bool:
    """NumPy's test of a 2-D operand for BLAS (`is_blasable2d` of its matmul): rows `stride1`
    bytes apart, `stride2` the element stride, d2 elements a row."""
    return stride2 == 4 and stride1 % 4 == 0 and stride1 // 4 >= d2


def row_major(x: np.ndarray) -> bool:
    """Would NumPy pass each 2-D slice of `x` to BLAS untransposed (N)?"""
    return _blasable(x.strides[-2], x.strides[-1], x.shape[-1])


def col_major(x: np.ndarray) -> bool:
    """... or transposed (T)?"""
    return _blasable(x.strides[-1], x.strides[-2], x.shape[-2])


def _mm(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    np.matmul(a, b, out=out)


def bmm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a [E, m, k] · b [E, k, n] -> [E, m, n] float32 on the CPU, one pinned `sgemm` a member,
    never in the row-major N·N form: where both operands are row-major the product is computed
    as (bᵀ·aᵀ)ᵀ, both transposed (T·T), and returned as a transposed view. The form depends on
    the operands' layouts only, which the code fixes, never on the machine."""
    e = max(a.shape[0], b.shape[0])
    an = a.detach().expand(e, -1, -1).numpy()
    bn = b.detach().expand(e, -1, -1).numpy()
    if not (row_major(an) or col_major(an)):
        an = np.ascontiguousarray(an)
    if not (row_major(bn) or col_major(bn)):
        bn = np.ascontiguousarray(bn)
    swap = row_major(an) and row_major(bn)
    if swap:  # (N, N) -> (T, T)
        an, bn = bn.transpose(0, 2, 1), an.transpose(0, 2, 1)
    m, k, n = an.shape[1], an.shape[2], bn.shape[2]
    out = np.empty((e, m, n), np.float32)
    big = 2 * m * n * k >= _PARALLEL_MIN_FLOPS
    if e >= 2:  # one call a member, the members in chunks over the threads
        parts = min(_threads, e) if big else 1
        cuts = [e * i // parts for i in range(parts + 1)]
        pieces = [(an[lo:hi], bn[lo:hi], out[lo:hi]) for lo, hi in zip(cuts[:-1], cuts[1:])]
    elif big and n >= 2 * _MIN_HALF:  # one member: always two calls, on the two halves of its columns
        half = n // 2
        pieces = [(an, bn[:, :, :half], out[:, :, :half]), (an, bn[:, :, half:], out[:, :, half:])]
    else:
        pieces = [(an, bn, out)]
    _run(pieces)
    # from the transposed array itself: a tensor of its own (not a view, which relu_ could not modify)
    return torch.from_numpy(out.transpose(0, 2, 1) if swap else out)


def _run(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """The products of `pieces`, the first in this thread, the others on the pool (if any)."""
    pool = _pool
    if pool is None or len(pieces) == 1:
        for piece in pieces:
            _mm(*piece)
        return
    futures = [pool.submit(_mm, *piece) for piece in pieces[1:]]
    _mm(*pieces[0])
    for f in futures:
        f.result()


class _Baddbmm(torch.autograd.Function):
    """bias + a·b with its two backward products through `bmm` (the bias gradient as torch's)."""

    @staticmethod
    def forward(ctx, bias: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
        ctx.save_for_backward(a, b)
        ctx.bias_shape = bias.shape
        return bmm(a, b).add_(bias)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # noqa: ANN001, ANN205
        a, b = ctx.saved_tensors
        grad_bias = grad_a = grad_b = None
        if ctx.needs_input_grad[0]:
            grad_bias = grad.sum_to_size(ctx.bias_shape)
        if ctx.needs_input_grad[1]:
            grad_a = bmm(grad, b.transpose(1, 2)).sum_to_size(a.shape)
        if ctx.needs_input_grad[2]:
            grad_b = bmm(a.transpose(1, 2), grad).sum_to_size(b.shape)
        return grad_bias, grad_a, grad_b


def baddbmm(bias: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """`torch.baddbmm(bias, a, b)` (β = α = 1) with its products in the pinned kernels."""
    return _Baddbmm.apply(bias, a, b)


def addmm(bias: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """`torch.addmm(bias, a, b)` for 2-D a, b, likewise."""
    return _Baddbmm.apply(bias.unsqueeze(0), a.unsqueeze(0), b.unsqueeze(0)).squeeze(0)


_from_environment()
