"""Display units of parameters (mm for lengths, mrad for angles, dimensionless gains) and of
joint readings (degrees, mm).

The one rule for parameters lives in :func:`estcal.cli.units.display_unit`
(``docs/conventions.md``, "Units on the command line"); the reports use the same function.
"""
from __future__ import annotations

import numpy as np

from estcal.cli.units import display_unit

__all__ = ["display_unit", "joint_display"]


def joint_display(robot, readings):
    """Readings (N, n) in display units (revolute: degrees, prismatic: mm) and each joint's unit."""
    rev = np.array([t == "revolute" for t in robot.joint_types])
    q = np.atleast_2d(np.asarray(readings, float)).copy()
    q[:, rev] = np.degrees(q[:, rev])
    q[:, ~rev] *= 1e3
    return q, ["deg" if r else "mm" for r in rev]
