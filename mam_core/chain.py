"""mam's own GEMM kernels (mam_core/chain_gemm.c), portable arithmetic's default for the
learner's products (`mam_core.gemm` routes them here): every element of a product is one chain of
fused multiply-adds over k in order, from +0, so its bits are the operands' alone on any CPU
(docs/DESIGN-DECISIONS.md, "The learner's GEMMs in mam's own kernels")."""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import tempfile
from pathlib import Path

import torch


class Chain:
    """The kernels of mam_core/chain_gemm.c (portable arithmetic's default): every element of a
    product is one FMA chain over k in order, from +0, so its bits are the operands' alone, on any
    CPU, kernel (AVX-512F, AVX2+FMA or plain C: `ISA_ENV` picks one, for tests) and thread. Built
    once with the C compiler (`CC`, else cc) into the user's cache (else the temporary
    directory's), named by the hash of the source and the flags."""

    ISA_ENV = "MAM_CHAIN_ISA"  # 1 plain C, 2 AVX2+FMA, 3 AVX-512F; unset: the best this CPU has
    SOURCE = Path(__file__).with_name("chain_gemm.c")
    FLAGS = ("-O2", "-shared", "-fPIC", "-pthread", "-ffp-contract=off")  # no -march: each kernel names its target
    SPIN_ENV = "MAM_GEMM_SPIN_US"  # how long an idle GEMM thread spins for the next product before it sleeps
    SPIN_US = 50

    def __init__(self, isa: int | None = None) -> None:
        lib = ctypes.CDLL(str(self.build()))
        long = ctypes.c_long
        self.fn = lib.chain_sgemm
        self.fn.restype = ctypes.c_int
        self.fn.argtypes = [ctypes.c_int, ctypes.c_int, long, long, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                            ctypes.c_void_p, long, long, long, ctypes.c_void_p, long, long, long,
                            ctypes.c_void_p, long, long, long]
        try:
            self.spin_us = int(os.environ.get(self.SPIN_ENV, self.SPIN_US))
        except ValueError:
            raise ValueError(f"{self.SPIN_ENV}={os.environ[self.SPIN_ENV]!r}: give microseconds") from None
        lib.chain_isa.restype, lib.chain_isa.argtypes = ctypes.c_int, [ctypes.c_int]
        if isa is None:
            try:
                isa = int(os.environ.get(self.ISA_ENV, "0"))
            except ValueError:
                raise ValueError(f"{self.ISA_ENV}={os.environ[self.ISA_ENV]!r}: give 1, 2 or 3") from None
        self.isa = lib.chain_isa(isa)  # what it runs: 0 (or more than the CPU has) the best there is

    @classmethod
    def build(cls) -> Path:
        name = f"chain-{hashlib.sha256(cls.SOURCE.read_bytes() + ' '.join(cls.FLAGS).encode()).hexdigest()[:16]}.so"
        caches = [Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mam",
                  Path(tempfile.gettempdir()) / f"mam-{os.getuid()}"]
        for cache in caches:
            if (cache / name).is_file():
                return cache / name
        for cache in caches:
            try:
                cache.mkdir(parents=True, exist_ok=True)
                if os.access(cache, os.W_OK):
                    break
            except OSError:
                continue
        lib = cache / name
        tmp = lib.with_suffix(f".{os.getpid()}.tmp")
        cc = os.environ.get("CC", "cc")
        try:
            subprocess.run([cc, *cls.FLAGS, "-o", str(tmp), str(cls.SOURCE)], check=True, capture_output=True,
                           text=True, timeout=120)
        except (OSError, subprocess.SubprocessError) as exc:
            detail = getattr(exc, "stderr", "") or exc
            raise RuntimeError(f"portable arithmetic needs a C compiler ({cc}; set CC to another) to build "
                               f"{cls.SOURCE}: {detail}; or run with --arithmetic native") from None
        os.replace(tmp, lib)  # whole or not at all, for processes building it at once
        return lib

    def bmm(self, a: torch.Tensor, b: torch.Tensor, threads: int = 1, transposed: bool = False) -> torch.Tensor:
        """a [E or 1, m, k] · b [E or 1, k, n] -> [E, m, n] (column-major if `transposed`), from the
        strided operands as they are, over `threads` threads where the product is big enough
        (the library cuts it by members, else by blocks of rows or columns: any cut, the same bits)."""
        a, b = a.detach(), b.detach()
        if a.dtype != torch.float32 or b.dtype != torch.float32 or a.device.type != "cpu" or b.device.type != "cpu":
            raise TypeError(f"chain kernels multiply float32 CPU tensors, not {a.dtype}/{b.dtype} on {a.device}")
        e, (m, k), n = max(a.shape[0], b.shape[0]), a.shape[1:], b.shape[2]
        out = torch.empty((e, n, m), dtype=torch.float32).mT if transposed else torch.empty((e, m, n),
                                                                                             dtype=torch.float32)
        (aes, ars, acs), (bes, brs, bcs), (ces, crs, ccs) = a.stride(), b.stride(), out.stride()
        if self.fn(self.isa, threads, self.spin_us, e, m, n, k,
                   a.data_ptr(), aes if a.shape[0] > 1 else 0, ars, acs,  # a member shared by all: stride 0
                   b.data_ptr(), bes if b.shape[0] > 1 else 0, brs, bcs,
                   out.data_ptr(), ces, crs, ccs) != 0:
            raise MemoryError("chain_sgemm: no memory for its packed operands")
        return out
