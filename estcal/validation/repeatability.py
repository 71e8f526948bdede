"""The repeatability floor: how much the same posture, measured again, differs.

Where postures repeat (within a file, or across files and sessions), the spread of
the measurements of one posture about their mean is an error no kinematic model can
remove: the model predicts one point per posture. It is estimated here from the data
alone, twice:

* **raw** — the pooled within-posture spread of the measured points;
* **registered** — the same after a rigid re-registration of every session
  (generalised Procrustes: each session's points rotated and translated onto the
  consensus of the repeated postures, 6 parameters per session after the first).
  What remains is the pose-to-pose repeatability; the difference between raw and
  registered is a per-session rigid shift (the tracker or the robot's base moved,
  re-homing of a base-like offset).

Estimator (per coordinate, k points per row, posture g measured n_g times)::

    σ_c² = Σ_g Σ_i ‖p_gi − p̄_g‖² / (3 k Σ_g (n_g − 1) − 6 (S − 1))      (pooled variance)
    floor = √(3 σ_c²)                                                    (RMS norm, m)

``floor`` is the root-mean-square length of a single measurement's deviation from the
posture mean: the RMSE a model that knew every posture's true mean would score. Two
measurements of a posture differ by √2 · floor in RMS (``difference_rms``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["repeatability_floor"]


def _rigid(P, Q):
    """R, t minimising Σ‖R P_i + t − Q_i‖² (Arun/Kabsch by SVD; P, Q (M, 3))."""
    cp, cq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - cp).T @ (Q - cq))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cq - R @ cp


def _pooled(P, groups, dof_removed: int):
    """(floor m, difference RMS m, dof) of points P (N, k, 3) grouped by ``groups``."""
    labels, inv, counts = np.unique(groups, return_inverse=True, return_counts=True)
    k = P.shape[1]
    means = np.zeros((len(labels), k, 3))
    np.add.at(means, inv, P)
    means /= counts[:, None, None]
    ss = float(np.sum((P - means[inv]) ** 2))
    dof = 3 * k * int(np.sum(counts - 1)) - dof_removed
    if dof <= 0:
        return None, None, dof
    var_c = ss / dof
    return float(np.sqrt(3 * var_c)), float(np.sqrt(6 * var_c)), dof


def repeatability_floor(points, groups, sessions=None, n_iter: int = 20) -> dict | None:
    """Repeatability of the measurements at repeated postures, raw and after per-session registration.

    Parameters
    ----------
    points : (N, k, 3) or (N, 3) measured positions (m): the markers, or the tool origin of pose data.
    groups : (N,) posture labels (:func:`estcal.validation.posture_groups`).
    sessions : (N,) session labels (files, days); default: one session.
    n_iter : generalised-Procrustes iterations.

    Returns
    -------
    ``None`` when no posture is measured twice, else a dict (lengths in mm):
    ``raw_mm``, ``registered_mm`` (the floor, see the module docstring; ``registered_mm`` is
    ``None`` with a single session), ``difference_rms_mm`` ({raw, registered}),
    ``n_repeated_postures``, ``n_rows``, ``n_sessions``, ``within_session_mm`` (floor from
    repeats inside one session only, or ``None``), ``sessions`` ({label: {rotation_mrad,
    translation_mm}} of each session's registration onto the consensus).
    """
    P = np.asarray(points, float)
    if P.ndim == 2:
        P = P[:, None, :]
    g = np.asarray(groups)
    s = np.zeros(len(g), int) if sessions is None else np.asarray(sessions)
    labels, counts = np.unique(g, return_counts=True)
    rep = np.isin(g, labels[counts > 1])
    if not rep.any():
        return None
    P, g, s = P[rep], g[rep], s[rep]
    sess = list(dict.fromkeys(s.tolist()))
    raw, raw_d, _ = _pooled(P, g, 0)
    out = {"raw_mm": raw * 1e3, "n_repeated_postures": int(len(np.unique(g))), "n_rows": int(len(g)),
           "n_sessions": len(sess)}
    # repeats inside one session: label by (session, posture)
    key = np.array([f"{a}|{b}" for a, b in zip(s.tolist(), g.tolist())])
    kl, kc = np.unique(key, return_counts=True)
    inside = np.isin(key, kl[kc > 1])
    w = _pooled(P[inside], key[inside], 0)[0] if inside.any() else None
    out["within_session_mm"] = None if w is None else w * 1e3
    reg, reg_d, info = None, None, {}
    if len(sess) > 1:
        Q = P.copy()
        for _ in range(n_iter):
            labels_g, inv = np.unique(g, return_inverse=True)
            means = np.zeros((len(labels_g),) + P.shape[1:])
            np.add.at(means, inv, Q)
            means /= np.bincount(inv)[:, None, None]
            shared = [sv for sv in sess if len(np.unique(g[s == sv])) >= 2]
            for sv in shared:
                m = s == sv
                R, t = _rigid(P[m].reshape(-1, 3), means[inv[m]].reshape(-1, 3))
                Q[m] = P[m] @ R.T + t
                info[sv] = (R, t)
        n_reg = sum(1 for sv in sess if sv in info)
        reg, reg_d, _ = _pooled(Q, g, 6 * max(n_reg - 1, 0))
        ref = info.get(sess[0])
        for sv, (R, t) in info.items():
            # each session relative to the first: R_rel = R_0ᵀ R_s
            R0, t0 = ref if ref is not None else (np.eye(3), np.zeros(3))
            Rr = R0.T @ R
            ang = float(np.arccos(np.clip((np.trace(Rr) - 1) / 2, -1, 1)))
            info[sv] = {"rotation_mrad": ang * 1e3, "translation_mm": float(np.linalg.norm(R0.T @ (t - t0)) * 1e3)}
    out["registered_mm"] = None if reg is None else reg * 1e3
    out["difference_rms_mm"] = {"raw": raw_d * 1e3, "registered": None if reg_d is None else reg_d * 1e3}
    out["sessions"] = {str(k): v for k, v in info.items()}
    return out
