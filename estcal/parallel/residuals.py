r"""Residuals of Gough-platform measurements, their noise covariance and analytic Jacobians.

Two residual models over the 42 parameters ``θ`` (:func:`~estcal.parallel.gough.gough_parameter_names`):

* **Inverse kinematics** (``residual="ik"``): for each measured platform pose ``T_i`` and leg
  readings ``ρ_i`` (6), ``e_ik = ρ_ik − (‖P_i + R_i b_k − a_k‖ − Δρ_k)``; Jacobian
  ``∂e/∂θ = −∂ρ/∂θ`` (:meth:`GoughPlatform.leg_jacobians`).
* **Forward kinematics** (``residual="fk"``): the pose predicted from the measured readings by the
  numerical FK, compared with the measured pose, ``e_i = (p_meas − p_fk, log(R_meas R_fkᵀ))``
  (estcal's pose-error convention). By the implicit function theorem on ``ρ(x, θ) = ρ_meas``,
  ``∂x_fk/∂θ = −J_x⁻¹ J_θ``, so ``∂e_p/∂θ = (J_x⁻¹ J_θ)_p`` and
  ``∂e_r/∂θ = J_r⁻¹(e_r) (J_x⁻¹ J_θ)_r`` with the right Jacobian of SO(3).

Noise (:meth:`GoughResiduals.pose_covariance`): a pose-measurement error moves all six predicted
lengths, so the six residuals of a pose are correlated, ``C_i = σ_ρ² I + J_x Σ_pose J_xᵀ`` (IK) or
``C_i = Σ_pose + σ_ρ² J_x⁻¹ J_x⁻ᵀ`` (FK), ``Σ_pose = diag(σ_p² I₃, σ_r² I₃)``. The estimators see
the decorrelated rows ``L_i⁻¹ e_i`` (``C_i = L_i L_iᵀ``): unit-variance, independent residuals.
The weights are evaluated once, at the measured poses and the reference parameters, so the cost is
a proper weighted least-squares cost.

This module is the measurement model only; the estimators run on it through the shared
``Problem`` interface (``estcal.workflows.gough``).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from estcal.base.errors import InputError
from estcal.kinematics.transforms import so3_right_jacobian_inv

from ._rot import so3_log
from .data import GoughData
from .gough import N_LEGS, GoughPlatform, split_pose

__all__ = ["GoughResiduals", "ResidualRows", "DEFAULT_SIGMA", "RESIDUALS"]

#: Standard deviations used when a noise level is not given (those of the shared ``NoiseModel``:
#: 0.1 mm, 1 mrad); the covariance is then rescaled by the residual variance, so only their
#: ratios matter.
DEFAULT_SIGMA = {"rho": 1e-4, "position": 1e-4, "orientation": 1e-3}

#: the residual models
RESIDUALS = ("ik", "fk")

#: row kind codes (as the shared residual rows): position m, orientation rad, scalar m
KIND_POSITION, KIND_ORIENTATION, KIND_SCALAR = 0, 1, 2


@dataclass
class ResidualRows:
    """Residual rows of all poses, six per pose.

    e : (6N,) measured − predicted; J : (6N, 42) ∂e/∂θ or None; kind : (6N,) row kind code;
    pose : (6N,) pose index of each row; fk_failed : (N,) poses whose FK failed (their rows are 0).
    """

    e: np.ndarray
    J: np.ndarray | None
    kind: np.ndarray
    pose: np.ndarray
    fk_failed: np.ndarray

    @property
    def n_fk_failures(self) -> int:
        return int(np.count_nonzero(self.fk_failed))


class GoughResiduals:
    """IK or FK residuals of ``data`` for ``robot``, whitened by the per-pose noise covariance.

    Parameters
    ----------
    robot : the platform (its limits, home pose and, by default, the parameters at which the
        weights are evaluated).
    data : the measurements.
    residual : ``"ik"`` or ``"fk"`` (module docstring).
    sigma_rho, sigma_p, sigma_r : noise standard deviations (m, m, rad); None takes those stored
        with ``data`` (None there too: :data:`DEFAULT_SIGMA`, relative weights only).
    propagate_pose_noise : include the pose noise in the IK covariance (reading noise in FK's).
    theta_weights : (42,) parameters at which the weights are evaluated (default ``robot.theta``).
    """

    def __init__(self, robot: GoughPlatform, data: GoughData, residual: str = "ik",
                 sigma_rho: float | None = None, sigma_p: float | None = None, sigma_r: float | None = None,
                 propagate_pose_noise: bool = True, theta_weights: np.ndarray | None = None):
        if residual not in RESIDUALS:
            raise InputError(f"residual must be 'ik' or 'fk', got {residual!r}")
        self.robot, self.data, self.kind = robot, data, residual
        self.sigma_rho = sigma_rho if sigma_rho is not None else data.sigma_rho
        self.sigma_p = sigma_p if sigma_p is not None else data.sigma_p
        self.sigma_r = sigma_r if sigma_r is not None else data.sigma_r
        self.propagate = propagate_pose_noise
        self.theta_weights = robot.theta if theta_weights is None else np.asarray(theta_weights, float).reshape(42)
        self._cov = self._Linv = None

    @property
    def n_poses(self) -> int:
        return len(self.data)

    @property
    def n_rows(self) -> int:
        return N_LEGS * len(self.data)

    @property
    def absolute_sigma(self) -> bool:
        """True when every noise level this residual needs is given: the covariance of the
        estimate is then absolute, not rescaled by the residual variance."""
        if self.kind == "ik":
            return self.sigma_rho is not None
        return self.sigma_p is not None and self.sigma_r is not None

    def pose_covariance(self) -> np.ndarray:
        """Covariance (N, 6, 6) of the six residuals of each pose (module docstring).

        Missing levels: σ_ρ defaults to :data:`DEFAULT_SIGMA` for IK and contributes nothing to
        FK; the pose levels default for FK and contribute nothing to IK.
        """
        if self._cov is None:
            n = len(self.data)
            _, Jx = self.robot.leg_jacobians(self.data.T, self.theta_weights)
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

    def subset(self, idx) -> "GoughResiduals":
        """The same residuals restricted to poses ``idx`` (weights kept)."""
        self.pose_covariance()
        sub = copy.copy(self)
        idx = np.asarray(idx, int)
        sub.data = self.data.subset(idx)
        sub._cov, sub._Linv = self._cov[idx], self._Linv[idx]
        return sub

    def raw(self, theta: np.ndarray, jacobian: bool = True) -> ResidualRows:
        """Unwhitened rows at the full (42,) ``theta`` (``e`` = measured − predicted, ``J = ∂e/∂θ``)."""
        return self._ik(theta, jacobian) if self.kind == "ik" else self._fk(theta, jacobian)

    def whitened(self, theta: np.ndarray, jacobian: bool = True) -> ResidualRows:
        """Decorrelated rows ``L_i⁻¹ e_i`` and ``L_i⁻¹ ∂e_i/∂θ``: unit variance, independent."""
        rows = self.raw(theta, jacobian)
        self.pose_covariance()
        n = len(self.data)
        rows.e = np.einsum("nij,nj->ni", self._Linv, rows.e.reshape(n, 6)).reshape(-1)
        if rows.J is not None:
            rows.J = np.einsum("nij,njk->nik", self._Linv, rows.J.reshape(n, 6, -1)).reshape(6 * n, -1)
        return rows

    def _ik(self, theta, jacobian):
        n = len(self.data)
        # leg lengths inline (hot path of the samplers: no pose re-splitting)
        th = np.asarray(theta, float).reshape(N_LEGS, 7)
        T = self.data.T
        v = T[:, None, :3, 3] + np.einsum("nij,kj->nki", T[:, :3, :3], th[:, 3:6]) - th[None, :, 0:3]
        e = (self.data.rho - (np.sqrt(np.einsum("nki,nki->nk", v, v)) - th[:, 6])).reshape(-1)
        J = None
        if jacobian:
            Jt, _ = self.robot.leg_jacobians(T, theta)
            J = -Jt.reshape(-1, 7 * N_LEGS)
        return ResidualRows(e, J, np.full(6 * n, KIND_SCALAR), np.repeat(np.arange(n), 6), np.zeros(n, bool))

    def _fk(self, theta, jacobian):
        n = len(self.data)
        fk = self.robot.forward_kinematics(self.data.rho, theta, guess=self.data.T, n_starts=2, tol=1e-13)
        ok = fk.success
        Pm, Rm = split_pose(self.data.T)
        e = np.zeros((n, 6))
        Tf = fk.T[ok]
        e[ok, :3] = Pm[ok] - Tf[:, :3, 3]
        e[ok, 3:] = so3_log(Rm[ok] @ np.swapaxes(Tf[:, :3, :3], -1, -2))
        J = None
        if jacobian:
            J = np.zeros((n, 6, 7 * N_LEGS))
            if ok.any():
                Jt, Jx = self.robot.leg_jacobians(Tf, theta)
                dx = np.linalg.solve(Jx, Jt)  # = −∂x_fk/∂θ
                # d/dδ of log(exp(e) exp(−δ)) is −J_r⁻¹(e) (right Jacobian of SO(3))
                dx[:, 3:] = np.einsum("nij,njk->nik", so3_right_jacobian_inv(e[ok, 3:]), dx[:, 3:])
                J[ok] = dx
            J = J.reshape(-1, 7 * N_LEGS)
        kind = np.tile([KIND_POSITION] * 3 + [KIND_ORIENTATION] * 3, n)
        return ResidualRows(e.reshape(-1), J, kind, np.repeat(np.arange(n), 6), ~ok)
