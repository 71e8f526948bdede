"""A (calibrated) robot model written as a URDF: ``estcal export`` and ``estcal.export_urdf``
(docs/export.md)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from estcal.base.errors import InputError
from estcal.workflows.inputs import check_input_files, input_errors

__all__ = ["Export", "export"]


@dataclass
class Export:
    """The model exported and the :class:`~estcal.kinematics.urdf_export.UrdfExport` (root, tip,
    changed joints, warnings: what a URDF cannot hold)."""

    model: object
    result: object
    urdf: Path
    from_urdf: Path | None = None

    def to_dict(self, robot_spec) -> dict:
        r = self.result
        return {"urdf": str(self.urdf), "robot": str(robot_spec),
                "from_urdf": str(self.from_urdf) if self.from_urdf else None, "root": r.root, "tip": r.tip,
                "changed": r.changed, "warnings": r.warnings}


def export(robot, urdf, *, from_urdf=None, root: str | None = None, tip: str | None = None) -> Export:
    """Write ``robot`` (spec or object; a URDF spec is loaded with ``root``/``tip``) as ``urdf``:
    joint origins carry the identified geometry, offsets are folded in, base and tool frames become
    fixed joints. ``from_urdf``: the original URDF of a model loaded from a URDF — all its elements
    are kept and only the calibrated joint origins change."""
    from estcal.io.robotfile import load_robot
    from estcal.kinematics.urdf_export import export_urdf

    urdf = Path(urdf)
    if from_urdf is not None:
        check_input_files([from_urdf], "URDF", "--from-urdf")
        if urdf.resolve() == Path(from_urdf).resolve():
            raise InputError(f"--urdf {urdf} is the original URDF; write the calibrated copy to another file "
                             f"(inputs are never overwritten)")
    is_urdf = isinstance(robot, (str, Path)) and str(robot).lower().endswith(".urdf")
    with input_errors():
        model = load_robot(robot, root=root if is_urdf else None, tip=tip if is_urdf else None)
    with input_errors(f"{from_urdf or robot}: "):
        res = export_urdf(model, urdf, from_urdf=from_urdf, root=None if is_urdf else root,
                          tip=None if is_urdf else tip, source=str(robot) if isinstance(robot, (str, Path)) else None,
                          warn=False)
    layer = (model.meta.get("calibration") or {}).get("residual_model")
    if layer:  # a URDF has no place for it
        cost = layer.get("cost_mm")
        res.warnings.append("the residual Gaussian-process layer (" + str(layer.get("space")) + " space) is dropped"
                            + (f": it removed {cost:.3g} mm RMS at new postures (posture-grouped CV)"
                               if cost is not None else ""))
    return Export(model, res, urdf, Path(from_urdf) if from_urdf is not None else None)
