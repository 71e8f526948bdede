r"""Classical (unconstrained) calibration of a Gough platform, identifiability, CLI entry points.

Two residual models over the 42 (Model 42) or 36 (Model 36) parameters:

* **Inverse kinematics** (``residual="ik"``): for each measured platform pose
  ``T_i`` and leg readings ``ρ_i`` (6), ``r_ik = ρ_ik − (‖P_i + R_i b_k − a_k‖ − Δρ_k)``;
  Jacobian ``∂r/∂θ = −∂ρ/∂θ`` (analytic, :meth:`GoughPlatform.leg_jacobians`).
* **Forward kinematics** (``residual="fk"``): the pose predicted from the
  measured readings by the numerical FK, compared with the measured pose,
  ``e_i = (p_meas − p_fk, log(R_meas R_fkᵀ))`` (estcal pose-error
  convention). By the implicit function theorem on ``ρ(x, θ) = ρ_meas``,
  ``∂x_fk/∂θ = −J_x⁻¹ J_θ``, so ``∂e_p/∂θ = (J_x⁻¹ J_θ)_p`` and
  ``∂e_r/∂θ = J_r⁻¹(e_r) (J_x⁻¹ J_θ)_r`` with the right Jacobian of SO(3).

Estimation is weighted nonlinear least squares. Residual standard deviations
are ``sigma_rho`` for IK (optionally inflated by the propagated pose noise,
``σ²_ik = σ_ρ² + J_x,k Σ_pose J_x,kᵀ``), and ``sigma_p``/``sigma_r`` for FK.
Covariance of the estimate: ``Σ_θ = s² (Jᵀ W J)⁻¹`` with ``s² = χ²/(m − p)``
when no absolute noise level is given (``scale_covariance=True``), else 1.

Identifiability is the shared priority-ordered QR of the (weighted) stacked
Jacobian, :func:`estcal.identify.core.identifiable` (GECARO App. III): columns
with zero norm have *no effect*; dependent columns are *regrouped* into the
identifiable ones (coefficients ``R11⁻¹ R12``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.linalg
import scipy.optimize

from estcal.kinematics.transforms import so3_right_jacobian_inv

from ._rot import euler_zyx_to_matrix, make_T, matrix_to_euler_zyx, so3_exp, so3_log
from .daney import generate_random_poses
from .gough import N_LEGS, GoughPlatform, load_gough, split_pose

__all__ = [
    "GoughData",
    "GoughProblem",
    "GoughCalibrationResult",
    "simulate_gough_data",
    "load_gough_data",
    "identifiable_gough",
    "calibrate_gough",
    "ESTIMATORS",
]


# ---------------------------------------------------------------- data
@dataclass
class GoughData:
    """Measured platform poses (base frame) and leg readings.

    Attributes
    ----------
    T : (N, 4, 4) measured ``T_base_platform``.
    rho : (N, 6) leg-sensor readings [m].
    sigma_rho, sigma_p, sigma_r : noise standard deviations (m, m, rad) if known.
    """

    T: np.ndarray
    rho: np.ndarray
    sigma_rho: float | None = None
    sigma_p: float | None = None
    sigma_r: float | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.T = np.asarray(self.T, float).reshape(-1, 4, 4)
        self.rho = np.asarray(self.rho, float).reshape(-1, N_LEGS)
        if len(self.T) != len(self.rho):
            raise ValueError(f"{self.source}: {len(self.T)} poses but {len(self.rho)} rows of leg readings")
        bad = ~np.isfinite(self.T).all(axis=(1, 2)) | ~np.isfinite(self.rho).all(axis=1)
        if bad.any():
            raise ValueError(f"{self.source}: non-finite values in rows {np.flatnonzero(bad)[:10].tolist()}")

    def __len__(self) -> int:
        return len(self.T)

    def subset(self, idx) -> "GoughData":
        return GoughData(self.T[idx], self.rho[idx], self.sigma_rho, self.sigma_p, self.sigma_r, self.source)

    def to_dict(self) -> dict:
        """JSON form: position [m], ZYX Euler angles [rad], readings [m]."""
        P, R = split_pose(self.T)
        return {"n_poses": len(self), "position": P.tolist(), "euler_zyx": matrix_to_euler_zyx(R).tolist(),
                "rho": self.rho.tolist(), "sigma_rho": self.sigma_rho, "sigma_p": self.sigma_p,
                "sigma_r": self.sigma_r}

    def save_csv(self, path: str | Path) -> None:
        """CSV with header ``x,y,z,psi,theta,phi,rho1..rho6`` (m, ZYX Euler rad, m)."""
        P, R = split_pose(self.T)
        arr = np.c_[P, matrix_to_euler_zyx(R), self.rho]
        hdr = "x,y,z,psi,theta,phi," + ",".join(f"rho{k}" for k in range(1, 7))
        from estcal.base.atomic import atomic_write

        with atomic_write(path) as fh:
            np.savetxt(fh, arr, delimiter=",", header=hdr, comments="", fmt="%.12g")


def load_gough_data(path: str | Path) -> GoughData:
    """Read measurements from CSV, NPZ or JSON.

    * CSV: header row with columns ``x,y,z`` (m), orientation as ``psi,theta,phi``
      (ZYX Euler, rad) or ``qw,qx,qy,qz`` (scalar-first, as the serial
      datasets), and the leg readings ``rho1..rho6`` (or ``leg1..6``, ``q1..6``) in m.
    * NPZ: arrays ``T`` (N,4,4) and ``rho`` (N,6) (optional scalars ``sigma_*``).
    * JSON: the output of :meth:`GoughData.to_dict`.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"Gough measurement file not found: {p}")
    suf = p.suffix.lower()
    if suf == ".npz":
        z = np.load(p)
        kw = {k: float(z[k]) for k in ("sigma_rho", "sigma_p", "sigma_r") if k in z.files}
        for key in ("T", "rho"):
            if key not in z.files:
                raise ValueError(f"{p}: NPZ needs arrays 'T' and 'rho' (found {z.files})")
        return GoughData(z["T"], z["rho"], source=str(p), **kw)
    if suf == ".json":
        d = json.loads(p.read_text())
        T = make_T(np.asarray(d["position"], float), euler_zyx_to_matrix(np.asarray(d["euler_zyx"], float)))
        return GoughData(T, d["rho"], d.get("sigma_rho"), d.get("sigma_p"), d.get("sigma_r"), str(p))
    with p.open() as fh:
        header = fh.readline().strip().lstrip("#").strip()
    cols = [c.strip() for c in header.split(",")]
    arr = np.atleast_2d(np.loadtxt(p, delimiter=",", skiprows=1))
    if arr.shape[1] != len(cols):
        raise ValueError(f"{p}: header has {len(cols)} columns but rows have {arr.shape[1]}")
    ix = {c: i for i, c in enumerate(cols)}

    def col(names):
        missing = [n for n in names if n not in ix]
        if missing:
            raise ValueError(f"{p}: missing column(s) {missing}; header is {cols}")
        return arr[:, [ix[n] for n in names]]

    P = col(["x", "y", "z"])
    if "psi" in ix:
        R = euler_zyx_to_matrix(col(["psi", "theta", "phi"]))
    elif "qw" in ix:
        q = col(["qw", "qx", "qy", "qz"])
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        w, x, y, z = q.T
        R = np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
    else:
        raise ValueError(f"{p}: orientation columns psi,theta,phi or qw,qx,qy,qz required; header is {cols}")
    for prefix in ("rho", "leg", "q"):
        if all(f"{prefix}{k}" in ix for k in range(1, 7)):
            rho = col([f"{prefix}{k}" for k in range(1, 7)])
            break
    else:
        raise ValueError(f"{p}: leg readings needed as columns rho1..rho6 (or leg1..leg6, q1..q6) in m; "
                         f"header is {cols}")
    return GoughData(make_T(P, R), rho, source=str(p))


def simulate_gough_data(
    robot: GoughPlatform,
    n_poses: int,
    rng: np.random.Generator | int = 0,
    sigma_rho: float = 0.0,
    sigma_p: float = 0.0,
    sigma_r: float = 0.0,
    T: np.ndarray | None = None,
) -> GoughData:
    """Synthetic measurements: random workspace poses (or ``T``), exact readings
    from ``robot`` (the *true* robot), Gaussian noise on readings (σ_ρ), on
    position components (σ_p) and as a world-frame rotation vector (σ_r)."""
    rng = np.random.default_rng(rng)
    T = generate_random_poses(robot, n_poses, rng) if T is None else np.asarray(T, float).reshape(-1, 4, 4)
    rho = robot.leg_lengths(T) + rng.normal(0, sigma_rho, (len(T), N_LEGS))
    P, R = split_pose(T)
    Tm = make_T(P + rng.normal(0, sigma_p, P.shape), so3_exp(rng.normal(0, sigma_r, P.shape)) @ R)
    return GoughData(Tm, rho, sigma_rho or None, sigma_p or None, sigma_r or None, "simulated")


# ---------------------------------------------------------------- problem
#: Relative weights used when a noise level is not given (the defaults of
#: :class:`estcal.methods.base.NoiseModel`); the covariance is then rescaled
#: by the residual variance, so only their ratios matter.
DEFAULT_SIGMA = {"rho": 1e-4, "position": 1e-4, "orientation": 1e-3}


class GoughProblem:
    """Weighted residual ``r(x)`` and Jacobian for the free parameters ``x``.

    Generic interface usable by any least-squares/Bayesian estimator:
    ``x0``, ``names``, ``residual(x)``, ``jacobian(x)`` (both whitened, i.e.
    divided by the residual standard deviations), ``n_residuals``.
    """

    def __init__(self, robot: GoughPlatform, data: GoughData, residual: str = "ik", model: int = 42,
                 free: Sequence[str] | None = None, theta0: np.ndarray | None = None,
                 sigma_rho: float | None = None, sigma_p: float | None = None, sigma_r: float | None = None,
                 propagate_pose_noise: bool = True):
        if residual not in ("ik", "fk"):
            raise ValueError(f"residual must be 'ik' or 'fk', got {residual!r}")
        self.robot, self.data, self.kind = robot, data, residual
        self.pv = robot.parameter_vector(model)
        if theta0 is not None:
            self.pv.values = np.asarray(theta0, float).reshape(42).copy()
        if free is not None:
            self.pv = self.pv.with_free(free)
        self.sigma_rho = sigma_rho if sigma_rho is not None else data.sigma_rho
        self.sigma_p = sigma_p if sigma_p is not None else data.sigma_p
        self.sigma_r = sigma_r if sigma_r is not None else data.sigma_r
        self.propagate = propagate_pose_noise
        self.fk_failures = 0

    @property
    def names(self) -> list[str]:
        return self.pv.free_names

    @property
    def x0(self) -> np.ndarray:
        return self.pv.to_flat()

    @property
    def n_residuals(self) -> int:
        return 6 * len(self.data)

    @property
    def absolute_sigma(self) -> bool:
        """True when all noise levels the residual needs are given (then the
        covariance is not rescaled by the residual variance)."""
        if self.kind == "ik":
            return self.sigma_rho is not None
        return self.sigma_p is not None and self.sigma_r is not None

    def theta(self, x: np.ndarray) -> np.ndarray:
        return self.pv.from_flat(x)

    # IK --------------------------------------------------------------
    def pose_covariance(self) -> np.ndarray:
        """Covariance (n, 6, 6) of the 6 residuals of each pose.

        IK: ``C = σ_ρ² I + J_x Σ_pose J_xᵀ`` — a pose-measurement error moves
        all six predicted lengths, so the residuals of one pose are correlated.
        FK: ``C = Σ_pose + σ_ρ² J_x⁻¹ J_x⁻ᵀ`` (reading noise through the FK).
        ``Σ_pose = diag(σ_p² I3, σ_r² I3)``. Missing levels: σ_ρ defaults to
        :data:`DEFAULT_SIGMA` for IK and contributes nothing to FK; pose levels
        default for FK and contribute nothing to IK. Evaluated once, at the
        measured poses and the initial parameters, so the weights are fixed
        during the estimation (a proper weighted least-squares cost).
        """
        if getattr(self, "_cov", None) is None:
            theta = self.pv.values
            n = len(self.data)
            _, Jx = self.robot.leg_jacobians(self.data.T, theta)
            sp, sr, srho = self.sigma_p, self.sigma_r, self.sigma_rho
            if self.kind == "ik":
                srho = srho if srho is not None else DEFAULT_SIGMA["rho"]
                C = np.broadcast_to(np.eye(6) * srho**2, (n, 6, 6)).copy()
                if self.propagate and (sp or sr):
                    w = np.r_[np.full(3, (sp or 0.0) ** 2), np.full(3, (sr or 0.0) ** 2)]
                    C += np.einsum("nki,i,nli->nkl", Jx, w, Jx)
            else:
                sp = sp if sp is not None else DEFAULT_SIGMA["position"]
                sr = sr if sr is not None else DEFAULT_SIGMA["orientation"]
                C = np.broadcast_to(np.diag(np.r_[np.full(3, sp**2), np.full(3, sr**2)]), (n, 6, 6)).copy()
                if self.propagate and srho:
                    Jinv = np.linalg.inv(Jx)
                    C += srho**2 * Jinv @ np.swapaxes(Jinv, -1, -2)
            self._cov = C
            self._Linv = np.linalg.inv(np.linalg.cholesky(C))
        return self._cov

    def subset(self, idx) -> "GoughProblem":
        """The same problem restricted to poses ``idx`` (weights kept)."""
        import copy

        self.pose_covariance()
        sub = copy.copy(self)
        idx = np.asarray(idx, int)
        sub.data = self.data.subset(idx)
        sub._cov, sub._Linv = self._cov[idx], self._Linv[idx]
        return sub

    def _fk(self, theta):
        fk = self.robot.forward_kinematics(self.data.rho, theta, guess=self.data.T, n_starts=2, tol=1e-13)
        self.fk_failures = fk.n_failed
        return fk

    def raw_rows(self, theta: np.ndarray, jacobian: bool = True):
        """Unwhitened residual rows at the full (42,) ``theta``.

        Returns ``e`` (m,) = measured − predicted, ``dE`` (m, 42) = ∂e/∂θ
        (or None), ``sigma`` (m,), ``pose`` (m,) source pose index and
        ``kind`` (m,) row kind (0 position m, 1 orientation rad, 2 scalar m).
        ``sigma`` is the square root of the diagonal of :meth:`pose_covariance`;
        the estimators use the decorrelated rows of :meth:`whitened`.
        """
        n = len(self.data)
        pose = np.repeat(np.arange(n), 6)
        if self.kind == "ik":
            # leg lengths inline (hot path of the samplers: no pose re-splitting)
            th = np.asarray(theta, float).reshape(N_LEGS, 7)
            T = self.data.T
            v = T[:, None, :3, 3] + np.einsum("nij,kj->nki", T[:, :3, :3], th[:, 3:6]) - th[None, :, 0:3]
            e = (self.data.rho - (np.sqrt(np.einsum("nki,nki->nk", v, v)) - th[:, 6])).reshape(-1)
            s = np.sqrt(np.diagonal(self.pose_covariance(), axis1=1, axis2=2)).reshape(-1)
            dE = None
            if jacobian:
                Jt, _ = self.robot.leg_jacobians(self.data.T, theta)
                dE = -Jt.reshape(-1, 42)
            return e, dE, s, pose, np.full(6 * n, 2)
        fk = self._fk(theta)
        ok = fk.success
        Pm, Rm = split_pose(self.data.T)
        e = np.zeros((n, 6))
        Tf = fk.T[ok]
        e[ok, :3] = Pm[ok] - Tf[:, :3, 3]
        e[ok, 3:] = so3_log(Rm[ok] @ np.swapaxes(Tf[:, :3, :3], -1, -2))
        s = np.sqrt(np.diagonal(self.pose_covariance(), axis1=1, axis2=2)).reshape(-1)
        kind = np.tile(np.r_[0, 0, 0, 1, 1, 1], n)
        dE = None
        if jacobian:
            J = np.zeros((n, 6, 42))
            if ok.any():
                Jt, Jx = self.robot.leg_jacobians(Tf, theta)
                dx = np.linalg.solve(Jx, Jt)  # = -∂x_fk/∂θ
                # exact derivative of log(exp(e) exp(-δ)) w.r.t. δ is -J_r⁻¹(e) (right Jacobian of SO(3))
                dx[:, 3:] = np.einsum("nij,njk->nik", so3_right_jacobian_inv(e[ok, 3:]), dx[:, 3:])
                J[ok] = dx
            dE = J.reshape(-1, 42)
        return e.reshape(-1), dE, s, pose, kind

    def whitened(self, theta: np.ndarray, jacobian: bool = True):
        """Decorrelated rows ``L_i⁻¹ e_i`` and ``L_i⁻¹ ∂e_i/∂θ`` (``C_i = L_i L_iᵀ``)
        at the full ``theta``: unit-variance, independent residuals (m,), (m, 42)."""
        e, dE, _, pose, kind = self.raw_rows(theta, jacobian)
        self.pose_covariance()
        n = len(self.data)
        r = np.einsum("nij,nj->ni", self._Linv, e.reshape(n, 6)).reshape(-1)
        J = None if dE is None else np.einsum("nij,njk->nik", self._Linv, dE.reshape(n, 6, -1)).reshape(6 * n, -1)
        return r, J, pose, kind

    def residual_and_jacobian(self, x: np.ndarray, jacobian: bool = True):
        """Whitened residual (m,) and Jacobian (m, p) w.r.t. the free parameters."""
        r, J, _, _ = self.whitened(self.theta(x), jacobian)
        if not jacobian:
            return r, None
        return r, J[:, self.pv.free]

    def residual(self, x: np.ndarray) -> np.ndarray:
        return self.residual_and_jacobian(x, jacobian=False)[0]

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return self.residual_and_jacobian(x)[1]


class _Noise:
    def __init__(self, known: bool):
        self.known = known


class _Data:
    """Dataset-like view of the Gough measurements for the shared estimators.

    ``kind = "none"`` tells :func:`estcal.estimate.lsq.score` there is no
    serial-chain accuracy to report; ``subset`` lets
    :class:`estcal.estimate._common.GroupedProblem` split the problem by pose
    (a Kalman step or a factor then evaluates only its own poses).
    """

    kind = "none"

    def __init__(self, prob: GoughProblem):
        self.prob = prob
        self.n = len(prob.data)
        self.where = f"{prob.data.source} (Gough {prob.kind.upper()} residuals)"
        self.context: dict = {}

    def subset(self, idx) -> "_Data":
        return _Data(self.prob.subset(idx))


class _Method:
    """Measurement-method-like object: the Gough IK or FK residual rows."""

    def __init__(self, residual: str):
        self.name = f"gough-{residual}"

    def rows(self, robot, theta, data: _Data, noise, jacobian: bool = True):
        from estcal.methods.base import Rows

        # decorrelated rows (unit σ): the shared estimators only use e/σ and H/σ
        r, J, pose, kind = data.prob.whitened(np.asarray(theta, float)[:42], jacobian)
        return Rows(r, None if J is None else -J, np.ones(len(r)), pose, kind)


class _Term:
    def __init__(self, prob: GoughProblem):
        self.method = _Method(prob.kind)
        self.data = _Data(prob)
        self.noise = _Noise(prob.absolute_sigma)


class GoughEstimationProblem:
    """Adapter giving a :class:`GoughProblem` the interface of
    :class:`estcal.methods.problem.Problem`, so the shared estimators of
    :mod:`estcal.estimate` (registry names ``lm``, ``gauss-newton``,
    ``iterated-lls``, ``scipy-lm``, ``gtsam``, ``kalman``, ``mcmc`` …) run on a
    Gough platform unchanged.

    ``evaluate(theta)`` returns :class:`estcal.methods.base.Rows` with
    ``e`` = measured − predicted, ``H = −∂e/∂θ`` (= ∂predicted/∂θ), one σ per row.
    """

    def __init__(self, prob: GoughProblem):
        self._prob = prob
        self.robot = prob.robot
        self.terms = [_Term(prob)]

    @property
    def params(self):
        return self._prob.pv

    def evaluate(self, theta=None, jacobian: bool = True):
        from estcal.methods.base import Rows

        theta = self.params.values if theta is None else np.asarray(theta, float)
        t = self.terms[0]
        r = t.method.rows(self.robot, theta, t.data, t.noise, jacobian)
        return Rows(r.e, r.H, r.sigma, r.pose, r.kind, np.zeros(len(r.e), int))

    def _copy(self, pv):
        import copy

        prob = copy.copy(self._prob)
        prob.pv = pv
        return GoughEstimationProblem(prob)

    def with_free(self, names) -> "GoughEstimationProblem":
        return self._copy(self.params.with_free(names))

    def with_values(self, theta) -> "GoughEstimationProblem":
        return self._copy(self.params.with_values(theta))

    def __repr__(self) -> str:
        return f"GoughEstimationProblem({self.robot.name!r}, {self._prob.kind}, {len(self._prob.data)} poses, " \
               f"{int(self.params.free.sum())} free)"


# ---------------------------------------------------------------- identifiability
def _identify(J: np.ndarray, names: Sequence[str]) -> dict:
    """Identifiability of the columns of the whitened Jacobian ``J``: the shared
    :func:`estcal.identify.core.identifiable` (GECARO App. III, sequential QR in parameter
    order, structural tolerance :data:`estcal.identify.core.STRUCTURAL_TOL`). Returns its dict
    (``n_parameters, n_identifiable, identifiable, no_effect, regrouped ({parameter,
    relation: {base: coefficient}}), condition_number`` …)."""
    from estcal.identify.core import identifiable

    out = identifiable(J, list(names)).to_dict()
    for g in out["regrouped"]:
        g.setdefault("combination", dict(g["relation"]))  # key of the earlier Gough-only analysis
    out["backend"] = "estcal.identify"
    return out


def identifiable_gough(
    robot: GoughPlatform | str | Path | Mapping,
    data: GoughData | str | Path | None = None,
    residual: str = "ik",
    model: int = 42,
    n_poses: int = 50,
    seed: int = 0,
    free: Sequence[str] | None = None,
) -> dict:
    """Identifiability of the Gough parameters (entry point for ``estcal identifiable``).

    Uses the measured poses of ``data`` if given, else ``n_poses`` random
    workspace poses (noise-free, from ``seed``). The analysis is the shared
    :func:`estcal.identify.core.identifiable` on the whitened Jacobian. Returns its dict (``n_parameters,
    n_identifiable, identifiable, no_effect, regrouped, condition_number`` …)
    plus ``robot``, ``model``, ``residual``, ``n_poses``.
    """
    robot = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    if data is None:
        data = simulate_gough_data(robot, n_poses, seed)
    elif not isinstance(data, GoughData):
        data = load_gough_data(data)
    prob = GoughProblem(robot, data, residual, model, free)
    J = prob.jacobian(prob.x0)
    out = _identify(J, prob.names)
    out.update({"robot": robot.name, "model": model, "residual": residual, "n_poses": len(data)})
    return out


# ---------------------------------------------------------------- result
@dataclass
class GoughCalibrationResult:
    """Outcome of a Gough calibration; ``parameters[name] = {estimate, std, initial}`` (SI).

    ``rmse`` is the RMS of the leg-reading residuals (IK) or of the position
    residual components (FK), in m; for FK ``extra["rmse_rotation_rad"]``
    holds that of the orientation components. ``std`` is None for free
    parameters found unidentifiable (kept at their initial value).
    """

    method: str
    residual: str
    model: int
    parameters: dict
    rmse: float
    n_iterations: int
    converged: bool
    covariance: np.ndarray
    free_names: list
    theta: np.ndarray
    identifiability: dict
    chi2: float
    n_residuals: int
    fk_failures: int = 0
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "method": self.method, "residual": self.residual, "model": self.model,
            "parameters": self.parameters, "rmse": self.rmse, "n_iterations": self.n_iterations,
            "converged": self.converged, "chi2": self.chi2, "n_residuals": self.n_residuals,
            "fk_failures": self.fk_failures,
            "identifiability": {k: v for k, v in self.identifiability.items()},
            "covariance": {"names": self.free_names, "matrix": np.asarray(self.covariance).tolist()},
            "extra": self.extra,
        }

    def __str__(self) -> str:
        # printed in mm like every estcal table (every Gough parameter is a length); to_dict() is SI
        rot = self.extra.get("rmse_rotation_rad")
        rows = [f"Gough calibration ({self.method}, {self.residual.upper()} residuals, Model {self.model}): "
                f"rmse {self.rmse * 1e3:.4g} mm" + ("" if rot is None else f" / {rot * 1e3:.4g} mrad")
                + f", {self.n_iterations} iterations, {'converged' if self.converged else 'NOT converged'}",
                f"{'parameter':<10}{'initial mm':>14}{'estimate mm':>14}{'std mm':>12}"]
        for n, v in self.parameters.items():
            std = "—" if v["std"] is None else f"{v['std'] * 1e3:.3e}"
            rows.append(f"{n:<10}{v['initial'] * 1e3:>14.6g}{v['estimate'] * 1e3:>14.6g}{std:>12}")
        ide = self.identifiability
        if ide.get("regrouped") or ide.get("no_effect"):
            rows.append(f"not identifiable (kept at initial value): "
                        f"{ide.get('no_effect', []) + [r['parameter'] for r in ide.get('regrouped', [])]}")
        return "\n".join(rows)


# ---------------------------------------------------------------- estimators
def _lm(prob: GoughProblem, x0: np.ndarray, max_iter: int = 100):
    res = scipy.optimize.least_squares(
        lambda x: prob.residual_and_jacobian(x, jacobian=False)[0], x0,
        jac=lambda x: prob.jacobian(x), method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14,
        max_nfev=max_iter * (len(x0) + 1))
    return res.x, int(res.nfev), bool(res.success), {"message": res.message}


def _gauss_newton(prob: GoughProblem, x0: np.ndarray, max_iter: int = 50, tol: float = 1e-12):
    x = x0.copy()
    r, J = prob.residual_and_jacobian(x)
    cost = r @ r
    for it in range(1, max_iter + 1):
        dx = scipy.linalg.lstsq(J, -r)[0]
        step = 1.0
        while step > 1e-6:
            xn = x + step * dx
            rn, Jn = prob.residual_and_jacobian(xn)
            if rn @ rn <= cost:
                break
            step /= 2
        x, r, J, cost_old, cost = xn, rn, Jn, cost, rn @ rn
        if np.max(np.abs(step * dx)) < tol * (1 + np.max(np.abs(x))) or abs(cost_old - cost) <= 1e-15 * max(cost, 1e-300):
            return x, it, True, {}
    return x, max_iter, False, {}


def _kalman(prob: GoughProblem, x0: np.ndarray, prior_std: float | None = None, max_passes: int = 15,
            tol: float = 1e-9):
    """Iterated extended Kalman filter over the poses (static parameter state).

    Each pose contributes a 6-row whitened measurement (R = I). A pass runs
    the filter over all poses from the prior ``(x0, prior_std² I)`` — or, by default, a
    diffuse prior centred on the previous pass' estimate ``lin`` (so the converged
    estimate carries no prior bias) — with the
    measurement model linearised at the previous pass' estimate; passes are
    repeated until the estimate stops moving (iterated EKF ≡ Gauss–Newton on
    prior + data). The default prior is diffuse relative to the data
    (``prior_std_j² = 1e8 / (JᵀJ)_jj`` per parameter), so the result is the recursive
    least-squares solution.
    """
    n = len(prob.data)
    p = len(x0)
    x = x0.copy()
    if prior_std is None:
        # diffuse per parameter: each column's prior information is 1e-8 of its data
        # information, so the prior biases by ~1e-8 σ while the Joseph update keeps
        # ~8 significant digits (one scale for all columns lost 12 digits on the weak ones)
        J0 = prob.jacobian(x0)
        info = np.sum(J0**2, axis=0)
        P0 = np.diag(1e8 / np.maximum(info, 1e-300 + 1e-12 * info.max()))
    else:
        P0 = np.eye(p) * prior_std**2
    for it in range(1, max_passes + 1):
        lin = x.copy()
        r_all, J_all = prob.residual_and_jacobian(lin)
        r_all, J_all = r_all.reshape(n, 6), J_all.reshape(n, 6, p)
        # the diffuse default is centred on the linearisation point: at the fixed point
        # x = lin it contributes nothing (no bias), elsewhere it only damps the step like
        # LM's μ; a user prior (prior_std) is information about x0 and stays there
        xk, P = (lin if prior_std is None else x0).copy(), P0.copy()
        for i in range(n):
            # whitened measurement linearised at `lin`: r_i(x) ≈ r_i(lin) + H (x − lin)
            H = J_all[i]
            innov = -(r_all[i] + H @ (xk - lin))
            S = H @ P @ H.T + np.eye(6)
            K = np.linalg.solve(S, H @ P).T
            xk = xk + K @ innov
            IKH = np.eye(p) - K @ H
            P = IKH @ P @ IKH.T + K @ K.T  # Joseph form keeps P symmetric positive
        x = xk
        if np.max(np.abs(x - lin)) < tol * (1 + np.max(np.abs(x))):
            return x, it, True, {}
    return x, max_passes, False, {}


def _gtsam(prob: GoughProblem, x0: np.ndarray, max_iter: int = 100):
    import gtsam

    key = gtsam.symbol("t", 0)
    graph = gtsam.NonlinearFactorGraph()
    n = len(prob.data)
    noise = gtsam.noiseModel.Unit.Create(6)

    # one factor per pose (each evaluates the batch; small n in practice)
    cache: dict = {}

    def batched(x):
        k = x.tobytes()
        if k not in cache:
            cache.clear()
            cache[k] = prob.residual_and_jacobian(x)
        return cache[k]

    def make_cached(i):
        def err(this, values, H):
            x = values.atVector(key)
            r, J = batched(x)
            if H is not None:
                H[0] = J.reshape(n, 6, -1)[i]
            return r.reshape(n, 6)[i]
        return gtsam.CustomFactor(noise, [key], err)

    for i in range(n):
        graph.add(make_cached(i))
    init = gtsam.Values()
    init.insert(key, x0)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iter)
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(1e-20)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, init, params)
    result = opt.optimize()
    x = result.atVector(key)
    return np.asarray(x), int(opt.iterations()), True, {}


def _emcee(prob: GoughProblem, x0: np.ndarray, n_walkers: int | None = None, n_steps: int = 2000,
           seed: int = 0, prior_std: float = 0.05):
    """Posterior sampling (Gaussian likelihood of the whitened residuals, broad
    Gaussian prior of std ``prior_std`` around the initial values), started
    around the LM optimum. Returns the posterior mean; ``extra`` holds the
    sample covariance."""
    import emcee

    x_ml, _, _, _ = _lm(prob, x0)
    J = prob.jacobian(x_ml)
    cov = np.linalg.pinv(J.T @ J)
    s2 = 1.0 if prob.absolute_sigma else float(prob.residual(x_ml) @ prob.residual(x_ml)) / max(
        prob.n_residuals - len(x0), 1)
    p = len(x0)
    nw = n_walkers or max(2 * p + 2, 32)
    rng = np.random.default_rng(seed)

    def logp(x):
        r = prob.residual(x)
        return -0.5 * (r @ r) / s2 - 0.5 * np.sum(((x - x0) / prior_std) ** 2)

    L = np.linalg.cholesky(cov * s2 + 1e-30 * np.eye(p))
    start = x_ml + (rng.standard_normal((nw, p)) @ L.T)
    sampler = emcee.EnsembleSampler(nw, p, logp)
    sampler.random_state = np.random.RandomState(seed).get_state()
    sampler.run_mcmc(start, n_steps, progress=False)
    chain = sampler.get_chain(discard=n_steps // 2, flat=True)
    return chain.mean(axis=0), n_steps, True, {"sample_covariance": np.cov(chain.T),
                                               "acceptance": float(np.mean(sampler.acceptance_fraction))}


#: Local implementations, used when the shared :mod:`estcal.estimate` registry
#: does not (yet) provide the estimator, or with ``backend="local"``.
ESTIMATORS = {"lm": _lm, "gauss-newton": _gauss_newton, "kalman": _kalman, "gtsam": _gtsam, "emcee": _emcee}
_LOCAL_ALIASES = {"mcmc": "emcee", "scipy-lm": "lm"}


def _shared_estimator(method: str):
    """The estimator of the shared registry, or None if it is not available."""
    try:
        from estcal.estimate.registry import get_estimator
    except ImportError:
        return None
    try:
        return get_estimator(method)
    except ValueError:
        return None


def estimator_names() -> list[str]:
    """Estimator names accepted by :func:`calibrate_gough` (shared registry ∪ local)."""
    names = set(ESTIMATORS) | set(_LOCAL_ALIASES)
    try:
        from estcal.estimate.registry import estimator_names as shared

        names |= set(shared())
    except ImportError:
        pass
    return sorted(names)


def calibrate_gough(
    robot: GoughPlatform | str | Path | Mapping,
    data: GoughData | str | Path,
    method: str = "lm",
    residual: str = "ik",
    model: int = 42,
    free: Sequence[str] | None = None,
    theta0: np.ndarray | None = None,
    initial: str = "nominal",
    daney_results: list | None = None,
    sigma_rho: float | None = None,
    sigma_p: float | None = None,
    sigma_r: float | None = None,
    backend: str = "auto",
    **estimator_kw: Any,
) -> GoughCalibrationResult:
    """Calibrate a Gough platform from measured poses and leg readings.

    Parameters
    ----------
    robot : nominal robot (object, built-in name, robot file or dict).
    data : :class:`GoughData` or a measurement file (see :func:`load_gough_data`).
    method : estimator name. With ``backend="auto"`` (default) the shared
        estimators of :mod:`estcal.estimate` (``lm``, ``gauss-newton``,
        ``iterated-lls``, ``scipy-lm``, ``gtsam``, ``kalman``, ``mcmc`` …) run
        on the problem through :class:`GoughEstimationProblem`; names the
        shared registry cannot provide fall back to the local
        implementations: ``lm`` (scipy Levenberg–Marquardt), ``gauss-newton``,
        ``kalman`` (iterated EKF), ``gtsam`` (factor graph, LM), ``emcee`` /
        ``mcmc`` (posterior mean and sample covariance).
    backend : ``"auto"``, ``"shared"`` (registry only) or ``"local"``.
    residual : ``"ik"`` or ``"fk"`` (module docstring).
    model : 42 (a, b, Δρ) or 36 (a, b; offsets fixed at their nominal values).
    free : parameter names/patterns to estimate (default: the model's set).
    theta0 / initial : initial value: explicit (42,) vector, or ``"nominal"``
        (robot file values), or ``"daney"`` (linear per-leg solutions in
        ``daney_results``, a list of :class:`~estcal.parallel.daney.LegDaneyResult`).
    sigma_* : noise std (m, m, rad); override those stored with the data.

    Non-identifiable free parameters (QR at the initial value) are kept at
    their initial value and reported with ``std = None``.
    """
    robot = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    data = data if isinstance(data, GoughData) else load_gough_data(data)
    if backend not in ("auto", "shared", "local"):
        raise ValueError(f"backend must be 'auto', 'shared' or 'local', got {backend!r}")
    shared = None if backend == "local" else _shared_estimator(method)
    local_name = _LOCAL_ALIASES.get(method, method)
    if shared is None and (backend == "shared" or local_name not in ESTIMATORS):
        raise ValueError(f"estimator {method!r} is not available (backend={backend!r}); "
                         f"choose from {estimator_names()}")
    if theta0 is None and initial == "daney":
        if not daney_results:
            raise ValueError("initial='daney' needs daney_results (see estcal.parallel.daney.calibrate_leg_daney)")
        from .daney import daney_initial_theta

        theta0 = daney_initial_theta(robot, daney_results)
    elif theta0 is None and initial != "nominal":
        raise ValueError(f"initial must be 'nominal' or 'daney', got {initial!r}")
    prob = GoughProblem(robot, data, residual, model, free, theta0, sigma_rho, sigma_p, sigma_r)
    x_init = prob.x0
    ide = _identify(prob.jacobian(x_init), prob.names)
    if ide["n_identifiable"] < len(prob.names):
        prob.pv = prob.pv.with_free(ide["identifiable"])
        x_init = prob.x0
    if shared is not None:
        res = shared(GoughEstimationProblem(prob), **estimator_kw)
        order = [res.names.index(n) for n in prob.names]
        x = np.asarray(res.estimate, float)[order]
        cov = np.asarray(res.covariance, float)[np.ix_(order, order)]
        nit, conv = int(res.n_iterations), bool(res.converged)
        extra = {"backend": f"estcal.estimate ({res.method})", "covariance_source": res.covariance_source}
        r, _ = prob.residual_and_jacobian(x, jacobian=False)
        chi2 = float(r @ r)
    else:
        x, nit, conv, extra = ESTIMATORS[local_name](prob, x_init, **estimator_kw)
        extra["backend"] = f"estcal.parallel.calibration ({local_name})"
        r, J = prob.residual_and_jacobian(x)
        chi2 = float(r @ r)
        dof = max(prob.n_residuals - len(x), 1)
        s2 = 1.0 if prob.absolute_sigma else chi2 / dof
        cov = np.linalg.inv(J.T @ J) * s2
        if local_name == "emcee":
            cov = extra.pop("sample_covariance")
    theta = prob.theta(x)
    std = dict(zip(prob.names, np.sqrt(np.diag(cov))))
    pv0 = robot.parameter_vector(model)
    init_vals = dict(zip(pv0.names, theta0 if theta0 is not None else pv0.values))
    names_out = GoughProblem(robot, data, residual, model, free).names
    params = {n: {"estimate": float(theta[pv0.index(n)]), "std": (float(std[n]) if n in std else None),
                  "initial": float(init_vals[n])} for n in names_out}
    # RMS of the raw residual components: leg readings (m) for IK; for FK the
    # position components (m), the orientation components (rad) go to extra.
    e, _, _, _, kind = GoughProblem(robot, data, residual, model).raw_rows(theta, jacobian=False)
    rmse = float(np.sqrt(np.mean(e[kind != 1] ** 2)))
    if residual == "fk":
        extra["rmse_rotation_rad"] = float(np.sqrt(np.mean(e[kind == 1] ** 2)))
    return GoughCalibrationResult(method, residual, model, params, rmse, nit, conv,
                                  cov, prob.names, theta, ide, chi2, prob.n_residuals, prob.fk_failures,
                                  {k: v for k, v in extra.items() if isinstance(v, (int, float, str))})
