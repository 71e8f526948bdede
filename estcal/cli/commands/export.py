"""``estcal export``: write a (calibrated) robot model as a URDF (docs/export.md)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("export")
    def export_cmd(
        robot: str = typer.Option(..., "--robot", "-r",
                                  help="Model to export: robot file (.yaml, e.g. a calibrated model), built-in "
                                       "name or URDF."),
        urdf: Path = typer.Option(..., "--urdf", help="URDF file to write."),
        from_urdf: Optional[Path] = typer.Option(
            None, "--from-urdf",
            help="Original URDF of a model loaded from a URDF: keep all its links, visuals, collisions, "
                 "inertials and other elements, change only the calibrated joint origins."),
        root: Optional[str] = typer.Option(None, help="Root link of the model's chain (URDF models)."),
        tip: Optional[str] = typer.Option(None, help="Tip link of the model's chain (URDF models)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write a JSON summary."),
    ) -> None:
        """Write the model as a URDF whose joint origins carry the identified geometry.

        Joint offsets are folded into the origins; base and tool frames become fixed joints.
        What a URDF cannot hold (gains ≠ 1, coupling, effects, markers) is named in a warning.
        Check the result with `estcal fk DATA --robot OUT.urdf --root ROOT --tip TIP`.
        """
        from estcal.cli.common import check_input_files, fail, write_json
        from estcal.io.robotfile import load_robot
        from estcal.kinematics.urdf_export import export_urdf

        if from_urdf is not None:
            check_input_files([from_urdf], "URDF", "--from-urdf")
            if urdf.resolve() == from_urdf.resolve():
                fail(f"--urdf {urdf} is the original URDF; write the calibrated copy to another file "
                     f"(inputs are never overwritten)")
        is_urdf = robot.lower().endswith(".urdf")
        try:
            model = load_robot(robot, root=root if is_urdf else None, tip=tip if is_urdf else None)
        except (ValueError, FileNotFoundError, KeyError) as exc:
            fail(str(exc))
        try:
            res = export_urdf(model, urdf, from_urdf=from_urdf, root=None if is_urdf else root,
                              tip=None if is_urdf else tip, source=robot, warn=False)
        except (ValueError, FileNotFoundError) as exc:
            fail(f"{from_urdf or robot}: {exc}")
        what = (f"origins of {len(res.changed)} joints changed, every other element of {from_urdf.name} kept"
                if from_urdf is not None else f"{model.n_joints} joints, origins carry the calibration")
        typer.echo(f"wrote {urdf} ({what}); tool frame: --root {res.root} --tip {res.tip}")
        if from_urdf is None and model.convention == "urdf":
            typer.echo("note: this model's frames are URDF joints; --from-urdf ORIGINAL.urdf writes a calibrated "
                       "copy of the original instead (its links, visuals, collisions and inertials kept)")
        for w in res.warnings:
            typer.echo(f"warning: {w}", err=True)
        if json_path is not None:
            write_json(json_path, {"urdf": str(urdf), "robot": robot, "from_urdf": str(from_urdf) if from_urdf
                                   else None, "root": res.root, "tip": res.tip, "changed": res.changed,
                                   "warnings": res.warnings})
