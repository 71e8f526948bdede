"""Residual analysis of a fitted model: where and how the model disagrees with the data.

For every pose i the residual of the measured points (or pose) ``e_i`` is
attributed to each joint j by its *partial joint residual*

    δq̂_ij = (J_ij ᵀ e_i) / (J_ij ᵀ J_ij),

the joint displacement of joint j alone that best explains pose i's residual
(``J_ij`` is the column of joint j in the pose's weighted rows). A
non-geometric joint effect ``δq_j = θ f(q)`` shows up as structure of δq̂_j
against its feature ``f`` (joint angle, gravity torque, its sign, time, …).
The statistics reported:

* ``noise_floor`` — χ² = Σ(e/σ)², dof, χ²/dof and the upper-tail probability
  P(χ²_dof ≥ χ²) when the noise is known: is the fit at the noise floor?
* ``features`` — for each joint and feature the fraction of the variance of
  δq̂_j explained by a straight line in the feature (R²), and the same for the
  residual norm against time, temperature and the workspace position;
* ``spectrum`` — for each revolute joint the least-squares amplitudes
  √(a_k² + b_k²) of ``δq̂_j ≈ c + Σ_k a_k sin(k q_j) + b_k cos(k q_j)``, k = 1…3,
  and their R² (harmonics of the joint angle).

:func:`residual_figures` draws the corresponding figures (:mod:`estcal.plots.diagnose`).
"""
from __future__ import annotations

import numpy as np

from estcal.plots.diagnose import partial_residuals_figure, residual_norm_figure, spectrum_figure

__all__ = ["residual_analysis", "partial_joint_residuals", "residual_figures", "r2_line"]


def r2_line(x, y) -> float:
    """R² of the least-squares line ``y ≈ a + b x`` (0 when x is constant)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.size < 3 or np.ptp(x) == 0 or np.var(y) == 0:
        return 0.0
    r = np.corrcoef(x, y)[0, 1]
    return float(r * r) if np.isfinite(r) else 0.0


def _r2_basis(F, y) -> float:
    X = np.c_[np.ones(len(y)), F]
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ coef
    tot = np.sum((y - y.mean()) ** 2)
    return float(1 - res @ res / tot) if tot > 0 else 0.0


def partial_joint_residuals(problem, theta):
    """Per-pose partial joint residuals δq̂ (N, n) (rad or m) and their std (N, n).

    Uses the rows of the first term; the joint columns are the Jacobian of the
    measured quantities w.r.t. the joint values (``Kinematics.J_q`` for poses,
    the screw columns for points).
    """
    robot = problem.robot
    term = problem.terms[0]
    data = term.data
    rows = term.method.rows(robot, theta, data, term.noise, jacobian=True)
    # Joint-value columns: the Jacobian w.r.t. the offsets is dq/d(offset) = I.
    Jq = rows.H[:, robot.offset_idx] / rows.sigma[:, None]
    b = rows.e / rows.sigma
    N, n = data.n, robot.n_joints
    pose = rows.pose
    num = np.zeros((N, n))
    den = np.zeros((N, n))
    np.add.at(num, pose, Jq * b[:, None])
    np.add.at(den, pose, Jq * Jq)
    with np.errstate(invalid="ignore", divide="ignore"):
        dq = np.where(den > 0, num / den, 0.0)
        sd = np.where(den > 0, 1.0 / np.sqrt(den), np.inf)
    return dq, sd


def residual_analysis(problem, theta, noise_known: bool, n_params: int, features_extra: dict | None = None,
                      harmonics=(1, 2, 3)) -> dict:
    """Statistics of the residual of ``problem`` at ``theta`` (see module docstring).

    ``features_extra`` adds per-pose features, e.g. ``{"tau": (N, n) gravity torques}``.
    """
    from scipy.special import chdtrc  # scipy.stats.chi2.sf's tail, without importing scipy.stats (~0.3 s)

    robot = problem.robot
    term = problem.terms[0]
    data = term.data
    rows = problem.evaluate(theta, jacobian=False)
    w = rows.e / rows.sigma
    chi2 = float(w @ w)
    M = len(w)
    dof = max(M - n_params, 1)
    floor = {"chi2": chi2, "dof": dof, "chi2_per_dof": chi2 / dof, "noise_known": bool(noise_known),
             "rms_row_mm": float(np.sqrt(np.mean(rows.e[rows.kind == 0] ** 2)) * 1e3)
             if np.any(rows.kind == 0) else None}
    if noise_known:
        floor["p_value"] = float(chdtrc(dof, chi2))
        floor["at_noise_floor"] = bool(floor["p_value"] > 1e-3)
        floor["noise_rms_row_mm"] = float(np.sqrt(np.mean(rows.sigma[rows.kind == 0] ** 2)) * 1e3) \
            if np.any(rows.kind == 0) else None
    # per-pose residual norms
    N = data.n
    pose_sq = np.zeros(N)
    np.add.at(pose_sq, rows.pose, rows.e ** 2 * (rows.kind == 0))
    n_pts = np.bincount(rows.pose, weights=(rows.kind == 0).astype(float), minlength=N) / 3.0
    pose_rms = np.sqrt(pose_sq / np.maximum(n_pts, 1))  # RMS point-error norm per pose (m)

    dq, _ = partial_joint_residuals(problem, theta)
    kin = robot.kinematics(data.readings, theta, data.context, jacobian=False)
    feats = {}
    per_joint = {}
    for j, name in enumerate(robot.joint_names):
        y = dq[:, j]
        if not np.any(y):
            continue
        d = {"angle" if robot.joint_types[j] == "revolute" else "position": r2_line(data.readings[:, j], y)}
        extra = features_extra or {}
        if "tau" in extra:
            t = extra["tau"][:, j]
            d["gravity_torque"] = r2_line(t, y)
            d["sign_gravity_torque"] = r2_line(np.sign(t), y)
        for k in ("t", "temperature"):
            if k in data.context:
                d[k] = r2_line(data.context[k], y)
        ac = f"approach_{name}"
        if ac in data.context:
            d[ac] = r2_line(data.context[ac], y)
        per_joint[name] = {"r2": d, "rms_partial": float(np.sqrt(np.mean(y ** 2)))}
    feats["joints"] = per_joint
    norm = {}
    for ax, c in zip("xyz", kin.p.T):
        norm[f"workspace_{ax}"] = r2_line(c, pose_rms)
    for k in ("t", "temperature", "payload"):
        if k in data.context:
            norm[k] = r2_line(data.context[k], pose_rms)
    feats["residual_norm"] = norm
    spec = {}
    for j, name in enumerate(robot.joint_names):
        if robot.joint_types[j] != "revolute" or not np.any(dq[:, j]):
            continue
        q = data.readings[:, j]
        amps, r2 = [], []
        for k in harmonics:
            F = np.c_[np.sin(k * q), np.cos(k * q)]
            X = np.c_[np.ones(N), F]
            coef, *_ = np.linalg.lstsq(X, dq[:, j], rcond=None)
            amps.append(float(np.hypot(coef[1], coef[2])))
            r2.append(_r2_basis(F, dq[:, j]))
        spec[name] = {"orders": list(harmonics), "amplitude_rad": amps, "r2": r2}
    # the strongest single structures, for the report
    top = []
    for name, d in per_joint.items():
        for f, v in d["r2"].items():
            top.append((v, name, f))
    for name, d in spec.items():
        for k, v in zip(d["orders"], d["r2"]):
            top.append((v, name, f"harmonic{k}"))
    top.sort(reverse=True)
    return {"noise_floor": floor, "features": feats, "spectrum": spec,
            "strongest": [{"joint": n, "feature": f, "r2": float(v)} for v, n, f in top[:8]],
            "pose_rms_mm": (pose_rms * 1e3).tolist(), "partial_joint_residuals_rad": dq.tolist()}


def residual_figures(problem, theta, analysis: dict, tau=None, title: str = "", extended=None) -> dict:
    """The residual figures of a diagnosis, ``{file name: matplotlib Figure}`` (nothing is written:
    :func:`estcal.report.diagnose.diagnose_report` saves them).

    ``partial_residuals.png`` (δq̂_j vs q_j per joint), ``vs_gravity_torque.png``
    (δq̂_j vs τ_j), ``residual_norm.png`` (per-pose residual vs time / workspace),
    ``spectrum.png`` (harmonic amplitudes per joint) and, with ``extended=(problem,
    theta)``, the same partial residuals after the extension
    (``partial_residuals_extended.png``). The figures come from
    :mod:`estcal.plots.diagnose` (no pyplot, no backend switch).
    """
    robot = problem.robot
    data = problem.terms[0].data
    dq = np.asarray(analysis["partial_joint_residuals_rad"])
    names = robot.joint_names
    out = {"partial_residuals.png": partial_residuals_figure(
        data.readings, dq, names, "reading (rad | m)", f"{title} partial joint residuals vs joint reading "
                                                       f"(geometric model)")}
    if tau is not None:
        out["vs_gravity_torque.png"] = partial_residuals_figure(
            tau, dq, names, "gravity torque (N·m | N)", f"{title} partial joint residuals vs gravity torque")
    if extended is not None:
        dq2, _ = partial_joint_residuals(*extended)
        out["partial_residuals_extended.png"] = partial_residuals_figure(
            data.readings, dq2, names, "reading (rad | m)", f"{title} partial joint residuals after the extension")
    pr = np.asarray(analysis["pose_rms_mm"])
    kin = robot.kinematics(data.readings, theta, data.context, jacobian=False)
    xs = [("pose index", np.arange(data.n))] + [(f"tool {a} (m)", kin.p[:, i]) for i, a in enumerate("xyz")]
    if "t" in data.context:
        xs[0] = ("t − t0 (s)", data.context["t"] - data.context["t"].min())
    out["residual_norm.png"] = residual_norm_figure(xs, pr, f"{title} residual norm vs time and workspace position")
    spec = analysis.get("spectrum", {})
    if spec:
        out["spectrum.png"] = spectrum_figure(spec, f"{title} harmonics of the partial joint residuals")
    return out
