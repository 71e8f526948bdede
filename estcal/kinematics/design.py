"""The design structure of a chain whose constant frames carry calibration errors.

Structural identifiability belongs to the *design* (docs/identification.md): consecutive joint
axes of a designed arm are parallel or perpendicular, and which parameters regroup follows
from that. A chain whose constant frames (URDF joint origins) carry a calibrated geometry —
a URDF written by ``estcal export`` from a calibrated model, a vendor's calibrated URDF — has
its axes off those right angles by the calibration errors (milliradians). There, the regrouped
parameters become separable by terms of the order of the errors (|R_jj| ~ 1e-3 … 1e-10 in the
priority-ordered QR instead of round-off): a structural selection would admit them, and the
estimators then find the set rank-deficient or ill-conditioned (condition number ~10⁹ on a
recalibrated PUMA 560 URDF, against 12 at its design).

:func:`design_structure` returns the chain with the angle between each joint axis and the
previous one snapped to the nearest multiple of 90° when it is within
:data:`DESIGN_ANGLE_TOL` of it (the rotation is about the common normal of the two axes, so the
azimuth about the previous axis — a joint offset — is kept). Only the constant frames change;
the parameter vector, and so every parameter name and value, is the same. Chains whose twists
are all parameters (Khalil–Kleinfinger, DH) are unchanged: a saved model of those is analysed at
its design robot's values instead (:func:`estcal.io.savedmodel.design_values`).
"""
from __future__ import annotations

import copy

import numpy as np

__all__ = ["DESIGN_ANGLE_TOL", "design_structure"]

#: Largest deviation (rad) of the angle between consecutive joint axes from a multiple of 90°
#: that is read as a calibration error of a right angle (1.1°: calibrated axes are off by
#: milliradians; a twist designed that close to a right angle would be unusual).
DESIGN_ANGLE_TOL = 0.02


def _rotation(axis, angle) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about the unit vector ``axis``."""
    n = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -n[2], n[1]], [n[2], 0.0, -n[0]], [-n[1], n[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def design_structure(robot, tol: float = DESIGN_ANGLE_TOL):
    """``robot`` with its consecutive joint axes at their designed right angles, or None when
    every angle already is one (to round-off) or is farther than ``tol`` from one.

    For each actuated link that directly follows the previous actuated link, the joint axis in
    the previous link's frame is ``C_R · a`` (``C``: the link's constant frame, ``a``: its local
    axis; the parameter-driven motions are read at zero, as a URDF chain's placement errors are
    when it is loaded); its angle φ to the previous axis is moved to the nearest multiple of π/2 by a rotation
    about their common normal, applied to ``C_R``.
    """
    links = [copy.copy(lk) for lk in robot.links]
    changed = False
    parent = None
    for lk in links:
        if lk.joint is None:
            parent = None  # a constant frame between two joints: its rotation is not a twist of theirs
            continue
        if parent is not None and lk.const is not None:
            R = lk.const[:3, :3]
            a = R @ lk.joint_axis
            phi = float(np.arccos(np.clip(parent @ a, -1.0, 1.0)))
            target = round(phi / (np.pi / 2)) * (np.pi / 2)
            if 1e-12 < abs(phi - target) < tol:
                normal = np.cross(parent, a)
                if np.linalg.norm(normal) < 1e-12:  # nearly (anti)parallel: any normal of the parent axis
                    normal = np.cross(parent, [1.0, 0.0, 0.0] if abs(parent[0]) < 0.9 else [0.0, 1.0, 0.0])
                C = lk.const.copy()
                C[:3, :3] = _rotation(normal, target - phi) @ R
                lk.const = C
                changed = True
        parent = np.asarray(lk.joint_axis, float)
    if not changed:
        return None
    out = robot.copy()
    out.links = links
    return out
