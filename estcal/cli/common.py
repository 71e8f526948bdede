"""Small helpers of the subcommands: failing (an error of :mod:`estcal.base.errors`, mapped to its
exit code by :mod:`estcal.cli.run`), warning lines, and hooks run when a command ends.

Exit codes (docs/reliability.md): 0 success, 2 bad input or usage (:data:`EXIT_INPUT`), 3
numerical refusal — well-formed input the numbers cannot answer honestly (:data:`EXIT_REFUSED`).
Errors and warnings go to stderr, results to stdout.
"""
from __future__ import annotations

import typer

from estcal.base.errors import InputError, NumericalRefusal
from estcal.cli.run import EXIT_INPUT, EXIT_REFUSED, on_exit, run_exit_hooks

__all__ = ["fail", "refuse", "message", "warn", "on_exit", "run_exit_hooks", "EXIT_INPUT", "EXIT_REFUSED"]

def fail(msg, code: int = EXIT_INPUT):
    """Stop the command with ``error: msg`` and exit code ``code`` (2: an ``InputError``, 3: a
    ``NumericalRefusal``), through the one mapping of :mod:`estcal.cli.run`."""
    raise (NumericalRefusal if code == EXIT_REFUSED else InputError)(str(msg))


def refuse(msg):
    """A numerical refusal: ``error: numerical refusal: msg``, exit code 3."""
    raise NumericalRefusal(str(msg))


def message(exc: BaseException) -> str:
    """The text of an exception (a KeyError's own quotes removed)."""
    if isinstance(exc, KeyError) and exc.args and isinstance(exc.args[0], str):
        return exc.args[0]
    return str(exc)


def warn(msg) -> None:
    """``warning: msg`` to stderr (results stay alone on stdout)."""
    typer.echo(f"warning: {msg}", err=True)

