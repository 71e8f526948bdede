"""Rotation helpers of the parallel-robot code, expressed with the shared transforms.

Daney's paper gives platform orientations as Euler angles without naming the
convention; estcal uses ZYX: ``R = Rz(ψ) Ry(θ) Rx(φ)`` for ``(ψ, θ, φ)`` (the URDF
roll–pitch–yaw in reverse order), converted by ``scipy.spatial.transform.Rotation``.
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.transforms import make_transform, skew, so3_exp, so3_log

__all__ = ["skew", "so3_exp", "so3_log", "euler_zyx_to_matrix", "matrix_to_euler_zyx", "make_T"]


def euler_zyx_to_matrix(angles: np.ndarray) -> np.ndarray:
    """``R = Rz(ψ) Ry(θ) Rx(φ)`` for ``angles = (ψ, θ, φ)`` in rad, shape (..., 3): intrinsic
    Z-Y′-X″ Euler angles, ``scipy.spatial.transform.Rotation.from_euler("ZYX", …)``."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(angles, dtype=float)
    return Rotation.from_euler("ZYX", a.reshape(-1, 3)).as_matrix().reshape(a.shape[:-1] + (3, 3))


def matrix_to_euler_zyx(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_zyx_to_matrix` (θ in [−π/2, π/2])."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("ZYX").reshape(R.shape[:-2] + (3,))


def make_T(P, R) -> np.ndarray:
    """Homogeneous transforms (..., 4, 4) from positions (..., 3) and rotations (..., 3, 3)."""
    return make_transform(R, P)
