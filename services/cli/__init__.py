"""The command line: `mam` and its commands (the top layer: docs/ARCHITECTURE.md)."""
