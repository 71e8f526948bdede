"""Measurement methods: residual rows and their analytic Jacobian rows.

Every method turns a :class:`~estcal.io.dataset.Dataset` into stacked rows of
GECARO's linearised calibration equation (eq. [6])::

    e(θ) = y_measured − y_predicted(θ)        H(θ) = ∂y_predicted/∂θ
    e(θ + Δθ) ≈ e(θ) − H(θ) Δθ

with one noise standard deviation per row (``sigma``) so that rows of
different kinds and units are weighted by ``1/sigma`` (position rows in m,
orientation rows in rad). Methods that need unknowns of their own (plane
coefficients, …) declare them with :meth:`Method.extra_parameters`; they join
the parameter vector.

This module holds the base class and the classical methods: ``position``
(GECARO eq. [7], rows 1–3), ``location``/``pose`` (eq. [7], all six rows) and
``points`` (k points of one rigid body with unknown coordinates in the tool
frame — the markers).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estcal.base.errors import InputError
from estcal.kinematics.transforms import pose_error, so3_right_jacobian_inv

__all__ = ["Rows", "NoiseModel", "NOISE_LEVER_M", "Method", "PositionMethod", "PoseMethod", "PointsMethod", "METHODS",
           "register_method", "get_method", "method_for_dataset"]


#: lever arm (m) turning a bare position std into the orientation std: σ_rot = σ_pos / 0.1 m
#: (the ratio of the command line's defaults, 0.1 mm and 1 mrad; docs/conventions.md, "Noise")
NOISE_LEVER_M = 0.1
_NOISE_KEYS = ("position", "orientation", "scalar", "known", "joint", "resolution", "distribution", "row_sigma",
               "row_sigma_unit_m")


@dataclass
class NoiseModel:
    """The measurement noise, one class for estimation (row weights) and simulation (draws).

    Attributes (SI)
    ---------------
    position : σ of each measured coordinate, m (default 0.1 mm).
    orientation : σ of each rotation-vector component of a measured orientation, rad (default 1 mrad).
    scalar : σ of scalar measurements — distances and plane residuals, m (default 0.1 mm).
    known : the stds are trusted absolute values (covariance from them) rather than relative
        weights (covariance scaled by the posterior variance factor σ0²).
    joint : σ of each joint reading, rad or m (simulation; default 0).
    resolution : encoder resolution, rad or m, a scalar or one per joint (simulation: recorded
        readings are multiples of it; default 0 = none).
    distribution : ``"gaussian"`` (the stds above are σ) or ``"uniform"`` (they are half-widths;
        simulation).
    row_sigma : name of a dataset column holding each row's own position σ (e.g. TIAGo's
        ``marker_std_mm``), in units of ``row_sigma_unit_m`` metres (1e-3 for a column in mm).
        Position rows (and the points of a row) are then weighted by 1/σ_row instead of
        1/``position`` — weighted least squares with per-row weights; orientation and scalar
        rows keep their σ. With ``known=False`` the weights are relative (σ0 rescales them all).

    :meth:`parse` turns the forms users write (a number, a pair, a mapping) into a NoiseModel by one
    rule (docs/conventions.md, "Noise"); :meth:`none` is the noise-free model of the simulator.
    """

    position: float = 1e-4
    orientation: float = 1e-3
    scalar: float = 1e-4
    known: bool = False
    joint: float = 0.0
    resolution: Any = 0.0
    distribution: str = "gaussian"
    row_sigma: str | None = None
    row_sigma_unit_m: float = 1.0

    def __post_init__(self):
        if self.distribution not in ("gaussian", "uniform"):
            raise ValueError(f"noise distribution must be 'gaussian' or 'uniform', got {self.distribution!r}")
        for k in ("position", "orientation", "scalar", "joint"):
            if not getattr(self, k) >= 0:
                raise ValueError(f"noise {k} must be >= 0, got {getattr(self, k)}")
        if self.row_sigma is not None and not (isinstance(self.row_sigma, str) and self.row_sigma_unit_m > 0):
            raise ValueError(f"noise row_sigma must be a column name with row_sigma_unit_m > 0, got "
                             f"{self.row_sigma!r}, {self.row_sigma_unit_m!r}")

    def position_sigma(self, data) -> np.ndarray:
        """(N,) position σ (m) of every row of ``data``: the ``row_sigma`` column × ``row_sigma_unit_m``,
        or ``position`` for every row. A missing column or a value that is not a positive finite number
        is an :class:`~estcal.base.errors.InputError` naming the file, the line and the column."""
        if self.row_sigma is None:
            return np.full(data.n, self.position)
        cols = getattr(data, "columns", {}) or {}
        where = getattr(data, "where", "data")
        if self.row_sigma not in cols:
            raise InputError(f"{where}: no column {self.row_sigma!r} for the per-row noise (--row-sigma-mm); the "
                             f"file's extra columns are {sorted(cols) or 'none'}")
        s = np.asarray(cols[self.row_sigma], float) * self.row_sigma_unit_m
        bad = np.flatnonzero(~(np.isfinite(s) & (s > 0)))
        if len(bad):
            lines = getattr(data, "lines", None)
            at = f"line {int(lines[bad[0]])}" if lines is not None and len(lines) == data.n else f"row {bad[0] + 1}"
            raise InputError(f"{where}, {at}: column {self.row_sigma!r} = {float(cols[self.row_sigma][bad[0]])} is not a "
                             f"positive noise std ({len(bad)} such row(s)); fix or drop those rows")
        return s

    @classmethod
    def none(cls) -> "NoiseModel":
        """No noise at all (the simulator's default)."""
        return cls(position=0.0, orientation=0.0, scalar=0.0)

    @classmethod
    def parse(cls, value=None, known: bool | None = None) -> "NoiseModel":
        """The NoiseModel meant by ``value`` — the one rule of every ``noise=`` (docs/conventions.md):

        * ``None`` — the defaults (0.1 mm, 1 mrad, 0.1 mm);
        * a number σ > 0 — position and scalar std σ (m), orientation std σ / 0.1 m (rad);
        * a pair ``(position m, orientation rad)`` — the scalar std is the position std;
        * a mapping of the attributes (``position``, ``orientation``, ``scalar``, ``known``, ``joint``,
          ``resolution``, ``distribution``) — the others keep their defaults, except ``scalar``, which
          follows ``position``;
        * a NoiseModel — returned as is.

        ``known`` (when not None) marks the stds as trusted absolute values; a mapping's own
        ``known`` key wins.
        """
        if isinstance(value, cls):
            return value
        kn = {} if known is None else {"known": bool(known)}
        if value is None:
            return cls(**kn)
        if isinstance(value, Mapping):
            bad = sorted(set(value) - set(_NOISE_KEYS))
            if bad:
                raise InputError(f"noise: unknown key(s) {bad}; use position (m), orientation (rad), scalar (m), "
                                 f"known (bool), joint (rad or m), resolution (rad or m), distribution")
            d = {**kn, **value}
            d.setdefault("scalar", d.get("position", cls.scalar))
            return cls(**d)
        if isinstance(value, (tuple, list)):
            if len(value) != 2:
                raise InputError(f"noise: expected (position m, orientation rad), got {value!r}")
            p, r = float(value[0]), float(value[1])
            return cls(position=p, orientation=r, scalar=p, **kn)
        s = float(value)
        if not s > 0:
            raise InputError(f"noise: the position std must be > 0 m, got {value!r}")
        return cls(position=s, orientation=s / NOISE_LEVER_M, scalar=s, **kn)

    def draw(self, scale: float, shape, rng) -> np.ndarray:
        """A draw of noise of std (Gaussian) or half-width (uniform) ``scale``."""
        if scale == 0:
            return np.zeros(shape)
        if self.distribution == "gaussian":
            return rng.normal(0.0, scale, shape)
        return rng.uniform(-scale, scale, shape)

    def std(self, scale: float) -> float:
        """Standard deviation of one component (uniform half-width a → a/√3)."""
        return scale if self.distribution == "gaussian" else scale / np.sqrt(3.0)

    def to_dict(self, simulation: bool = False) -> dict:
        """``{position, orientation, scalar, known}`` (SI); with ``simulation`` also the joint noise,
        the resolution, the distribution and the units (a simulation's truth)."""
        d = {"position": self.position, "orientation": self.orientation, "scalar": self.scalar, "known": self.known}
        if self.row_sigma is not None:
            d.update(row_sigma=self.row_sigma, row_sigma_unit_m=self.row_sigma_unit_m)
        if simulation:
            d.update(joint=self.joint, resolution=np.asarray(self.resolution, float).tolist(),
                     distribution=self.distribution,
                     units={"position": "m", "orientation": "rad", "scalar": "m", "joint": "rad or m",
                            "resolution": "rad or m"})
        return d


@dataclass
class Rows:
    """Stacked residual rows.

    e : (M,) measured − predicted; H : (M, P) ∂predicted/∂θ; sigma : (M,) noise std per row;
    pose : (M,) index of the dataset row each residual row comes from;
    kind : (M,) row kind code: 0 position (m), 1 orientation (rad), 2 scalar (m).
    """

    e: np.ndarray
    H: np.ndarray | None
    sigma: np.ndarray
    pose: np.ndarray
    kind: np.ndarray
    term: np.ndarray = field(default=None)

    @staticmethod
    def concatenate(parts: list["Rows"]) -> "Rows":
        H = None if any(p.H is None for p in parts) else np.concatenate([p.H for p in parts], 0)
        term = np.concatenate([np.full(len(p.e), i) for i, p in enumerate(parts)])
        return Rows(np.concatenate([p.e for p in parts]), H, np.concatenate([p.sigma for p in parts]),
                    np.concatenate([p.pose for p in parts]), np.concatenate([p.kind for p in parts]), term)


class Method:
    """Base class of a measurement method (see module docstring).

    Subclasses implement :meth:`rows`; ``requires`` names the dataset kinds accepted.
    """

    name = "base"
    requires: tuple = ()

    def check(self, robot, data) -> None:
        if self.requires and data.kind not in self.requires:
            raise ValueError(f"{data.where}: method {self.name!r} needs a dataset of kind {self.requires}, "
                             f"got {data.kind!r} (columns x,y,z for a point, x1..zk for points, "
                             f"x,y,z,qw,qx,qy,qz for a pose)")

    def extra_parameters(self, robot, data) -> list[tuple[str, float]]:
        """(name, initial value) of unknowns this method adds to the parameter vector."""
        return []

    def rows(self, robot, theta, data, noise: NoiseModel, jacobian: bool = True) -> Rows:
        raise NotImplementedError

    def point_errors(self, data, e) -> np.ndarray | None:
        """The point-error norms (N, k) in m that :func:`estcal.estimate.result.pose_errors` gives for
        ``data``, read from this method's residual ``e`` of :meth:`rows` when its rows are the measured minus
        the predicted points (a fit then scores itself without another kinematics pass); None otherwise."""
        return None

    def residuals_many(self, robot, thetas, data) -> np.ndarray:
        """Residuals ``e`` (W, M) at each row of ``thetas`` (W, P) — MCMC walkers, sigma points.

        This default evaluates :meth:`rows` θ by θ; the classical methods override it
        with one call of the batched kinematics (``robot.kinematics`` with θ (W, P))."""
        return np.stack([self.rows(robot, th, data, NoiseModel(), jacobian=False).e for th in thetas])

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def _point_rows(kin, data, robot, which: int):
    """Predicted point ``which`` (marker index or -1 for the tool origin) and its Jacobian."""
    if which < 0:
        return kin.p, (None if kin.J is None else kin.J[:, :3])
    return kin.points[:, which], (None if kin.J_points is None else kin.J_points[:, which])


class PositionMethod(Method):
    """Position measure (GECARO eq. [7], rows 1–3): one point per pose.

    The measured point is marker 1 when the robot has markers (a point with
    unknown coordinates in the tool frame), otherwise the tool-frame origin.
    """

    name = "position"
    requires = ("position", "points")

    def rows(self, robot, theta, data, noise, jacobian=True):
        self.check(robot, data)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        pred, J = _point_rows(kin, data, robot, 0 if robot.n_markers else -1)
        e = (data.points[:, 0] - pred).reshape(-1)
        H = None if J is None else J.reshape(-1, J.shape[-1])
        N = data.n
        return Rows(e, H, np.repeat(noise.position_sigma(data), 3), np.repeat(np.arange(N), 3), np.zeros(3 * N, int))

    def point_errors(self, data, e):
        # the rows are point 1 only: they are pose_errors' when the data measure that one point
        if data.n_points != 1 or np.size(e) != 3 * data.n:
            return None
        return np.linalg.norm(np.reshape(e, (data.n, 1, 3)), axis=2)

    def residuals_many(self, robot, thetas, data):
        self.check(robot, data)
        kin = robot.kinematics(data.readings, thetas, data.context, jacobian=False)
        pred = kin.points[:, :, 0] if robot.n_markers else kin.p
        return (data.points[None, :, 0] - pred).reshape(len(pred), -1)


class PointsMethod(Method):
    """k points of one rigid body (markers 1..k, unknown coordinates in the tool frame).

    Together the points carry the full pose; their coordinates are the ``markerk_*``
    parameters, estimated with the rest (the TIAGo case).
    """

    name = "points"
    requires = ("position", "points")

    def rows(self, robot, theta, data, noise, jacobian=True):
        self.check(robot, data)
        k = data.n_points
        if robot.n_markers < k:
            raise ValueError(f"{data.where}: {k} measured points but the robot defines {robot.n_markers} markers; "
                             f"load the robot with n_markers={k} (or use --points)")
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        e = (data.points - kin.points[:, :k]).reshape(-1)
        H = None if kin.J_points is None else kin.J_points[:, :k].reshape(-1, robot.n_params)
        N = data.n
        return Rows(e, H, np.repeat(noise.position_sigma(data), 3 * k), np.repeat(np.arange(N), 3 * k),
                    np.zeros(3 * k * N, int))

    def point_errors(self, data, e):
        k = data.n_points
        return None if np.size(e) != 3 * k * data.n else np.linalg.norm(np.reshape(e, (data.n, k, 3)), axis=2)

    def residuals_many(self, robot, thetas, data):
        self.check(robot, data)
        k = data.n_points
        if robot.n_markers < k:
            return super().residuals_many(robot, thetas, data)  # rows() raises the clear error
        kin = robot.kinematics(data.readings, thetas, data.context, jacobian=False)
        return (data.points[None] - kin.points[:, :, :k]).reshape(len(kin.points), -1)


class PoseMethod(Method):
    """Location (full pose) measure, GECARO eq. [7]: 6 rows per pose.

    e = [p_meas − p_pred ; log(R_meas R_predᵀ)] (GECARO App. I with a proper
    rotation logarithm, which the paper's "method 2" recommends). A change of the
    prediction R_pred → exp([J_ω Δθ]x) R_pred changes the rotation residual by
    −J_r⁻¹(e_rot) J_ω Δθ (J_r: right Jacobian of SO(3)), so the orientation rows are
    J_r⁻¹(e_rot) J_ω — exact at any residual, equal to J_ω at e = 0 (GECARO eq. [7]).
    """

    name = "pose"  # GECARO's "location"; both names select it (METHODS)
    requires = ("pose",)

    def rows(self, robot, theta, data, noise, jacobian=True):
        self.check(robot, data)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        err = pose_error(data.R, data.p, kin.R, kin.p)
        e = err.reshape(-1)
        H = None
        if kin.J is not None:
            H = np.array(kin.J)
            H[:, 3:] = so3_right_jacobian_inv(err[:, 3:]) @ H[:, 3:]
            H = H.reshape(-1, robot.n_params)
        N = data.n
        sig = np.tile(np.r_[np.zeros(3), np.full(3, noise.orientation)], N).reshape(N, 6)
        sig[:, :3] = noise.position_sigma(data)[:, None]
        sig = sig.reshape(-1)
        return Rows(e, H, sig, np.repeat(np.arange(N), 6), np.tile(np.r_[0, 0, 0, 1, 1, 1], N))

    def residuals_many(self, robot, thetas, data):
        self.check(robot, data)
        kin = robot.kinematics(data.readings, thetas, data.context, jacobian=False)
        return pose_error(data.R[None], data.p[None], kin.R, kin.p).reshape(len(kin.p), -1)


METHODS: dict[str, type] = {"position": PositionMethod, "location": PoseMethod, "pose": PoseMethod,
                            "points": PointsMethod}


def register_method(name: str, cls: type) -> None:
    """Make a method available by name (used by the other method modules and by users)."""
    METHODS[name] = cls


def get_method(name: str, **kwargs) -> Method:
    """The measurement method ``name`` (the GECARO link, plane and distance methods are registered by
    :mod:`estcal.methods.links`, which the package imports)."""
    try:
        return METHODS[name](**kwargs)
    except KeyError:
        raise ValueError(f"unknown measurement method {name!r}; available: {sorted(METHODS)}") from None


def method_for_dataset(data, robot) -> Method:
    """The method implied by the dataset's columns: pose → location, k points → points, x,y,z → position."""
    if data.kind == "pose":
        return PoseMethod()
    if data.kind == "points":
        return PointsMethod()
    if data.kind == "position":
        return PositionMethod()
    raise ValueError(f"{data.where}: no measurement columns (x,y,z / x1..zk / x,y,z,qw,qx,qy,qz); "
                     f"give --method for an encoder-only (link) method")
