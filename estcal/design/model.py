"""The linearised measurement model an experiment design works on.

A :class:`DesignModel` turns a batch of plans (joint readings) into the
identification-Jacobian blocks and the information matrix

.. math::  M(Q) = \\sum_i J_i^T W J_i + \\Sigma_0^{-1}

for a robot, a measurement method and a noise model. The Jacobian rows are the
same ones the measurement models of :mod:`estcal.methods` stack
(``kinematics(...).J`` rows of the free parameters, world frame), so ``M⁻¹``
is the covariance the least-squares / MAP / Kalman estimators report for the
same poses, noise and prior (tested in ``tests/test_design_model.py``).

Methods
-------
``position``  one point: marker 1 if the robot has markers, else the tool origin (3 rows, σ in m)
``pose``      tool position + orientation (6 rows; σ in m and ``sigma_rot`` in rad)
``points``    positions of all marker points (3 k rows, σ in m)
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.identify.core import STRUCTURAL_TOL
from estcal.identify.select import select_identifiable
from estcal.io.savedmodel import design_values
from estcal.kinematics.chain import SerialRobot
from estcal.kinematics.robots import get_builtin

from .criteria import accuracy_map, covariance

__all__ = ["DesignModel", "identifiable_subset", "resolve_robot", "ToolBox"]

METHODS = ("position", "pose", "points")


def resolve_robot(spec) -> SerialRobot:
    """A robot from a :class:`SerialRobot`, a built-in name, a robot file or a URDF.

    Uses :func:`estcal.io.robotfile.load_robot` when that module exists, else the
    built-ins of :mod:`estcal.kinematics.robots`.
    """
    if isinstance(spec, SerialRobot):
        return spec
    try:
        from estcal.io.robotfile import load_robot  # type: ignore
    except Exception:  # pragma: no cover - depends on the tree state
        load_robot = None
    if load_robot is not None:
        return load_robot(spec)

    return get_builtin(str(spec))


@dataclass
class DesignModel:
    """Robot + method + free parameters + noise (+ prior) for experiment design.

    Parameters
    ----------
    robot : SerialRobot
    method : 'position', 'pose' or 'points'
    free : list of str, optional
        Parameters to identify (default: the robot's free parameters). Fixed
        parameters are assumed exactly known.
    sigma : float
        Standard deviation of each position coordinate (m), per coordinate
        (Klimchik's convention, E(ε εᵀ) = σ² I).
    sigma_rot : float, optional
        Standard deviation of each orientation component (rad), ``pose`` only.
    prior_cov : (p, p) array, optional
        Prior covariance of the free parameters; its inverse is added to ``M``.
    theta : (P,) array, optional
        Linearisation point (full parameter vector); default the robot's values.
    """

    robot: SerialRobot
    method: str = "position"
    free: list | None = None
    sigma: float = 1e-3
    sigma_rot: float | None = None
    prior_cov: np.ndarray | None = None
    theta: np.ndarray | None = None
    _idx: np.ndarray = field(default=None, init=False, repr=False)

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {METHODS}")
        if self.method == "points" and self.robot.n_markers == 0:
            raise ValueError(f"method 'points' needs marker points; robot {self.robot.name!r} has none")
        if self.method == "pose" and self.sigma_rot is None:
            raise ValueError("method 'pose' needs sigma_rot (rad)")
        self.free = list(self.robot.params.free_names if self.free is None else self.free)
        self._idx = self.robot.params.indices(self.free)
        self.theta = self.robot.params.values.copy() if self.theta is None else np.asarray(self.theta, float)
        if self.prior_cov is not None:
            self.prior_cov = np.asarray(self.prior_cov, float)
            if self.prior_cov.shape != (self.p, self.p):
                raise ValueError(f"prior_cov must be ({self.p}, {self.p}) for free parameters {self.free}")

    # ----------------------------------------------------------- sizes
    @property
    def p(self) -> int:
        return len(self.free)

    @property
    def n_joints(self) -> int:
        return self.robot.n_joints

    @property
    def rows_per_pose(self) -> int:
        return {"position": 3, "pose": 6, "points": 3 * self.robot.n_markers}[self.method]

    @property
    def row_sigma(self) -> np.ndarray:
        """(r,) standard deviation of each measurement row."""
        if self.method == "pose":
            return np.array([self.sigma] * 3 + [self.sigma_rot] * 3, float)
        return np.full(self.rows_per_pose, float(self.sigma))

    @property
    def prior_information(self) -> np.ndarray | None:
        return None if self.prior_cov is None else np.linalg.inv(self.prior_cov)

    def with_prior(self, prior_cov) -> "DesignModel":
        return DesignModel(self.robot, self.method, list(self.free), self.sigma, self.sigma_rot,
                           None if prior_cov is None else np.asarray(prior_cov, float), self.theta.copy())

    def with_free(self, free) -> "DesignModel":
        return DesignModel(self.robot, self.method, list(free), self.sigma, self.sigma_rot, None,
                           self.theta.copy())

    # ------------------------------------------------------- Jacobians
    def _flat(self, Q):
        Q = np.asarray(Q, float)
        if Q.shape[-1] != self.n_joints:
            raise ValueError(f"plan has {Q.shape[-1]} joint columns, robot {self.robot.name!r} has "
                             f"{self.n_joints} ({self.robot.joint_names})")
        return Q.reshape(-1, self.n_joints), Q.shape[:-1]

    def jacobian(self, Q) -> np.ndarray:
        """Measurement Jacobian blocks (..., r, p) for readings ``Q`` (..., n)."""
        flat, lead = self._flat(Q)
        kin = self.robot.kinematics(flat, self.theta, jacobian=True)
        if self.method == "position":  # as PositionMethod: marker 1 if the robot has markers
            J = (kin.J_points[:, 0] if self.robot.n_markers else kin.J[:, :3])[:, :, self._idx]
        elif self.method == "pose":
            J = kin.J[:, :, self._idx]
        else:
            J = kin.J_points[..., self._idx].reshape(flat.shape[0], -1, self.p)
        return J.reshape(lead + J.shape[1:])

    def position_jacobian(self, Q) -> np.ndarray:
        """Tool-position Jacobian (..., 3, p) — the prediction rows of the test-pose criterion."""
        flat, lead = self._flat(Q)
        J = self.robot.kinematics(flat, self.theta, jacobian=True).J[:, :3][:, :, self._idx]
        return J.reshape(lead + (3, self.p))

    def positions(self, Q) -> np.ndarray:
        flat, lead = self._flat(Q)
        return self.robot.kinematics(flat, self.theta, jacobian=False).p.reshape(lead + (3,))

    def pose_information(self, Q) -> np.ndarray:
        """Per-pose information ``J_iᵀ W J_i`` (..., p, p) (no prior)."""
        J = self.jacobian(Q)
        w = 1.0 / self.row_sigma ** 2
        return np.einsum("...rp,r,...rq->...pq", J, w, J, optimize=True)

    def information(self, Q, include_prior: bool = True) -> np.ndarray:
        """``M = Σ_i J_iᵀ W J_i (+ Σ₀⁻¹)`` for plans ``Q`` (..., m, n) → (..., p, p)."""
        Q = np.asarray(Q, float)
        if Q.ndim == 1:
            Q = Q[None]
        M = self.pose_information(Q).sum(-3)
        if include_prior and self.prior_cov is not None:
            M = M + self.prior_information
        return M

    def covariance(self, Q) -> np.ndarray:
        """Predicted parameter covariance ``(JᵀWJ + Σ₀⁻¹)⁻¹`` of plan ``Q`` (m, n)."""
        return covariance(self.information(Q))

    def accuracy_map(self, C, region=None, n: int = 1000, rng=None, grid: int | None = None, constraint=None):
        """Expected position error after calibration over a workspace region.

        Parameters
        ----------
        C : (p, p) parameter covariance (a plan's :meth:`covariance`, or an estimator's).
        region : (n_joints, 2) joint-space box (rad / m); default the joint limits.
        n : number of uniform random poses in the box (ignored when ``grid`` is given).
        grid : points per joint of a regular grid instead (grid**n_joints poses).
        constraint : per-pose feasibility callback (e.g. :class:`ToolBox` for a Cartesian box).

        Returns
        -------
        :class:`~estcal.design.criteria.AccuracyMap` (std = sqrt(trace(J_k C J_kᵀ)) per pose, m).
        """
        box = self.robot.limits if region is None else np.asarray(region, float)
        if grid:
            axes = [np.linspace(lo, hi, grid) for lo, hi in box]
            Q = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, self.n_joints)
        else:
            Q = self.random_readings(n, rng, box)
        if constraint is not None:
            g = np.asarray(constraint(Q), float).reshape(len(Q), -1)
            Q = Q[np.all(g >= 0, axis=1)]
            if not len(Q):
                raise ValueError("no pose of the region satisfies the constraint")
        return accuracy_map(C, self.position_jacobian(Q), Q, self.positions(Q))

    # -------------------------------------------------------- sampling
    def random_readings(self, n, rng=None, limits=None) -> np.ndarray:
        """Uniform random readings within ``limits`` (n_joints, 2) (default: joint limits)."""
        rng = np.random.default_rng(rng)
        lim = self.robot.limits if limits is None else np.asarray(limits, float)
        shape = (n, self.n_joints) if np.ndim(n) == 0 else tuple(n) + (self.n_joints,)
        return rng.uniform(lim[:, 0], lim[:, 1], size=shape)


def identifiable_subset(robot: SerialRobot, method: str = "position", candidates=None, n_poses: int = 60,
                        rng=0, tol: float | None = None, exclude=("gain_*",), prefer=None) -> list[str]:
    """A set of free parameters with independent Jacobian columns (a base set).

    The stacked Jacobian over ``n_poses`` random poses (or ``candidates``) goes through
    :func:`estcal.identify.select_identifiable` (GECARO App. III, priority-ordered
    sequential QR on unit-norm columns) with priorities
    ``prefer`` (highest, in the given order) > joint offsets > geometric >
    base > tool > markers; ``tol`` is its structural tolerance on the unit-norm columns
    (:data:`estcal.identify.core.STRUCTURAL_TOL`).

    Parameters whose names match ``exclude`` patterns are not considered.
    Returns the selected names in the robot's parameter order.
    """
    import fnmatch

    names = [nm for nm in robot.params.free_names if not any(fnmatch.fnmatchcase(nm, e) for e in exclude or ())]
    dv = design_values(robot)  # a saved model: the structure of its design geometry
    if dv is not None:
        robot = robot.with_values(dv)
    model = DesignModel(robot, method, names, sigma=1.0, sigma_rot=1.0 if method == "pose" else None)
    Q = model.random_readings(n_poses, rng) if candidates is None else np.asarray(candidates, float)
    J = model.jacobian(Q).reshape(-1, model.p)
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    rank_of = {"offset": 5, "geometric": 4, "base": 3, "tool": 2, "marker": 1}
    pri = np.array([rank_of.get(kinds[n], 1) for n in names], int)
    for i, nm in enumerate(prefer or []):
        if nm in names:
            pri[names.index(nm)] = 100 + len(prefer) - i
    tol = STRUCTURAL_TOL if tol is None else tol
    keep = set(select_identifiable(J, names=names, priorities=pri, tol=tol, zero_tol=tol).identifiable)
    return [n for n in robot.params.names if n in keep]


class ToolBox:
    """Workspace constraint: tool (or marker ``point``) position inside an axis-aligned box.

    ``ToolBox(robot, lower=(x, y, z), upper=(x, y, z))(Q)`` returns (N, 6) margins
    (m), all ≥ 0 when the point is inside — the vectorised per-pose constraint
    format of :mod:`estcal.design.plans`. ``None`` bounds are ignored. Picklable,
    so it also works with process pools.
    """

    def __init__(self, robot: SerialRobot, lower=None, upper=None, point: int | None = None):
        self.robot = robot
        inf = np.inf
        self.lower = np.array([-inf] * 3 if lower is None else [(-inf if v is None else v) for v in lower], float)
        self.upper = np.array([inf] * 3 if upper is None else [(inf if v is None else v) for v in upper], float)
        self.point = point

    def __call__(self, Q) -> np.ndarray:
        Q = np.atleast_2d(np.asarray(Q, float))
        kin = self.robot.kinematics(Q, jacobian=False)
        x = kin.p if self.point is None else kin.points[:, self.point]
        g = np.concatenate([x - self.lower, self.upper - x], -1)
        return np.where(np.isfinite(g), g, 1e3)
