"""Measured and predicted points, and the fits of a stage on a set of rows: registration only, a geometric
level, the level plus effects (:func:`fit_stage`; the diagnosis starts from the registration)."""
from __future__ import annotations

import numpy as np

from estcal.discrepancy.geometric import fit_geometric, gravity_ready
from estcal.estimate import calibrate_lsq
from estcal.methods import Problem

__all__ = ["STAGES", "fit_stage", "measured_points", "predicted_points"]

STAGES = ("nominal", "geometric", "named")


def measured_points(data) -> np.ndarray:
    """(N, k, 3) measured positions: the points, or the tool origin of pose data."""
    if data.points is not None:
        return np.asarray(data.points, float)
    if data.p is not None:
        return np.asarray(data.p, float)[:, None, :]
    raise ValueError(f"{data.where}: no measured positions (kind {data.kind!r}) for an error budget")


def predicted_points(robot, theta, data) -> np.ndarray:
    """(N, k, 3) the model's prediction of :func:`measured_points`."""
    from estcal.kinematics.chunked import tool_poses

    kin = tool_poses(robot, data.readings, theta, data.context, fields=("p", "points"))
    if data.points is not None and robot.n_markers >= data.n_points and data.n_points:
        return kin.points[:, : data.n_points]
    k = data.n_points or 1
    return np.repeat(kin.p[:, None, :], k, axis=1)


def _registration_free(robot) -> list[str]:
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    return [n for n in robot.params.names if kinds[n] in ("base", "marker")
            or (kinds[n] == "tool" and robot.n_markers == 0)]


def fit_stage(robot, data, noise, stage: str, level: str = "full", effects=(), max_iter: int = 100):
    """Fit one stage of the budget on ``data``; returns ``(robot, theta, free, result)``.

    stage : ``nominal`` (registration), ``geometric`` (``level``) or ``named`` (``level`` +
    ``effects``, a list of ``(effect name, joints, options)`` of :func:`estcal.effects.make_effect`).
    The effects read their context columns (``approach_<joint>``, ``t`` …) from ``data.context``.
    """
    from estcal.effects import make_effect

    if stage == "nominal":
        problem, res, free, _ = fit_geometric(robot, data, noise, free=_registration_free(robot), max_iter=max_iter)
        return problem.robot, res.theta, free, res
    problem, res, free, _ = fit_geometric(robot, data, noise, level=level, max_iter=max_iter)
    if stage == "geometric" or not effects:
        return problem.robot, res.theta, free, res
    if stage != "named":
        raise ValueError(f"unknown budget stage {stage!r}; choose one of {STAGES}")
    rb, _ = gravity_ready(problem.robot, res.theta, robot.params.values)
    for name, joints, opts in effects:
        rb = rb.add_effect(make_effect(name, rb, joints=list(joints), **dict(opts or {})))
    en = [n for n, kd in zip(rb.params.names, rb.params.kinds) if kd == "effect"]
    free = list(free) + en
    res = calibrate_lsq(Problem(rb, [(None, data, noise)]), "lm", free=free, check=False, max_iter=max_iter)
    return rb, res.theta, free, res
