"""Moved to `mam_lab.experiment`; kept so `python -m services.experiment ...` still runs the grid."""

from mam_lab.experiment import experiment_command, main

__all__ = ["experiment_command", "main"]

if __name__ == "__main__":
    main()
