"""Suite-wide settings."""

import os
import shutil
import subprocess
import uuid
from pathlib import Path

import mam_core  # noqa: F401  (before torch: the suite computes with the pinned arithmetic of a run)

# isort: split
import pytest
import torch

# One torch thread in the test process, as the learner uses by default: with two threads on a
# 2-core box that also runs the test's learner/worker processes (or a noisy neighbour), OpenMP's
# spinning threads wait on each other; an in-process training test measured 8 s with one thread
# and 180 s with two while another run shared the box. Results do not depend on it.
torch.set_num_threads(1)


@pytest.fixture
def tmpfs(tmp_path: Path):
    """A small (8 MB) tmpfs, for a disk that fills up; skipped where mounting is not allowed."""
    mnt = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("needs root and mount for a small tmpfs")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"mount not permitted here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
