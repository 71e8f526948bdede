"""The robots ``--robot`` accepts by name: ``estcal robots``.

Serial built-ins (:mod:`estcal.kinematics.robots`, the packaged robot files of
:mod:`estcal.robots`) and parallel platforms (:mod:`estcal.parallel`). Each row says what the robot
is — joints, kinematic convention, number of parameters and where the model comes from — or why it
cannot be loaded here (TIAGo reads the shared data folder).
"""
from __future__ import annotations

__all__ = ["builtin_robots"]


def _source(name: str) -> str:
    """One line on where the model comes from: the built-in's docstring, the packaged file's description."""
    from estcal.kinematics.robots import BUILTIN

    fn = BUILTIN.get(name)
    if fn is not None and fn.__doc__:
        return fn.__doc__.strip().splitlines()[0].rstrip(".").replace("``", "")
    from estcal.base.textinput import read_yaml
    from estcal.robots import robot_file

    try:
        return str(read_yaml(robot_file(name), "robot file").get("description", ""))
    except (OSError, ValueError, AttributeError):
        return ""


def _serial_row(name: str) -> dict:
    from estcal.io.robotfile import load_robot

    try:
        rb = load_robot(name)
    except Exception as exc:  # noqa: BLE001 - a robot that cannot load here is listed with the reason
        return {"name": name, "kind": "serial", "available": False, "reason": str(exc).splitlines()[0]}
    src = _source(name)
    return {"name": name, "kind": "serial", "available": True, "joints": rb.n_joints,
            "joint_types": "".join("P" if t == "prismatic" else "R" for t in rb.joint_types),
            "convention": rb.convention, "parameters": len(rb.params.names), "source": str(src)}


def builtin_robots() -> list[dict]:
    """One row per robot name: ``name``, ``kind`` (serial / parallel), ``available`` and, when it
    loads, ``joints``, ``joint_types`` (R/P per joint), ``convention``, ``parameters`` (count) and
    ``source``; otherwise ``reason``."""
    from estcal.io.robotfile import robot_names
    from estcal.parallel.gough import BUILTINS

    rows = [_serial_row(n) for n in robot_names()]
    for name in sorted(BUILTINS):
        rows.append({"name": name, "kind": "parallel", "available": True, "joints": 6, "joint_types": "PPPPPP",
                     "convention": "gough", "source": "Gough–Stewart platform (docs/parallel.md)"})
    return rows
