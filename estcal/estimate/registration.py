"""Closed-form initial guesses: the base (registration) transform from point correspondences.

Motion-capture and tracker data live in an unknown world frame; starting a
nonlinear fit from an identity base can fail. :func:`register_base` solves the
absolute-orientation problem (Kabsch / Horn, SVD form) between points
predicted in the robot's base frame and the measured points, and returns base
parameters (``base_tx … base_rz``) that put the robot near the data.
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.chunked import tool_poses
from estcal.kinematics.transforms import kabsch, matrix_to_rpy, rpy_to_matrix

__all__ = ["kabsch", "register_base"]


def register_base(robot, data, theta=None):
    """Full parameter vector with the base frame set by Kabsch on the measured points.

    Predictions use the current marker values (or the tool origin). The existing base
    transform is composed with the correction, so it works for any starting base.
    """
    theta = robot.params.values.copy() if theta is None else np.asarray(theta, float).copy()

    kin = tool_poses(robot, data.readings, theta, data.context, fields=("p", "points"))  # bounded memory
    if data.kind == "pose":
        pred, meas = kin.p, data.p
    else:
        k = data.n_points
        pred = kin.points[:, :k] if robot.n_markers >= k else np.repeat(kin.p[:, None], k, 1)
        pred, meas = pred.reshape(-1, 3), data.points.reshape(-1, 3)
    R, t = kabsch(pred, meas)
    names = ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz"]
    idx = robot.params.indices(names)
    Rb = rpy_to_matrix(theta[idx[3:]])
    pb = theta[idx[:3]]
    Rn, pn = R @ Rb, R @ pb + t
    theta[idx[:3]] = pn
    theta[idx[3:]] = matrix_to_rpy(Rn)
    return theta
