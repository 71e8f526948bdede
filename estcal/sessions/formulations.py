"""The repeatability model solved three ways, on the same linearisation.

* :func:`solve_gls` — generalised least squares with the sessions' random
  effects integrated out (:mod:`estcal.sessions.system`).
* :func:`solve_factor_graph` — a **gtsam** Gaussian factor graph: one node for
  the shared parameters ``δθ``, one node ``v_s`` per session for the varying
  subset (``v_s = δθ_S + u_s``), the session's measurements on ``(δθ, v_s)`` and
  a between factor ``v_s − δθ_S ~ N(0, Q)`` tying each session to the shared
  value (a hard constraint where ``q_j = 0``); solved by gtsam's multifrontal
  elimination, covariance from ``gtsam.Marginals``.
* :func:`solve_kalman` — a **filterpy** Kalman filter whose state is
  ``[δθ, v]``: at each session boundary the predict step copies ``δθ_S`` into
  ``v`` and adds the process noise ``Q`` on ``v`` (the new session's parameters
  are the population's plus a fresh repeatability draw), then the session's
  rows update the state. Started from a diffuse prior.

For a linear-Gaussian model the three are algebraically identical (the mixed
model's GLS estimate equals the joint mode of (θ, u) — Henderson's equations —
and the Kalman filter computes that posterior recursively), so they must agree
to rounding; the tests check agreement to 1e-6 σ and to 0.1 σ after the
nonlinear iterations of :func:`estcal.sessions.fit.fit_sessions`.

Inputs are per-session whitened Jacobians ``A_s`` (m_s, p) and pseudo-data
``r_s`` (m_s,), the indices ``S`` of the varying subset in the free parameters,
``q`` (k,) and the variance factor ``s2``.
"""
from __future__ import annotations

import numpy as np

from .system import blocks_from_rows, gls

__all__ = ["solve_gls", "solve_factor_graph", "solve_kalman"]


def solve_gls(A_list, r_list, S, q, s2=1.0):
    """``(δθ, cov, u (n_s, k))`` by GLS (:func:`estcal.sessions.system.gls`)."""
    delta, cov, u, _ = gls([blocks_from_rows(A, r) for A, r in zip(A_list, r_list)], S, q, s2)
    return delta, cov, u


def solve_factor_graph(A_list, r_list, S, q, s2=1.0):
    """``(δθ, cov, u)`` from a gtsam Gaussian factor graph with per-session nodes and between factors."""
    import gtsam

    S = np.asarray(S, int)
    p = A_list[0].shape[1]
    k = len(S)
    X = gtsam.symbol("x", 0)
    g = gtsam.GaussianFactorGraph()
    sd = np.sqrt(np.maximum(np.asarray(q, float), 0.0))
    E = np.zeros((k, p))
    E[np.arange(k), S] = 1.0
    between_noise = (gtsam.noiseModel.Constrained.MixedSigmas(1e3, sd) if np.any(sd == 0)
                     else gtsam.noiseModel.Diagonal.Sigmas(sd))
    meas_sigma = float(np.sqrt(s2))
    for i, (A, r) in enumerate(zip(A_list, r_list)):
        V = gtsam.symbol("v", i)
        A_shared = A.copy()
        A_shared[:, S] = 0.0
        noise = gtsam.noiseModel.Isotropic.Sigma(A.shape[0], meas_sigma)
        if k:
            g.add(gtsam.JacobianFactor(X, A_shared, V, A[:, S], r, noise))
            g.add(gtsam.JacobianFactor(X, -E, V, np.eye(k), np.zeros(k), between_noise))
        else:
            g.add(gtsam.JacobianFactor(X, A, r, noise))
    sol = g.optimize()
    delta = np.asarray(sol.at(X))
    cov = gtsam.Marginals(g, sol).marginalCovariance(X)
    u = np.array([np.asarray(sol.at(gtsam.symbol("v", i))) - delta[S] for i in range(len(A_list))]) if k \
        else np.zeros((len(A_list), 0))
    return delta, cov, u


def solve_kalman(A_list, r_list, S, q, s2=1.0, diffuse: float = 1e8, q_within=None, rows_per_pose=None):
    """``(δθ, cov, u)`` from a filterpy Kalman filter with process noise Q at each session boundary.

    The diffuse prior is ``diffuse / (Σ AᵀA)_jj`` per column (centred on the
    linearisation point), so its weight is 1/``diffuse`` of the data's on every
    parameter whatever its units.

    ``q_within`` (k,) adds the within-session random walk of the drift model
    (:mod:`estcal.estimate.kalman`, ``estcal online --q``): the session's parameters
    ``v`` then also diffuse by ``q_within`` between consecutive poses (``rows_per_pose``
    rows each), processed pose by pose. With ``q_within = 0`` this is the same filter.
    """
    from filterpy.kalman import KalmanFilter

    S = np.asarray(S, int)
    p = A_list[0].shape[1]
    k = len(S)
    n = p + k
    kf = KalmanFilter(dim_x=n, dim_z=1)
    scale = sum(np.einsum("ij,ij->j", A, A) for A in A_list)
    P0 = np.zeros((n, n))
    P0[:p, :p] = np.diag(diffuse * s2 / np.maximum(scale, 1e-300))
    kf.x = np.zeros((n, 1))
    kf.P = P0
    F = np.eye(n)
    F[p:, :] = 0.0
    F[p + np.arange(k), S] = 1.0  # v := δθ_S at the start of every session
    Qp = np.zeros((n, n))
    Qp[p:, p:] = np.diag(np.maximum(np.asarray(q, float), 0.0))
    Qw = None
    if q_within is not None and k:
        Qw = np.zeros((n, n))
        Qw[p:, p:] = np.diag(np.maximum(np.asarray(q_within, float), 0.0))
    for A, r in zip(A_list, r_list):
        kf.predict(F=F, Q=Qp)
        H = np.zeros((A.shape[0], n))
        H[:, :p] = A
        H[:, S] = 0.0
        H[:, p:] = A[:, S]
        if Qw is None:
            kf.update(r[:, None], R=s2 * np.eye(A.shape[0]), H=H)
            continue
        d = int(rows_per_pose or A.shape[0])
        for a in range(0, A.shape[0], d):
            if a:
                kf.predict(F=np.eye(n), Q=Qw)  # within-session drift between poses
            kf.update(r[a:a + d, None], R=s2 * np.eye(len(r[a:a + d])), H=H[a:a + d])
    x = kf.x.ravel()
    cov = 0.5 * (kf.P[:p, :p] + kf.P[:p, :p].T)
    # The filter's v is the last session's; the earlier sessions' u_s given all the data
    # would need a smoother: they are the BLUPs at the final δθ (as in GLS).
    u = _blup(A_list, r_list, S, q, s2, x[:p]) if k else np.zeros((len(A_list), 0))
    return x[:p], cov, u


def _blup(A_list, r_list, S, q, s2, delta):
    """û_s = D K⁻¹ D Bᵀ(r − A δθ) for every session at a given δθ."""
    d = np.sqrt(np.maximum(np.asarray(q, float), 0.0))
    out = []
    for A, r in zip(A_list, r_list):
        B = A[:, S]
        K = s2 * np.eye(len(S)) + (d[:, None] * (B.T @ B) * d[None, :])
        out.append(d * np.linalg.solve(K, d * (B.T @ (r - A @ delta))))
    return np.array(out)
