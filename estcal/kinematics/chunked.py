"""Forward kinematics of many poses in bounded memory.

:meth:`SerialRobot.kinematics` vectorises over poses and keeps, for every pose, every link's
frame, axis and origin (and, with Jacobians, N × 6 × P blocks): ~3.5 kB per pose without
Jacobians for a 6-axis arm, so 10⁶ poses would need ~3.5 GB. Callers that only need the tool
pose or the marker points go through :func:`tool_poses`, which evaluates chunks of
:data:`CHUNK` poses and keeps only those arrays (≈ 100 B per pose). The result is the same
array, element for element: every pose's kinematics is independent of the others.
"""
from __future__ import annotations

import numpy as np

__all__ = ["CHUNK", "tool_poses"]

#: poses per kinematics call (~70 MB of intermediate arrays for a 6-axis arm)
CHUNK = 20_000


def tool_poses(robot, readings, theta=None, context: dict | None = None, fields=("R", "p"), chunk: int = CHUNK):
    """``fields`` among ``R``, ``p``, ``points``, ``q`` (tool frame, marker points, joint values) of
    every pose, computed ``chunk`` poses at a time: a namespace with those attributes that also
    reads like a dict (``out.p`` or ``out["p"]``)."""
    readings = np.asarray(readings, float)
    n = readings.shape[0]
    ctx = context or {}
    out = {f: [] for f in fields}
    for a in range(0, max(n, 1), chunk):
        sl = slice(a, min(a + chunk, n))
        c = {k: np.asarray(v)[sl] if np.ndim(v) and np.shape(v)[0] == n else v for k, v in ctx.items()}
        kin = robot.kinematics(readings[sl], theta, c, jacobian=False)
        for f in fields:
            out[f].append(getattr(kin, f))
    return _Fields({f: np.concatenate(v, axis=0) if v else np.zeros((0,)) for f, v in out.items()})


class _Fields(dict):
    __getattr__ = dict.__getitem__
