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
    urdf: Optional[Path] = typer.Option(None, "--urdf", help="URDF file to write."),
    ur_kinematics: Optional[Path] = typer.Option(
        None, "--ur-kinematics",
        help="UR kinematics file to write (ur_description's default_kinematics.yaml format: the calibrated "
             "origins of shoulder … wrist_3, joint offsets folded in, a content hash)."),
    robot_spec: Optional[Path] = typer.Option(
        None, "--robot-spec",
        help="With --ur-kinematics: also write a robot spec (the nominal URDF, the kinematics file, the base "
             "and tool frames) that --robot reads back as the whole calibrated model."),
    from_urdf: Optional[Path] = typer.Option(
        None, "--from-urdf",
        help="Original URDF of a model loaded from a URDF: keep all its links, visuals, collisions, "
             "inertials and other elements, change only the calibrated joint origins. With --ur-kinematics: "
             "the nominal UR description (default: the one the model was calibrated from)."),
    root: Optional[str] = typer.Option(None, "--root", help="Root link of the model's chain (URDF models)."),
    tip: Optional[str] = typer.Option(None, "--tip", help="Tip link of the model's chain (URDF models)."),
    json_path: Optional[Path] = json_option("Write a JSON summary."),
) -> None:
    """Write the model as a URDF whose joint origins carry the identified geometry, or a UR arm's
    calibration as a UR kinematics file (--ur-kinematics).

    Joint offsets are folded into the origins; base and tool frames become fixed joints.
    What a URDF cannot hold (gains ≠ 1, coupling, effects, markers) is named in a warning.
    Check the result with `estcal fk DATA --robot OUT.urdf --root ROOT --tip TIP`.
    """
    from estcal.base.errors import InputError

    if (urdf is None) == (ur_kinematics is None):
        raise InputError("give one of --urdf OUT.urdf and --ur-kinematics OUT.yaml (the file to write)")
    if robot_spec is not None and ur_kinematics is None:
        raise InputError("--robot-spec goes with --ur-kinematics (the spec names the kinematics file)")
    if ur_kinematics is not None:
        _ur(robot, ur_kinematics, robot_spec, from_urdf, root, tip, json_path)
    else:
        _urdf(robot, urdf, from_urdf, root, tip, json_path)


def _ur(robot, path, spec, from_urdf, root, tip, json_path) -> None:
    from estcal.cli.common import warn
    from estcal.workflows.export import export_ur_kinematics

    ex = export_ur_kinematics(robot, path, from_urdf=from_urdf, root=root, tip=tip, robot_spec=spec)
    o = ex.origins
    moved = ", ".join(f"{e} {dp:.3g} mm / {dr:.3g} mrad" for e, (dp, dr) in o.changed.items()) or "none"
    typer.echo(f"wrote {path} (UR kinematics file, hash {o.kinematics.hash}); origins changed from "
               f"{_near(ex.nominal)}: {moved}")
    if ex.spec is not None:
        typer.echo(f"wrote {ex.spec} (load it with --robot {ex.spec}: the nominal URDF with these origins, the base "
                   f"and the tool frames)")
    for w in ex.warnings:
        warn(w)
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, ex.to_dict(robot))


def _near(path) -> str:
    """``path`` relative to the working folder when it is near (``../shared/…``), else as given."""
    import os

    try:
        rel = os.path.relpath(path)
    except ValueError:
        return str(path)
    return rel if Path(rel).parts[:2].count("..") <= 1 else str(path)


def _urdf(robot, urdf, from_urdf, root, tip, json_path) -> None:
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
