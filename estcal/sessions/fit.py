"""Calibration over several sessions with a repeatability model (orchestration).

:func:`fit_sessions` estimates the population parameters θ shared by every
session, the per-session deviations ``u_s`` of a chosen subset (``vary``) and
their variance components ``Q`` (REML), by Gauss–Newton iterations on the
linearised mixed model of :mod:`estcal.sessions.system`, solved by one of the
three agreeing formulations of :mod:`estcal.sessions.formulations`
(``"gls"``, ``"gtsam"``, ``"kalman"``).

Units: SI inside (m, rad); :meth:`SessionFit.variance_components` reports the
between-session standard deviation of each varying parameter in mm (lengths)
or mrad (angles).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.base.atomic import refuse_input
from estcal.base.jsonio import to_jsonable
from estcal.base.result import Result
from estcal.base.tables import Table, parameter_table, si_unit
from estcal.base.units import display_unit
from estcal.io.savedmodel import calibration_block, write_saved_model
from estcal.methods import NoiseModel, Problem

from .formulations import solve_factor_graph, solve_gls, solve_kalman
from .system import blocks_from_rows, reml, reml_objective

__all__ = ["SessionFit", "fit_sessions", "session_problems", "SOLVERS"]

SOLVERS = {"gls": solve_gls, "gtsam": solve_factor_graph, "kalman": solve_kalman}
_ANGLE_PREFIXES = ("alpha", "theta", "beta", "rx", "ry", "rz")


def _is_angle(robot, name: str) -> bool:
    """Whether parameter ``name`` is an angle (rad) rather than a length (m) or a gain (1)."""
    pv = robot.params
    kind = pv.kinds[pv.index(name)]
    if kind == "offset":
        j = next((i for i, idx in enumerate(robot.offset_idx) if pv.names[idx] == name), None)
        return j is not None and robot.joint_types[j] == "revolute"
    return name.split("_")[0] in _ANGLE_PREFIXES or name.endswith(("_rx", "_ry", "_rz"))


@dataclass(repr=False)
class SessionFit(Result):
    """Result of :func:`fit_sessions` (the result protocol of :class:`estcal.base.result.Result`:
    ``to_dict``, ``to_json``, ``save_model``, ``table``).

    names : free parameter names; estimate (p,) and cov (p, p) their population
    values and covariance (SI); vary : the parameters that vary between sessions,
    q (k,) their variance components (SI², 0 = does not vary) with q_std; s2 :
    variance factor of the measurement noise (1 when the noise is known);
    u (n_s, k), u_cov (n_s, k, k) : each session's deviation (BLUP) and its
    prediction-error covariance; theta : the full parameter vector (population).
    """

    names: list
    estimate: np.ndarray
    cov: np.ndarray
    vary: list
    q: np.ndarray
    q_std: np.ndarray
    s2: float
    u: np.ndarray
    sessions: list
    formulation: str
    n_iterations: int
    converged: bool
    theta: np.ndarray = field(repr=False)
    robot: object = field(repr=False, default=None)
    noise: object = field(repr=False, default=None)
    reml_objective: float = float("nan")
    n_rows: int = 0
    #: the sessions' datasets (for :meth:`save_model`'s provenance; not serialised)
    datasets: list = field(default_factory=list, repr=False)
    #: files the fit was computed from: never written over
    inputs: tuple = field(default=(), repr=False)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def vary_index(self) -> np.ndarray:
        return np.array([self.names.index(n) for n in self.vary], int)

    def new_session_cov(self) -> np.ndarray:
        """Covariance of a new session's parameters: ``cov + E Q Eᵀ`` (free parameters)."""
        C = self.cov.copy()
        S = self.vary_index
        C[S, S] += self.q
        return C

    def variance_components(self) -> list[dict]:
        """Between-session std of every varying parameter, in mm / mrad (or 1 for gains)."""
        out = []
        for n, q, qs in zip(self.vary, self.q, self.q_std):
            ang = _is_angle(self.robot, n) if self.robot is not None else False
            f, unit = (1e3, "mrad") if ang else (1e3, "mm")
            sd = float(np.sqrt(q))
            # delta method: sd(√q) = sd(q) / (2√q)
            sd_err = float(qs / (2 * sd)) if sd > 0 and np.isfinite(qs) else float("nan")
            out.append({"parameter": n, "std": sd * f, "std_err": sd_err * f, "unit": unit,
                        "varies": bool(q > 0)})
        return out

    def table(self) -> Table:
        """Population estimate and std of every free parameter (mm / mrad when the robot is known)."""
        robot = self.robot
        unit = si_unit if robot is None else (lambda n: display_unit(n, robot))
        return parameter_table(self, unit, title="")

    def summary(self) -> str:
        return (f"SessionFit({self.formulation}, {len(self.sessions)} sessions, {len(self.names)} parameters, "
                f"{len(self.vary)} varying, iterations={self.n_iterations}, converged={self.converged})")

    def save_model(self, path, provenance: dict | None = None):
        """Write the population robot (every session's mean geometry) as a saved model: a robot file
        with a ``calibration:`` block holding the free names, the sessions' files, the between-session
        variance components and, as ``covariance``, that of a *new* session's parameters
        (:meth:`new_session_cov`: the population's plus Q) — what ``compensate`` should expect on a
        day not measured yet; the population's own is ``population_covariance`` (docs/repeatability.md)."""
        if self.robot is None:
            raise ValueError("this SessionFit does not know its robot; it was not made by fit_sessions")
        refuse_input(path, self.inputs)
        robot = self.robot.with_values(self.theta[: self.robot.n_params])
        block = calibration_block(estimator=f"sessions ({self.formulation})", train=list(self.datasets),
                                  free=self.names, covariance=self.new_session_cov(), noise=self.noise,
                                  sigma0=float(np.sqrt(self.s2)),
                                  covariance_source="new session: population + between-session Q (REML)",
                                  population_covariance=np.asarray(self.cov).tolist(),
                                  sessions={"names": list(self.sessions), "vary": list(self.vary)},
                                  variance_components=self.variance_components(),
                                  converged=bool(self.converged), **(provenance or {}))
        return write_saved_model(robot, block, path)

    def to_dict(self) -> dict:
        return to_jsonable({
            "formulation": self.formulation, "sessions": list(self.sessions), "n_rows": self.n_rows,
            "parameters": {n: {"estimate": float(v), "std": float(s)}
                           for n, v, s in zip(self.names, self.estimate, self.std)},
            "vary": list(self.vary), "variance_components": self.variance_components(),
            "q": self.q.tolist(), "q_std": self.q_std.tolist(), "s2": self.s2,
            "session_deviations": {s: dict(zip(self.vary, map(float, u))) for s, u in zip(self.sessions, self.u)},
            "n_iterations": self.n_iterations, "converged": self.converged,
            "reml_objective": self.reml_objective})


def session_problems(robot, datasets, noise):
    """One :class:`estcal.methods.Problem` per session, all on the same robot."""
    return [Problem(robot, [(None, ds, noise)], noise) for ds in datasets]


def _linearise(problems, theta, free_idx, S, u):
    A_list, r_list = [], []
    for s, prob in enumerate(problems):
        th = theta.copy()
        th[free_idx[S]] += u[s]
        rows = prob.evaluate(th)
        w = 1.0 / rows.sigma
        A = rows.H[:, free_idx] * w[:, None]
        r = rows.e * w + A[:, S] @ u[s]  # pseudo-data: the session's current deviation added back
        A_list.append(A)
        r_list.append(r)
    return A_list, r_list


def fit_sessions(robot, datasets, free, vary=(), *, noise=None, q=None, formulation: str = "gls",
                 theta=None, max_iter: int = 30, tol: float = 1e-9, session_names=None) -> SessionFit:
    """Fit the repeatability model ``θ_s = θ + E u_s, u_s ~ N(0, Q)`` to several sessions.

    Parameters
    ----------
    robot : SerialRobot (its values are the starting point unless ``theta`` is given).
    datasets : list of Dataset, one per session (same robot, same markers).
    free : free parameter names (population θ).
    vary : subset of ``free`` that varies between sessions.
    noise : :class:`estcal.methods.NoiseModel`; with ``known=False`` the variance factor s² is
        estimated with Q by REML.
    q : fixed variance components (SI², one per ``vary``), or None to estimate them by REML.
    formulation : ``"gls"``, ``"gtsam"`` or ``"kalman"`` (:mod:`estcal.sessions.formulations`).
    """
    if formulation not in SOLVERS:
        raise ValueError(f"unknown formulation {formulation!r}; choose one of {sorted(SOLVERS)}")
    noise = noise or NoiseModel()
    free = list(free)
    vary = list(vary)
    missing = [n for n in vary if n not in free]
    if missing:
        raise ValueError(f"vary: {missing} are not free parameters; a varying parameter must be estimated")
    if len(datasets) < 1:
        raise ValueError("fit_sessions needs at least one session")
    problems = session_problems(robot, datasets, noise)
    pv = problems[0].params
    free_idx = np.array(pv.indices(free), int)
    S = np.array([free.index(n) for n in vary], int)
    theta = (pv.values if theta is None else np.asarray(theta, float)).copy()
    n_s, k = len(datasets), len(S)
    u = np.zeros((n_s, k))
    solver = SOLVERS[formulation]
    estimate_q = q is None and k > 0
    qv = np.zeros(k) if q is None else np.asarray(q, float).copy()
    if qv.shape != (k,):
        raise ValueError(f"q must have one variance per varying parameter ({k}), got shape {qv.shape}")
    s2 = 1.0
    A_list, r_list = _linearise(problems, theta, free_idx, S, u)
    # column scaling (fixed from the first linearisation) keeps N well conditioned across m / rad / 1
    c = np.sqrt(sum(np.einsum("ij,ij->j", A, A) for A in A_list))
    c = np.where(c > 0, c, 1.0)
    _check_rank(A_list, c, free)
    converged = False
    obj = float("nan")
    it = 0
    for it in range(1, max_iter + 1):
        As = [A / c for A in A_list]
        blocks = [blocks_from_rows(A, r) for A, r in zip(As, r_list)]
        qs = qv * c[S] ** 2
        if estimate_q or not noise.known:
            if estimate_q:
                qs, s2, _, info = reml(blocks, S, q0=qs if it > 1 else None, estimate_scale=not noise.known,
                                       scale0=s2, q_max=1e10)
            else:
                qs, s2 = _scale_only(blocks, S, qs, s2)
        delta_s, cov_s, u_s = solver(As, r_list, S, qs, s2)
        delta = delta_s / c
        theta[free_idx] += delta
        u = u_s / c[S] if k else u
        qv = qs / c[S] ** 2 if k else qv
        step = np.max(np.abs(delta_s) / np.sqrt(np.maximum(np.diag(cov_s), 1e-300)))
        A_list, r_list = _linearise(problems, theta, free_idx, S, u)
        if step < tol ** 0.5 * 1e-2 or step < 1e-6:
            converged = True
            break
    # final solve and uncertainties at the converged linearisation
    As = [A / c for A in A_list]
    blocks = [blocks_from_rows(A, r) for A, r in zip(As, r_list)]
    qs = qv * c[S] ** 2
    q_std = np.full(k, np.nan)
    if estimate_q:
        qs, s2, qstd_s, info = reml(blocks, S, q0=qs, estimate_scale=not noise.known, scale0=s2, q_max=1e10)
        q_std = qstd_s / c[S] ** 2
    delta_s, cov_s, u_s = solver(As, r_list, S, qs, s2)
    theta[free_idx] += delta_s / c
    obj = reml_objective(blocks, S, qs, s2)
    cov = cov_s / np.outer(c, c)
    return SessionFit(free, theta[free_idx].copy(), cov, vary, qs / c[S] ** 2 if k else np.zeros(0), q_std,
                      float(s2), u_s / c[S] if k else np.zeros((n_s, 0)),
                      list(session_names or [getattr(d, "where", None) or f"session{i + 1}"
                                             for i, d in enumerate(datasets)]),
                      formulation, it, converged, theta, problems[0].robot, noise, float(obj),
                      int(sum(A.shape[0] for A in A_list)), datasets=list(datasets),
                      inputs=tuple(p for d in datasets if (p := getattr(d, "path", None))))


def _check_rank(A_list, c, free, max_cond: float = 1e10):
    """Refuse a free set that the sessions' data cannot determine, naming the parameters: the one
    identifiable-set entry (:func:`estcal.identify.select.select_identifiable`, structural tolerance) on the
    stacked, column-scaled Jacobians of all sessions — a parameter without effect or dependent on the
    others — and, as before, a set whose normal matrix has a condition number above ``max_cond``
    (independent but not determined by noisy data)."""
    from estcal.identify.select import select_identifiable

    W = np.vstack([A / c for A in A_list])
    sel = select_identifiable(W, names=list(free))
    bad = list(sel.no_effect) + list(sel.regrouped)
    if bad or sel.condition_number ** 2 > max_cond:
        why = (f"{bad} have no effect or depend on the others" if bad else
               f"condition number {sel.condition_number ** 2:.3g} of the normal matrix")
        raise ValueError(f"the free parameters are not identifiable from these sessions ({why}): fix some of them "
                         f"or choose the free set with estcal.estimate.levels.select_free on the stacked sessions")


def _scale_only(blocks, S, q, s2):
    """REML variance factor s² with fixed q (unknown noise level, known Q)."""
    from scipy import optimize

    res = optimize.minimize_scalar(lambda ls: reml_objective(blocks, S, q, float(np.exp(ls))),
                                   bounds=(np.log(1e-6), np.log(1e6)), method="bounded")
    return q, float(np.exp(res.x))
