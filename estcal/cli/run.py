"""How every subcommand runs: the one place that turns exceptions into exit codes and warnings into lines.

Exit codes (docs/reliability.md): 0 success; 2 bad input or usage —
:class:`~estcal.base.errors.InputError` and its subclasses (``DatasetError``,
``RobotFileError``, ``ParameterError`` …), and :class:`~estcal.base.errors.MissingExtraError`,
whose message names the ``pip install "estcal[EXTRA]"`` that mends it; 3 numerical refusal —
:class:`~estcal.base.errors.NumericalRefusal`, well-formed input that the numbers cannot answer
honestly; 1 anything else (an internal error, reported by :func:`estcal.cli.main.main` as a bug).
Errors and warnings go to stderr (``error: …``, ``warning: …``), results to stdout.

The workflows below the command line raise these errors and warn with
``warnings.warn(msg, EstcalWarning)``; :func:`guarded` prints each such warning as a
``warning: msg`` line while the command runs.
"""
from __future__ import annotations

import contextlib
import functools
import inspect
import warnings
from pathlib import Path
from typing import Optional

import typer

from estcal.base.errors import EstcalWarning, InputError, MissingExtraError, NumericalRefusal, missing_extra

__all__ = ["EXIT_INPUT", "EXIT_REFUSED", "exit_code", "error_line", "mapped_errors", "printed_warnings", "guarded",
           "on_exit", "run_exit_hooks"]

EXIT_INPUT = 2
EXIT_REFUSED = 3

_ON_EXIT: list = []


def on_exit(fn) -> None:
    """Run ``fn()`` when the current subcommand ends, however it ends (a lock to release …);
    :func:`guarded` runs them. Also right for in-process runs (tests, notebooks) where the
    process — and with it what the kernel would release — lives on."""
    _ON_EXIT.append(fn)


def run_exit_hooks() -> None:
    while _ON_EXIT:
        fn = _ON_EXIT.pop()
        try:
            fn()
        except Exception:  # noqa: BLE001 - one failing clean-up must not hide the command's outcome
            pass


def exit_code(exc: BaseException) -> int | None:
    """The exit code of an exception estcal raises on purpose (None: not one of them)."""
    if isinstance(exc, NumericalRefusal):
        return EXIT_REFUSED
    if isinstance(exc, InputError):  # MissingExtraError included
        return EXIT_INPUT
    return None


def error_line(exc: BaseException) -> str:
    """The ``error: …`` line of an exception (a KeyError's own quotes removed; a refusal named)."""
    text = exc.args[0] if isinstance(exc, KeyError) and exc.args and isinstance(exc.args[0], str) else str(exc)
    if isinstance(exc, NumericalRefusal) and not text.startswith("numerical refusal"):
        text = f"numerical refusal: {text}"
    return f"error: {text}"


@contextlib.contextmanager
def mapped_errors():
    """Exceptions of the error hierarchy → an ``error:`` line on stderr and their exit code."""
    try:
        yield
    except (InputError, NumericalRefusal, MissingExtraError) as exc:
        typer.echo(error_line(exc), err=True)
        raise typer.Exit(exit_code(exc)) from None
    except ImportError as exc:  # an optional module imported without require(): still its extra, not a bug
        extra = missing_extra(exc)
        if extra is None:
            raise
        typer.echo(error_line(extra), err=True)
        raise typer.Exit(exit_code(extra)) from None


@contextlib.contextmanager
def printed_warnings():
    """Every :class:`EstcalWarning` raised meanwhile → ``warning: msg`` on stderr (each time, not once)."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", EstcalWarning)
        shown = warnings.showwarning

        def show(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, EstcalWarning):
                typer.echo(f"warning: {message}", err=True)
            else:
                shown(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        yield


def _config_option():
    from estcal.cli.config import apply_config

    return typer.Option(None, "--config", is_eager=True, callback=apply_config, metavar="FILE.toml",
                        help="TOML file holding this command's options (keys: the option names, e.g. "
                             "robot = \"puma560\", noise-pos-mm = 0.05); options on the command line win.")


def guarded(command: str, func):
    """``func`` wrapped with the conventions every subcommand shares (signature kept for typer):
    ``--config``, the number and output checks of :mod:`estcal.cli.checks` before any work,
    errors mapped to exit codes, warnings printed, exit hooks run however the command ends."""
    from estcal.cli.checks import option_checks

    sig = inspect.signature(func, eval_str=True)
    checks = option_checks(command, sig)

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        kwargs.pop("config", None)
        try:
            with printed_warnings(), mapped_errors():
                checks(sig.bind_partial(*args, **kwargs).arguments)
                return func(*args, **kwargs)
        finally:
            run_exit_hooks()

    config = inspect.Parameter("config", inspect.Parameter.KEYWORD_ONLY, default=_config_option(),
                               annotation=Optional[Path])
    params = list(sig.parameters.values())
    wrapper.__signature__ = sig.replace(parameters=[p.replace(kind=inspect.Parameter.KEYWORD_ONLY)
                                                    for p in params] + [config])
    wrapper.__annotations__ = {**{p.name: p.annotation for p in params}, "config": Optional[Path]}
    return wrapper
