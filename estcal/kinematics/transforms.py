"""Rotations and rigid transforms, vectorised over a leading batch axis.

Conventions (documented once, used everywhere in estcal)
-------------------------------------------------------
* A transform ``T_a_b`` maps coordinates in frame *b* to frame *a*:
  ``p_a = R_a_b @ p_b + p_a_b`` (pytransform3d / GTSAM naming).
* Roll–pitch–yaw follows URDF: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
* Quaternions are scalar-first ``(w, x, y, z)``.
* A pose error between a measured and a predicted frame is the 6-vector
  ``[p_meas - p_pred ; log(R_meas R_pred^T)]`` expressed in the common
  (world / measurement) frame; this is GECARO eq. [21] with the rotation
  taken as a proper matrix logarithm (GECARO eq. [23]-[24], "method 2").
* Units: metres and radians.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "rot_x", "rot_y", "rot_z", "rot_axis", "skew", "cross", "rpy_to_matrix", "matrix_to_rpy",
    "quat_to_matrix", "matrix_to_quat", "so3_exp", "so3_log", "pose_error",
    "make_transform", "invert_transform", "so3_right_jacobian_inv", "kabsch",
]


def _c_s(angle):
    a = np.asarray(angle, dtype=float)
    return np.cos(a), np.sin(a)


def rot_x(angle):
    """Rotation matrix about x, shape ``angle.shape + (3, 3)``."""
    c, s = _c_s(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(angle):
    """Rotation matrix about y, shape ``angle.shape + (3, 3)``."""
    c, s = _c_s(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(angle):
    """Rotation matrix about z, shape ``angle.shape + (3, 3)``."""
    c, s = _c_s(angle)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def skew(v):
    """Skew-symmetric matrix ``[v]x`` with ``[v]x @ w == cross(v, w)``; shape ``v.shape[:-1] + (3, 3)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def cross(a, b) -> np.ndarray:
    """``a × b`` over the last axis (length 3), the other axes broadcast: np.cross's products without its
    axis moves (several times faster on the small stacked arrays of the gravity loads and the link tilt,
    which evaluate it tens of thousands of times in a prior-model diagnosis)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def cross_at(a, b, axis: int, out=None) -> np.ndarray:
    """``a × b`` along ``axis`` (length 3; the other axes broadcast) into ``out`` (allocated when None): the
    products of :func:`cross` in the same order, for arrays whose coordinates are not the last axis (the
    Jacobians' (N, k, 3, P) point columns, corrected in place without a transposed copy)."""
    if out is None:
        out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    lead = (slice(None),) * axis
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        o = out[lead + (i,)]
        np.multiply(a[lead + (j,)], b[lead + (k,)], out=o)
        np.subtract(o, a[lead + (k,)] * b[lead + (j,)], out=o)
    return out


def rot_axis(axis, angle):
    """Rotation about a unit ``axis`` (3,) by ``angle`` (any shape): Rodrigues' formula.

    R = I + sin(a) K + (1 - cos(a)) K^2 with K = [u]x (textbook eq. 2.73).
    """
    u = np.asarray(axis, dtype=float)
    u = u / np.linalg.norm(u)
    K = skew(u)
    c, s = _c_s(angle)
    return np.eye(3) + s[..., None, None] * K + (1.0 - c)[..., None, None] * (K @ K)


def rpy_to_matrix(rpy):
    """URDF roll-pitch-yaw (..., 3) -> rotation (..., 3, 3): ``Rz(y) Ry(p) Rx(r)``."""
    rpy = np.asarray(rpy, dtype=float)
    return rot_z(rpy[..., 2]) @ rot_y(rpy[..., 1]) @ rot_x(rpy[..., 0])


def matrix_to_rpy(R):
    """Inverse of :func:`rpy_to_matrix` (pitch in [-pi/2, pi/2])."""
    R = np.asarray(R, dtype=float)
    # atan2 of (sin, cos) rather than arcsin: arcsin loses half the digits near pitch = ±90°
    # (a rotation saved as rpy then reloaded 5e-12 away instead of bit-exact)
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def _scipy_rotation(x, tail: int):
    """``(scipy Rotation, leading shape)`` for arrays (..., k) / (..., 3, 3) of any leading shape."""
    from scipy.spatial.transform import Rotation

    x = np.asarray(x, dtype=float)
    lead = x.shape[:-tail]
    return Rotation, x.reshape((-1,) + x.shape[len(lead):]), lead


def quat_to_matrix(q):
    """Unit quaternion (..., 4) scalar-first -> rotation matrix (..., 3, 3). Normalises the input.

    The closed form of the rotation of a unit quaternion (Shuster 1993, eq. 161; what
    ``scipy.spatial.transform.Rotation.from_quat(...).as_matrix()`` computes, equal to it to
    round-off, tested): written out in numpy because every dataset with orientations goes
    through it and importing ``scipy.spatial`` for it cost a fifth of a small command's start-up."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    R = np.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
                  2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
                  2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], axis=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R):
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4), scalar-first, w >= 0
    (``scipy.spatial.transform.Rotation``, canonical sign)."""
    Rotation, R, lead = _scipy_rotation(R, 2)
    return Rotation.from_matrix(R).as_quat(canonical=True, scalar_first=True).reshape(lead + (4,))


def so3_exp(w):
    """Rotation vector (..., 3) -> rotation matrix (..., 3, 3) (Rodrigues, series near 0)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    K = skew(w)
    return np.eye(3) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_log(R):
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3), angle in [0, pi].

    Accurate near 0 (series) and near pi (axis from the symmetric part).
    """
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    cos = np.clip((tr - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = th < 1e-6
    sin = np.sin(th)
    factor = np.where(small, 0.5 + th**2 / 12.0, th / (2.0 * np.where(small, 1.0, sin)))
    out = factor[..., None] * v
    near_pi = th > np.pi - 1e-4
    if np.any(near_pi):
        Rp = R[near_pi]
        B = (Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - np.eye(3) * cos[near_pi][..., None, None]
        B = B / np.maximum(1.0 - cos[near_pi], 1e-300)[..., None, None]
        idx = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(B.shape[0]), idx]
        axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.sign(np.sum(axis * v[near_pi], -1))
        sign = np.where(sign == 0, 1.0, sign)
        out[near_pi] = axis * (sign * th[near_pi])[..., None]
    return out


def pose_error(R_meas, p_meas, R_pred, p_pred):
    """6-vector pose error ``[p_meas - p_pred ; log(R_meas R_pred^T)]`` (..., 6), world frame."""
    dR = np.asarray(R_meas) @ np.swapaxes(np.asarray(R_pred), -1, -2)
    return np.concatenate([np.asarray(p_meas) - np.asarray(p_pred), so3_log(dR)], -1)


def make_transform(R, p):
    """Stack R (..., 3, 3) and p (..., 3) into homogeneous (..., 4, 4)."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], p.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T):
    """Inverse of homogeneous transforms (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return make_transform(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def so3_right_jacobian_inv(phi):
    """Inverse right Jacobian of SO(3) at rotation vectors ``phi`` (..., 3) -> (..., 3, 3).

    ``log(exp(φ) exp(δ)) ≈ φ + J_r⁻¹(φ) δ`` with
    ``J_r⁻¹ = I + ½[φ]x + (1/θ² − (1 + cos θ)/(2 θ sin θ)) [φ]x²`` (series near 0).
    """
    phi = np.asarray(phi, dtype=float)
    th = np.linalg.norm(phi, axis=-1)
    small = th < 1e-5
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th**2 / 720.0,
                 1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(np.where(small, 1.0, ths))))
    K = skew(phi)
    return np.eye(3) + 0.5 * K + c[..., None, None] * (K @ K)


def kabsch(P, Q):
    """Rotation R and translation t minimising Σ‖R P_i + t − Q_i‖² (P, Q: (M, 3)): the absolute orientation
    problem in its SVD form (Arun, Huang & Blostein 1987; Kabsch 1976), det(R) = +1."""
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    cp, cq = P.mean(0), Q.mean(0)
    H = (P - cp).T @ (Q - cq)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cq - R @ cp
