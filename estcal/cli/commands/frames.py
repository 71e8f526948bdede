"""``estcal frames``: the URDF frame the data measure (:func:`estcal.workflows.frames.frames_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option, map_option, points_option

__all__ = ["frames"]


@command("frames")
def frames(
    data: Path = typer.Argument(..., help="Dataset CSV (through --map: the file as published)."),
    robot: Path = typer.Option(..., "--robot", "-r", help="URDF whose links are searched."),
    column_map: Optional[Path] = map_option(),
    points: Optional[int] = points_option(),
    json_path: Optional[Path] = json_option("Write {\"candidates\": [{root, tip, rmse_mm, rmse_mrad, …}]}."),
) -> None:
    """Rank the (root, tip) link pairs of the URDF whose actuated joints are the data's joint columns by the
    RMSE left after registering the base (pose data: the tip frame as the URDF places it; point data: and
    the markers), best first. docs/dataset.md, "Which frame was measured"."""
    from estcal.workflows.frames import format_frames, frames_file

    out = frames_file(data, robot, column_map=column_map, points=points)
    typer.echo(format_frames(out))  # the best ten; all in --json
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, out)

