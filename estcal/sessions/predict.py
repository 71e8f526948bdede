"""Predictions for a new session, and the few measurements that re-calibrate it.

A new session's parameters are ``θ_new = θ + E u``, ``u ~ N(0, Q)``, so the
predicted measurement of pose i has covariance

    Σ_i = J_i (C_θ + E Q Eᵀ) J_iᵀ + s² R_i,

(``J_i`` the Jacobian of pose i's measured coordinates w.r.t. the free
parameters, ``C_θ`` the population covariance, ``R_i`` the measurement noise).
The 95 % prediction region of a measured point is the ellipsoid
``eᵀ Σ_i⁻¹ e ≤ χ²₃(0.95)``; its *coverage* on held-out sessions is the fraction
of measured points inside it (binomial band ``0.95 ± 1.96 √(0.95·0.05/n)``).

:func:`update_session` starts the recursive filter from the population
estimate with that inflated covariance and updates it with k measured poses of
the new session (a linear Kalman update at the population estimate, iterated);
:func:`choose_poses` picks those k poses greedily by the covariance: each next
pose is the one that most reduces the summed predicted variance of all the
session's poses (the "next pose" rule of :mod:`estcal.design.sequential` applied
to the new session's prior).
"""
from __future__ import annotations

import numpy as np

__all__ = ["predict_session", "coverage_band", "update_session", "choose_poses", "recalibration_curve"]


def _pose_blocks(fit, data, theta=None):
    """Per-pose residuals e (N, d), whitened Jacobians and noise of ``data`` under ``fit``'s model."""
    from estcal.methods import Problem

    prob = Problem(fit.robot, [(None, data, fit.noise)], fit.noise)
    pv = prob.params
    th = fit.theta if theta is None else theta
    rows = prob.evaluate(th)
    N = data.n
    d = len(rows.e) // N
    if d * N != len(rows.e) or not np.array_equal(rows.pose, np.repeat(np.arange(N), d)):
        raise ValueError("predict_session needs direct measurements (position, points or pose): one block of "
                         "rows per pose")
    idx = np.array(pv.indices(fit.names), int)
    return rows.e.reshape(N, d), rows.H[:, idx].reshape(N, d, -1), rows.sigma.reshape(N, d)


def predict_session(fit, data, cov=None, theta=None, level: float = 0.95) -> dict:
    """Score ``data`` (a session the fit did not use) against the new-session prediction.

    Returns a dict with ``rmse_mm`` (all measured points), ``rmse_mm_per_point``,
    ``coverage`` (fraction of measured points inside their ``level`` ellipsoid),
    ``coverage_per_point``, ``n_points``, ``band`` (binomial band of the coverage),
    ``predicted_std_mm`` (mean over poses of √(trace Σ/3) per point) and
    per-pose ``d2`` (N, k) squared Mahalanobis distances. ``cov`` defaults to
    ``fit.new_session_cov()``; pass ``fit.cov`` to score without the repeatability term.
    """
    from scipy import stats

    e, J, sig = _pose_blocks(fit, data, theta)
    N, d, p = J.shape
    C = fit.new_session_cov() if cov is None else cov
    k = d // 3
    e3 = e.reshape(N, k, 3)
    J3 = J.reshape(N, k, 3, p)
    S = np.einsum("nkap,pq,nkbq->nkab", J3, C, J3) + fit.s2 * np.einsum(
        "nka,ab->nkab", sig.reshape(N, k, 3) ** 2, np.eye(3))
    d2 = np.einsum("nka,nka->nk", e3, np.linalg.solve(S, e3[..., None])[..., 0])
    inside = d2 <= stats.chi2.ppf(level, 3)
    err = np.linalg.norm(e3, axis=2)
    return {"rmse_mm": float(np.sqrt(np.mean(err ** 2)) * 1e3),
            "rmse_mm_per_point": (np.sqrt(np.mean(err ** 2, 0)) * 1e3).tolist(),
            "coverage": float(inside.mean()), "coverage_per_point": inside.mean(0).tolist(),
            "n_points": int(inside.size), "band": coverage_band(inside.size, level),
            "predicted_std_mm": (np.sqrt(np.einsum("nkaa->nk", S) / 3).mean(0) * 1e3).tolist(),
            "d2": d2}


def coverage_band(n: int, level: float = 0.95, z: float = 1.96) -> list:
    """Binomial band of an empirical coverage over n independent points."""
    h = z * np.sqrt(level * (1 - level) / max(n, 1))
    return [float(max(level - h, 0.0)), float(min(level + h, 1.0))]


def update_session(fit, data, idx, n_iter: int = 3):
    """Free-parameter estimate and covariance of a new session after measuring poses ``idx``.

    Prior ``N(θ̂, C_θ + E Q Eᵀ)``; the update is the Kalman (information) update with
    the poses' rows, relinearised ``n_iter`` times (an iterated EKF on a static state).
    Returns ``(theta_full, cov)``.
    """
    from filterpy.kalman import KalmanFilter

    idx = np.asarray(idx, int)
    theta = fit.theta.copy()
    pos = fit.robot.params.indices(fit.names)
    C0 = fit.new_session_cov()
    if idx.size == 0:
        return theta, C0
    sub = data.subset(idx)
    x_prior = theta[pos].copy()
    for _ in range(n_iter):
        e, J, sig = _pose_blocks(fit, sub, theta)
        H = J.reshape(-1, J.shape[-1])
        z = e.reshape(-1) + H @ (theta[pos] - x_prior)  # measurement of (x − x_prior) at this linearisation
        kf = KalmanFilter(dim_x=len(pos), dim_z=len(z))
        kf.x = np.zeros((len(pos), 1))
        kf.P = C0.copy()
        kf.update(z[:, None], R=fit.s2 * np.diag(sig.reshape(-1) ** 2), H=H)
        theta = theta.copy()
        theta[pos] = x_prior + kf.x.ravel()
    return theta, 0.5 * (kf.P + kf.P.T)


def choose_poses(fit, data, k: int) -> list:
    """Greedy covariance-driven choice of k poses of ``data`` to re-measure (indices)."""
    _, J, sig = _pose_blocks(fit, data)
    N, d, p = J.shape
    W = J / (np.sqrt(fit.s2) * sig[..., None])  # whitened rows per pose
    P = fit.new_session_cov()
    chosen = []
    for _ in range(min(k, N)):
        # candidate c: P' = P − P Hcᵀ (Hc P Hcᵀ + I)⁻¹ Hc P; score = Σ_i trace(J_i P' J_iᵀ)
        JP = np.einsum("ndp,pq->ndq", J, P)  # (N, d, p)
        total = np.einsum("ndq,ndq->", JP, J)
        WP = np.einsum("ndp,pq->ndq", W, P)
        Sc = np.einsum("ndq,neq->nde", WP, W) + np.eye(d)  # (N, d, d)
        # reduction_c = Σ_i trace(J_i P Wcᵀ Sc⁻¹ Wc P J_iᵀ) = trace(Sc⁻¹ Wc P (Σ_i J_iᵀ J_i) P Wcᵀ)
        G = np.einsum("ndp,ndq->pq", J, J)
        M = np.einsum("ndp,pq,neq->nde", WP, G, WP)
        red = np.einsum("nde,ned->n", np.linalg.inv(Sc), M)
        red[chosen] = -np.inf
        c = int(np.argmax(red))
        chosen.append(c)
        Wc = W[c]
        Kc = P @ Wc.T @ np.linalg.inv(Sc[c])
        P = P - Kc @ Wc @ P
        P = 0.5 * (P + P.T)
        del total
    return chosen


def recalibration_curve(fit, data, ks=range(0, 11), rule: str = "covariance", rng=0, n_random: int = 20) -> dict:
    """Error on the rest of a new session after re-measuring k of its poses, for k in ``ks``.

    ``rule="covariance"`` picks the poses with :func:`choose_poses` (nested: the first k of
    the greedy order); ``"random"`` averages ``n_random`` random draws. The error is the
    RMSE (mm) of all measured points of the poses not re-measured.
    """
    ks = list(ks)
    N = data.n
    if rule == "covariance":
        order = choose_poses(fit, data, max(ks))
        draws = [order]
    else:
        g = np.random.default_rng(rng)
        draws = [list(g.permutation(N)[:max(ks)]) for _ in range(n_random)]
    out = []
    for k in ks:
        vals = []
        for order in draws:
            idx = order[:k]
            rest = np.setdiff1d(np.arange(N), idx)
            theta, _ = update_session(fit, data, idx)
            e, _, _ = _pose_blocks(fit, data.subset(rest), theta)
            vals.append(np.sqrt(np.mean(np.sum(e.reshape(len(rest), -1, 3) ** 2, -1))) * 1e3)
        out.append(float(np.mean(vals)))
    return {"k": ks, "rmse_mm": out, "rule": rule}
