"""The ``estcal`` command object and the decorator that makes a module-level function a subcommand.

Every subcommand module under :mod:`estcal.cli.commands` defines its command at module level::

    @command("calibrate")
    def calibrate(data: list[Path] = typer.Argument(...), ...) -> None:
        from estcal.workflows.calibrate import calibrate_files   # imported when the command runs
        ...

:func:`command` registers the function with the conventions every subcommand shares
(:func:`estcal.cli.run.guarded`): ``--config FILE.toml``, the option checks of
:mod:`estcal.cli.checks`, the one mapping of exceptions to exit codes and the
``warning: …`` lines. The function itself stays a plain function (tests and readers call it).
Command modules import their workflow inside the function, so that ``estcal --help`` stays
cheap (docs/architecture.md).
"""
from __future__ import annotations

import typer

__all__ = ["app", "command"]

app = typer.Typer(
    name="estcal",
    help="Probabilistic and recursive estimation for robot kinematic calibration.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _print_version(value: bool) -> None:
    if value:
        from estcal.base.version import __version__

        typer.echo(f"estcal {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                 help="Print estcal's version and exit."),
) -> None:
    """Probabilistic and recursive estimation for robot kinematic calibration."""


def command(name: str, **kwargs):
    """Register the decorated module-level function as ``estcal NAME`` (with the shared
    conventions of :func:`estcal.cli.run.guarded`); the function is returned unchanged."""

    def decorate(func):
        from estcal.cli.run import guarded

        app.command(name, **kwargs)(guarded(name, func))
        return func

    return decorate
