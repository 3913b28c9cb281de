"""The processes of a run (learner, worker, referee, monitor) and the messaging layer."""

import os

import mam_core  # noqa: F401  (first: pins the arithmetic before numpy or torch load, mam_core/arithmetic.py)

# numpy's OpenBLAS starts one thread per core for a GEMM as small as a 20-row policy forward;
# on a box shared by a learner and M workers those threads spin against each other (a 20-row
# actor forward measured 7.0 ms with them, 0.36 ms on one thread). Set before numpy is imported;
# a value the user exported wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
