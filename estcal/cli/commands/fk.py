"""``estcal fk``: forward kinematics of every row of a dataset (:func:`estcal.workflows.fk.fk_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option, map_option, root_option, tip_option

__all__ = ["fk"]


@command("fk")
def fk(
    data: Path = typer.Argument(..., help="Dataset CSV with one column per joint (rad / m)."),
    robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF (.urdf)."),
    output: Path = typer.Option(..., "--output", "-o", help="CSV to write: x,y,z,qw,qx,qy,qz per row."),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    column_map: Optional[Path] = map_option(),
    with_joints: bool = typer.Option(False, "--with-joints", help="Also copy the joint columns."),
    markers: bool = typer.Option(False, "--markers", help="Also write the robot's marker points x1,y1,z1,…"),
    json_path: Optional[Path] = json_option("Write a short JSON summary."),
) -> None:
    """Tool frame in the world (x,y,z in m; quaternion qw,qx,qy,qz) for every row's joint readings.

    Effects in the robot file are evaluated with the row's t / temperature / payload / approach_<joint>
    columns; a model saved by `estcal diagnose --save-model` re-applies its data preparation (t from the
    file's first row, approach directions from the posture order) as recorded in its calibration block.
    When the file has x,y,z (and qw,qx,qy,qz) columns — a dataset, compensation targets or commands —
    it also prints how far the computed tool frame is from them (RMS and max, mm and mrad).
    """
    from rich.console import Console

    from estcal.workflows.fk import fk_file
    from estcal.workflows.inputs import warn_datasets

    fw = fk_file(robot, data, output, root=root, tip=tip, with_joints=with_joints, markers=markers,
                 column_map=column_map)
    console = Console()
    console.print(f"{fw.rows} rows -> {output} ({', '.join(fw.columns)})")
    if fw.against:
        console.print(fw.against["text"], soft_wrap=True)
    warn_datasets([fw.data])
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, fw.to_dict(data, output))
