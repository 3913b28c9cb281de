"""Run supervision: the launcher, the run directory and its locks, the chaos driver."""
