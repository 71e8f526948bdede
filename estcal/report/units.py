"""Display units of parameters: mm for lengths, mrad for angles, dimensionless gains.

Everything inside estcal is SI (m, rad); printed tables and report figures use
mm / mrad (``docs/conventions.md``). :func:`display_unit` is the one rule for
both the terminal tables of ``estcal calibrate`` and the reports.
"""
from __future__ import annotations

import numpy as np

__all__ = ["display_unit", "joint_display"]

_ANGLE_PREFIX = ("alpha", "theta", "beta", "rx", "ry", "rz")


def display_unit(name: str, robot) -> tuple[str, float]:
    """Display unit and factor from SI for a parameter name of ``robot``."""
    head = name.split("_")[0]
    if name.startswith(("base_r", "tool_r")) or head in _ANGLE_PREFIX:
        return "mrad", 1e3
    if head == "gain":
        return "", 1.0
    if head == "offset":
        for j, li in enumerate(robot.offset_idx):
            if robot.params.names[li] == name:
                return ("mm", 1e3) if robot.joint_types[j] == "prismatic" else ("mrad", 1e3)
    return "mm", 1e3


def joint_display(robot, readings):
    """Readings (N, n) in display units (revolute: degrees, prismatic: mm) and each joint's unit."""
    rev = np.array([t == "revolute" for t in robot.joint_types])
    q = np.atleast_2d(np.asarray(readings, float)).copy()
    q[:, rev] = np.degrees(q[:, rev])
    q[:, ~rev] *= 1e3
    return q, ["deg" if r else "mm" for r in rev]
