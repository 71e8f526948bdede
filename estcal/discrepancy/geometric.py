"""The geometric model the diagnosis starts from, and helpers shared by its steps.

* :func:`geometric_candidates` — the parameters of the standard geometric
  calibration in priority order: base, markers (or tool), joint offsets, link
  parameters, tool. Joint gains are *not* candidates: an encoder gain error is
  one of the non-geometric effects the diagnosis can name.
* the identifiable subset is :func:`estcal.identify.select_identifiable` in priority order
  with the *data-level* tolerance :data:`~estcal.identify.core.DATA_TOL` (1e-4): a column is
  kept when its component orthogonal to the columns kept so far is at least ``tol`` of its
  norm — the diagnosis fits only what the data pin down, not every structurally independent
  column.
* :func:`fit_geometric` — registration (Kabsch), then base + markers, then the
  identifiable set, by Levenberg–Marquardt.
* :func:`gravity_ready` — the robot with gravity expressed in the measurement
  frame and, when the robot file has no masses, a lumped mass model.
"""
from __future__ import annotations

import numpy as np

from estcal.estimate import calibrate_lsq, register_base
from estcal.identify.core import DATA_TOL
from estcal.identify.select import select_identifiable
from estcal.kinematics.chain import SerialRobot
from estcal.kinematics.transforms import rpy_to_matrix
from estcal.methods import Problem

__all__ = ["geometric_candidates", "fit_geometric", "gravity_ready", "weighted_system",
           "orthonormal_basis"]

BASE = ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz"]


def geometric_candidates(robot) -> list[str]:
    """Geometric calibration parameters in priority order (no gains, no effects)."""
    pv = robot.params
    kinds = dict(zip(pv.names, pv.kinds))
    out = [n for n in pv.names if kinds[n] == "base"]
    out += [n for n in pv.names if kinds[n] == "marker"]
    out += [n for n in pv.names if kinds[n] == "offset"]
    out += [n for n in pv.names if kinds[n] == "geometric"]
    out += [n for n in pv.names if kinds[n] == "tool"]
    return out


def weighted_system(problem, theta, names):
    """Weighted residual ``b = e/σ`` and Jacobian columns ``A = H[:, names]/σ`` at ``theta``."""
    rows = problem.evaluate(theta)
    idx = problem.params.indices(names)
    return rows.e / rows.sigma, rows.H[:, idx] / rows.sigma[:, None], rows


def orthonormal_basis(A, tol: float = 1e-9):
    """Orthonormal basis of the column space of ``A`` (SVD, relative tolerance)."""
    if A.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    U, S, _ = np.linalg.svd(A / s, full_matrices=False)
    return U[:, S > tol * max(S.max(), 1e-300)]


def gravity_ready(robot, theta=None, nominal_theta=None):
    """Copy of ``robot`` ready for gravity-driven effects.

    * Gravity is given in the robot's nominal world frame. The measurement frame
      differs from it by the registration correction ``R_fit R_nomᵀ`` of the
      base rotation, so gravity in the measurement frame is ``R_fit R_nomᵀ g``.
    * When the robot has no link masses (``mass == 0`` everywhere) a *lumped*
      model is used: 1 kg at the end frame of every moving link. Each joint's
      compliance then multiplies the torque of these unit masses — one scale
      per joint, the parameterisation of a robot file without inertials.

    Returns ``(robot, lumped)``.
    """
    import dataclasses


    links = list(robot.links)
    lumped = not any(lk.mass > 0 for lk in links)
    if lumped:
        first = min(i for i, lk in enumerate(links) if lk.joint is not None)
        links = [dataclasses.replace(lk, mass=1.0, com=np.zeros(3)) if i >= first else lk
                 for i, lk in enumerate(links)]
    g = robot.gravity.copy()
    if theta is not None and all(n in robot.params for n in BASE):
        idx = robot.params.indices(BASE[3:])
        R_fit = rpy_to_matrix(np.asarray(theta, float)[idx])
        th0 = robot.params.values if nominal_theta is None else np.asarray(nominal_theta, float)
        R_nom = rpy_to_matrix(th0[idx])
        g = R_fit @ R_nom.T @ g
    new = SerialRobot(robot.name, links, robot.params.copy(), robot.joint_names, robot.joint_types, robot.limits,
                      robot.offset_idx, robot.gain_idx, robot.marker_idx, g, robot.payload_mass,
                      robot.payload_com, robot.coupling, robot.convention, list(robot.effects), robot.meta)
    if theta is not None:
        new = new.with_values(theta)
    return new, lumped


def fit_geometric(robot, data, noise, free=None, tol: float = DATA_TOL, register: bool = True, max_iter: int = 100,
                  level: str = "full"):
    """The standard geometric calibration of ``robot`` on ``data``.

    Registration (Kabsch) and a base + marker fit first (so that the identifiable
    set is judged at a sensible linearisation point), then the identifiable
    parameters of :func:`geometric_candidates` (or ``free``) of ``level``:

    * ``full`` — every identifiable one (the issue's "standard geometric calibration");
    * ``aic`` — those an Akaike criterion supports, in priority order
      (:func:`estcal.estimate.levels.select_free` with ``criterion="aic"``);
      structurally identifiable but unsupported parameters stay nominal;
    * ``joint_offset`` — base, markers/tool and joint offsets only.

    Returns ``(problem, result, free_names, dropped_names)``.
    """
    theta = robot.params.values.copy()
    has_base = all(n in robot.params for n in BASE)
    if register and has_base and data.kind in ("position", "points", "pose"):
        theta = register_base(robot, data, theta)
    problem = Problem(robot.with_values(theta), [(None, data, noise)])
    first = [n for n in geometric_candidates(robot) if n.startswith("base_") or n.startswith("marker")]
    if first:
        _, A0, _ = weighted_system(problem, theta, first)
        k0 = select_identifiable(A0, names=first, tol=tol).identifiable
        if k0:
            r0 = calibrate_lsq(problem, "lm", free=k0, check=False, max_iter=max_iter)
            theta = r0.theta
            problem = problem.with_values(theta)
    if level not in ("full", "aic", "joint_offset"):
        raise ValueError(f"unknown geometric level {level!r}; choose full, aic or joint_offset")
    cands = list(free) if free is not None else geometric_candidates(problem.robot)
    if free is None and level == "joint_offset":
        kinds = dict(zip(problem.params.names, problem.params.kinds))
        cands = [n for n in cands if kinds[n] in ("base", "marker", "offset")
                 or (kinds[n] == "tool" and problem.robot.n_markers == 0)]
    _, A, _ = weighted_system(problem, theta, cands)
    sel = select_identifiable(A, names=cands, tol=tol)
    keep, dropped = sel.identifiable, sel.dropped
    if free is None and level == "aic":
        from estcal.estimate.levels import select_free

        # Linearise at the joint-offset solution (offsets before geometry, GECARO's priority),
        # then keep the link/tool parameters that lower AIC.
        kinds = dict(zip(problem.params.names, problem.params.kinds))
        first = [n for n in keep if kinds[n] in ("base", "marker", "offset")]
        rest = [n for n in keep if n not in first]
        r1 = calibrate_lsq(problem.with_values(theta), "lm", free=first, check=False, max_iter=max_iter)
        theta = r1.theta
        problem = problem.with_values(theta)
        sel = select_free(problem, groups=[first, rest], criterion="aic", theta=theta, refine_registration=False)
        dropped = dropped + [n for n in keep if n not in sel.identifiable]
        keep = [n for n in keep if n in sel.identifiable]
    res = calibrate_lsq(problem, "lm", free=keep, check=False, max_iter=max_iter)
    # Re-check at the solution: a parameter can lose identifiability away from nominal.
    _, A, _ = weighted_system(problem, res.theta, keep)
    sel = select_identifiable(A, names=keep, tol=tol)
    keep2, dropped2 = sel.identifiable, sel.dropped
    if dropped2:
        problem = problem.with_values(res.theta)
        res = calibrate_lsq(problem, "lm", free=keep2, check=False, max_iter=max_iter)
        keep, dropped = keep2, dropped + dropped2
    return problem.with_values(res.theta), res, keep, dropped
