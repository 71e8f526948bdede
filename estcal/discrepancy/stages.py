"""The stages of the error budget, fitted on a set of rows: registration only, a geometric level, the
level plus named effects — optionally with a rigid registration of every session's measuring frame.

:func:`fit_stage_sessions` returns a :class:`FittedStage` that predicts the measured points in each
row's own session frame; :func:`point_covariance` propagates the fit's parameter covariance to the
predicted points (J C_θ Jᵀ, the parametric part of a prediction region).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.discrepancy.geometric import fit_geometric, gravity_ready
from estcal.estimate import calibrate_lsq
from estcal.methods import Problem

__all__ = ["STAGES", "FittedStage", "fit_stage", "fit_stage_sessions", "measured_points", "predicted_points",
           "point_covariance"]

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


@dataclass
class FittedStage:
    """A fitted stage: the robot at ``theta`` plus, per session, a rigid registration of the
    measuring frame (``R_s``, ``t_s``) and a change of the measured points on the tool (``dm_s``,
    (k, 3) in the tool frame) relative to the first session (identity, 0 for a session the fit
    never saw). ``predict`` returns points in each row's own session frame."""

    robot: object
    theta: np.ndarray
    free: list
    result: object
    sessions: dict = field(default_factory=dict)

    def _each(self, data):
        """(row mask, R, t, dm) of every session the fit knows, for the rows of ``data``."""
        lab = np.asarray(data.columns.get("session", np.zeros(data.n)))
        for sv, (R, t, dm) in self.sessions.items():
            yield lab == sv, R, t, dm

    def predict_common(self, data):
        """(N, k, 3) points in the common frame (first session), with each session's marker change."""
        pred = predicted_points(self.robot, self.theta, data)
        if not self.sessions:
            return pred
        R_tool = self.tool_rotations(data)
        for m, R, t, dm in self._each(data):
            if m.any() and np.any(dm):
                pred[m] += np.einsum("nij,kj->nki", R_tool[m], dm)
        return pred

    def tool_rotations(self, data):
        """(N, 3, 3) the fitted tool frame's orientation at every row (the frame of the per-session point change)."""
        from estcal.kinematics.chunked import tool_poses

        return tool_poses(self.robot, data.readings, self.theta, data.context, fields=("R",)).R

    def _map(self, data, vec, forward: bool, shift: bool):
        out = np.array(vec, float)
        for m, R, t, dm in self._each(data):
            out[m] = out[m] @ (R.T if forward else R) + (t if shift else 0.0)
        return out

    def to_session(self, data, pts):
        """Points of the common frame in each row's session frame."""
        return self._map(data, pts, True, True)

    def residual_common(self, data):
        """Measured − predicted, rotated back into the common frame (N, k, 3)."""
        return self._map(data, measured_points(data) - self.predict(data), False, False)

    def rotate_to_session(self, data, vec):
        """Vectors (corrections) of the common frame in each row's session frame."""
        return self._map(data, vec, True, False)

    def predict(self, data):
        return self.to_session(data, self.predict_common(data))

    def common_data(self, data):
        """A copy of ``data`` with every session's measurements in the common frame (each session's rigid
        registration undone: points ``R_sᵀ (p − t_s)``, a measured orientation ``R_sᵀ R``; a per-session point
        change is not undone), so that the one robot model describes every row."""
        return _in_common_frame(data, self.sessions)


def _in_common_frame(data, sessions: dict, R_tool=None):
    """A copy of ``data`` with the measurements of every session of ``sessions`` (``{label: (R, t, dm)}``) mapped
    into the common frame — points ``R_sᵀ (p − t_s)``, a measured orientation ``R_sᵀ R`` — and, with the tool's
    orientations ``R_tool`` (N, 3, 3), each session's point change ``dm`` undone too."""
    lab = np.asarray(data.columns.get("session", np.zeros(data.n)))
    out = data.subset(slice(None))
    P = measured_points(data).copy()
    for sv, (R, t, dm) in sessions.items():
        m = lab == sv
        P[m] = (P[m] - t) @ R
        if R_tool is not None and np.any(dm):
            P[m] -= np.einsum("nij,kj->nki", R_tool[m], dm)
        if out.R is not None:  # pose data: the measured orientation in the common frame too
            out.R[m] = np.einsum("ji,njk->nik", R, data.R[m])
    if out.points is not None:
        out.points = P
    else:
        out.p = P[:, 0]
    return out


def fit_stage_sessions(robot, data, noise, stage: str, level: str = "full", effects=(), per_session: str | None = None,
                       n_iter: int = 6, max_iter: int = 100, fit=None) -> FittedStage:
    """:func:`fit_stage` with, when ``per_session`` is ``"registration"`` (or ``"registration+points"``),
    a rigid registration of every session's measuring frame (and a change of the measured points on the
    tool) onto the first session's, by alternation: the shared model is fitted to the measurements mapped
    into the common frame, then each session's transform (Kabsch) and point change (linear least squares)
    are re-estimated from the model's prediction.

    ``fit``: a callable ``(robot, data) → FittedStage`` fitting the shared model instead of :func:`fit_stage`
    (``stage``, ``level``, ``effects`` and ``max_iter`` are then unused), e.g. a MAP model with a prior
    (``experiments/prior_study.py``)."""
    from estcal.estimate.registration import kabsch

    if fit is None:
        def fit(rb, d):
            return FittedStage(*fit_stage(rb, d, noise, stage, level, effects, max_iter))

    lab = np.asarray(data.columns.get("session", np.zeros(data.n)))
    svals = list(dict.fromkeys(lab.tolist()))
    if per_session is None or len(svals) < 2:
        return fit(robot, data)
    if per_session not in ("registration", "registration+points"):
        raise ValueError(f"per_session must be None, 'registration' or 'registration+points', got {per_session!r}")
    points = per_session == "registration+points"  # else the point change stays 0: no tool frame, one Kabsch
    k = measured_points(data).shape[1]
    sess = {sv: (np.eye(3), np.zeros(3), np.zeros((k, 3))) for sv in svals}
    meas = measured_points(data)
    fitted = None
    for _ in range(n_iter):
        adj = _in_common_frame(data, sess, fitted.tool_rotations(data) if fitted is not None and points else None)
        fitted = fit(robot, adj)
        base = predicted_points(fitted.robot, fitted.theta, data)
        R_tool = fitted.tool_rotations(data) if points else None
        for sv in svals[1:]:
            m = lab == sv
            R, t, dm = sess[sv]
            for _inner in range(3 if points else 1):
                pred = base[m] + np.einsum("nij,kj->nki", R_tool[m], dm) if points else base[m]
                R, t = kabsch(pred.reshape(-1, 3), meas[m].reshape(-1, 3))
                if points:
                    local = np.einsum("nji,nkj->nki", R_tool[m], (meas[m] - t) @ R - base[m])
                    dm = local.mean(axis=0)
            sess[sv] = (R, t, dm)
    fitted.sessions = {sv: sess[sv] for sv in svals[1:]}
    return fitted


def point_covariance(fitted: FittedStage, data) -> np.ndarray:
    """(N, k, 3, 3) covariance of the predicted points from the fit's parameter covariance, J C_θ Jᵀ
    (analytic Jacobian of the points with respect to the estimated parameters; in the common frame,
    which a rigid session registration rotates without changing its trace)."""
    fs = fitted
    names = list(fs.result.names)
    kin = fs.robot.kinematics(data.readings, fs.theta, data.context, jacobian=True)
    idx = fs.robot.params.indices(names)
    k = measured_points(data).shape[1]
    if data.points is not None and fs.robot.n_markers >= k and k:
        J = kin.J_points[:, :k][..., idx]
    else:
        J = np.repeat(kin.J[:, None, :3][..., idx], k, axis=1)
    C = np.asarray(fs.result.covariance, float)
    return np.einsum("nkip,pq,nkjq->nkij", J, C, J)
