"""``compensate``: corrected joint commands from a calibrated model (Python entry point).

A program written on the nominal model sends readings ``q_start`` for a target
it believes they reach. :func:`compensate` returns the readings at which the
*calibrated* model (its parameters and its effects: compliance under the
file's payload or a per-row ``payload``, backlash with ``approach_<joint>``,
thermal expansion with ``temperature`` …) reaches the target, starting from
``q_start`` (which fixes the inverse-kinematics branch), plus the residual of
the solve and, when the model carries a ``calibration:`` block, the predicted
position uncertainty of the reached point. The numerical core is
:mod:`estcal.compensation.solve`; the method is documented in docs/compensation.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.io.robotfile import calibration_covariance, load_robot
from estcal.kinematics.transforms import quat_to_matrix

from .solve import parameter_jacobian, propagate, solve_readings

__all__ = ["CompensationResult", "compensate", "split_targets"]


@dataclass
class CompensationResult:
    """Compensated commands for N rows (SI arrays; ``to_dict`` for JSON).

    Attributes
    ----------
    joint_names : list of str
    readings : (N, n) compensated joint readings (rad / m), inside the joint limits.
    reachable : (N,) bool — position error ≤ ``tol_mm`` (and orientation ≤ ``tol_mrad``).
    error_mm : (N,) position residual of the solve (mm); ``rot_error_mrad`` likewise (or None).
    std_mm : (N,) predicted RMS position error of the reached point from the saved covariance
        (mm), or None when the model has no calibration block; ``rot_std_mrad`` likewise.
    joint_std : (N, n) std of the compensated readings through the implicit function (rad / m; NaN on
        unreachable rows) or None.
    at_limit : (N, n) bool — reading on a joint limit at the solution.
    start_outside : (N,) bool — the starting readings were outside the limits (projected first).
    iterations : (N,) LM steps.
    lines : (N,) CSV line numbers (header = line 1) or row numbers + 2 for in-memory targets.
    """

    joint_names: list
    readings: np.ndarray
    reachable: np.ndarray
    error_mm: np.ndarray
    rot_error_mrad: np.ndarray | None
    std_mm: np.ndarray | None
    rot_std_mrad: np.ndarray | None
    joint_std: np.ndarray | None
    at_limit: np.ndarray
    start_outside: np.ndarray
    iterations: np.ndarray
    lines: np.ndarray
    task_point: str = "tool"
    tol_mm: float = 1e-3
    tol_mrad: float = 1e-3
    covariance_names: list = field(default_factory=list)

    @property
    def unreachable_lines(self) -> list[int]:
        return [int(v) for v in self.lines[~self.reachable]]

    def to_dict(self) -> dict:
        def lst(a, f=1.0):
            return None if a is None else (np.asarray(a, float) * f).tolist()

        unreach = []
        for i in np.flatnonzero(~self.reachable):
            d = {"line": int(self.lines[i]), "error_mm": float(self.error_mm[i]),
                 "joints_at_limit": [j for j, b in zip(self.joint_names, self.at_limit[i]) if b]}
            if self.rot_error_mrad is not None:
                d["rot_error_mrad"] = float(self.rot_error_mrad[i])
            unreach.append(d)
        out = {
            "rows": int(len(self.reachable)), "reachable": int(self.reachable.sum()),
            "unreachable": unreach, "unreachable_lines": self.unreachable_lines,
            "task_point": self.task_point, "tol_mm": self.tol_mm, "tol_mrad": self.tol_mrad,
            "joint_names": list(self.joint_names),
            "max_error_mm": float(self.error_mm[self.reachable].max(initial=0.0)),
            "max_iterations": int(self.iterations.max(initial=0)),
            "start_outside_limits_lines": [int(v) for v in self.lines[self.start_outside]],
            "error_mm": lst(self.error_mm), "rot_error_mrad": lst(self.rot_error_mrad),
            "std_mm": lst(self.std_mm), "rot_std_mrad": lst(self.rot_std_mrad),
            "covariance_parameters": list(self.covariance_names),
        }
        if self.joint_std is not None and self.reachable.any():
            # median over the reachable rows: a row near a singularity has a large, legitimate std
            # on the nearly parallel axes that would dominate a mean
            out["joint_std_median"] = {j: float(v) for j, v in
                                       zip(self.joint_names, np.median(self.joint_std[self.reachable], axis=0))}
        return out


def split_targets(targets, orientations=None):
    """Targets → ``(x (N, 3), R (N, 3, 3) or None)``.

    ``targets``: (N, 3) points, (N, 7) ``x, y, z, qw, qx, qy, qz`` or (N, 4, 4) frames;
    ``orientations``: optional (N, 3, 3) rotations or (N, 4) quaternions (scalar first)."""
    T = np.asarray(targets, float)
    R = None
    if T.ndim == 3 and T.shape[1:] == (4, 4):
        x, R = T[:, :3, 3], T[:, :3, :3]
    elif T.ndim == 2 and T.shape[1] == 7:
        x, R = T[:, :3], quat_to_matrix(T[:, 3:] / np.linalg.norm(T[:, 3:], axis=1, keepdims=True))
    elif T.ndim == 2 and T.shape[1] == 3:
        x = T
    elif T.ndim == 1 and T.shape[0] in (3, 7):
        return split_targets(T[None], orientations)
    else:
        raise ValueError(f"targets must be (N, 3) points, (N, 7) x,y,z,qw,qx,qy,qz or (N, 4, 4) frames; "
                         f"got shape {T.shape}")
    if orientations is not None:
        if R is not None:
            raise ValueError("orientations given twice (in targets and in orientations)")
        O = np.asarray(orientations, float)
        R = quat_to_matrix(O / np.linalg.norm(O, axis=-1, keepdims=True)) if O.shape[-1] == 4 else O
        R = R.reshape(-1, 3, 3)
        if R.shape[0] != x.shape[0]:
            raise ValueError(f"{R.shape[0]} orientations for {x.shape[0]} targets")
    if not np.all(np.isfinite(x)) or (R is not None and not np.all(np.isfinite(R))):
        raise ValueError("targets contain NaN or infinite values")
    return x, R


def compensate(robot, targets, q_start, orientations=None, context: dict | None = None,
               covariance="saved", tol_mm: float = 1e-3, tol_mrad: float = 1e-3, max_iter: int = 100,
               rot_weight_m: float = 0.1, lines=None) -> CompensationResult:
    """Joint readings at which ``robot`` (effects included) reaches ``targets``.

    Parameters
    ----------
    robot : SerialRobot or robot spec (a saved model ``.yaml``, built-in name …).
    targets : (N, 3) points, (N, 7) points + quaternions or (N, 4, 4) frames, world frame, m.
        The point is the tool origin, or marker 1 when the model has markers.
    q_start : (N, n) readings a nominal program would send (fix the IK branch).
    orientations : optional (N, 4) quaternions / (N, 3, 3) rotations of the tool frame.
    context : per-row effect context: ``payload`` (kg), ``approach_<joint>`` (±1),
        ``temperature`` (°C), ``t`` (s); see docs/effects.md.
    covariance : ``"saved"`` (the model's ``calibration:`` block, if any), ``None`` (no
        uncertainty) or ``(names, C)`` in SI.
    tol_mm, tol_mrad : a row is reachable when its residual is within these.
    rot_weight_m : metres per radian weighting orientation against position in the solve.
    lines : CSV line numbers used in messages (default row index + 2).
    """
    import math

    for name, v in (("tol_mm", tol_mm), ("tol_mrad", tol_mrad), ("rot_weight_m", rot_weight_m)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer ≥ 1, got {max_iter!r}")
    robot = load_robot(robot)
    x, R = split_targets(targets, orientations)
    N = x.shape[0]
    q0 = robot.check_readings(q_start, "q_start")
    if q0.shape[0] != N:
        raise ValueError(f"q_start has {q0.shape[0]} rows for {N} targets")
    lines = np.arange(2, N + 2) if lines is None else np.asarray(lines, int)
    use_marker = robot.n_markers > 0
    ctx = dict(context or {})
    for k, v in ctx.items():
        if np.ndim(v) and np.size(v) != N:
            raise ValueError(f"context {k!r} has {np.size(v)} values for {N} targets (give one per row or a scalar)")
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    start_outside = np.any((q0 < lo) | (q0 > hi), axis=1)
    sol = solve_readings(robot, x, q0, R, ctx, rot_weight=rot_weight_m, use_marker=use_marker,
                         max_iter=max_iter)
    err_mm = sol.pos_error * 1e3
    rot_mrad = None if sol.rot_error is None else sol.rot_error * 1e3
    reachable = err_mm <= tol_mm
    if rot_mrad is not None:
        reachable &= rot_mrad <= tol_mrad

    if isinstance(covariance, str):
        if covariance != "saved":
            raise ValueError(f"covariance must be 'saved', None or (names, C), got {covariance!r}")
        covariance = calibration_covariance(robot)
    std = rot_std = jstd = None
    names: list = []
    if covariance is not None:
        names, C = list(covariance[0]), np.asarray(covariance[1], float)
        if C.shape != (len(names), len(names)):
            raise ValueError(f"covariance is {C.shape} for {len(names)} parameter names")
        Jt = parameter_jacobian(robot, sol.readings, ctx, names, use_marker, orientation=R is not None)
        prop = propagate(Jt, C, sol.J_r, rot_weight_m)
        std = prop["position_std"] * 1e3
        rot_std = prop["rotation_std"] * 1e3 if "rotation_std" in prop else None
        # the implicit derivative assumes the target is met; at a best-effort row it is meaningless
        jstd = np.where(reachable[:, None], prop["joint_std"], np.nan)
    return CompensationResult(list(robot.joint_names), sol.readings, reachable, err_mm, rot_mrad, std, rot_std,
                              jstd, sol.at_limit, start_outside, sol.iterations, lines,
                              "marker1" if use_marker else "tool", tol_mm, tol_mrad, names)
