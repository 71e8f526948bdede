"""Rotation helpers of the parallel-robot code, expressed with the shared transforms.

Daney's paper gives platform orientations as Euler angles without naming the
convention; estcal uses ZYX: ``R = Rz(ψ) Ry(θ) Rx(φ)`` for ``(ψ, θ, φ)`` (the URDF
roll–pitch–yaw in reverse order), written out in closed form below.
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.transforms import make_transform, skew, so3_exp, so3_log

__all__ = ["skew", "so3_exp", "so3_log", "euler_zyx_to_matrix", "matrix_to_euler_zyx", "make_T"]


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


def make_T(P, R) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) from positions (..., 3) and rotations (..., 3, 3)."""
    return make_transform(R, P)
