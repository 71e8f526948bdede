"""The ``estcal`` command.

Each subcommand lives in its own module under :mod:`estcal.cli.commands`, defined at module
level with :func:`estcal.cli.app.command`; this module only imports them, so that adding a
subcommand never touches shared code. The command modules import their workflow inside the
command function: ``estcal --help`` loads typer and the option declarations, no numerical code.
"""
from __future__ import annotations

import importlib
import pkgutil

import typer

from estcal.cli import commands as _commands
from estcal.cli.app import app

__all__ = ["app", "main"]


def _mount() -> None:
    """Import every command module: each registers its module-level commands with ``@command``."""
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda m: m.name):
        importlib.import_module(f"{_commands.__name__}.{info.name}")


_mount()


#: an option a command does not have, where another of its options means what was meant
#: (the same concept named differently across commands: docs/conventions.md, "One vocabulary")
OPTION_POINTERS = {
    ("diagnose", "--level"): "the geometric model of `estcal diagnose` is --geometric (registration, joint_offset, "
                             "full, prior, auto)",
}


def _usage_error(exc) -> int:
    """A command-line usage error as one line on stderr (Click draws a box of several lines):
    ``error: estcal calibrate: No such option: --nosuch — see `estcal calibrate --help```.
    Returns the exit code (2). Running ``estcal`` alone still shows the help."""
    import sys

    ctx = getattr(exc, "ctx", None)
    if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:
        print(ctx.get_help())
        return exc.exit_code
    path = ctx.command_path if ctx is not None else "estcal"
    msg = " ".join(exc.format_message().split()).rstrip(".")
    pointer = OPTION_POINTERS.get((path.split()[-1], getattr(exc, "option_name", None)))
    if pointer and type(exc).__name__ == "NoSuchOption":
        msg += f" — {pointer}"
    print(f"error: {path}: {msg} — see `{path} --help`", file=sys.stderr)
    return exc.exit_code


#: environment variables that choose the number of BLAS threads; when the user sets none of them
#: the command runs BLAS single-threaded (see :func:`single_threaded_blas_by_default`)
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas_by_default(environ) -> None:
    """One BLAS thread unless the user chose a number (``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``
    or ``MKL_NUM_THREADS`` set). A command's matrices are tall and thin (rows × ≲ 100 parameters,
    GP kernels of a few hundred rows): OpenBLAS's threads bring no speed-up on them, and on a busy
    machine their spin-waiting cost a 50-pose ``estcal calibrate`` up to 1.3 s of CPU on top of 0.9 s
    (docs/benchmarks.md, "Everyday commands"). Set before numpy is first imported, so it holds for
    the whole process and the worker processes it starts."""
    if not any(environ.get(v) for v in BLAS_THREAD_VARIABLES):
        environ["OPENBLAS_NUM_THREADS"] = "1"
        environ["MKL_NUM_THREADS"] = "1"


def main() -> None:  # pragma: no cover - thin entry point (tested through a subprocess)
    """Run the CLI; an unexpected exception becomes a one-line message and exit code 1
    (``ESTCAL_DEBUG=1`` shows the traceback). Expected problems exit with 2 or 3 before
    reaching here (:mod:`estcal.cli.run`, docs/reliability.md)."""
    import os
    import sys

    single_threaded_blas_by_default(os.environ)
    from typer._click import exceptions as click_exceptions

    try:
        rc = app(prog_name="estcal", standalone_mode=False)
        sys.exit(rc if isinstance(rc, int) else 0)
    except click_exceptions.UsageError as exc:
        sys.exit(_usage_error(exc))
    except click_exceptions.ClickException as exc:  # e.g. a file Click itself could not open
        print(f"error: {exc.format_message()}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except typer.Abort:
        print("error: aborted", file=sys.stderr)
        sys.exit(1)
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
