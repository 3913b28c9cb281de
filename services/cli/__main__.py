"""`python -m services.cli`: the `mam` command."""

from services.cli.app import app

app()
