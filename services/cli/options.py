"""The option table moved to services/run/options.py (roles and the lab read it; the command line
is the top layer). mam_lab/bench.py still imports `PlainFlags` from here until it is changed."""

from services.run.options import PlainFlags  # noqa: F401
