"""Residuals of one problem at many parameter vectors at once (walkers, sigma points).

:meth:`SerialRobot.kinematics` is vectorised over poses for *one* parameter
vector θ. MCMC (every walker of an ensemble) and the unscented filter (every
sigma point) need the residuals at W different θ. :func:`evaluate_many` runs
the forward kinematics of the chain once for all (θ_w, pose_i) pairs — the
same link algebra as ``SerialRobot.kinematics`` (constant transform, the
link's elementary motions, the joint motion ``q = K·r (+ coupling) + offset
(+ θ_j)``, the motions after the joint, markers ``p + R m``) with a leading
walker axis — and forms the rows of the classical methods (``position``,
``location``/``pose``, ``points``) exactly as :mod:`estcal.methods.base` does.

Anything else (robots with non-geometric effects, other methods, Problem-like
objects) falls back to a Python loop over the W vectors, which gives the same
numbers more slowly. ``tests/test_mcmc.py`` checks both paths against
``Problem.evaluate`` θ by θ.
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.transforms import pose_error, rot_axis, rot_x, rot_y, rot_z

__all__ = ["evaluate_many", "batched_kinematics", "can_batch"]

_ROT = {"x": rot_x, "y": rot_y, "z": rot_z}
_AX = {"x": 0, "y": 1, "z": 2}


def _exact_methods():
    from estcal.methods.base import PointsMethod, PoseMethod, PositionMethod

    return (PositionMethod, PoseMethod, PointsMethod)


def can_batch(problem) -> bool:
    """True when :func:`evaluate_many` can use the vectorised path for ``problem``."""
    robot = getattr(problem, "robot", None)
    terms = getattr(problem, "terms", None)
    if robot is None or not terms or getattr(robot, "effects", None) or not hasattr(robot, "links"):
        return False
    ok = _exact_methods()
    return all(type(t.method) in ok for t in terms)


def _segment(const, elems, TH):
    """Local rotation (W, 3, 3) and translation (W, 3) of a constant frame followed by motions."""
    W = TH.shape[0]
    LR = np.broadcast_to(np.eye(3) if const is None else const[:3, :3], (W, 3, 3)).copy()
    Lp = np.broadcast_to(np.zeros(3) if const is None else const[:3, 3], (W, 3)).copy()
    for e in elems:
        v = TH[:, e.param]
        if e.kind == "R":
            LR = LR @ _ROT[e.axis](v)
        else:
            Lp = Lp + LR[:, :, _AX[e.axis]] * v[:, None]
    return LR, Lp


def _mm(R, L):
    """Component-wise product of stacks of 3×3 matrices, layout (3, 3, ...): R·L.

    Nine explicit sums of (W, N) arrays: several times faster than ``matmul`` on
    (W, N, 3, 3) stacks, whose per-matrix overhead dominates for 3×3 blocks.
    """
    out = np.empty(np.broadcast_shapes(R.shape, L.shape))
    for i in range(3):
        for k in range(3):
            out[i, k] = R[i, 0] * L[0, k] + R[i, 1] * L[1, k] + R[i, 2] * L[2, k]
    return out


def _mv(R, v):
    """R (3, 3, ...) times v (3, ...) component-wise."""
    return np.stack([R[i, 0] * v[0] + R[i, 1] * v[1] + R[i, 2] * v[2] for i in range(3)])


def batched_kinematics(robot, readings, TH):
    """Tool rotation (W, N, 3, 3), position (W, N, 3) and markers (W, N, k, 3) for W parameter vectors."""
    TH = np.atleast_2d(np.asarray(TH, float))
    r = np.asarray(readings, float)
    W, N = TH.shape[0], r.shape[0]
    K = TH[:, robot.gain_idx][:, None, :]
    off = TH[:, robot.offset_idx][:, None, :]
    if robot.coupling is None:
        q = K * r[None] + off
    else:
        Cj, Cm = (np.asarray(c, float) for c in robot.coupling)
        q = (K * (r @ Cm.T)[None]) @ Cj.T + off
    # layout: component axes first, then (walker, pose)
    R = np.zeros((3, 3, W, N))
    R[0, 0] = R[1, 1] = R[2, 2] = 1.0
    p = np.zeros((3, W, N))
    for link in robot.links:
        if link.before or not np.array_equal(link.const, np.eye(4)):
            LR, Lp = _segment(link.const, link.before, TH)
            p = p + _mv(R, Lp.T[..., None])
            R = _mm(R, LR.transpose(1, 2, 0)[..., None])  # (3, 3, W, 1)
        if link.joint is not None:
            val = q[:, :, link.joint]
            if link.joint_param >= 0:
                val = val + TH[:, link.joint_param][:, None]
            ax = np.asarray(link.joint_axis, float)
            if link.joint_kind == "R" and ax[0] == 0.0 and ax[1] == 0.0 and ax[2] == 1.0:
                # rotation about local z: mix the first two columns (as the core does)
                c, s = np.cos(val), np.sin(val)
                x0, y0 = R[:, 0].copy(), R[:, 1].copy()
                R[:, 0] = c * x0 + s * y0
                R[:, 1] = c * y0 - s * x0
            elif link.joint_kind == "R":
                R = _mm(R, rot_axis(ax, val).transpose(2, 3, 0, 1))
            else:
                p = p + (R[:, 0] * ax[0] + R[:, 1] * ax[1] + R[:, 2] * ax[2]) * val
        if link.after:
            LR, Lp = _segment(None, link.after, TH)
            p = p + _mv(R, Lp.T[..., None])
            R = _mm(R, LR.transpose(1, 2, 0)[..., None])
    Rout = R.transpose(2, 3, 0, 1)
    pout = p.transpose(1, 2, 0)
    if robot.n_markers:
        m = TH[:, robot.marker_idx]  # (W, k, 3)
        pts = pout[:, :, None, :] + np.einsum("wnij,wkj->wnki", Rout, m)
    else:
        pts = np.zeros((W, N, 0, 3))
    return Rout, pout, pts


def evaluate_many(problem, thetas) -> np.ndarray:
    """Residuals ``e`` (W, M) at every row of ``thetas`` (W, P), rows ordered as ``problem.evaluate``."""
    TH = np.atleast_2d(np.asarray(thetas, float))
    if not can_batch(problem):
        return np.stack([problem.evaluate(th, jacobian=False).e for th in TH])
    from estcal.methods.base import PointsMethod, PoseMethod

    robot = problem.robot
    out = []
    W = TH.shape[0]
    for t in problem.terms:
        d = t.data
        t.method.check(robot, d)
        R, p, pts = batched_kinematics(robot, d.readings, TH)
        if isinstance(t.method, PoseMethod):
            e = pose_error(d.R[None], d.p[None], R, p)
        elif isinstance(t.method, PointsMethod):
            k = d.n_points
            if robot.n_markers < k:
                raise ValueError(f"{d.where}: {k} measured points but the robot defines {robot.n_markers} markers")
            e = d.points[None] - pts[:, :, :k]
        else:  # position: marker 1 when the robot has markers, else the tool origin
            pred = pts[:, :, 0] if robot.n_markers else p
            e = d.points[None, :, 0] - pred
        out.append(e.reshape(W, -1))
    return np.concatenate(out, axis=1)
