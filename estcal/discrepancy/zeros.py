"""Joint zeros that moved between sessions, decided on a validation file's rows at seen postures.

A robot whose encoders are homed at start-up, or whose absolute encoder slipped, reads every posture of a
new session with its joint zero shifted. A model identified in one session is then wrong by that shift in
the next one, wherever it is used — it is not an error of the model (no parameter of it can know), it is a
change of the session, like its measuring frame. A validation file from another session that repeats some
training postures measures it: :func:`moved_zeros` tests, on those rows alone (never on the rows it scores),
whether letting one joint's zero move lowers the error at held-out postures, one joint at a time.

The test, on the seen rows linearised at their registered frame (weighted residual ``r``, columns ``X`` of
the frame's six parameters and of the candidate zeros): the leave-one-posture-out residual of the least-
squares fit, ``r_(−g) = (I − H_gg)⁻¹ r̂_g`` (``H`` the hat matrix, ``r̂`` the fitted residual; the grouped
deletion formula of Belsley, Kuh & Welsch 1980, §2.1), summed over each posture's rows. A zero moves when
its column lowers that sum by more than three standard errors of the per-posture differences (the best of
several joints is taken: on a simulated robot re-measured with no zero moved, two standard errors moved a
zero — by a twentieth of a milliradian — in 2 of 40 draws, three in none) and it is then kept in the frame's
registration; the next joint is tried on top of it.
The moved zero's standard deviation is the grouped jackknife of its estimate (the rows of a posture share
a rigid error: a covariance from independent rows would be too narrow).
"""
from __future__ import annotations

import numpy as np

__all__ = ["moved_zeros", "zero_parameters", "MIN_POSTURES"]

#: a zero is tested only on this many seen postures or more (the leave-one-posture-out needs them)
MIN_POSTURES = 8
#: a zero moves when its held-out gain exceeds this many standard errors (module docstring)
SE_RULE = 3.0


def zero_parameters(robot) -> list[tuple[str, str]]:
    """``[(joint, its zero's parameter)]``: the ``offset`` parameters, named ``offset_<joint>`` (URDF chains) or
    ``offset_<i>`` (i = 1…n, Khalil–Kleinfinger robots)."""
    names = set(robot.params.names)
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    out = []
    for i, j in enumerate(robot.joint_names):
        for n in (f"offset_{j}", f"offset_{i + 1}"):
            if n in names and kinds[n] == "offset":
                out.append((j, n))
                break
    return out


def _groups(pose):
    """The rows of each posture as index arrays, grouped by their number of rows: ``{m: (G, m)}``."""
    order = np.argsort(pose, kind="stable")
    labels, starts, counts = np.unique(pose[order], return_index=True, return_counts=True)
    by = {}
    for s, c in zip(starts, counts):
        by.setdefault(int(c), []).append(order[s: s + c])
    return {m: np.stack(v) for m, v in by.items()}, len(labels)


def _loo(X, r, groups):
    """Per posture: the squared leave-one-posture-out residual (G,), and the estimates without it (G, p)."""
    Q, R = np.linalg.qr(X)
    coef = np.linalg.solve(R, Q.T @ r)
    fitted = r - X @ coef
    sq, est = [], []
    for m, idx in groups.items():
        Qg = Q[idx]  # (G, m, p)
        Hgg = Qg @ np.swapaxes(Qg, 1, 2)
        e = np.linalg.solve(np.eye(m) - Hgg, fitted[idx][..., None])  # (G, m, 1)
        sq.append(np.sum(e[..., 0] ** 2, axis=1))
        # coef_(−g) = coef − (XᵀX)⁻¹ X_gᵀ e_(−g): with X = QR, (XᵀX)⁻¹ X_gᵀ = R⁻¹ Q_gᵀ
        est.append(coef - np.linalg.solve(R, (np.swapaxes(Qg, 1, 2) @ e)[..., 0].T).T)
    return np.concatenate(sq), np.concatenate(est), coef


def moved_zeros(robot, theta, data, frame, max_joints: int = 2) -> list[dict]:
    """The joint zeros that moved between the training session and ``data``'s (module docstring).

    Parameters
    ----------
    robot : the model (with ``offset_<joint>`` parameters); theta : (P,) its parameters with ``data``'s frame
        registered; data : the validation file's rows at seen postures; frame : the six frame parameter names
        (registered with the zeros); max_joints : most zeros moved.

    Returns
    -------
    ``[{"joint", "parameter", "value" (rad or m), "std", "cv_gain" (share of the seen rows' held-out squared
    error the zero removes)}]`` in the order they were chosen; empty when no zero moved or the data have fewer
    than :data:`MIN_POSTURES` postures.
    """
    from estcal.methods import NoiseModel, Problem

    cands = zero_parameters(robot)
    if not cands:
        return []
    ev = Problem(robot, [(None, data, NoiseModel(known=False))]).evaluate(theta, jacobian=True)
    groups, n_post = _groups(np.asarray(ev.pose))
    if n_post < MIN_POSTURES:
        return []
    r = ev.e / ev.sigma
    A = ev.H / ev.sigma[:, None]
    cols = list(robot.params.indices(list(frame)))
    base_sq, _, _ = _loo(A[:, cols], r, groups)
    chosen = []
    while len(chosen) < max_joints:
        best = None
        for j, name in cands:
            k = robot.params.index(name)
            if k in cols or not np.any(A[:, k]):
                continue
            sq, est, coef = _loo(A[:, cols + [k]], r, groups)
            d = base_sq - sq
            gain, se = float(d.sum()), float(np.sqrt(len(d)) * d.std(ddof=1))
            if gain > SE_RULE * se and (best is None or gain > best[0]):
                best = (gain, j, name, k, sq, est[:, -1])
        if best is None:
            break
        gain, j, name, k, sq, loo_est = best
        jack = float(np.sqrt((len(loo_est) - 1) / len(loo_est) * np.sum((loo_est - loo_est.mean()) ** 2)))
        chosen.append({"joint": j, "parameter": name, "cv_gain": gain / float(base_sq.sum()), "std": jack})
        cols.append(k)
        base_sq = sq
    return chosen
