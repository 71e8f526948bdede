"""Calibration levels and the choice of the free (identifiable) parameter set.

A *level* names what is estimated — ``registration`` (base + markers, or the
tool frame), ``joint_offset`` (+ offsets) and ``full`` (+ geometry and tool) —
and :func:`select_free` reduces it to an identifiable set on the calibration
data only: columns of the weighted observation matrix in priority order
(markers and method unknowns, base, offsets, geometric, tool — GECARO's
"offsets before geometry before base/tool", with the registration set nested
first because the data frame is unknown); a column is kept when its component
orthogonal to the kept ones is not numerically zero (GECARO App. III, the shared
:func:`estcal.identify.select_identifiable` with the structural tolerance
:data:`~estcal.identify.core.STRUCTURAL_TOL` on unit-norm columns). Dropped columns are reported as *no
effect* or *regrouped* with ``a_j = Σ β_k a_k`` (β = R1⁻¹R2). ``criterion="aic"``
/ ``"bic"`` additionally prunes, greedily, candidates that do not lower the
information criterion of the linearised fit (opt-in).

The calibration job around it (problem, base registration, free set, estimator, accuracy
before/after) is :func:`estcal.workflows.calibrate.run_calibration`.
"""
from __future__ import annotations

import numpy as np

from estcal.identify.core import STRUCTURAL_TOL
from estcal.identify.select import Selection, select_identifiable
from estcal.kinematics.design import design_structure
from estcal.methods.reduced import reduce_system, use_chunks, weighted

from .lsq import calibrate_lsq
from .robust import check_kernel, group_norms, outlier_report

__all__ = ["LEVELS", "level_candidates", "select_free", "robust_report"]

LEVELS = ("registration", "joint_offset", "full")

def level_candidates(pv, level: str, pose_data: bool = False) -> list[list[str]]:
    """Candidate groups of a level, in priority order (the first group is the registration set)."""
    if level not in LEVELS:
        raise ValueError(f"unknown level {level!r}; choose one of {LEVELS}")
    kinds = dict(zip(pv.names, pv.kinds))
    markers = [n for n in pv.names if kinds[n] == "marker"]
    other = [n for n in pv.names if kinds[n] == "other"]  # unknowns added by the methods
    base = [n for n in pv.names if kinds[n] == "base"]
    tool = [n for n in pv.names if kinds[n] == "tool"]
    if markers:
        reg_tool = []
    else:
        reg_tool = [n for n in tool if n.startswith("tool_t") or pose_data]
    groups = [markers + other + base + reg_tool]
    if level in ("joint_offset", "full"):
        groups.append([n for n in pv.names if kinds[n] == "offset"])
    if level == "full":
        groups.append([n for n in pv.names if kinds[n] == "geometric"])
        groups.append([n for n in tool if n not in reg_tool])
    return groups


def _weighted_matrix(problem, theta):
    """``(A, b, M, bᵀb)``; on large data (A, b) = (R, Qᵀb) of :mod:`estcal.methods.reduced` — the
    ordered QR below, the regrouping coefficients and the condition number are invariant under Qᵀ."""
    ck = use_chunks(problem)
    if ck is not None:
        R, c, rss, m = reduce_system(problem, theta, np.arange(len(problem.params.names)), ck)
        return R, c, m, rss
    A, b = weighted(problem.evaluate(theta), slice(None))
    return A, b, A.shape[0], float(b @ b)


def _design_matrix(problem, theta):
    """The weighted observation matrix of the problem's robot at its design structure
    (:func:`estcal.kinematics.design.design_structure`), or None when the robot is its own design."""
    design = design_structure(problem.robot)
    if design is None:
        return None
    structural = problem.with_values(theta)
    structural.robot = design.with_values(theta)
    return _weighted_matrix(structural, theta)[0]


def select_free(problem, level: str = "full", criterion: str = "structural", theta=None,
                groups: list[list[str]] | None = None, known_noise: bool | None = None,
                refine_registration: bool = True, exclude=()) -> Selection:
    """Identifiable free set of a level on the problem's (calibration) data.

    Parameters
    ----------
    problem : :class:`estcal.methods.Problem` (its data: the calibration file only)
    level : ``registration``, ``joint_offset`` or ``full`` (ignored when ``groups`` is given)
    criterion : ``structural`` (QR rank only), ``aic`` (+ Akaike's criterion, see module docstring)
        or ``bic`` (Schwarz: penalty ln M per parameter instead of 2)
    theta : linearisation point (default: the problem's values)
    groups : explicit candidate groups in priority order (first group = always-kept set)
    known_noise : AIC with absolute weights (default: from the problem's noise models)
    refine_registration : linearise at the fit of the first group (registration) for higher levels
    exclude : names reported as *no effect* without looking at their columns (e.g. the
        parameters a structural analysis on consistent simulated data found without effect)

    The scan is :func:`estcal.identify.select_identifiable` — QR without pivoting on the
    priority-sorted, unit-norm columns: ``|R_jj| ≤ STRUCTURAL_TOL`` marks a dependent column
    (GECARO App. III, with the priority order of §1.5 deciding which of dependent columns is kept).
    The columns scanned are those of the robot's design structure
    (:func:`estcal.kinematics.design.design_structure`: consecutive joint axes at their right
    angles) when its constant frames carry calibration errors; the condition number is the data's.
    """
    if criterion not in ("structural", "aic", "bic"):
        raise ValueError(f"unknown selection criterion {criterion!r}; choose 'structural', 'aic' or 'bic'")
    pv = problem.params
    pose = any(t.data.kind == "pose" for t in problem.terms)
    if groups is None:
        groups = level_candidates(pv, level, pose)
    exclude = set(exclude)
    if exclude:
        groups = [[n for n in g if n not in exclude] for g in groups]
    theta = pv.values.copy() if theta is None else np.asarray(theta, float)
    A, b, M, rss = _weighted_matrix(problem, theta)
    first = set(pv.indices(groups[0])) if groups and groups[0] else set()
    order = [pv.index(n) for g in groups for n in g]
    if known_noise is None:
        known_noise = all(t.noise.known for t in problem.terms)
    if refine_registration and len(groups) > 1 and first:
        # Linearise where the registration set fits the data: at the nominal point the
        # unknown markers sit at the tool origin, which creates dependencies (marker vs
        # last-joint placement) that vanish once the markers are located.
        reg_sel = select_free(problem, groups=[groups[0]], theta=theta)
        if reg_sel.identifiable:
            try:
                r0 = calibrate_lsq(problem.with_values(theta), "lm", free=reg_sel.identifiable, check=False)
                theta = r0.theta
                A, b, M, rss = _weighted_matrix(problem, theta)
            except (ValueError, np.linalg.LinAlgError):  # keep the given linearisation point
                pass
    # the rank is the design's: at axes off their right angles by calibration errors, regrouped
    # parameters are separable by terms of the size of those errors (estcal.kinematics.design)
    W = _design_matrix(problem, theta)
    W = A if W is None else W
    n_kept = 0
    pen = np.log(M) if criterion == "bic" else 2.0  # Akaike: 2 per parameter; Schwarz: ln M

    def aic(r, p):
        return r + pen * p if known_noise else M * np.log(max(r, 1e-300) / M) + pen * p

    def accept(i, u):
        # information criterion on the new orthonormal direction u: RSS drops by (uᵀb)²
        nonlocal rss, n_kept
        if criterion == "structural":
            return True
        r_new = rss - float(u @ b) ** 2
        if i not in first and not aic(r_new, n_kept + 1) < aic(rss, n_kept):
            return False
        rss, n_kept = r_new, n_kept + 1
        return True

    sel = select_identifiable(W, names=list(pv.names), order=order, tol=STRUCTURAL_TOL, accept=accept)
    if W is not A and sel.identifiable:  # the condition number is the data's
        kept = pv.indices(sel.identifiable)
        s = np.linalg.svd(A[:, kept] / np.linalg.norm(A[:, kept], axis=0), compute_uv=False)
        sel.condition_number = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    sel.no_effect = [n for n in pv.names if n in exclude] + sel.no_effect
    sel.level, sel.criterion, sel.theta = level, criterion, theta
    return sel


def robust_report(problem, res, kernel, k=None) -> dict:
    """:func:`estcal.estimate.robust.outlier_report` at the estimate — at each batch's state for the
    time-varying smoother (its poses were fitted by their own batch's parameters)."""
    kernel = check_kernel(kernel)
    traj = res.extra.get("trajectory")
    if res.method == "gtsam-timevarying" and traj is not None:
        fidx = problem.params.indices(res.names)
        est = np.asarray(traj["estimate"])
        r = dims = lines = None
        bs = int(traj["batch_size"])
        for b in range(est.shape[0]):
            th = res.theta.copy()
            th[fidx] = est[b]
            rb, db, lb, _ = group_norms(problem, th)
            if r is None:
                r, dims, lines = rb.copy(), db, lb
            r[b * bs:(b + 1) * bs] = rb[b * bs:(b + 1) * bs]
        return outlier_report(problem, res.theta, kernel, k, n_params=len(res.names), norms=(r, dims, lines))
    return outlier_report(problem, res.theta, kernel, k, n_params=len(res.names))
