"""Sequential design: the next measurement pose from the current error covariance.

Given the current estimate ``x`` and covariance ``C`` of the free parameters
(from any estimator: least squares, Kalman filter, iSAM2, MCMC), measuring a
pose with Jacobian rows ``H`` (r × p) and noise ``R = diag(σ²)`` would give
the MAP / Kalman update (Mooring 4.104, 4.106; the information form 4.69–4.70)

.. math::

    K = C H^T (H C H^T + R)^{-1}, \\qquad
    x^+ = x + K\\,(y - h(x)), \\qquad
    C^+ = (I - K H)\\, C = (C^{-1} + H^T R^{-1} H)^{-1}.

``C⁺`` does not depend on the measured value, so every candidate pose can be
scored before measuring; :mod:`estcal.design.update` evaluates the criterion
of ``C⁺`` for thousands of candidates with the Woodbury identity. The proposal
is the candidate that minimises the chosen criterion of ``C⁺`` (optionally
refined by a local optimisation of its joint values).

:func:`active_calibration` runs the loop "propose → measure (simulated) →
update → …" until the predicted test-pose error ``ρ0 = sqrt(trace(J0 C J0ᵀ))``
reaches a target. The update is the extended Kalman filter of
:class:`estcal.estimate.kalman.ParameterFilter` (filterpy EKF, Joseph form)
linearised at the current estimate when that module is available, otherwise
the equations above.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.jsonio import write_json
from estcal.base.textinput import read_json
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.transforms import so3_exp
from estcal.methods.base import NoiseModel
from estcal.methods.problem import Problem

from .criteria import CRITERIA, covariance, criterion_value, larger_is_better, normalise_criterion
from .model import DesignModel
from .update import FAST_CRITERIA, added_criterion_value, whiten, woodbury_covariance

__all__ = ["CalibrationState", "NextPose", "propose_next_pose", "kalman_update", "ActiveRun",
           "active_calibration", "model_for_state", "covariance_after"]


# ------------------------------------------------------------------- state
@dataclass
class CalibrationState:
    """Current parameter estimate and covariance (free parameters only, SI units).

    JSON form: ``{"parameters": [names], "estimate": [...], "covariance": [[...]]}``.
    :meth:`from_json` also reads a :class:`~estcal.estimate.result.CalibrationResult`
    JSON (``parameters`` as ``{name: {"estimate": ...}}`` plus ``covariance``); its
    ``robot`` key, when present, is kept as :attr:`robot` (the robot it was computed for).
    """

    parameters: list
    estimate: np.ndarray
    covariance: np.ndarray
    robot: str | None = None

    def __post_init__(self):
        self.parameters = list(self.parameters)
        self.estimate = np.asarray(self.estimate, float).reshape(-1)
        self.covariance = np.asarray(self.covariance, float)
        p = len(self.parameters)
        if self.estimate.shape != (p,) or self.covariance.shape != (p, p):
            raise ValueError(f"state: {p} parameter names but estimate {self.estimate.shape} and covariance "
                             f"{self.covariance.shape}")
        if not np.all(np.isfinite(self.covariance)) or not np.all(np.isfinite(self.estimate)):
            raise ValueError("state: estimate and covariance must be finite numbers")
        # Symmetry is judged on the correlation scale: a filter's covariance is symmetric
        # only to round-off (Joseph-form updates leave |P - Pᵀ| ~ 1e-19 on entries of
        # ~1e-12), and an absolute or element-relative test rejects near-zero
        # correlations. Accepted states are then symmetrised exactly.
        d = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        scale = np.outer(d, d) + np.finfo(float).tiny
        asym = np.abs(self.covariance - self.covariance.T) / scale
        if asym.size and asym.max() > 1e-6:
            i, j = np.unravel_index(np.argmax(asym), asym.shape)
            raise ValueError(f"state: covariance is not symmetric (entries [{self.parameters[i]}, "
                             f"{self.parameters[j]}] differ by {asym[i, j]:.2g} on the correlation scale)")
        self.covariance = 0.5 * (self.covariance + self.covariance.T)

    def check_robot(self, robot, where: str = "state") -> None:
        """Raise ``ValueError`` when parameter names of the state are not ``robot``'s (a state
        written for another robot), naming ``where`` (the file), the foreign names and the robot's."""
        unknown = [n for n in self.parameters if n not in robot.params]
        if unknown:
            from estcal.kinematics.parameters import summarize_names

            raise ValueError(
                f"{where}: {len(unknown)} of the state's {len(self.parameters)} parameters are not parameters of "
                f"robot {robot.name!r} ({', '.join(unknown[:4])}{' …' if len(unknown) > 4 else ''}) — was the "
                f"state written for another robot? {robot.name} has: {summarize_names(robot.params.names)}")

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @classmethod
    def from_dict(cls, d: dict, where: str = "<dict>") -> "CalibrationState":
        if "parameters" not in d or "covariance" not in d:
            raise ValueError(f"{where}: a state needs keys 'parameters' and 'covariance' "
                             f"(and 'estimate'); got {sorted(d)}")
        par = d["parameters"]
        if isinstance(par, dict):  # CalibrationResult.to_dict()
            names = list(par)
            est = [par[n]["estimate"] if isinstance(par[n], dict) else par[n] for n in names]
        else:
            names = list(par)
            if "estimate" not in d:
                raise ValueError(f"{where}: key 'estimate' missing")
            est = d["estimate"]
        robot = d.get("robot") if isinstance(d.get("robot"), str) else None
        try:
            return cls(names, est, d["covariance"], robot)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    @classmethod
    def from_json(cls, path) -> "CalibrationState":
        path = Path(path)
        return cls.from_dict(read_json(path, "state", ValueError), str(path))

    @classmethod
    def prior(cls, model: DesignModel, std) -> "CalibrationState":
        """Nominal values of ``model.free`` with a diagonal prior ``std`` (scalar, array or {name: std})."""
        if isinstance(std, dict):
            s = np.array([std[n] for n in model.free], float)
        else:
            s = np.broadcast_to(np.asarray(std, float), (model.p,)).copy()
        return cls(list(model.free), model.theta[model.robot.params.indices(model.free)], np.diag(s ** 2))

    def to_dict(self) -> dict:
        d = {"parameters": self.parameters, "estimate": self.estimate.tolist(),
             "covariance": self.covariance.tolist(), "std": self.std.tolist()}
        if self.robot is not None:
            d["robot"] = self.robot
        return d

    def to_json(self, path) -> Path:
        return write_json(path, self.to_dict())


def model_for_state(model: DesignModel, state: CalibrationState) -> DesignModel:
    """``model`` with free parameters = the state's, linearised at the state's estimate."""
    state.check_robot(model.robot)
    theta = model.theta.copy()
    theta[model.robot.params.indices(state.parameters)] = state.estimate
    return DesignModel(model.robot, model.method, list(state.parameters), model.sigma, model.sigma_rot, None, theta)


def kalman_update(x, C, H, e, sigma):
    """One Kalman / MAP update of a constant parameter vector (Mooring 4.104, 4.106).

    ``K = C Hᵀ (H C Hᵀ + R)⁻¹``, ``x⁺ = x + K e`` (``e = y − h(x)``) and the
    Joseph form ``C⁺ = (I − K H) C (I − K H)ᵀ + K R Kᵀ`` (= (C⁻¹ + HᵀR⁻¹H)⁻¹).
    """
    H = np.atleast_2d(np.asarray(H, float))
    R = np.diag(np.broadcast_to(np.asarray(sigma, float), (H.shape[0],)) ** 2)
    S = H @ C @ H.T + R
    K = np.linalg.solve(S, H @ C).T
    IKH = np.eye(C.shape[0]) - K @ H
    Cn = IKH @ C @ IKH.T + K @ R @ K.T
    return x + K @ np.asarray(e, float), 0.5 * (Cn + Cn.T)


# ---------------------------------------------------------------- proposal
@dataclass
class NextPose:
    """The proposed pose and how much it improves the criterion of the predicted covariance."""

    readings: np.ndarray
    criterion: str
    value_before: float
    value_after: float
    joint_names: list
    n_candidates: int
    refined: bool
    predicted_std: dict = field(default_factory=dict)

    @property
    def reduction(self) -> float:
        """Relative improvement of the criterion (positive = better)."""
        if larger_is_better(self.criterion):
            return self.value_after / self.value_before - 1.0
        return 1.0 - self.value_after / self.value_before

    def to_dict(self) -> dict:
        return {"readings_rad": self.readings.tolist(), "readings_deg": np.degrees(self.readings).tolist(),
                "joint_names": self.joint_names, "criterion": self.criterion,
                "value_before": self.value_before, "value_after": self.value_after,
                "reduction": self.reduction, "n_candidates": self.n_candidates, "refined": self.refined,
                "predicted_std": self.predicted_std}

    def __str__(self) -> str:
        q = ", ".join(f"{n}={v:.4g}" for n, v in zip(self.joint_names, np.degrees(self.readings)))
        return (f"next pose ({q}) [deg]\n  {self.criterion}: {self.value_before:.6g} -> {self.value_after:.6g} "
                f"({100 * self.reduction:.2f} % better; {self.n_candidates} candidates"
                f"{', refined' if self.refined else ''})")


def covariance_after(model: DesignModel, state: CalibrationState, q) -> np.ndarray:
    """Predicted covariance after measuring the single pose ``q`` (n,):
    ``C⁺ = C − C Hᵀ (H C Hᵀ + R)⁻¹ H C`` at the state's estimate."""
    mdl = model_for_state(model, state)
    return woodbury_covariance(state.covariance, whiten(mdl.jacobian(np.asarray(q, float)[None]), mdl.row_sigma))[0]


def _values_after(crit, C, B, J_test):
    """Criterion of C⁺ for each candidate (Woodbury; general criteria via C⁺ → M⁺)."""
    if crit in FAST_CRITERIA:
        return added_criterion_value(crit, C, B, J_test)
    Cp = woodbury_covariance(C, B)
    return criterion_value(crit, covariance(Cp, allow_singular=True), 1, J_test)


def propose_next_pose(model: DesignModel, state: CalibrationState, criterion: str = "test-pose", q_test=None,
                      J_test=None, candidates=None, n_candidates: int = 2000, rng=None,
                      refine: bool = True) -> NextPose:
    """The pose whose measurement most improves ``criterion`` of the predicted covariance.

    Parameters
    ----------
    model : DesignModel (robot, method, noise); its free set is replaced by the state's.
    state : current estimate and covariance.
    q_test / J_test : test poses for ``test-pose`` / ``G`` (readings (K, n) or Jacobians).
    candidates : (K, n) readings; default ``n_candidates`` uniform within the joint limits.
    refine : polish the best candidate's joint values (L-BFGS-B within the limits).

    Notes
    -----
    O1 uses m = 1 (it ranks candidates like D for any fixed m).
    """
    crit = normalise_criterion(criterion)
    rng = np.random.default_rng(rng)
    mdl = model_for_state(model, state)
    if J_test is None and q_test is not None:
        J_test = mdl.position_jacobian(np.atleast_2d(q_test))
    if CRITERIA[crit][1] and J_test is None:
        raise ValueError(f"criterion {crit!r} needs test poses (q_test)")
    C = state.covariance
    cand = mdl.random_readings(n_candidates, rng) if candidates is None else np.asarray(candidates, float)
    B = whiten(mdl.jacobian(cand), mdl.row_sigma)
    vals = _values_after(crit, C, B, J_test)
    sign = -1.0 if larger_is_better(crit) else 1.0
    k = int(np.argmin(sign * vals))
    best_q, best_v = cand[k].copy(), float(vals[k])
    refined = False
    if refine:
        from scipy.optimize import minimize

        lim = mdl.robot.limits

        def f(q):
            Bq = whiten(mdl.jacobian(q[None]), mdl.row_sigma)
            v = float(_values_after(crit, C, Bq, J_test)[0])
            return sign * v if np.isfinite(v) else 1e300

        res = minimize(f, best_q, method="L-BFGS-B", bounds=list(zip(lim[:, 0], lim[:, 1])),
                       options={"maxiter": 100})
        if sign * res.fun < sign * best_v:
            best_q, best_v, refined = np.clip(res.x, lim[:, 0], lim[:, 1]), sign * float(res.fun), True
    Cp = covariance_after(mdl, state, best_q)
    before = float(criterion_value(crit, covariance(C), 1, J_test))
    return NextPose(best_q, crit, before, best_v, list(mdl.robot.joint_names), len(cand), refined,
                    {n: float(s) for n, s in zip(state.parameters, np.sqrt(np.diag(Cp)))})


# ------------------------------------------------------------------ loop
@dataclass
class ActiveRun:
    """History of a sequential calibration.

    ``predicted`` is ρ0 = sqrt(mean_t trace(J0_t C J0_tᵀ)) (m) after each
    measurement (index 0: before any), ``true_error`` the RMS over the test
    poses of ‖p_true − p_estimated‖ (m), ``n_reached`` the number of
    measurements at which ``predicted ≤ target`` (None if never).
    """

    strategy: str
    readings: np.ndarray
    predicted: np.ndarray
    true_error: np.ndarray
    target: float
    n_reached: int | None
    estimate: np.ndarray
    covariance: np.ndarray
    parameters: list

    def to_dict(self) -> dict:
        return {"strategy": self.strategy, "n_measurements": int(len(self.readings)),
                "predicted_m": self.predicted.tolist(), "true_error_m": self.true_error.tolist(),
                "target_m": self.target, "n_reached": self.n_reached,
                "readings_rad": self.readings.tolist(), "parameters": self.parameters,
                "estimate": self.estimate.tolist()}

    def __str__(self) -> str:
        return (f"{self.strategy}: {len(self.readings)} measurements, predicted rho0 "
                f"{self.predicted[0] * 1e3:.4g} -> {self.predicted[-1] * 1e3:.4g} mm, true error "
                f"{self.true_error[-1] * 1e3:.4g} mm, target {self.target * 1e3:.4g} mm reached at "
                f"n={self.n_reached}")


def _measure(true_robot, method, q, sigma, sigma_rot, rng, n_markers):
    """Simulated measurement of one pose by ``method`` on the true robot (dataset)."""

    kin = true_robot.kinematics(q[None], jacobian=False)
    names = true_robot.joint_names
    if method == "pose":
        R = so3_exp(rng.normal(0, sigma_rot, 3)) @ kin.R[0]
        p = kin.p[0] + rng.normal(0, sigma, 3)
        return dataset_from_arrays(names, q[None], R=R[None], p=p[None])
    if method == "points":
        pts = kin.points[0] + rng.normal(0, sigma, kin.points[0].shape)
        return dataset_from_arrays(names, q[None], points=pts[None])
    pt = kin.points[0, 0] if n_markers else kin.p[0]
    return dataset_from_arrays(names, q[None], points=(pt + rng.normal(0, sigma, 3))[None, None])


class _OwnFilter:
    """EKF with the equations of :func:`kalman_update` (used when estcal.estimate.kalman is absent)."""

    def __init__(self, theta, fidx, P0):
        self.theta0 = np.asarray(theta, float).copy()
        self.fidx = np.asarray(fidx, int)
        self.x = self.theta0[self.fidx].copy()
        self.P = np.asarray(P0, float).copy()

    def full(self, x=None):
        th = self.theta0.copy()
        th[self.fidx] = self.x if x is None else x
        return th

    def step(self, sub):
        rows = sub.evaluate(self.full())
        self.x, self.P = kalman_update(self.x, self.P, rows.H[:, self.fidx], rows.e, rows.sigma)


def active_calibration(true_robot, model: DesignModel, state0: CalibrationState, q_test, target: float,
                       strategy: str = "active", criterion: str = "test-pose", max_measurements: int = 100,
                       rng=None, n_candidates: int = 500, plan=None, refine: bool = False,
                       estimator: str = "auto", run_to_max: bool = False) -> ActiveRun:
    """Sequential calibration on a simulated robot: choose → measure → update → repeat.

    Parameters
    ----------
    true_robot : SerialRobot with the "true" parameter values (same parameter names as ``model.robot``).
    model : DesignModel (method, noise σ) of the nominal robot.
    state0 : prior estimate and covariance of the free parameters.
    q_test : (K, n) test poses; the stopping rule is predicted ρ0 ≤ ``target`` (m).
    strategy : ``'active'`` (covariance-driven :func:`propose_next_pose`), ``'random'``
        (uniform within the joint limits) or ``'plan'`` (the rows of ``plan`` in turn, cycled).
    estimator : ``'auto'`` (filterpy EKF of :mod:`estcal.estimate.kalman` if present),
        ``'ekf'`` (that one, required) or ``'own'`` (:func:`kalman_update`).
    run_to_max : continue after the target is reached (to record whole curves).
    """

    rng = np.random.default_rng(rng)
    q_test = np.atleast_2d(np.asarray(q_test, float))
    robot = model.robot
    fidx = robot.params.indices(state0.parameters)
    theta = model.theta.copy()
    theta[fidx] = state0.estimate
    flt = None
    if estimator in ("auto", "ekf"):
        try:
            from estcal.estimate.kalman import ParameterFilter

            flt = ParameterFilter(theta, fidx, state0.covariance, None, kind="ekf", names=state0.parameters)
        except ImportError:
            if estimator == "ekf":
                raise
    if flt is None:
        flt = _OwnFilter(theta, fidx, state0.covariance)
    method_name = {"position": "position", "pose": "pose", "points": "points"}[model.method]
    noise = NoiseModel(position=model.sigma, orientation=model.sigma_rot or 1.0, known=True)
    p_true = true_robot.kinematics(q_test, jacobian=False).p

    def status():
        x, P = np.asarray(flt.x, float), np.asarray(flt.P, float)
        st = CalibrationState(state0.parameters, x, 0.5 * (P + P.T))
        mdl = model_for_state(model, st)
        J0 = mdl.position_jacobian(q_test)
        pred = float(np.sqrt(np.mean(np.einsum("tap,pq,taq->t", J0, st.covariance, J0))))
        p_est = robot.kinematics(q_test, flt.full(x), jacobian=False).p
        err = float(np.sqrt(np.mean(np.sum((p_est - p_true) ** 2, -1))))
        return st, pred, err

    st, pred, err = status()
    preds, errs, taken = [pred], [err], []
    n_reached = 0 if pred <= target else None
    for i in range(max_measurements):
        if n_reached is not None and not run_to_max:
            break
        if strategy == "active":
            q = propose_next_pose(model, st, criterion, q_test=q_test, n_candidates=n_candidates, rng=rng,
                                  refine=refine).readings
        elif strategy == "random":
            q = model.random_readings(1, rng)[0]
        elif strategy == "plan":
            if plan is None:
                raise ValueError("strategy 'plan' needs plan=(m, n) readings")
            P_ = np.asarray(plan, float)
            q = P_[i % len(P_)]
        else:
            raise ValueError(f"unknown strategy {strategy!r}; choose active, random or plan")
        data = _measure(true_robot, model.method, q, model.sigma, model.sigma_rot, rng, robot.n_markers)
        flt.step(Problem(robot, [(method_name, data, noise)]))
        taken.append(q)
        st, pred, err = status()
        preds.append(pred)
        errs.append(err)
        if n_reached is None and pred <= target:
            n_reached = i + 1
    return ActiveRun(strategy, np.array(taken).reshape(-1, robot.n_joints), np.array(preds), np.array(errs),
                     float(target), n_reached, st.estimate, st.covariance, list(state0.parameters))
