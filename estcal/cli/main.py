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
    from estcal.cli.checks import guard

    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{_commands.__name__}.{info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)
    # every subcommand gets the option checks (numbers, output paths) before it runs
    for cmd in app.registered_commands:
        if cmd.callback is not None and not getattr(cmd.callback, "_estcal_guarded", False):
            name = cmd.name or cmd.callback.__name__.replace("_", "-")
            cmd.callback = guard(name, cmd.callback)
            cmd.callback._estcal_guarded = True


_mount()


def main() -> None:  # pragma: no cover - thin entry point (tested through a subprocess)
    """Run the CLI; an unexpected exception becomes a one-line message and exit code 1
    (``ESTCAL_DEBUG=1`` shows the traceback). Expected problems exit with 2 or 3 before
    reaching here (docs/reliability.md)."""
    import os
    import sys

    try:
        app()
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - the last line of defence, never a traceback for users
        if os.environ.get("ESTCAL_DEBUG"):
            raise
        first = (str(exc).strip().splitlines() or [""])[0]
        print(f"error: internal error ({type(exc).__name__}: {first}) — this is a bug in estcal; please report "
              f"it with the command line (ESTCAL_DEBUG=1 shows the traceback)", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    main()
