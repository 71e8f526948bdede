"""Small vectorised rotation helpers used by the parallel-robot code.

Kept private to :mod:`estcal.parallel` so that the Gough model does not depend
on the exact signatures of :mod:`estcal.kinematics.transforms`; the
conventions are the same (world-frame small-rotation perturbation
``R <- exp([δ]x) R``, orientation error ``δ = log(R_meas R_predᵀ)``).
"""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices ``[v]x`` for ``v`` of shape (..., 3)."""
    v = np.asarray(v, dtype=float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula ``exp([w]x)`` for rotation vectors of shape (..., 3)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + A * K + B * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``w`` with ``exp([w]x) = R`` for R of shape (..., 3, 3)."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    c = np.clip((tr - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    vee = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    s = np.sin(th)
    small = th < 1e-6
    fac = np.where(small, 1.0 + th**2 / 6.0, th / np.where(small, 1.0, s))
    w = fac[..., None] * vee
    # Near pi the antisymmetric part vanishes; recover the axis from R + I.
    near_pi = th > np.pi - 1e-4
    if np.any(near_pi):
        Rp = R[near_pi]
        B = (Rp + np.eye(3)) / 2.0
        idx = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        ax = B[np.arange(len(idx)), :, idx]
        ax = ax / np.linalg.norm(ax, axis=-1, keepdims=True)
        w[near_pi] = ax * th[near_pi][..., None]
    return w


def euler_zyx_to_matrix(angles: np.ndarray) -> np.ndarray:
    """``R = Rz(ψ) Ry(θ) Rx(φ)`` for ``angles = (ψ, θ, φ)`` in rad, shape (..., 3)."""
    a = np.asarray(angles, dtype=float)
    ps, th, ph = a[..., 0], a[..., 1], a[..., 2]
    cps, sps, cth, sth, cph, sph = np.cos(ps), np.sin(ps), np.cos(th), np.sin(th), np.cos(ph), np.sin(ph)
    return np.stack(
        [
            np.stack([cps * cth, cps * sth * sph - sps * cph, cps * sth * cph + sps * sph], -1),
            np.stack([sps * cth, sps * sth * sph + cps * cph, sps * sth * cph - cps * sph], -1),
            np.stack([-sth, cth * sph, cth * cph], -1),
        ],
        -2,
    )


def matrix_to_euler_zyx(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_zyx_to_matrix` (θ in (−π/2, π/2))."""
    R = np.asarray(R, dtype=float)
    ps = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    th = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    ph = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return np.stack([ps, th, ph], -1)


def make_T(P: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) from positions (..., 3) and rotations (..., 3, 3)."""
    P = np.asarray(P, dtype=float)
    R = np.asarray(R, dtype=float)
    T = np.zeros(np.broadcast_shapes(R.shape[:-2], P.shape[:-1]) + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = P
    T[..., 3, 3] = 1.0
    return T
