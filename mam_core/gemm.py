"""The learner's GEMMs under portable arithmetic: fast kernels whose bits do not depend on the CPU.

torch's CPU GEMMs run in MKL, whose only branch with the same bits on Intel and AMD is
COMPATIBLE (`MKL_CBWR`), about 3-6x slower than the machine's own kernels. Here every product of
the learner's layers (the forward one and both backward ones) runs in other kernels:

- By default in mam_core's own (mam_core/chain.py, mam_core/chain_gemm.c): every element of a product is
  one chain of fused multiply-adds over k in order, from +0, a sum defined by the operands alone.
  FMA rounds once, by IEEE 754, on every CPU; the kernels vectorize across the elements, never
  along k, so the AVX-512, AVX2 and plain C kernels, any blocking, layout and cut over threads
  give the same bits, and no library's version or CPU table enters. They are built with the C
  compiler at the first use (or by `make venv`) into the user's cache.
- With `MAM_PORTABLE_GEMM=openblas` (the default from 08c3077 until the chain kernels; other
  bits, kept to rerun records of those commits) in NumPy's OpenBLAS, pinned so that the kernel,
  its blocking and its path are fixed (mam_core/arithmetic.py); the rest of this docstring is
  about it:

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
are always cut the same way, one member a call. A product of one member (TD3's actor) is always
cut into two calls on the two halves of its output's columns, whatever the thread count (a cut
changes a product's bits, so it depends on the shapes alone). The calls of one `bmm` spread over
`threads()` threads in one call of OpenBLAS's `sgemm_batch` (`_Batch`): it hands each product
whole to one of its own threads, which runs the single-threaded driver that `sgemm` runs with one
thread, with the same arguments NumPy's matmul would pass (so the same bits), and its threads
wait spinning, not sleeping, between calls (a thread woken by the kernel took 20-100 µs a call on
a virtual machine, which ate the second core's gain). Where that entry point is missing, the
calls spread over Python threads instead (NumPy drops the GIL in BLAS). Which thread computes a
call does not change its bits, so the learner's thread count is free (`set_threads`,
`learner_threads`).

A warm-up before a thread's first product (`_warm`). On a 2-core AMD EPYC of family 23 (Zen 1,
AVX2 without AVX-512) OpenBLAS's Haswell `sgemm` ran a 256x256x256 product in ~3,450 µs in a
thread until that thread had computed one product whose output has 384 or more columns, and in
~900-1,000 µs from then on (the machine's peak; MKL takes ~1,000 µs): TD3's portable learner took
55 ms an update, not 24 (docs/PERFORMANCE.md, "A slow first state"). Why is not known (no
hardware counters on that virtual machine; no allocation happens in between). The bits are the
same cold or warm (tests/test_gemm.py), so every thread that computes the learner's products
first computes one 64x512x1024 product (~5 ms cold), once; `WARM_ENV=0` leaves it out.

`tests/test_gemm.py` checks the products against float64, the bits against every thread count, and
that no call takes the row-major N·N form.
"""

from __future__ import annotations

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from mam_core import arithmetic
from mam_core.chain import Chain as _Chain

_PARALLEL_MIN_FLOPS = 1 << 20  # a one-member product this big is cut in two; smaller ones run in this thread
_MIN_HALF = 32  # a one-member product is cut in two column halves of at least this many columns
THREADS_ENV = "MAM_GEMM_THREADS"  # the threads a process starts with (default 1; `set_threads` changes it)
BATCH_ENV = "MAM_GEMM_BATCH"  # 0: spread over Python threads, not OpenBLAS's `sgemm_batch` (the same bits)
WARM_ENV = "MAM_GEMM_WARM"  # 0: no warm-up product before a thread's first (the same bits; slower where it matters)
_WARM_SHAPE = (64, 512, 1024)  # m, k, n of the warm-up product: n >= 384 output columns
_warm_thread = threading.local()  # .done: this thread computed the warm-up
_warm_batch = [0]  # the most `sgemm_batch` threads warmed so far
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
        _pool = ThreadPoolExecutor(n - 1, thread_name_prefix="mam-gemm") \
            if n > 1 and _chain() is None and _batch() is None else None
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
    return arithmetic.usable_cores()


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
    if not getattr(_warm_thread, "done", False):
        _warm_thread.done = True
        _warm([_warm_operands(1)])
    np.matmul(a, b, out=out)


def _warm_operands(e: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`e` warm-up products, both operands transposed (T·T, as `bmm` passes row-major ones)."""
    m, k, n = _WARM_SHAPE
    a, b = np.ones((e, k, m), np.float32), np.ones((e, n, k), np.float32)
    return a.transpose(0, 2, 1), b.transpose(0, 2, 1), np.empty((e, m, n), np.float32)


def _warm(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]], batch: _Batch | None = None) -> None:
    """The warm-up products (module docstring): in this thread, or one in each of `batch`'s threads."""
    if os.environ.get(WARM_ENV, "1") == "0":
        return
    if batch is not None:
        batch.run(pieces, len(pieces[0][0]))
    else:
        for a, b, out in pieces:
            np.matmul(a, b, out=out)


def bmm(a: torch.Tensor, b: torch.Tensor, like: torch.Tensor | None = None) -> torch.Tensor:
    """a [E, m, k] · b [E, k, n] -> [E, m, n] float32 on the CPU. In the chain kernels, laid out
    as `like` (row- or column-major: a gradient in its variable's layout, which spares autograd a
    transposing copy; the bits do not depend on it), else row-major. In pinned OpenBLAS one
    `sgemm` a member, never in the row-major N·N form: where both operands are row-major the
    product is computed as (bᵀ·aᵀ)ᵀ, both transposed (T·T), and returned as a transposed view.
    The form depends on the operands' layouts only, which the code fixes, never on the machine."""
    chain = _chain()
    if chain is not None:
        return chain.bmm(a, b, _threads, transposed=like is not None and _transposed(like))
    e = max(a.shape[0], b.shape[0])
    an, a_rows = _operand(a, e)
    bn, b_rows = _operand(b, e)
    swap = a_rows and b_rows
    if swap:  # (N, N) -> (T, T)
        an, bn = bn.transpose(0, 2, 1), an.transpose(0, 2, 1)
    m, k, n = an.shape[1], an.shape[2], bn.shape[2]
    out = np.empty((e, m, n), np.float32)
    if k == 1:  # one term: every BLAS or NumPy path gives round(a·b) added to a zero, in any form
        torch.mul(torch.from_numpy(an), torch.from_numpy(bn), out=torch.from_numpy(out)).add_(0.0)  # -0 to +0 as there
        return torch.from_numpy(out.transpose(0, 2, 1) if swap else out)
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


def _operand(x: torch.Tensor, e: int) -> tuple[np.ndarray, bool]:
    """x [1 or e, r, c] as the [e, r, c] array BLAS is given (a copy only if neither row- nor
    column-major), and whether it is row-major."""
    xn = (x.detach() if x.shape[0] == e else x.detach().expand(e, -1, -1)).numpy()
    if row_major(xn):
        return xn, True
    if not col_major(xn):
        xn = np.ascontiguousarray(xn)
        return xn, row_major(xn)
    return xn, False


def _run(pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """The products of `pieces`: in one `sgemm_batch` call over `threads()` threads, or the first
    in this thread and the others on the pool (if any)."""
    batch = _batch() if _threads > 1 and len(pieces) > 1 else None
    if batch is not None and _warm_batch[0] < _threads:
        _warm_batch[0] = _threads
        _warm([_warm_operands(_threads)], batch)
    if batch is not None and batch.run(pieces, _threads):
        return
    pool = _pool
    if pool is None or len(pieces) == 1:
        for piece in pieces:
            _mm(*piece)
        return
    futures = [pool.submit(_mm, *piece) for piece in pieces[1:]]
    _mm(*pieces[0])
    for f in futures:
        f.result()


class _Batch:
    """OpenBLAS's `cblas_sgemm_batch`, in the library NumPy's matmul calls (its pins apply), for
    the products NumPy would hand to `cblas_sgemm`, with the arguments it would pass.

    In `sgemm_batch` each product of the batch runs whole in one thread, in the same
    single-threaded driver that `sgemm` runs on one thread (OpenBLAS `driver/level3/
    gemm_batch_thread.c`): the same bits as NumPy's call, for any thread count and any thread.
    OpenBLAS's thread count is raised to `threads` for the call only (its products elsewhere
    must stay on one thread: a product split over threads is cut another way)."""

    ROW_MAJOR, NO_TRANS, TRANS = 101, 111, 112
    # Up to this m·n·k `interface/gemm_batch.c` sends a product to the small-matrix kernels,
    # unasked (`sgemm` asks the core's permit first), and in a DYNAMIC_ARCH build calls them
    # through an unresolved table offset (a crash, found here with 0.3.31): never at or below it.
    SMALL = 100 ** 3

    def __init__(self, lib: ctypes.CDLL, batch: str, set_threads: str) -> None:
        self.int = ctypes.c_int64 if batch.endswith("64_") else ctypes.c_int
        self.fn = getattr(lib, batch)
        self.fn.restype = None
        self.set_threads = getattr(lib, set_threads)
        self.set_threads.argtypes, self.set_threads.restype = [ctypes.c_int], None
        self.lock = threading.Lock()

    @staticmethod
    def _form(x: np.ndarray, rows: int, cols: int) -> tuple[int, int] | None:
        """(transpose, leading dimension) of a 2-D operand as NumPy's matmul passes it, or None
        if NumPy would not pass it to BLAS."""
        s1, s2 = x.strides
        if _blasable(s1, s2, cols):
            return _Batch.NO_TRANS, s1 // 4
        if _blasable(s2, s1, rows):
            return _Batch.TRANS, s2 // 4
        return None

    def run(self, pieces: list[tuple[np.ndarray, np.ndarray, np.ndarray]], threads: int) -> bool:
        """Compute the products of `pieces` (3-D operands, one product a member) if every one of
        them is one NumPy would compute with `sgemm`; False (nothing computed) if not."""
        calls = []
        for a3, b3, c3 in pieces:
            for a, b, c in zip(a3, b3, c3):
                (m, k), n = a.shape, b.shape[1]
                fa, fb = self._form(a, m, k), self._form(b, k, n)
                if min(m, n, k) < 2 or fa is None or fb is None or not _blasable(c.strides[0], c.strides[1], n):
                    return False  # NumPy takes dot, gemv or its own loop there
                if m * n * k <= self.SMALL:
                    return False  # `sgemm_batch` takes its small-matrix kernels there (`sgemm` may not)
                if a.ctypes.data == b.ctypes.data and m == n and a.strides == b.strides[::-1] and fa[0] != fb[0]:
                    return False  # NumPy takes syrk for a matrix times its transpose
                calls.append((fa, fb, m, n, k, a.ctypes.data, b.ctypes.data, c.ctypes.data, c.strides[0] // 4))
        g = len(calls)
        ints, ptrs = self.int * g, ctypes.c_void_p * g
        enums, floats = ctypes.c_int * g, ctypes.c_float * g
        with self.lock:  # OpenBLAS's thread count is one per process
            self.set_threads(threads)
            try:
                self.fn(ctypes.c_int(self.ROW_MAJOR), enums(*(c[0][0] for c in calls)),
                        enums(*(c[1][0] for c in calls)), ints(*(c[2] for c in calls)),
                        ints(*(c[3] for c in calls)), ints(*(c[4] for c in calls)),
                        floats(*([1.0] * g)), ptrs(*(c[5] for c in calls)), ints(*(c[0][1] for c in calls)),
                        ptrs(*(c[6] for c in calls)), ints(*(c[1][1] for c in calls)), floats(*([0.0] * g)),
                        ptrs(*(c[7] for c in calls)), ints(*(c[8] for c in calls)), self.int(g), ints(*([1] * g)))
            finally:
                self.set_threads(1)
        return True


_BATCH: list[_Batch | None] = []


def _batch() -> _Batch | None:
    """NumPy's OpenBLAS's batch entry point (found once), or None: another BLAS, an OpenBLAS
    without `sgemm_batch`, or BATCH_ENV=0."""
    if not _BATCH:
        _BATCH.append(_find_batch() if os.environ.get(BATCH_ENV, "1") != "0" else None)
    return _BATCH[0]


def _find_batch() -> _Batch | None:
    try:
        with open("/proc/self/maps") as maps:  # the very library NumPy loaded (not another copy)
            paths = {line.split()[-1] for line in maps if "openblas" in line.rsplit("/", 1)[-1].lower()}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for batch, set_threads in (("scipy_cblas_sgemm_batch64_", "scipy_openblas_set_num_threads64_"),
                                   ("scipy_cblas_sgemm_batch", "scipy_openblas_set_num_threads"),
                                   ("cblas_sgemm_batch", "openblas_set_num_threads")):
            if hasattr(lib, batch) and hasattr(lib, set_threads):
                return _Batch(lib, batch, set_threads)
    return None


_CHAIN: list[_Chain | None] = []  # the chain kernels (mam_core/chain.py), once found


def ready() -> str:
    """Load the kernels this process's GEMMs use (building the chain kernels if need be); their
    name (arithmetic.status()["gemm"]). RuntimeError: they cannot be built here (no C compiler);
    ValueError: MAM_PORTABLE_GEMM names no kernels."""
    arithmetic.portable_gemm()
    _chain()
    return arithmetic.status()["gemm"]


def _chain() -> _Chain | None:
    """The chain kernels, under portable arithmetic unless MAM_PORTABLE_GEMM picks others (built
    at the first call)."""
    if not _CHAIN:
        _CHAIN.append(_Chain() if arithmetic.portable_gemm() and arithmetic.status()["gemm"] == "chain" else None)
    return _CHAIN[0]


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
            grad_a = _summed_to(bmm(grad, b.transpose(1, 2), like=a), a.shape)
        if ctx.needs_input_grad[2]:
            grad_b = _summed_to(bmm(a.transpose(1, 2), grad, like=b), b.shape)
        return grad_bias, grad_a, grad_b


class _ReLU(torch.autograd.Function):
    """`torch.relu_` whose backward masks the gradient in its output's memory layout.

    A product of `bmm` comes out row-major or transposed depending on its operands' layouts, so
    a hidden layer's output (kept for the backward) and the gradient that reaches it are often
    laid out transposed to each other; torch's `threshold_backward` then walks one of them
    against its strides, 4-5x the time of a copy (docs/PERFORMANCE.md). Here the gradient is
    copied into the output's layout first. The mask is exact (a gradient element is kept or
    zeroed) and the result is laid out as torch's (which follows the output), so the products
    after it keep their forms: the same bits (tests/test_gemm.py)."""

    @staticmethod
    def forward(ctx, h: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
        torch.relu_(h)
        ctx.mark_dirty(h)
        ctx.save_for_backward(h)
        return h

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # noqa: ANN001, ANN205
        (out,) = ctx.saved_tensors
        if out.stride() != grad.stride() and _dense(out):
            grad = torch.empty_like(out).copy_(grad)
        return torch.ops.aten.threshold_backward(grad, out, 0)


def _transposed(x: torch.Tensor) -> bool:
    """Is x [.., r, c] laid out column-major (a transposed view of a row-major array)?"""
    return x.shape[-1] > 1 and x.shape[-2] > 1 and x.stride(-2) == 1 and x.stride(-1) >= x.shape[-2]


def _dense(x: torch.Tensor) -> bool:
    """Does x cover its storage without gaps or overlaps in some order of its dims (so that
    `empty_like` keeps its strides)?"""
    return x.is_contiguous() or x.mT.is_contiguous()


def relu_(h: torch.Tensor) -> torch.Tensor:
    """`torch.relu_(h)`, its backward in the output's layout (`_ReLU`)."""
    return _ReLU.apply(h) if h.requires_grad else torch.relu_(h)


def _summed_to(grad: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """The gradient of an operand that was expanded (a member axis shared by all): summed back."""
    return grad if grad.shape == shape else grad.sum_to_size(shape)


def baddbmm(bias: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """`torch.baddbmm(bias, a, b)` (β = α = 1) with its products in the pinned kernels."""
    if torch.is_grad_enabled() and (bias.requires_grad or a.requires_grad or b.requires_grad):
        return _Baddbmm.apply(bias, a, b)
    return bmm(a, b).add_(bias)  # nothing to differentiate (target networks): no autograd node


def addmm(bias: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """`torch.addmm(bias, a, b)` for 2-D a, b, likewise."""
    return baddbmm(bias.unsqueeze(0), a.unsqueeze(0), b.unsqueeze(0)).squeeze(0)


_from_environment()

if __name__ == "__main__":  # `make venv`: build the chain kernels now (an error names what is missing)
    print(f"mam: portable GEMM kernels in {_Chain.build()}")
