"""Moved to `mam_lab.bench`; kept so `python -m services.bench ...` still runs the bench."""

from mam_lab.bench import app, bench_command, cli

__all__ = ["app", "bench_command", "cli"]

if __name__ == "__main__":
    cli()
