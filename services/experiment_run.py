"""Moved to `mam_lab.experiment_run`; kept so `python -m services.experiment_run RUN_DIR` (how grids
started by older code start a run) still runs one run of a grid."""

import sys

from mam_lab.experiment_run import FAILED, FINISHED, INTERRUPTED, LAUNCH_FILE, main

__all__ = ["FAILED", "FINISHED", "INTERRUPTED", "LAUNCH_FILE", "main"]

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
