"""Offline covariance analysis from the Kalman recursion alone (textbook §4.5, §5.3 of the digest).

The filter covariance does not depend on the measured values, only on the
poses (through H_k), the noise R_k, the process noise Q and the prior P0, so
the accuracy a calibration will reach, its floor, and the number of
measurements after which more data no longer help can be computed before any
experiment:

* :func:`covariance_sequence` — P_k for a planned sequence of measurement
  Jacobians (eqs 4.111–4.112; Q = 0 gives 4.106);
* :func:`steady_state` — P∞ for a constant H (a whole planned pass of poses
  stacked as one measurement), from the discrete algebraic Riccati equation
  solved by :func:`scipy.linalg.solve_discrete_are`; with M = P∞ + Q it is
  ``M = M − M Hᵀ (H M Hᵀ + R)⁻¹ H M + Q`` i.e. eq. 4.113
  ``(P∞+Q) Hᵀ [H (P∞+Q) Hᵀ + R]⁻¹ H (P∞+Q) = Q``;
  :func:`riccati_residual` evaluates 4.113; :func:`periodic_steady_state`
  iterates the recursion over a cycle of single poses until it repeats;
* :func:`repetition_covariance` — after j repetitions of a pass with
  information F = Λᵀ Σ_Ψ⁻¹ Λ: P(j) = (P0⁻¹ + j F)⁻¹ = P0 (I + j F P0)⁻¹
  (eq. 4.202 / corrected 4.222: the book's print ``(I + jFP0)⁻¹ P0`` is not symmetric);
* :func:`stopping_index` — smallest j with ‖P(j)‖ ≤ ε ‖P0‖ (eq. 4.220) and the
  lower bound M1 from ‖(I + j F P0)⁻¹‖ ≤ ε (4.223–4.224);
  :func:`stopping_index_sequence` — rule 4.114 ‖P_k − P∞‖ ≤ δ for all k ≥ M on a sequence;
* :func:`planned_jacobians` — the H_k of a planned pose list for a robot and a
  measurement method, at the nominal parameters (no measurement needed);
* :func:`plan_calibration` — all of the above for a planned pose list: predicted stds after
  every pose, the floor and the stopping index (:class:`CalibrationPlan`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from estcal.io.dataset import dataset_from_arrays
from estcal.methods.base import NoiseModel
from estcal.methods.problem import Problem

__all__ = ["covariance_sequence", "steady_state", "riccati_residual", "periodic_steady_state",
           "repetition_covariance", "stopping_index", "stopping_index_sequence", "information_matrix",
           "planned_jacobians", "matrix_norm", "plan_calibration", "CalibrationPlan"]


def matrix_norm(A, norm=2) -> float:
    """‖A‖ for ``norm`` in {2, 1, inf, 'fro'} (numpy's matrix norms)."""
    return float(np.linalg.norm(A, ord=norm))


def covariance_sequence(Hs, Rs, P0, Q=None, out: str = "full"):
    """Covariances P_k, k = 1..K, of the random-walk filter for measurement Jacobians ``Hs``.

    Parameters
    ----------
    Hs : sequence of (m_k, p) Jacobians (or an array (K, m, p)).
    Rs : sequence of (m_k, m_k) noise covariances or (m_k,) noise stds; (K, m) stds; or one
        (m, m) covariance shared by every step.
    P0 : (p, p) prior covariance.  Q : (p, p) process noise per step (None = 0).
    out : ``"full"`` → (K, p, p); ``"trace"`` → (K,); ``"std"`` → (K, p).

    Uses ``P_k = M − M Hᵀ (H M Hᵀ + R)⁻¹ H M`` with ``M = P_{k−1} + Q`` (4.111–4.112),
    symmetrised each step.
    """
    P = np.array(P0, float)
    p = P.shape[0]
    Q = np.zeros((p, p)) if Q is None else np.asarray(Q, float)
    K = len(Hs)
    Rl = _noise_list(Rs, K)
    res = []
    for k in range(K):
        H = np.asarray(Hs[k], float)
        R = Rl[k]
        M = P + Q
        MHt = M @ H.T
        S = H @ MHt + R
        P = M - MHt @ np.linalg.solve(S, MHt.T)
        P = 0.5 * (P + P.T)
        res.append(P if out == "full" else (np.trace(P) if out == "trace" else np.sqrt(np.clip(np.diag(P), 0, None))))
    return np.array(res)


def _noise_list(Rs, K):
    """Per-step noise covariances from a list (matrices or std vectors), an array (K, m) of
    stds, an array (K, m, m) of matrices, or one (m, m) matrix shared by every step (``K != m``)."""
    if isinstance(Rs, np.ndarray) and Rs.ndim == 2 and Rs.shape[0] == Rs.shape[1] and Rs.shape[0] != K:
        Rs = [Rs] * K
    out = []
    for R in Rs:
        R = np.asarray(R, float)
        out.append(np.diag(R ** 2) if R.ndim == 1 else R)
    if len(out) != K:
        raise ValueError(f"{len(out)} noise entries for {K} measurements")
    return out


def steady_state(H, R, Q):
    """A-posteriori floor P∞ of the random-walk filter for a constant measurement (H, R).

    Solves the DARE ``X = X − X Hᵀ (R + H X Hᵀ)⁻¹ H X + Q`` (scipy's
    ``solve_discrete_are(a=I, b=Hᵀ, q=Q, r=R)``) for the a-priori covariance
    X = P∞ + Q and returns P∞ = X − Q. Needs Q > 0 (Q = 0 gives P∞ = 0, 4.108)
    and H of full column rank (stack a pass of poses into H otherwise).
    """
    H = np.atleast_2d(np.asarray(H, float))
    R = np.asarray(R, float)
    if R.ndim == 1:
        R = np.diag(R ** 2)
    Q = np.asarray(Q, float)
    p = H.shape[1]
    if np.linalg.matrix_rank(H) < p:
        raise ValueError(f"constant H has rank {np.linalg.matrix_rank(H)} < {p} parameters: the floor is unbounded "
                         f"in the unobserved directions; stack a whole pass of poses into H "
                         f"(or use periodic_steady_state)")
    X = sla.solve_discrete_are(np.eye(p), H.T, Q, R)
    X = 0.5 * (X + X.T)
    return X - Q


def riccati_residual(P, H, R, Q) -> np.ndarray:
    """Left side minus right side of eq. 4.113: (P+Q)Hᵀ[H(P+Q)Hᵀ+R]⁻¹H(P+Q) − Q."""
    R = np.asarray(R, float)
    if R.ndim == 1:
        R = np.diag(R ** 2)
    M = np.asarray(P, float) + Q
    MHt = M @ H.T
    return MHt @ np.linalg.solve(H @ MHt + R, MHt.T) - Q


def periodic_steady_state(Hs, Rs, Q, P0=None, tol: float = 1e-10, max_cycles: int = 10000):
    """Covariance at the end of a cycle of measurements repeated until it no longer changes.

    For a planned pose list measured over and over (Q > 0), the recursion converges
    to a periodic solution; this returns its value after the last pose of the cycle
    (the floor of the time-varying-H case) and the number of cycles needed.
    """
    p = np.asarray(Hs[0]).shape[1]
    P = np.eye(p) if P0 is None else np.asarray(P0, float)
    for c in range(1, max_cycles + 1):
        Pn = covariance_sequence(Hs, Rs, P, Q)[-1]
        if np.linalg.norm(Pn - P) <= tol * max(np.linalg.norm(Pn), 1e-300):
            return Pn, c
        P = Pn
    raise RuntimeError(f"periodic Riccati recursion did not converge in {max_cycles} cycles")


def information_matrix(Hs, Rs) -> np.ndarray:
    """F = Σ_k H_kᵀ R_k⁻¹ H_k — the information of one pass (Λᵀ Σ_Ψ⁻¹ Λ, eq. 4.202)."""
    F = 0.0
    for H, R in zip(Hs, Rs):
        H = np.asarray(H, float)
        R = np.asarray(R, float)
        if R.ndim == 1:
            R = np.diag(R ** 2)
        F = F + H.T @ np.linalg.solve(R, H)
    return np.asarray(F)


def repetition_covariance(F, P0, j) -> np.ndarray:
    """P(j) = (P0⁻¹ + j F)⁻¹ (symmetric; corrected 4.222), for scalar or array ``j`` → (..., p, p).

    Computed from the eigen-decomposition of P0^{1/2} F P0^{1/2} = V Λ Vᵀ as
    P0^{1/2} V diag(1/(1 + jλ)) Vᵀ P0^{1/2}, valid for singular F as well.
    """
    P0 = np.asarray(P0, float)
    w0, U0 = np.linalg.eigh(P0)
    S = U0 @ np.diag(np.sqrt(w0)) @ U0.T
    lam, V = np.linalg.eigh(S @ F @ S)
    lam = np.clip(lam, 0, None)
    B = S @ V
    j = np.asarray(j, float)
    d = 1.0 / (1.0 + j[..., None] * lam)
    return np.einsum("ik,...k,jk->...ij", B, d, B)


def stopping_index(F, P0, eps: float, norm=2, j_max: int = 10_000_000) -> dict:
    """Stopping index of eq. 4.220: smallest j with ‖P(j)‖ ≤ ε ‖P0‖, P(j) = (P0⁻¹ + jF)⁻¹.

    Also returns M1, the smallest j with ‖(I + j F P0)⁻¹‖ ≤ ε (lower bound, 4.223–4.224),
    and ``t_star``, the continuous crossing point (bisection on real j).
    Raises if the criterion cannot be met (ε ‖P0‖ below the floor, 4.221).
    """
    P0 = np.asarray(P0, float)
    target = eps * matrix_norm(P0, norm)
    p = P0.shape[0]

    def f(j):
        return matrix_norm(repetition_covariance(F, P0, j), norm)

    def g(j):
        return matrix_norm(np.linalg.inv(np.eye(p) + j * F @ P0), norm)

    def first(fun, limit):
        if fun(0) <= limit:
            return 0, 0.0
        hi = 1
        while fun(hi) > limit:
            hi *= 2
            if hi > j_max:
                raise ValueError(f"‖P(j)‖ never reaches ε‖P0‖ = {limit:g} (j > {j_max}): the information F does "
                                 f"not determine every parameter (rank-deficient pass), or ε is too small (4.221)")
        lo = hi // 2
        while hi - lo > 1:  # ‖P(j)‖ decreases monotonically in j for the 2-norm; for 1/∞ we scan below
            mid = (lo + hi) // 2
            if fun(mid) > limit:
                lo = mid
            else:
                hi = mid
        a, b = float(lo), float(hi)
        for _ in range(60):
            m = 0.5 * (a + b)
            a, b = (m, b) if fun(m) > limit else (a, m)
        return hi, b

    M, t = first(f, target)
    if norm != 2:  # 1- and ∞-norms need not be monotone: take the first crossing by a scan
        js = np.arange(1, M + 1)
        vals = np.array([f(j) for j in js])
        M = int(js[np.argmax(vals <= target)])
    M1, _ = first(g, eps)
    return {"M": int(M), "M1": int(M1), "t_star": float(t), "target": target, "norm": norm, "eps": eps}


def stopping_index_sequence(Ps, P_inf, delta: float, norm=2) -> int:
    """Rule 4.114: smallest M (1-based) with ‖P_k − P∞‖ ≤ δ for every k ≥ M in the sequence (−1 if none)."""
    d = np.array([matrix_norm(P - P_inf, norm) for P in Ps])
    ok = d <= delta
    if not ok[-1]:
        return -1
    bad = np.flatnonzero(~ok)
    return int(bad[-1] + 2) if bad.size else 1


def planned_jacobians(robot, readings, method: str = "location", free=None, theta=None, sigma_p: float = 1e-4,
                      sigma_r: float = 1e-3):
    """Per-pose Jacobians H_k (rows of the free parameters) and noise stds of a planned pose list.

    Only the robot model and the readings are used (the predicted measurement
    stands in for the data, which H does not depend on).
    """

    readings = np.atleast_2d(np.asarray(readings, float))
    th = robot.params.values if theta is None else np.asarray(theta, float)
    kin = robot.kinematics(readings, th, jacobian=False)
    if method in ("location", "pose"):
        ds = dataset_from_arrays(robot.joint_names, readings, R=kin.R, p=kin.p)
    else:
        ds = dataset_from_arrays(robot.joint_names, readings, points=kin.points if robot.n_markers else kin.p)
    prob = Problem(robot, [(method, ds, NoiseModel(sigma_p, sigma_r, known=True))])
    if free is not None:
        prob = prob.with_free(free)
    rows = prob.evaluate(th)
    fidx = prob.params.free_indices
    N = readings.shape[0]
    m = len(rows.e) // N
    H = rows.H[:, fidx].reshape(N, m, -1)
    s = rows.sigma.reshape(N, m)
    return H, s, [prob.params.names[i] for i in fidx]


@dataclass
class CalibrationPlan:
    """Predicted accuracy of a planned pose sequence (no measurement needed).

    Attributes
    ----------
    names : free parameter names.
    std : (K, p) predicted standard deviations after each pose (√diag P_k).
    trace : (K,) tr P_k.
    floor_std : (p,) √diag P∞ (end-of-cycle periodic floor; zeros when Q = 0).
    stop : stopping index (1-based pose count): rule 4.114 ‖P_k − P∞‖₂ ≤ δ‖P∞‖₂ at cycle ends
        when Q > 0, rule 4.220 ‖P_k‖₂ ≤ ε‖P0‖₂ when Q = 0; −1 if not reached.
    rule : which rule gave ``stop``.
    """

    names: list
    std: np.ndarray
    trace: np.ndarray
    floor_std: np.ndarray
    stop: int
    rule: str

    def to_dict(self) -> dict:
        return {"names": list(self.names), "std_final": self.std[-1].tolist(), "trace": self.trace.tolist(),
                "floor_std": self.floor_std.tolist(), "stop": int(self.stop), "rule": self.rule}

    def __str__(self) -> str:
        return (f"CalibrationPlan({len(self.names)} parameters, {len(self.trace)} poses: max std "
                f"{self.std[-1].max():.3g} at the end, floor {self.floor_std.max():.3g}; stop after {self.stop} "
                f"poses by {self.rule})")


def plan_calibration(robot, readings, method: str = "location", free=None, sigma_p: float = 1e-4,
                     sigma_r: float = 1e-3, prior_std: float = 0.1, q=0.0, cycle: int | None = None,
                     delta: float = 0.1, eps: float = 1e-4, theta=None) -> CalibrationPlan:
    """Offline analysis of a planned pose list measured in order (and, with ``cycle``, repeated).

    ``q`` is the process-noise std per pose (scalar or per free parameter). With Q > 0 the floor is
    the periodic solution of the first ``cycle`` poses (default: all) and the stop is rule 4.114
    applied at cycle ends; with Q = 0 it is rule 4.220 with ``eps``.
    """
    H, s, names = planned_jacobians(robot, readings, method, free, theta, sigma_p, sigma_r)
    p = len(names)
    P0 = np.eye(p) * prior_std ** 2
    qv = np.broadcast_to(np.asarray(q, float), (p,))
    Q = np.diag(qv ** 2)
    Ps = covariance_sequence(list(H), list(s), P0, Q)
    K = len(Ps)
    if np.any(qv > 0):
        c = cycle or K
        P_inf, _ = periodic_steady_state(list(H[:c]), list(s[:c]), Q, P0=Ps[c - 1])
        Mc = stopping_index_sequence(Ps[c - 1::c], P_inf, delta * matrix_norm(P_inf))
        stop, rule = (Mc * c if Mc > 0 else -1), f"4.114 (δ = {delta} ‖P∞‖, at cycle ends of {c})"
        floor = np.sqrt(np.clip(np.diag(P_inf), 0, None))
    else:
        target = eps * matrix_norm(P0)
        ok = np.array([matrix_norm(P) <= target for P in Ps])
        stop = int(np.argmax(ok) + 1) if ok.any() else -1
        rule, floor = f"4.220 (ε = {eps})", np.zeros(p)
    return CalibrationPlan(names, np.sqrt(np.clip(np.diagonal(Ps, axis1=1, axis2=2), 0, None)),
                           np.trace(Ps, axis1=1, axis2=2), floor, stop, rule)
