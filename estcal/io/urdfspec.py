"""URDF robot specs: a URDF, its chain and — for a Universal Robots arm — a kinematics file, as one ``--robot``.

A small YAML file that ``--robot`` accepts wherever it accepts a robot file (docs/export.md,
"Reading a kinematics file")::

    estcal_robot: 1
    urdf: ../shared/data/ur10/ur10_robot.urdf   # the nominal description (paths: from this file's folder)
    ur_kinematics: ur10_kinematics.yaml         # optional: its origins replace the URDF's six UR joint origins
    root: world                                  # optional (else --root, else the URDF's root link)
    tip: camera_color_optical_frame              # optional (else --tip)
    base: {xyz: [x, y, z], rpy: [r, p, y]}       # optional: base_tx … base_rz (m, rad), as in a robot file
    tool: {xyz: [x, y, z], rpy: [r, p, y]}       # optional: tool_tx … tool_rz

The model is the URDF's chain with the kinematics file's origins put in as the ``ur_description``
xacro puts them (:func:`estcal.kinematics.ur_kinematics.apply_to_tree`), plus the base and tool frames
a UR kinematics file has no place for. ``estcal export --ur-kinematics K.yaml --robot-spec S.yaml``
writes both files.
"""
from __future__ import annotations

import difflib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.errors import RobotFileError
from estcal.base.textinput import check_input_file

__all__ = ["SPEC_KEYS", "is_urdf_spec", "robot_from_spec", "nominal_description", "Nominal", "write_spec"]

SPEC_KEYS = ("estcal_robot", "name", "urdf", "ur_kinematics", "root", "tip", "base", "tool")


def is_urdf_spec(d) -> bool:
    """A parsed robot file that is a URDF robot spec (it names a ``urdf``)."""
    return isinstance(d, dict) and "urdf" in d


def _err(source, where: str, msg: str) -> RobotFileError:
    return RobotFileError(f"{source}: {where + ': ' if where else ''}{msg}")


def _file(d, key: str, source, what: str) -> Path | None:
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, str) or not v.strip():
        raise _err(source, key, f"expected the path of the {what} file, got {v!r}")
    p = Path(v) if Path(v).is_absolute() else Path(source).parent / v  # as the user would write it
    try:
        return check_input_file(p, what, RobotFileError)
    except RobotFileError as exc:
        raise _err(source, key, str(exc)) from None


def _frame(d, key: str, source) -> tuple | None:
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, dict) or any(k not in ("xyz", "rpy") for k in v):
        raise _err(source, key, f"expected {{xyz: [x, y, z], rpy: [roll, pitch, yaw]}} (m, rad), got {v!r}")
    out = []
    for k in ("xyz", "rpy"):
        x = v.get(k, [0.0, 0.0, 0.0])
        if (not isinstance(x, list) or len(x) != 3
                or not all(isinstance(a, (int, float)) and not isinstance(a, bool) and np.isfinite(a) for a in x)):
            raise _err(source, f"{key}.{k}", f"expected 3 finite numbers, got {x!r}")
        out += [float(a) for a in x]
    return tuple(out)


def _chain_end(d, key: str, given, source):
    """The spec's root / tip, or the command line's; both and different is an error."""
    v = d.get(key)
    if v is not None and not isinstance(v, str):
        raise _err(source, key, f"expected a link name, got {v!r}")
    if v is not None and given is not None and v != given:
        raise _err(source, key, f"the file says {v!r}, --{key} {given!r}: give one of them")
    return v if v is not None else given


def _check_keys(d, source) -> None:
    for k in d:
        if k not in SPEC_KEYS:
            close = difflib.get_close_matches(str(k), SPEC_KEYS, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise _err(source, "", f"unknown key {k!r}{hint} in a URDF robot spec; valid keys: {', '.join(SPEC_KEYS)}")
    if d.get("estcal_robot") != 1:
        raise _err(source, "estcal_robot", f"expected 1 (the format version), got {d.get('estcal_robot')!r}")


def _tree(urdf: Path, kin_path: Path | None, root, tip):
    """The URDF's tree with the kinematics file's origins on its UR joints, and the file."""
    from estcal.kinematics.ur_kinematics import apply_to_tree, read_ur_kinematics
    from estcal.kinematics.urdf import chain_joints, load_urdf, root_links

    tree = load_urdf(urdf)
    if kin_path is None:
        return tree, None
    kin = read_ur_kinematics(kin_path)
    joints = None
    if tip is not None:  # look for the arm on the chain (a cell with two arms)
        top = root if root is not None else (root_links(tree) or [None])[0]
        joints = [j.name for j in chain_joints(tree, top, tip, urdf) if j.type != "fixed"]
    return apply_to_tree(tree, kin, urdf, joints), kin


def robot_from_spec(d: dict, source, root=None, tip=None, n_markers: int | None = None):
    """The robot of a URDF robot spec (module docstring); ``root``/``tip``: the command line's."""
    from estcal.kinematics.urdf import robot_from_tree

    _check_keys(d, source)
    urdf = _file(d, "urdf", source, "URDF")
    kin_path = _file(d, "ur_kinematics", source, "UR kinematics")
    root, tip = _chain_end(d, "root", root, source), _chain_end(d, "tip", tip, source)
    name = d.get("name")
    if name is not None and not isinstance(name, str):
        raise _err(source, "name", f"expected a text, got {name!r}")
    base, tool = _frame(d, "base", source), _frame(d, "tool", source)
    tree, kin = _tree(urdf, kin_path, root, tip)
    robot = robot_from_tree(tree, urdf, root, tip, np.zeros((n_markers, 3)) if n_markers else None, name)
    for prefix, values in (("base", base), ("tool", tool)):
        for k, v in zip(("tx", "ty", "tz", "rx", "ry", "rz"), values or ()):
            robot.params[f"{prefix}_{k}"] = v
    robot.meta.update(robot_file=str(source), urdf_spec=str(Path(source).resolve()))
    if kin is not None:
        robot.meta.update(ur_kinematics=str(kin_path.resolve()), ur_kinematics_hash=kin.hash)
    return robot


@dataclass
class Nominal:
    """A nominal description: the URDF's tree (a kinematics file's origins applied), where it was read
    (``source``: the ``.urdf`` or the spec), the URDF file, the chain's ``root``/``tip`` (None: not given)
    and every file it was read from."""

    tree: object
    source: str
    urdf: Path
    root: str | None
    tip: str | None
    inputs: list


def nominal_description(spec, root=None, tip=None) -> Nominal:
    """The nominal description a UR model is exported against: a ``.urdf`` file, or a URDF robot spec
    (its kinematics file applied; its root/tip unless given)."""
    from estcal.base.textinput import read_yaml
    from estcal.kinematics.urdf import load_urdf

    spec = Path(spec)
    if spec.suffix.lower() == ".urdf":
        return Nominal(load_urdf(spec), str(spec), spec, root, tip, [spec])
    d = read_yaml(spec, "robot", RobotFileError)
    if not is_urdf_spec(d):
        raise RobotFileError(f"{spec}: is not a URDF or a URDF robot spec (a YAML file with urdf: …) — give the "
                             f"description the model was calibrated from")
    _check_keys(d, spec)
    urdf = _file(d, "urdf", spec, "URDF")
    kin_path = _file(d, "ur_kinematics", spec, "UR kinematics")
    root, tip = root or d.get("root"), tip or d.get("tip")
    tree, _ = _tree(urdf, kin_path, root, tip)
    return Nominal(tree, str(spec), urdf, root, tip, [p for p in (spec, urdf, kin_path) if p is not None])


def _rel(target, folder: Path) -> str:
    """``target`` relative to ``folder`` when it is near (at most one level up: ``../shared/…``), else absolute."""
    target = Path(target).resolve()
    try:
        rel = os.path.relpath(target, folder)
    except ValueError:  # another drive (Windows)
        return str(target)
    return rel if Path(rel).parts[:2].count("..") <= 1 else str(target)


def write_spec(path, urdf, ur_kinematics=None, root=None, tip=None, base=None, tool=None, name=None) -> Path:
    """Write a URDF robot spec (paths relative to its folder; ``base``/``tool``: six numbers xyz + rpy, written
    with the shortest repr that reads back to the same floats)."""
    import yaml

    path = Path(path)
    folder = path.resolve().parent
    d: dict = {"estcal_robot": 1}
    if name:
        d["name"] = str(name)
    d["urdf"] = _rel(urdf, folder)
    if ur_kinematics is not None:
        d["ur_kinematics"] = _rel(ur_kinematics, folder)
    d.update({k: v for k, v in (("root", root), ("tip", tip)) if v is not None})
    for key, v in (("base", base), ("tool", tool)):
        if v is not None:
            v = [float(x) + 0.0 for x in v]
            d[key] = {"xyz": v[:3], "rpy": v[3:]}
    header = ("# estcal URDF robot spec: --robot reads it as the URDF's chain with the UR kinematics file's origins,\n"
              "# plus the base and tool frames a kinematics file has no place for (docs/export.md)\n")
    body = yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=110)
    return atomic_write_text(path, header + body)
