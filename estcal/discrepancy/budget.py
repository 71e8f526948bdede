"""The error budget: where the error at new postures goes, by posture-grouped cross-validation.

Every figure is a cross-validated RMSE (mm) of the point-error norms over the same rows,
with folds that never split a posture (:func:`estcal.validation.grouped_folds`): the
twin of a held-out row measured in another session is never in training. Each fold
refits every stage from scratch (registration, the geometric level's own selection,
the named effects, the residual GP).

=========================  ==============================================================
``nominal_mm``             registration only: base frame and unknown points/tool fitted,
                           nominal geometry
``geometric_mm``           the chosen geometric level (``full``, ``aic``, ``joint_offset``)
``named_mm``               + the named effects (equal to ``geometric_mm`` when none)
``structured_unnamed_mm``  the RMSE reduction a Gaussian process on the named model's
                           residual still achieves (:mod:`estcal.discrepancy.residual`,
                           the better of the joint and Cartesian spaces); 0 when none
``unstructured_mm``        what is left after it: ``named_mm − structured_unnamed_mm``
``repeatability_mm``       the floor from repeated postures after per-session rigid
                           registration (raw when one session;
                           :func:`estcal.validation.repeatability_floor`); ``None``
                           when no posture repeats
``predicted_validation_mm`` the CV RMSE of the recommended model (named, or named + GP
                           when the residual model is used): the expected RMSE at new
                           postures of the same sessions
=========================  ==============================================================

The reduction is a plain difference of RMSEs (not a quadrature split): the budget reads
"the GP would take the error from 2.6 to 2.4 mm". Folds are few on real data (tens of
postures), so the per-fold RMSEs are reported and their spread gives the uncertainty of
``predicted_validation_mm`` (``predicted_validation_se_mm``, the standard error over folds).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.discrepancy.geometric import fit_geometric, gravity_ready
from estcal.discrepancy.residual import SPACES, fit_residual_model, residual_correction
from estcal.estimate import calibrate_lsq
from estcal.methods import NoiseModel, Problem
from estcal.validation import (DEFAULT_TOL_M, DEFAULT_TOL_RAD, grouped_folds, n_postures, posture_groups,
                               repeatability_floor, rmse_mm)

__all__ = ["ErrorBudget", "FittedStage", "error_budget", "diagnosis_budget", "budget_lines", "predicted_at", "fit_stage", "fit_stage_sessions", "predicted_points",
           "measured_points", "prediction_coverage", "STAGES"]

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
        from estcal.kinematics.chunked import tool_poses

        R_tool = tool_poses(self.robot, data.readings, self.theta, data.context, fields=("R",)).R
        for m, R, t, dm in self._each(data):
            if m.any() and np.any(dm):
                pred[m] += np.einsum("nij,kj->nki", R_tool[m], dm)
        return pred

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


def fit_stage_sessions(robot, data, noise, stage: str, level: str = "full", effects=(), per_session: str | None = None,
                       n_iter: int = 6, max_iter: int = 100) -> FittedStage:
    """:func:`fit_stage` with, when ``per_session`` is ``"registration"`` (or ``"registration+points"``),
    a rigid registration of every session's measuring frame (and a change of the measured points on the
    tool) onto the first session's, by alternation: the shared model is fitted to the measurements mapped
    into the common frame, then each session's transform (Kabsch) and point change (linear least squares)
    are re-estimated from the model's prediction."""
    from estcal.estimate.registration import kabsch
    from estcal.kinematics.chunked import tool_poses

    lab = np.asarray(data.columns.get("session", np.zeros(data.n)))
    svals = list(dict.fromkeys(lab.tolist()))
    if per_session is None or len(svals) < 2:
        return FittedStage(*fit_stage(robot, data, noise, stage, level, effects, max_iter))
    if per_session not in ("registration", "registration+points"):
        raise ValueError(f"per_session must be None, 'registration' or 'registration+points', got {per_session!r}")
    k = measured_points(data).shape[1]
    sess = {sv: (np.eye(3), np.zeros(3), np.zeros((k, 3))) for sv in svals}
    meas = measured_points(data)
    fitted = None
    for _ in range(n_iter):
        adj = data.subset(slice(None))
        P = meas.copy()
        if fitted is not None:
            R_tool = tool_poses(fitted.robot, data.readings, fitted.theta, data.context, fields=("R",)).R
        for sv, (R, t, dm) in sess.items():
            m = lab == sv
            P[m] = (P[m] - t) @ R
            if fitted is not None and np.any(dm):
                P[m] -= np.einsum("nij,kj->nki", R_tool[m], dm)
        if adj.points is not None:
            adj.points = P
        else:
            adj.p = P[:, 0]
        if adj.R is not None:  # pose data: the measured orientation in the common frame too
            for sv, (R, t, dm) in sess.items():
                m = lab == sv
                adj.R[m] = np.einsum("ji,njk->nik", R, data.R[m])
        fitted = FittedStage(*fit_stage(robot, adj, noise, stage, level, effects, max_iter))
        base = predicted_points(fitted.robot, fitted.theta, data)
        R_tool = tool_poses(fitted.robot, data.readings, fitted.theta, data.context, fields=("R",)).R
        for sv in svals[1:]:
            m = lab == sv
            R, t, dm = sess[sv]
            for _inner in range(3):
                pred = base[m] + np.einsum("nij,kj->nki", R_tool[m], dm)
                R, t = kabsch(pred.reshape(-1, 3), meas[m].reshape(-1, 3))
                if per_session == "registration+points":
                    local = np.einsum("nji,nkj->nki", R_tool[m], (meas[m] - t) @ R - base[m])
                    dm = local.mean(axis=0)
            sess[sv] = (R, t, dm)
    fitted.sessions = {sv: sess[sv] for sv in svals[1:]}
    return fitted


@dataclass
class ErrorBudget:
    """Result of :func:`error_budget` (mm; see the module docstring for each entry)."""

    nominal_mm: float
    geometric_mm: float
    named_mm: float
    structured_unnamed_mm: float
    unstructured_mm: float
    repeatability_mm: float | None
    predicted_validation_mm: float
    predicted_validation_se_mm: float
    recommended: str
    unnamed: dict
    per_fold_mm: dict
    gp_mm: dict
    repeatability: dict | None
    n_postures: int
    n_rows: int
    k_folds: int
    level: str
    effects: list
    residual_model: object = None
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("nominal_mm", "geometric_mm", "named_mm", "structured_unnamed_mm",
                                           "unstructured_mm", "repeatability_mm", "predicted_validation_mm",
                                           "predicted_validation_se_mm", "recommended", "unnamed", "per_fold_mm",
                                           "gp_mm", "repeatability", "n_postures", "n_rows", "k_folds", "level")}
        d["effects"] = [{"effect": e[0], "joints": list(e[1])} for e in self.effects]
        d["cross_validation"] = "posture-grouped"
        d.update({k: v for k, v in self.extra.items() if not k.startswith("fitted")})
        return d

    def lines(self) -> list[str]:
        """The budget as text lines (the ``diagnose`` output)."""
        return budget_lines(self.to_dict())

    def __str__(self) -> str:
        return "\n".join(self.lines())


def budget_lines(b: dict) -> list[str]:
    """Text lines of a budget dict (:meth:`ErrorBudget.to_dict`)."""
    rep = "—" if b["repeatability_mm"] is None else f"{b['repeatability_mm']:.3f}"
    top = ", ".join(f"{k} {v:.2f}" for k, v in list(b["unnamed"].get("relevance", {}).items())[:3])
    return [f"error budget (posture-grouped {b['k_folds']}-fold CV, {b['n_postures']} postures, {b['n_rows']} rows; mm):",
            f"  nominal (registration)   {b['nominal_mm']:8.3f}",
            f"  geometric ({b['level']:<12}) {b['geometric_mm']:8.3f}",
            f"  + named effects          {b['named_mm']:8.3f}",
            f"  structured, unnamed      {b['structured_unnamed_mm']:8.3f}   "
            f"(GP over {b['unnamed'].get('space', '-')}: {top or '-'})",
            f"  unstructured             {b['unstructured_mm']:8.3f}",
            f"  repeatability floor      {rep:>8}",
            f"  predicted at new postures {b['predicted_validation_mm']:7.3f} ± {b['predicted_validation_se_mm']:.3f}"
            f"  ({b['recommended']})"]


def _fold_rmse(sq_rows, folds):
    return [float(np.sqrt(np.mean(sq_rows[f])) * 1e3) for f in folds]


def error_budget(robot, data, noise=None, *, level: str = "full", effects=(), groups=None, sessions=None,
                 k_folds: int = 5, rng=0, tol_rad: float = DEFAULT_TOL_RAD, tol_m: float = DEFAULT_TOL_M,
                 spaces=SPACES, residual_model: str | None = None, gp_restarts: int = 1,
                 max_iter: int = 60, per_session: str | None = None) -> ErrorBudget:
    """The error budget of the module docstring on ``data`` (all sessions stacked).

    Parameters
    ----------
    robot : nominal robot; data : Dataset (position, points or pose rows; a ``session`` column
        marks sessions, see :func:`estcal.sessions.stack_sessions`).
    noise : NoiseModel for the fits (default: unknown, 0.2 mm / 0.2 mrad starting scale).
    level, effects : the geometric level and the named effects (``(name, joints, options)``).
    groups : posture labels (default: :func:`estcal.validation.posture_groups` with ``tol_rad``, ``tol_m``).
    sessions : session labels (default: the ``session`` column, else one session).
    k_folds : posture-grouped folds (capped at the number of postures).
    spaces : residual GP spaces tried (``joints``, ``cartesian``).
    residual_model : ``"gp"`` makes named + GP the recommended model (its CV RMSE is then the
        prediction) and returns the GP fitted on all rows in ``residual_model``.
    per_session : ``"registration"`` / ``"registration+points"``: every stage with a rigid registration
        of each session (and a per-session change of the measured points), see :func:`fit_stage_sessions`.
    """
    noise = noise or NoiseModel(position=2e-4, orientation=2e-4, known=False)
    n = data.n
    g = posture_groups(data.readings, robot.joint_types, tol_rad, tol_m) if groups is None else np.asarray(groups)
    if sessions is None:
        sessions = data.columns.get("session", np.zeros(n))
    folds = grouped_folds(g, k_folds, rng)
    meas = measured_points(data)
    held = {s: np.zeros_like(meas) for s in STAGES}
    held_gp = {sp: np.zeros_like(meas) for sp in spaces}
    stages = STAGES if effects else STAGES[:2]
    # the final model and its residual GPs on every row first: the folds' GP fits start from their
    # hyperparameters (each fold still optimises on its own rows only)
    final = fit_stage_sessions(robot, data, noise, stages[-1], level, effects, per_session, max_iter=max_iter)
    r_all = final.residual_common(data)
    gps_all = {sp: fit_residual_model(sp, final.robot, final.theta, data.readings, r_all, data.context, gp_restarts,
                                      rng) for sp in spaces}
    outside = np.zeros(n, bool)  # held-out rows beyond their fold's training joint ranges (extrapolated)
    for test in folds:
        train = np.setdiff1d(np.arange(n), test)
        dtr, dte = data.subset(train), data.subset(test)
        lo, hi = dtr.readings.min(0), dtr.readings.max(0)
        outside[test] = np.any((dte.readings < lo) | (dte.readings > hi), axis=1)
        for st in stages:
            fs = fit_stage_sessions(robot, dtr, noise, st, level, effects, per_session, max_iter=max_iter)
            held[st][test] = meas[test] - fs.predict(dte)
            if st == stages[-1]:
                r_tr = fs.residual_common(dtr)
                for sp in spaces:
                    gp = fit_residual_model(sp, fs.robot, fs.theta, dtr.readings, r_tr, dtr.context, 0, rng,
                                            start=gps_all[sp])
                    corr = residual_correction(gp, fs.robot, fs.theta, dte.readings, dte.context)
                    held_gp[sp][test] = held[st][test] - fs.rotate_to_session(dte, corr)
    if not effects:
        held["named"] = held["geometric"]
    sq = {k: np.sum(v ** 2, axis=-1) for k, v in held.items()}  # (N, k) squared norms
    rm = {k: rmse_mm(np.sqrt(v)) for k, v in sq.items()}
    sq_gp = {sp: np.sum(v ** 2, axis=-1) for sp, v in held_gp.items()}
    gp_mm = {sp: rmse_mm(np.sqrt(v)) for sp, v in sq_gp.items()}
    best = min(gp_mm, key=gp_mm.get) if gp_mm else None
    structured = max(rm["named"] - gp_mm[best], 0.0) if best else 0.0
    unstructured = rm["named"] - structured
    # relevance from the GP fitted on every row's residual of the final named model
    rb, th = final.robot, final.theta
    unnamed, final_gp = {}, None
    if best:
        final_gp = gps_all[best]
        names = final_gp.joint_names if best == "joints" else final_gp.input_names
        unnamed = {"space": best, "relevance": final_gp.relevance,
                   "length_scales": dict(zip(names, np.asarray(final_gp.length_scales).tolist()))}
    use_gp = residual_model == "gp" and best is not None
    pred_sq = sq_gp[best] if use_gp else sq["named"]
    per_fold = {k: _fold_rmse(v, folds) for k, v in sq.items()}
    if best:
        per_fold["gp"] = _fold_rmse(sq_gp[best], folds)
    pf = np.array(per_fold["gp"] if use_gp else per_fold["named"])
    se = float(pf.std(ddof=1) / np.sqrt(len(pf))) if len(pf) > 1 else float("nan")
    # the recommended model's CV error inside / outside the training joint ranges (extrapolation):
    # predicted_at() weights them by where the robot will be used
    in_out = {"cv_inside_mm": rmse_mm(np.sqrt(pred_sq[~outside])), "cv_outside_mm": rmse_mm(np.sqrt(pred_sq[outside])),
              "fraction_outside": float(outside.mean())}
    rep = repeatability_floor(meas, g, sessions)
    rep_mm = None if rep is None else (rep["registered_mm"] if rep["registered_mm"] is not None else rep["raw_mm"])
    label = ("named" if effects else "geometric") + (" + GP" if use_gp else "")
    return ErrorBudget(rm["nominal"], rm["geometric"], rm["named"], float(structured), float(unstructured), rep_mm,
                       rmse_mm(np.sqrt(pred_sq)), se, label, unnamed, per_fold, gp_mm, rep, n_postures(g), n,
                       len(folds), level, [tuple(e) for e in effects], final_gp if use_gp else None,
                       {"fitted_robot": rb, "fitted_theta": th, "fitted": final, "per_session": per_session,
                        "extrapolation": in_out})


def prediction_coverage(robot, theta, free, covariance, data, sigma_extra_m: float, level: float = 0.95) -> dict:
    """Coverage of the ``level`` prediction ellipsoids of the measured points of ``data``.

    Each point's prediction covariance is ``J C_θ Jᵀ + σ² I₃`` (θ covariance of the free
    parameters propagated by the analytic Jacobian, plus ``sigma_extra_m`` per coordinate:
    the unstructured residual, which includes the between-session repeatability); a point
    is covered when ``eᵀ Σ⁻¹ e ≤ χ²₃(level)``. Returns ``{coverage, n_points, level}``.
    """
    from scipy import stats

    problem = Problem(robot.with_values(theta), [(None, data, NoiseModel(position=1e-3, orientation=1e-3))])
    rows = problem.evaluate(np.asarray(theta, float))
    pos = rows.kind == 0
    idx = problem.params.indices(list(free))
    H = rows.H[pos][:, idx].reshape(-1, 3, len(idx))
    e = rows.e[pos].reshape(-1, 3)
    C = np.asarray(covariance, float)
    S = np.einsum("nip,pq,njq->nij", H, C, H) + sigma_extra_m ** 2 * np.eye(3)
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(S, e[..., None])[..., 0])
    covered = d2 <= stats.chi2.ppf(level, 3)
    return {"coverage": float(covered.mean()), "n_points": int(len(covered)), "level": level}


def predicted_at(budget, train_readings, target_readings) -> float | None:
    """Expected RMSE (mm) at the postures where the robot will be used (readings only, no measurement):
    the budget's CV error inside and outside the training joint ranges (``extrapolation``), weighted by
    the fraction of target rows outside them: √(f_in · CV_in² + f_out · CV_out²). Falls back to
    ``predicted_validation_mm`` when the CV had no row of the needed kind."""
    b = budget.to_dict() if hasattr(budget, "to_dict") else budget
    ex = b.get("extrapolation") or {}
    A, T = np.asarray(train_readings, float), np.asarray(target_readings, float)
    out = np.any((T < A.min(0)) | (T > A.max(0)), axis=1)
    f_out = float(out.mean()) if len(T) else 0.0
    cin, cout = ex.get("cv_inside_mm"), ex.get("cv_outside_mm")
    if (cin is None and f_out < 1) or (cout is None and f_out > 0):
        return b["predicted_validation_mm"]
    return float(np.sqrt((1 - f_out) * (cin or 0.0) ** 2 + f_out * (cout or 0.0) ** 2))


def diagnosis_budget(robot, diagnosis, **kw) -> ErrorBudget:
    """The error budget of a :class:`~estcal.discrepancy.diagnose.DiagnosisResult`: its training data as it
    prepared them, its geometric level and its named causes (``kw`` as :func:`error_budget`)."""
    effects = [(c.effect, list(c.joints), dict(c.options or {})) for c in diagnosis.causes]
    level = diagnosis.analysis.get("geometric_level", "full")
    return error_budget(robot, diagnosis.train_data, kw.pop("noise", None), level=level, effects=effects, **kw)
