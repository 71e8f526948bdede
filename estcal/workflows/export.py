"""A (calibrated) robot model written as a URDF: ``estcal export`` and ``estcal.export_urdf``
(docs/export.md)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from estcal.base.errors import InputError
from estcal.workflows.inputs import check_input_files, input_errors

__all__ = ["Export", "export", "UrExport", "export_ur_kinematics"]


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


# ------------------------------------------------------------------ UR kinematics file
@dataclass
class UrExport:
    """A UR kinematics file written from a model: the model, the calibrated origins
    (:class:`~estcal.kinematics.ur_kinematics.UrOrigins`), the file, the robot spec (or None), the nominal
    description it was expressed in, and one line for each part of the calibration the file cannot hold."""

    model: object
    origins: object
    path: Path
    spec: Path | None
    nominal: str
    warnings: list

    def to_dict(self, robot_spec) -> dict:
        o = self.origins
        return {"ur_kinematics": str(self.path), "robot": str(robot_spec), "nominal": self.nominal,
                "robot_spec": str(self.spec) if self.spec else None, "hash": o.kinematics.hash, "root": o.root,
                "tip": o.tip, "joints": o.joints,
                "kinematics": {e: dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), v))
                               for e, v in o.kinematics.entries.items()},
                "changed": {e: {"mm": dp, "mrad": dr} for e, (dp, dr) in o.changed.items()},
                "warnings": self.warnings}


def _chain_model(robot) -> bool:
    """``--root``/``--tip`` choose the model's chain (a URDF, a URDF robot spec), else the nominal's."""
    from estcal.base.textinput import read_yaml
    from estcal.io.urdfspec import is_urdf_spec

    s = str(robot).lower() if isinstance(robot, (str, Path)) else ""
    if s.endswith(".urdf"):
        return True
    if s.endswith((".yaml", ".yml")) and Path(robot).is_file():
        with input_errors():
            return is_urdf_spec(read_yaml(robot, "robot"))
    return False


def _nominal_source(model, from_urdf):
    """``(description, root, tip)`` the model was calibrated from: ``--from-urdf``, the URDF or robot spec
    it was loaded from, or a saved model's ``calibration.robot``."""
    if from_urdf is not None:
        return from_urdf, None, None
    m = model.meta
    for key in ("urdf_spec", "urdf"):
        if m.get(key):
            return m[key], m.get("root"), m.get("tip")
    cal = m.get("calibration") or {}
    src = cal.get("robot")
    if isinstance(src, str) and src.lower().endswith((".urdf", ".yaml", ".yml")) and Path(src).is_file():
        return src, cal.get("root"), cal.get("tip")
    raise InputError(f"{m.get('robot_file', model.name)}: the UR description the model was calibrated from is not "
                     f"known — give it with --from-urdf (the URDF, or a URDF robot spec)")


def _frame_line(what: str, params: str, link_from: str, link_to: str, nominal, calibrated, where: str) -> str:
    from estcal.kinematics.transforms import matrix_to_rpy

    def f(T):
        xyz = ", ".join(f"{round(v, 6) + 0.0:.6f}" for v in T[:3, 3])
        rpy = ", ".join(f"{round(v, 6) + 0.0:.6f}" for v in matrix_to_rpy(T[:3, :3]))
        return f"xyz [{xyz}] rpy [{rpy}]"

    return (f"the {what} frame ({params}) is not part of a UR kinematics file: {link_from} -> {link_to} is "
            f"{f(calibrated)} calibrated ({f(nominal)} nominal) — {where}; --robot-spec keeps it for estcal")


def _ur_warnings(model, origins) -> list[str]:
    import numpy as np

    from estcal.kinematics.urdf_export import unexpressible

    out = []
    link, T0, T1 = origins.mount
    if not np.allclose(T0, T1, atol=0, rtol=0):
        out.append(_frame_line("base", "base_tx … base_rz", origins.root, link, T0, T1,
                               f"in a UR description, the origin of the joint that mounts {link}"))
    tip, T0, T1 = origins.end
    if not np.allclose(T0, T1, atol=0, rtol=0):
        out.append(_frame_line("tool", "tool_tx … tool_rz", origins.joints["wrist_3"].replace("_joint", "_link"), tip,
                               T0, T1, "it belongs to the description of what is mounted on the flange"))
    if origins.others:
        out.append(f"the calibrated origins of {', '.join(origins.others)} (not joints of the UR arm) are not part of "
                   f"a UR kinematics file (not written)")
    out += unexpressible(model, "a UR kinematics file")
    if model.payload_mass:
        out.append(f"the payload ({model.payload_mass:.6g} kg) is not part of a UR kinematics file (not written)")
    layer = (model.meta.get("calibration") or {}).get("residual_model")
    if layer:
        cost = layer.get("cost_mm")
        out.append("the residual Gaussian-process layer (" + str(layer.get("space")) + " space) is dropped"
                   + (f": it removed {cost:.3g} mm RMS at new postures (posture-grouped CV)" if cost is not None else ""))
    return out


def export_ur_kinematics(robot, path, *, from_urdf=None, root: str | None = None, tip: str | None = None,
                         robot_spec=None) -> UrExport:
    """Write the calibrated joint origins of a UR model (spec or object) as a UR kinematics file at ``path``
    (docs/export.md): offsets folded in as rotations about the joint axes, a content hash, atomically.
    ``from_urdf``: the nominal description (a ``.urdf`` or a URDF robot spec; default: the one the model was
    loaded or calibrated from). ``robot_spec``: also write a URDF robot spec that ``--robot`` reads back as
    the whole calibrated model (the base and tool frames included). ``root``/``tip``: the chain of a URDF or
    robot-spec model, else of the nominal description."""
    from estcal.base.atomic import refuse_input
    from estcal.io.robotfile import load_robot
    from estcal.io.urdfspec import nominal_description, write_spec
    from estcal.kinematics.ur_kinematics import ur_origins

    path = Path(path)
    if from_urdf is not None:
        check_input_files([from_urdf], "URDF", "--from-urdf")
    chain_model = _chain_model(robot)
    with input_errors():
        model = load_robot(robot, root=root if chain_model else None, tip=tip if chain_model else None)
    src, r0, t0 = _nominal_source(model, from_urdf)
    with input_errors():
        nominal = nominal_description(src, root=None if chain_model else root or r0,
                                      tip=None if chain_model else tip or t0)
        if chain_model:
            nominal.root, nominal.tip = model.meta.get("root"), model.meta.get("tip")
    inputs = [*nominal.inputs, model.meta.get("robot_file"), model.meta.get("ur_kinematics"),
              robot if isinstance(robot, (str, Path)) else None]
    for out in (path, robot_spec):
        if out is not None:
            refuse_input(out, inputs)
    with input_errors():
        origins = ur_origins(model, nominal.tree, nominal.source, nominal.root, nominal.tip)
    warns = _ur_warnings(model, origins)
    origins.kinematics.write(path)
    spec = None
    if robot_spec is not None:
        p = model.params
        frame = {k: [p[f"{k}_{c}"] for c in ("tx", "ty", "tz", "rx", "ry", "rz")] for k in ("base", "tool")}
        spec = write_spec(robot_spec, nominal.urdf, path, origins.root, origins.tip,
                          **{k: v if any(v) else None for k, v in frame.items()})
    return UrExport(model, origins, path, spec, nominal.source, warns)
