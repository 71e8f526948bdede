"""``estcal frames``: the URDF frame the data measure (:func:`estcal.workflows.frames.frames_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

__all__ = ["frames", "register"]


def frames(
    data: Path = typer.Argument(..., help="Dataset CSV (through --map: the file as published)."),
    robot: Path = typer.Option(..., "--robot", "-r", help="URDF whose links are searched."),
    column_map: Optional[Path] = typer.Option(None, "--map", metavar="FILE.yaml",
                                              help="Column map of the data file (docs/dataset.md)."),
    points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points (x1..zN)."),
    json_path: Optional[Path] = typer.Option(None, "--json",
                                             help="Write {\"candidates\": [{root, tip, rmse_mm, rmse_mrad, …}]}."),
) -> None:
    """Rank the (root, tip) link pairs of the URDF whose actuated joints are the data's joint columns by the
    RMSE left after registering the base (pose data: the tip frame as the URDF places it; point data: and
    the markers), best first. docs/dataset.md, "Which frame was measured"."""
    from estcal.cli.common import fail, message
    from estcal.workflows.frames import format_frames, frames_file

    try:
        out = frames_file(data, robot, column_map=column_map, points=points)
    except (ValueError, KeyError, FileNotFoundError) as exc:
        fail(message(exc))
    typer.echo(format_frames(out))  # the best ten; all in --json
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, out)


def register(app: typer.Typer) -> None:
    app.command("frames")(frames)
