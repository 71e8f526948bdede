"""Display units (docs/conventions.md, "Units on the command line"): SI inside, mm / mrad /
degrees for people.

One rule for the printed unit of a parameter (:func:`display_unit`) and of a joint reading
(:func:`joint_display`), used by the command line, the reports and the parameter tables.
"""
from __future__ import annotations

import numpy as np

__all__ = ["MILLI", "display_unit", "joint_display"]

MILLI = 1e-3  # mm -> m, mrad -> rad


def display_unit(name: str, robot) -> tuple[str, float]:
    """Printed unit and factor from SI of parameter ``name``: mrad for angles (and offsets of
    revolute joints), mm for lengths, none for gains and other dimensionless parameters."""
    head = name.split("_")[0]
    if name.startswith(("base_r", "tool_r")) or head in ("alpha", "theta", "beta", "rx", "ry", "rz"):
        return "mrad", 1e3
    if head == "gain":
        return "", 1.0
    if head == "offset":
        for j, li in enumerate(robot.offset_idx):
            if robot.params.names[li] == name:
                return ("mm", 1e3) if robot.joint_types[j] == "prismatic" else ("mrad", 1e3)
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    if kinds.get(name) == "effect":
        return "SI", 1.0
    return "mm", 1e3


def joint_display(robot, readings):
    """Readings (N, n) in display units (revolute: degrees, prismatic: mm) and each joint's unit."""
    rev = np.array([t == "revolute" for t in robot.joint_types])
    q = np.atleast_2d(np.asarray(readings, float)).copy()
    q[:, rev] = np.degrees(q[:, rev])
    q[:, ~rev] *= 1e3
    return q, ["deg" if r else "mm" for r in rev]
