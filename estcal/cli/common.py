"""Small helpers shared by the subcommands: failing with a clear message, writing JSON."""
from __future__ import annotations

import typer

from estcal.io.jsonio import write_json

__all__ = ["fail", "write_json"]


def fail(msg: str, code: int = 2):
    """Print ``error: msg`` to stderr and exit with ``code`` (no traceback)."""
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)
