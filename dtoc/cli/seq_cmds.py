"""CLI commands of the `dtoc.seq` stage (registered by :mod:`dtoc.cli.main`)."""

import typer


def register(app: typer.Typer) -> None:
    """Add this stage's commands to app."""
