"""Helpers shared by the ``estcal design`` and ``estcal next-pose`` commands (units at the edge)."""
from __future__ import annotations

import numpy as np


def parse_poses(specs, robot) -> np.ndarray | None:
    """``["10,-60,120,0,30,0", ...]`` → (K, n) readings: revolute joints in degrees,
    prismatic joints in millimetres (converted to rad / m)."""
    if not specs:
        return None
    rows = []
    for s in specs:
        try:
            vals = [float(v) for v in str(s).replace(";", ",").split(",") if v.strip()]
        except ValueError:
            raise ValueError(f"--test-pose {s!r}: expected {robot.n_joints} comma-separated numbers") from None
        if len(vals) != robot.n_joints:
            raise ValueError(f"--test-pose {s!r}: expected {robot.n_joints} values for joints "
                             f"{robot.joint_names}, got {len(vals)}")
        rows.append(vals)
    Q = np.asarray(rows, float)
    rev = np.array([t == "revolute" for t in robot.joint_types])
    Q[:, rev] = np.radians(Q[:, rev])
    Q[:, ~rev] *= 1e-3
    return Q


def default_test_pose(robot) -> np.ndarray:
    """Mid-range of every joint (documented default when a test pose is needed but not given)."""
    return robot.limits.mean(1)[None]


def format_readings(Q, robot) -> list[str]:
    rev = np.array([t == "revolute" for t in robot.joint_types])
    out = []
    for q in np.atleast_2d(Q):
        out.append("  ".join(f"{np.degrees(v):9.3f}°" if r else f"{v * 1e3:9.2f}mm" for v, r in zip(q, rev)))
    return out


def parse_free(spec, robot, method) -> list[str]:
    """``--free`` (comma-separated names / shell patterns) or the identifiable subset."""
    from .model import identifiable_subset

    if not spec:
        return identifiable_subset(robot, method)
    pats = [s.strip() for s in spec.split(",") if s.strip()]
    return robot.params.with_free(pats).free_names
