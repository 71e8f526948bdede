"""Registration of measurements to a chain's frames, without a kinematic fit.

The data are measured in an unknown frame (where the instrument stands) of an unknown frame
or points on the last link. With the chain's frames ``T_i = (R_i, t_i)`` (N poses, the tip in
the root frame at the nominal geometry):

* **poses** ``M_i ≈ B·T_i`` (base only, :func:`register_base_pose`): minimise
  ``Σ‖R_B t_i + p_B − m_i‖² + w Σ‖R_B R_i − R_Mi‖²_F``. With ``p_B = m̄ − R_B t̄`` the cost
  is a constant minus ``2 tr(R_B K)``, ``K = Σ (t_i − t̄)(m_i − m̄)ᵀ + w Σ R_i R_Miᵀ`` — the
  Kabsch/Horn problem, solved by one SVD (vectorised over candidate chains). ``w = L²/2``
  weighs an angle θ like the displacement ``L θ`` at ``L`` = 1 m (1 mrad ≈ 1 mm), since
  ``‖ΔR‖²_F ≈ 2θ²``.
* **poses** ``M_i ≈ B·T_i·X`` (base and tool, :func:`register_pose`): Gauss–Newton
  (``scipy.optimize.least_squares``, LM) from the base-only solution.
* **points** ``p_ik ≈ B·T_i·m_k`` (base and k unknown marker points,
  :func:`register_points`): in the robot's frame ``Gᵀ := R_Bᵀ`` the model
  ``G p_ik + g − R_i m_k = t_i`` is *linear* in ``(G, g, m_k)`` (12 + 3k unknowns); the
  linear solution projected on SO(3) starts an LM refinement of the 6 + 3k parameters.

Units: SI (m, rad). Residuals are returned per pose, in metres and radians.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.kinematics.transforms import so3_exp, so3_log

__all__ = ["Registration", "register_base_pose", "register_pose", "register_points", "project_so3"]

#: lever arm (m) at which an angle counts like a displacement in the pose registration cost
LEVER_M = 1.0


@dataclass
class Registration:
    """Outcome of a registration: base ``(R_B, p_B)`` (measurement frame ← root), tool ``(R_X, p_X)``
    (tip ← measured frame) or marker points ``markers`` (k, 3) in the tip frame; per-pose residual
    norms ``e_pos`` (N,) [m] (for points: (N, k)) and ``e_rot`` (N,) [rad] (pose data)."""

    R_B: np.ndarray
    p_B: np.ndarray
    e_pos: np.ndarray
    e_rot: np.ndarray | None = None
    R_X: np.ndarray | None = None
    p_X: np.ndarray | None = None
    markers: np.ndarray | None = None
    residual: np.ndarray | None = None  # (N, k, 3) point residuals (points) or (N, 6) pose residuals

    @property
    def rmse_mm(self) -> float:
        return float(1e3 * np.sqrt(np.mean(self.e_pos ** 2)))

    @property
    def rmse_mrad(self) -> float | None:
        return None if self.e_rot is None else float(1e3 * np.sqrt(np.mean(self.e_rot ** 2)))


def project_so3(M):
    """Nearest rotation(s) to ``M`` (..., 3, 3) in the Frobenius norm (SVD, det fixed to +1)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones(U.shape[:-1])
    D[..., -1] = d
    return (U * D[..., None, :]) @ Vt


def register_base_pose(R, t, R_M, p_M, lever: float = LEVER_M):
    """Base-only registration of measured poses, vectorised over candidates (module docstring).

    ``R`` (C, N, 3, 3), ``t`` (C, N, 3): the chain's tip in the root frame for C candidates;
    ``R_M`` (N, 3, 3), ``p_M`` (N, 3): measured poses. Returns ``R_B`` (C, 3, 3), ``p_B`` (C, 3),
    position and angle residual norms (C, N) in m and rad."""
    w = lever ** 2 / 2.0
    tb = t.mean(axis=1, keepdims=True)
    mb = p_M.mean(axis=0)
    K = np.einsum("cni,nj->cij", t - tb, p_M - mb) + w * np.einsum("cnik,njk->cij", R, R_M)
    # maximise tr(R_B K): K = U S Vᵀ → R_B = V diag(1, 1, det) Uᵀ
    U, _, Vt = np.linalg.svd(K)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    D = np.ones(U.shape[:-1])
    D[..., -1] = d
    R_B = (V * D[..., None, :]) @ np.swapaxes(U, -1, -2)
    p_B = mb - np.einsum("cij,cj->ci", R_B, tb[:, 0])
    pred_p = np.einsum("cij,cnj->cni", R_B, t) + p_B[:, None]
    e_pos = np.linalg.norm(pred_p - p_M, axis=-1)
    dR = np.einsum("nji,cjk,cnkl->cnil", R_M, R_B, R)
    e_rot = np.linalg.norm(so3_log(dR), axis=-1)
    return R_B, p_B, e_pos, e_rot


def register_pose(R, t, R_M, p_M, lever: float = LEVER_M, tools=None) -> Registration:
    """Base and tool registration ``M_i ≈ B·T_i·X`` of N measured poses (module docstring);
    ``R`` (N, 3, 3), ``t`` (N, 3). ``tools`` (C, 4, 4): starting guesses of X (e.g. the fixed
    frames below the tip); each starts an LM run from its base-only registration and the
    lowest cost wins (the cost has local minima far from the answer)."""
    from scipy.optimize import least_squares

    tools = np.eye(4)[None] if tools is None else np.asarray(tools, float)
    Rc = np.einsum("nij,cjk->cnik", R, tools[:, :3, :3])
    tc = np.einsum("nij,cj->cni", R, tools[:, :3, 3]) + t[None]
    R_B0, p_B0, e_p, e_r = register_base_pose(Rc, tc, R_M, p_M, lever)

    def residual(x):
        RB, RX = so3_exp(x[3:6]), so3_exp(x[9:12])
        Rp = RB @ R @ RX
        pp = (RB @ (R @ x[6:9] + t).T).T + x[:3]
        return np.c_[pp - p_M, lever * so3_log(np.einsum("nji,njk->nik", R_M, Rp))].ravel()

    best = None
    for c in np.argsort((e_p ** 2 + (lever * e_r) ** 2).sum(axis=1))[:3]:  # the three best starts
        x0 = np.r_[p_B0[c], so3_log(R_B0[c]), tools[c, :3, 3], so3_log(tools[c, :3, :3])]
        run = least_squares(residual, x0, method="lm")
        if best is None or run.cost < best.cost:
            best = run
    e = best.fun.reshape(-1, 6)
    x = best.x
    return Registration(so3_exp(x[3:6]), x[:3], np.linalg.norm(e[:, :3], axis=1),
                        np.linalg.norm(e[:, 3:], axis=1) / lever, so3_exp(x[9:12]), x[6:9], residual=e)


def _points_linear(R, t, P):
    """Linear initial registration of points (module docstring): (R_B, p_B, markers)."""
    N, k, _ = P.shape
    n_u = 12 + 3 * k
    A = np.zeros((N, k, 3, n_u))
    eye = np.eye(3)
    # G p_ik: row a of G times p_ik → columns 3a..3a+2 of the first 9
    for a in range(3):
        A[:, :, a, 3 * a:3 * a + 3] = P
    A[:, :, :, 9:12] = eye
    for m in range(k):
        A[:, m, :, 12 + 3 * m:15 + 3 * m] = -R
    b = np.broadcast_to(t[:, None, :], (N, k, 3))
    sol, *_ = np.linalg.lstsq(A.reshape(-1, n_u), b.reshape(-1), rcond=None)
    G = project_so3(sol[:9].reshape(3, 3))
    R_B = G.T
    p_B = -R_B @ sol[9:12]
    # markers again with the projected rotation: m_k = mean_i R_iᵀ (G p_ik + g − t_i)
    loc = np.einsum("nji,nkj->nki", R, (P - p_B) @ R_B - t[:, None, :])
    return R_B, p_B, loc.mean(axis=0)


def register_points(R, t, P, weights=None) -> Registration:
    """Base and marker registration ``p_ik ≈ B·T_i·m_k`` (module docstring).

    ``R`` (N, 3, 3), ``t`` (N, 3): the tip in the root frame; ``P`` (N, k, 3) measured points.
    ``weights`` (N,) optional pose weights (0 excludes a pose: rows flagged by a check)."""
    from scipy.optimize import least_squares

    R, t, P = (np.asarray(a, float) for a in (R, t, P))
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
    use = w > 0
    R_B, p_B, m = _points_linear(R[use], t[use], P[use])
    k = P.shape[1]
    sw = np.sqrt(w)[:, None, None]

    def predict(x):
        RB, mk = so3_exp(x[3:6]), x[6:].reshape(k, 3)
        return np.einsum("ij,nkj->nki", RB, np.einsum("nij,kj->nki", R, mk) + t[:, None, :]) + x[:3]

    x0 = np.r_[p_B, so3_log(R_B), m.ravel()]
    res = least_squares(lambda x: ((predict(x) - P) * sw).ravel(), x0, method="lm")
    x = res.x
    e = predict(x) - P
    return Registration(so3_exp(x[3:6]), x[:3], np.linalg.norm(e, axis=-1), markers=x[6:].reshape(k, 3),
                        residual=e)
