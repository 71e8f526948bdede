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

* **registered + points** (when the model carries a per-session measured point, e.g. a
  marker glued anew for every session: ``tool_rotations`` given) — the same after removing,
  per session, exactly what such a model treats as per-session: the rigid registration *and*
  a change ``d_s`` of the measured points in the tool frame. Model of a measurement of
  posture g in session s (first registered session: R = I, t = 0, d = 0)::

      p_sg = R_s (c_g + R_g d_s) + t_s + ε        (R_g: the tool's orientation at posture g)

  fitted by alternation (consensus c_g; then per session a Kabsch step for R_s, t_s and a
  linear least-squares step for R_sᵀt_s, d_s), 6 + 3k parameters per session after the
  first. ``d_s`` is told from ``t_s`` only through the rotation of the tool between the
  repeated postures: when the stacked ``[I, R_g]`` of a session's repeated postures is
  (numerically) rank-deficient, or no degree of freedom is left, the figure is ``None`` with
  the reason. Sessions that each measure a *different* point of the tool differ by far more
  than their repeatability at the same posture (the TALOS sessions: 35 mm after a rigid
  registration) — that spread is not a floor.

* **registered + zeros** (when the model registers joint zeros per session — an encoder homed
  anew at every start-up: ``zero_jacobians`` given) — the same after removing, per session, the
  rigid registration *and* a change ``z_s`` of those zeros, through the model's derivative ``J_g``
  of the measured points with respect to them at posture g (first-order: a zero moves by
  milliradians)::

      p_sg = R_s (c_g + J_g z_s) + t_s + ε

  fitted by the same alternation (Kabsch for R_s, t_s; linear least squares for R_sᵀt_s, z_s),
  6 + z parameters per session after the first. On TIAGo's two sessions arm_5's zero moved by
  about 14 mrad: the rigid registration alone leaves 0.96 mm, with it 0.44 mm.

``floor`` is the root-mean-square length of a single measurement's deviation from the
posture mean: the RMSE a model that knew every posture's true mean would score. Two
measurements of a posture differ by √2 · floor in RMS (``difference_rms``).
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.transforms import kabsch

__all__ = ["repeatability_floor"]


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


def _point_design(k: int, Rg, s, shared, rcond: float = 1e-6):
    """``(D, None)``: the design (N, k, 3, 3k) of a per-session change of the k measured points — point j of a row
    moves by R_g d_j, so D holds R_g (N, 3, 3), the tool's orientation, in point j's block — or ``(None,
    reason)`` when a session's tool orientation does not vary enough to tell its point from its frame."""
    for sv in shared[1:]:
        m = s == sv
        A = np.concatenate([np.eye(3)[None].repeat(m.sum(), 0), Rg[m]], axis=2).reshape(-1, 6)
        sv_ = np.linalg.svd(A, compute_uv=False)
        if sv_[-1] <= rcond * sv_[0]:
            return None, (f"session {sv}: the tool's orientation does not vary enough across its repeated "
                          f"postures to tell its measured point from its frame")
    D = np.zeros((len(Rg), k, 3, 3 * k))
    for j in range(k):
        D[:, j, :, 3 * j: 3 * j + 3] = Rg
    return D, None


def _per_session(P, g, s, sess, X, kind: str, n_iter: int):
    """(floor m, difference RMS m, reason) after per-session registration and a per-session change (module
    docstring): ``kind`` ``"points"`` (X (N, 3, 3) the tool's orientation per row) or ``"zeros"`` (X (N, k, 3, z)
    the points' derivatives with respect to the zeros). P (N, k, 3) points, g, s (N,) labels."""
    if len(sess) < 2:
        return None, None, "one session: nothing is per session"
    shared = [sv for sv in sess if len(np.unique(g[s == sv])) >= 2]
    if len(shared) < 2:
        return None, None, "fewer than two sessions share two or more postures"
    D, why = _point_design(P.shape[1], X, s, shared) if kind == "points" else (X, None)
    if why:
        return None, None, why
    fl, fd, _, why = _registered(P, g, s, D, shared, n_iter, "a point" if kind == "points" else "the zeros")
    return fl, fd, why


def repeatability_floor(points, groups, sessions=None, n_iter: int = 20, tool_rotations=None,
                        zero_jacobians=None) -> dict | None:
    """Repeatability of the measurements at repeated postures, raw and after per-session registration.

    Parameters
    ----------
    points : (N, k, 3) or (N, 3) measured positions (m): the markers, or the tool origin of pose data.
    groups : (N,) posture labels (:func:`estcal.validation.posture_groups`).
    sessions : (N,) session labels (files, days); default: one session.
    n_iter : generalised-Procrustes iterations.
    tool_rotations : (N, 3, 3) the tool's orientation at every row (the model's), when the model carries a
        per-session measured point: adds ``registered_points_mm`` (module docstring).
    zero_jacobians : (N, k, 3, z) the derivative of every measured point with respect to the z joint zeros the
        model registers per session (m/rad or m/m): adds ``registered_zeros_mm`` (module docstring).

    Returns
    -------
    ``None`` when no posture is measured twice, else a dict (lengths in mm):
    ``raw_mm``, ``registered_mm`` (the floor, see the module docstring; ``registered_mm`` is
    ``None`` with a single session), ``difference_rms_mm`` ({raw, registered}),
    ``n_repeated_postures``, ``n_rows``, ``n_sessions``, ``within_session_mm`` (floor from
    repeats inside one session only, or ``None``), ``sessions`` ({label: {rotation_mrad,
    translation_mm}} of each session's registration onto the consensus); with ``tool_rotations``
    also ``registered_points_mm`` (the floor after per-session registration and point change, ``None``
    when it cannot be estimated) and ``registered_points_reason`` (why not, else ``None``); with
    ``zero_jacobians`` ``registered_zeros_mm`` and ``registered_zeros_reason`` likewise.
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
                R, t = kabsch(P[m].reshape(-1, 3), means[inv[m]].reshape(-1, 3))
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
    for kind, per_row in (("points", tool_rotations), ("zeros", zero_jacobians)):
        if per_row is None:
            continue
        fl, fd, why = _per_session(P, g, s, sess, np.asarray(per_row, float)[rep], kind, 5 * n_iter)
        out[f"registered_{kind}_mm"] = None if fl is None else fl * 1e3
        out[f"registered_{kind}_reason"] = why
        out["difference_rms_mm"][f"registered_{kind}"] = None if fd is None else fd * 1e3
    return out


def _registered(P, g, s, D, shared, n_iter: int, what: str):
    """The floor after every session of ``shared`` (the first the reference) is registered by a rigid motion and
    a change ``x_s`` (p,) that moves a row's points by ``D x_s`` (D (N, k, 3, p) per row) — the model
    ``p_sg = R_s (c_g + D_g x_s) + t_s + ε`` (module docstring), fitted by alternation: the consensus c_g; then
    per session a Kabsch step for R_s, t_s and a linear least-squares step for R_sᵀt_s, x_s. Returns (floor m,
    difference RMS m, dof, None), or (None, None, dof, reason) when no degree of freedom is left."""
    k, n_par = P.shape[1], D.shape[-1]
    keep = np.isin(s, shared)
    P, g, s, D = P[keep], g[keep], s[keep], D[keep]
    dof = 3 * k * (len(g) - len(np.unique(g))) - (6 + n_par) * (len(shared) - 1)
    if dof <= 0:
        return None, None, dof, f"too few repeated postures for a registration and {what} per session"
    par = {sv: (np.eye(3), np.zeros(3), np.zeros(n_par)) for sv in shared}
    labels, inv = np.unique(g, return_inverse=True)
    cnt = np.bincount(inv)[:, None, None]

    def common():  # every measurement mapped into the first session's frame and change, and the consensus
        U = np.empty_like(P)
        for sv, (R, t, x) in par.items():
            m = s == sv
            U[m] = (P[m] - t) @ R - D[m] @ x
        c = np.zeros((len(labels), k, 3))
        np.add.at(c, inv, U)
        return U, c / cnt

    for _ in range(n_iter):
        U, c = common()
        for sv in shared[1:]:
            m = s == sv
            R, t, x = par[sv]
            for _inner in range(3):
                R, t = kabsch((c[inv[m]] + D[m] @ x).reshape(-1, 3), P[m].reshape(-1, 3))
                # R_sᵀ p − c_g = w + D_g x (w = R_sᵀ t): linear in (w, x)
                y = (P[m] @ R - c[inv[m]]).reshape(-1)
                A = np.concatenate([np.broadcast_to(np.eye(3), (int(m.sum()), k, 3, 3)), D[m]], axis=-1)
                sol = np.linalg.lstsq(A.reshape(-1, 3 + n_par), y, rcond=None)[0]
                t, x = R @ sol[:3], sol[3:]
            par[sv] = (R, t, x)
    U, c = common()
    var_c = float(np.sum((U - c[inv]) ** 2)) / dof
    return float(np.sqrt(3 * var_c)), float(np.sqrt(6 * var_c)), dof, None
