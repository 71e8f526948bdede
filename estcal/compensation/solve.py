"""Numerical core of compensation: joint readings that make a model reach given targets.

Pure functions on arrays; no file handling (see :mod:`estcal.compensation.core`).

Task
----
For every row i, find readings ``r_i`` (the encoder values a controller commands)
such that the model's task point ``x(r_i, θ̂)`` — the tool origin, or marker 1
when the model has markers (the dataset convention of ``x,y,z``, docs/dataset.md)
— equals the target ``x*_i`` and, when a target orientation ``R*_i`` is given,
``log(R*_i R(r_i, θ̂)ᵀ) = 0``. The residual is

    e_i(r) = [x*_i − x(r) ; w · log(R*_i R(r)ᵀ)]          (m; w in m/rad)

with the conventions of docs/conventions.md (world-frame rotation vector).

Solver
------
Levenberg–Marquardt on the readings, vectorised over all rows (one kinematics
call per iteration for every row still iterating, batched (n × n) solves):

    (J_rᵀ J_r + λ_i μ_i I) Δ_i = J_rᵀ e_i,   r_i ← Π(r_i + Δ_i)   if ‖e‖ decreases

``J_r = J_q · M`` where ``J_q`` is the analytic joint Jacobian of the chain (screw
columns ``a_j × (x − o_j)`` / ``a_j`` through the current joint axes) and
``M = C_j diag(K) C_m`` the linear reading→joint map (GECARO eq. 4). The
effects' own dependence on the readings (a gravity torque changing with the
posture, a gear harmonic of the reading) is left out of ``J_r``: it is small
against ``M`` (compliance: c·∂τ/∂q ≈ 1e-3), so the iteration stays a contraction and,
because the residual itself is always the full model (effects included), the
fixed point is exact; only the rate becomes linear near the solution.

Joint limits (readings, as ``check_units`` treats them) are enforced by
projection Π onto the box and an active set: a reading at a bound whose
gradient pushes it outward is frozen for the step, so a constrained row still
decreases its residual along the free joints instead of stalling.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.kinematics.transforms import so3_log

__all__ = ["SolveResult", "reading_map", "task_residual", "solve_readings", "parameter_jacobian",
           "propagate"]


@dataclass
class SolveResult:
    """Per-row outcome of :func:`solve_readings` (N rows, n joints)."""

    readings: np.ndarray      # (N, n) solution (inside the limits)
    residual: np.ndarray      # (N, 3) or (N, 6) final e (m, and w·rad)
    pos_error: np.ndarray     # (N,) ‖x* − x‖ (m)
    rot_error: np.ndarray | None  # (N,) ‖log(R* Rᵀ)‖ (rad) or None
    iterations: np.ndarray    # (N,) accepted + rejected steps
    at_limit: np.ndarray      # (N, n) bool: reading on a bound at the solution
    J_r: np.ndarray           # (N, d, n) task Jacobian wrt the readings at the solution


def reading_map(robot, theta) -> np.ndarray:
    """``M = C_j diag(K) C_m`` (n, n): joint values change by ``M Δr`` for a reading change ``Δr``
    (without the effects' own dependence on the readings)."""
    K = np.asarray(theta, float)[robot.gain_idx]
    if robot.coupling is None:
        return np.diag(K)
    Cj, Cm = (np.asarray(c, float) for c in robot.coupling)
    return Cj @ np.diag(K) @ Cm


def _task(robot, r, theta, context, use_marker: bool):
    """Task point (N, 3), tool rotation (N, 3, 3) and joint Jacobians (N, 3, n) of both."""
    kin = robot.kinematics(r, theta, context, jacobian=False)
    x = kin.points[:, 0] if use_marker else kin.p
    a, o = kin.joint_axis, kin.joint_origin  # (N, n, 3)
    rot = np.array([t == "revolute" for t in robot.joint_types])
    Jx = np.where(rot[None, :, None], np.cross(a, x[:, None, :] - o), a)  # (N, n, 3)
    Jw = a * rot[None, :, None]
    return x, kin.R, np.swapaxes(Jx, 1, 2), np.swapaxes(Jw, 1, 2)


def task_residual(robot, r, theta, context, target_x, target_R=None, rot_weight: float = 0.1,
                  use_marker: bool = False):
    """Residual ``e`` (N, d) and its Jacobian wrt the readings ``J_r`` (N, d, n); d = 3 or 6.

    ``e(r + Δ) ≈ e(r) − J_r Δ`` (``J_r`` is d(task)/dr, see the module docstring)."""
    x, R, Jx, Jw = _task(robot, r, theta, context, use_marker)
    M = reading_map(robot, theta)
    if target_R is None:
        return target_x - x, Jx @ M
    e = np.concatenate([target_x - x, rot_weight * so3_log(target_R @ np.swapaxes(R, 1, 2))], 1)
    return e, np.concatenate([Jx, rot_weight * Jw], 1) @ M


def _subset_context(context: dict, idx, N: int) -> dict:
    out = {}
    for k, v in (context or {}).items():
        a = np.asarray(v, float)
        out[k] = a if a.ndim == 0 else np.broadcast_to(a.reshape(-1), (N,))[idx]
    return out


def solve_readings(robot, target_x, r_start, target_R=None, context: dict | None = None, theta=None,
                   rot_weight: float = 0.1, use_marker: bool = False, max_iter: int = 100,
                   step_tol: float = 1e-13, lambda0: float = 1e-6) -> SolveResult:
    """Damped least squares (Levenberg–Marquardt) on the readings of N rows at once.

    Parameters
    ----------
    robot : SerialRobot (effects included; ``theta`` default its current values).
    target_x : (N, 3) target points (m). target_R : optional (N, 3, 3) target tool rotations.
    r_start : (N, n) starting readings (the branch of the solution); projected onto the limits.
    context : per-row effect context (``payload``, ``approach_<joint>``, ``temperature``, ``t``).
    rot_weight : w (m/rad) weighting the orientation rows against the position rows.
    use_marker : the task point is marker 1 instead of the tool origin.
    max_iter : most LM steps per row. step_tol : a row stops when its accepted step is below this
        (rad / m) or its residual is numerically zero.
    """
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    r = np.clip(np.asarray(r_start, float).copy(), lo, hi)
    N, n = r.shape
    tx = np.asarray(target_x, float)
    tR = None if target_R is None else np.asarray(target_R, float)

    def evaluate(idx, rr):
        e, J = task_residual(robot, rr, theta, _subset_context(context, idx, N), tx[idx],
                             None if tR is None else tR[idx], rot_weight, use_marker)
        return e, J

    e, J = evaluate(np.arange(N), r)
    cost = np.einsum("nd,nd->n", e, e)
    lam = np.full(N, float(lambda0))
    iters = np.zeros(N, int)
    active = np.ones(N, bool)
    # a residual below this is at the float64 resolution of coordinates of order 1 m
    floor = (1e-14 * max(1.0, float(np.abs(tx).max(initial=0.0)))) ** 2
    active &= cost > floor
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Ja, ea, ra = J[idx], e[idx], r[idx]
        g = np.einsum("ndk,nd->nk", Ja, ea)  # descent direction of ½‖e‖²
        H = np.einsum("ndk,ndl->nkl", Ja, Ja)
        frozen = ((ra <= lo) & (g < 0)) | ((ra >= hi) & (g > 0))
        free = ~frozen
        mu = np.maximum(np.trace(H, axis1=1, axis2=2) / n, 1e-30)
        Hf = H * free[:, :, None] * free[:, None, :]
        diag = np.where(free, (lam[idx] * mu)[:, None], 1.0)
        Hf[:, np.arange(n), np.arange(n)] += diag
        delta = np.linalg.solve(Hf, (g * free)[..., None])[..., 0]
        r_try = np.clip(ra + delta, lo, hi)
        e_try, J_try = evaluate(idx, r_try)
        c_try = np.einsum("nd,nd->n", e_try, e_try)
        iters[idx] += 1
        ok = c_try < cost[idx]
        acc = idx[ok]
        r[acc], e[acc], J[acc], cost[acc] = r_try[ok], e_try[ok], J_try[ok], c_try[ok]
        lam[acc] = np.maximum(lam[acc] / 10.0, 1e-12)
        lam[idx[~ok]] *= 10.0
        step = np.abs(r_try - ra).max(axis=1)
        done = (ok & (step < step_tol)) | (cost[idx] <= floor) | (lam[idx] > 1e12) | (~ok & (step < step_tol))
        active[idx[done]] = False
    x_err = np.linalg.norm(e[:, :3], axis=1)
    rot_err = None if tR is None else np.linalg.norm(e[:, 3:], axis=1) / rot_weight
    at_limit = (r <= lo) | (r >= hi)
    return SolveResult(r, e, x_err, rot_err, iters, at_limit, J)


def parameter_jacobian(robot, r, context, names, use_marker: bool = False, orientation: bool = False,
                       theta=None) -> np.ndarray:
    """d(task)/dθ_names (N, 3 or 6, p) at readings ``r`` with the readings held fixed
    (the chain's analytic identification Jacobian, effect columns included)."""
    kin = robot.kinematics(r, theta, context, jacobian=True)
    cols = robot.params.indices(names)
    Jx = kin.J_points[:, 0][..., cols] if use_marker else kin.J[:, :3][..., cols]
    if orientation:
        return np.concatenate([Jx, kin.J[:, 3:][..., cols]], 1)
    return Jx


def propagate(J_theta, C, J_r=None, rot_weight: float = 0.1) -> dict:
    """First-order covariance propagation of the parameter covariance ``C`` (p, p).

    * ``position_std`` (N,): ``√tr(J_x C J_xᵀ)`` (m), the RMS length of the error of the point
      reached by the *fixed* commands on a robot whose parameters are θ̂ + δθ, δθ ~ N(0, C).
    * ``rotation_std`` (N,) (rad) likewise for the orientation rows when ``J_theta`` has 6 rows.
    * ``joint_std`` (N, n) when ``J_r`` (the weighted task Jacobian wrt the readings) is given:
      std of the compensated readings themselves, through the implicit function
      ``dr*/dθ = J_r⁺ J_task,θ`` (minimum-norm pseudo-inverse for redundant tasks).
    """
    J_theta = np.asarray(J_theta, float)
    S = np.einsum("ndp,pq,neq->nde", J_theta, C, J_theta)
    out = {"position_std": np.sqrt(np.clip(np.trace(S[:, :3, :3], axis1=1, axis2=2), 0, None))}
    if J_theta.shape[1] == 6:
        out["rotation_std"] = np.sqrt(np.clip(np.trace(S[:, 3:, 3:], axis1=1, axis2=2), 0, None))
    if J_r is not None:
        Jt = J_theta.copy()
        if Jt.shape[1] == 6:
            Jt[:, 3:] *= rot_weight
        D = np.linalg.pinv(J_r, rcond=1e-10) @ Jt  # (N, n, p)
        Sr = np.einsum("nkp,pq,nlq->nkl", D, C, D)
        out["joint_std"] = np.sqrt(np.clip(np.diagonal(Sr, axis1=1, axis2=2), 0, None))
    return out
