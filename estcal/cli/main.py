"""The ``estcal`` command.

Each subcommand lives in its own module under :mod:`estcal.cli.commands` and
exposes ``register(app)``; this module only discovers and mounts them, so that
adding a subcommand never touches shared code.
"""
from __future__ import annotations

import importlib
import pkgutil

import typer

from estcal.cli import commands as _commands

app = typer.Typer(
    name="estcal",
    help="Probabilistic and recursive estimation for robot kinematic calibration.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _mount() -> None:
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{_commands.__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)


_mount()


def main() -> None:  # pragma: no cover - thin entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
