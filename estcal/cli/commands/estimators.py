"""``estcal estimators``: the estimators and the ``--option KEY=VALUE`` keys each accepts."""
from __future__ import annotations

from typing import Optional

import typer

from estcal.cli.app import command

__all__ = ["estimators"]


@command("estimators")
def estimators(
    name: Optional[str] = typer.Argument(None, help="Only this estimator (default: all)."),
) -> None:
    """List the estimators of `estcal calibrate --estimator` and their options (for --option KEY=VALUE).

    Defaults are shown as the estimator function declares them; SI units (m, rad).
    """
    from estcal.base.errors import InputError
    from estcal.estimate.registry import estimator_names, estimator_options

    names = estimator_names()
    if name is not None:
        if name not in names:
            raise InputError(f"unknown estimator {name!r}; choose one of {', '.join(names)}")
        names = [name]
    for n in names:
        try:
            opts = estimator_options(n)
        except ValueError as exc:
            typer.echo(f"{n}: not available ({exc})")
            continue
        body = ", ".join(f"{k}={v!r}" for k, v in opts.items()) or "(no options)"
        typer.echo(f"{n}: {body}")
