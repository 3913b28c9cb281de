"""The command line: `mam` and its commands, the option table, plots and the live view."""
