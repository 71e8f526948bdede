"""``estcal export``: write a (calibrated) robot model as a URDF (docs/export.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option

__all__ = ["export"]


@command("export")
def export(
    robot: str = typer.Option(..., "--robot", "-r",
                              help="Model to export: robot file (.yaml, e.g. a calibrated model), built-in "
                                   "name or URDF."),
    urdf: Path = typer.Option(..., "--urdf", help="URDF file to write."),
    from_urdf: Optional[Path] = typer.Option(
        None, "--from-urdf",
        help="Original URDF of a model loaded from a URDF: keep all its links, visuals, collisions, "
             "inertials and other elements, change only the calibrated joint origins."),
    root: Optional[str] = typer.Option(None, "--root", help="Root link of the model's chain (URDF models)."),
    tip: Optional[str] = typer.Option(None, "--tip", help="Tip link of the model's chain (URDF models)."),
    json_path: Optional[Path] = json_option("Write a JSON summary."),
) -> None:
    """Write the model as a URDF whose joint origins carry the identified geometry.

    Joint offsets are folded into the origins; base and tool frames become fixed joints.
    What a URDF cannot hold (gains ≠ 1, coupling, effects, markers) is named in a warning.
    Check the result with `estcal fk DATA --robot OUT.urdf --root ROOT --tip TIP`.
    """
    from estcal.cli.common import warn
    from estcal.workflows.export import export as run_export

    ex = run_export(robot, urdf, from_urdf=from_urdf, root=root, tip=tip)
    res, model = ex.result, ex.model
    what = (f"origins of {len(res.changed)} joints changed, every other element of {from_urdf.name} kept"
            if from_urdf is not None else f"{model.n_joints} joints, origins carry the calibration")
    typer.echo(f"wrote {urdf} ({what}); tool frame: --root {res.root} --tip {res.tip}")
    if from_urdf is None and model.convention == "urdf":
        typer.echo("note: this model's frames are URDF joints; --from-urdf ORIGINAL.urdf writes a calibrated "
                   "copy of the original instead (its links, visuals, collisions and inertials kept)")
    for w in res.warnings:
        warn(w)
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, ex.to_dict(robot))
