"""The result object every estimator returns, and accuracy statistics.

All estimators (least squares, Kalman filter, factor graph, MCMC) fill the
same :class:`CalibrationResult`, so results compare field by field and
serialise to the same JSON::

    {"method": ..., "parameters": {name: {"estimate", "std", "nominal"}},
     "rmse_mm": {"train": .., "validation": [..]}, "n_iterations", "converged", ...}
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from estcal.base.atomic import refuse_input
from estcal.base.jsonio import to_jsonable
from estcal.base.result import Result
from estcal.base.tables import Table, parameter_table, si_unit
from estcal.base.units import display_unit
from estcal.io.savedmodel import save_calibration
from estcal.kinematics.chunked import CHUNK, tool_poses
from estcal.kinematics.transforms import pose_error

__all__ = ["CalibrationResult", "accuracy", "pose_errors", "score"]


def pose_errors(robot, theta, data, kin=None):
    """Per-pose position error norms (m) of every measured point and orientation errors (rad).

    Returns ``(pos (N, k), rot (N,) or None)``. For pose data the point is the tool
    origin; for point data each marker is compared with its measured point. ``kin``: the tool
    frames and points at ``theta`` when the caller has them (:func:`score`).
    """
    if kin is None:
        # chunked: only the tool frame and the points are kept (bounded memory on large files)
        kin = tool_poses(robot, data.readings, theta, data.context, fields=_fields(data))
    if data.kind == "pose":
        err = pose_error(data.R, data.p, kin.R, kin.p)
        return np.linalg.norm(err[:, :3], axis=1)[:, None], np.linalg.norm(err[:, 3:], axis=1)
    if data.points is None:
        return None, None
    k = data.n_points
    pred = kin.points[:, :k] if robot.n_markers >= k else kin.p[:, None, :]
    return np.linalg.norm(data.points - pred, axis=2), None


def _fields(data):
    return ("R", "p") if data.kind == "pose" else ("p", "points")


def accuracy(robot, theta, data, kin=None) -> dict:
    """Accuracy statistics in mm / mrad: RMSE (root mean square of error norms), mean, max.

    ``rmse_mm`` is √(mean‖e‖²) over every measured point of every pose (the
    "norm RMSE" of FIGAROH's tables); per-point RMSE are in ``rmse_mm_per_point``.
    """
    pos, rot = pose_errors(robot, theta, data, kin)
    return error_statistics(pos, rot, data.n)


def error_statistics(pos, rot, n_poses: int) -> dict:
    """:func:`accuracy` from the error norms ``pos`` (N, k) in m and ``rot`` (N,) in rad (or None)."""
    if pos is None:
        return {"n_poses": n_poses}
    out = {"n_poses": int(n_poses), "rmse_mm": float(np.sqrt(np.mean(pos**2)) * 1e3),
           "mean_mm": float(pos.mean() * 1e3), "max_mm": float(pos.max() * 1e3)}
    if pos.shape[1] > 1:
        out["rmse_mm_per_point"] = [float(v) for v in np.sqrt(np.mean(pos**2, axis=0)) * 1e3]
    if rot is not None:
        out.update(rmse_mrad=float(np.sqrt(np.mean(rot**2)) * 1e3), mean_mrad=float(rot.mean() * 1e3),
                   max_mrad=float(rot.max() * 1e3))
    return out


@dataclass(repr=False)
class CalibrationResult(Result):
    """Estimated parameters with uncertainty, fit statistics and accuracy (the result protocol of
    :class:`estcal.base.result.Result`: ``to_dict``, ``to_json``, ``save_model``, ``table``).

    Attributes
    ----------
    method : estimator name (``lm``, ``gauss-newton``, ``iterated-lls``, ``kalman``, ``gtsam``, ``mcmc`` …)
    names : free parameter names (those estimated)
    estimate, std : (p,) estimates and standard deviations (SI units)
    covariance : (p, p) parameter covariance
    nominal : (p,) initial values of the free parameters
    theta : (P,) full parameter vector at the solution; ``all_names`` its names
    n_iterations, converged : iteration count and convergence flag
    chi2, dof : weighted residual sum of squares and degrees of freedom (rows − p)
    sigma0 : posterior standard deviation of unit weight √(χ²/dof)
    accuracy : {"train": accuracy dict before/after, "validation": [...]} (mm / mrad)
    extra : estimator-specific fields (e.g. credible intervals, innovation statistics)
    samples : (n_draws, p) posterior draws of the free parameters (MCMC only; kept in memory
        for plots, not serialised)
    """

    method: str
    names: list
    estimate: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    nominal: np.ndarray
    theta: np.ndarray
    all_names: list
    n_iterations: int = 0
    converged: bool = True
    chi2: float = float("nan")
    dof: int = 0
    covariance_source: str = "model"
    accuracy: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    samples: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: files the result was computed from (dataset, validation files, robot file): never written over
    inputs: tuple = field(default=(), repr=False, compare=False)
    # What the fit was run on, for :meth:`save_model` (not serialised by to_dict):
    # the Problem (robot, datasets, noise) and the validation datasets.
    problem: object = field(default=None, repr=False, compare=False)
    validation_data: list = field(default_factory=list, repr=False, compare=False)

    @property
    def sigma0(self) -> float:
        return float(np.sqrt(self.chi2 / self.dof)) if self.dof > 0 else float("nan")

    def parameter(self, name: str) -> tuple[float, float]:
        """``(estimate, std)`` of a free parameter (SI units)."""
        if name not in self.names:
            raise ValueError(f"{name!r} is not an estimated parameter; estimated: {', '.join(self.names)}")
        i = self.names.index(name)
        return float(self.estimate[i]), float(self.std[i])

    def robot(self, base_robot=None):
        """The robot at the estimate: ``base_robot`` (default: the problem's robot) with the
        estimated values, matched by parameter name. Its ``meta["calibration"]`` carries the
        estimated robot parameters (``free``) and their ``covariance`` (SI), as a saved model does,
        so that ``estcal.compensate(result.robot(), …)`` predicts the error of its commands."""
        if base_robot is None:
            if self.problem is None:
                raise ValueError("this result does not know its robot; pass the robot it was fitted to")
            base_robot = self.problem.robot
        idx = {n: i for i, n in enumerate(self.all_names)}
        if all(n in idx for n in base_robot.params.names):
            out = base_robot.with_values(self.theta[[idx[n] for n in base_robot.params.names]])
        else:
            out = base_robot.with_values(self.theta[: base_robot.n_params])
        if self.problem is not None:
            from estcal.io.savedmodel import robot_covariance

            free, C, _ = robot_covariance(self)
            if free and all(n in out.params.names for n in free) and np.all(np.isfinite(C)):
                old = out.meta.get("calibration") or {}  # a saved model's: keep where its design robot is
                cal = {k: old[k] for k in ("robot", "root", "tip") if k in old}
                cal.update(estimator=self.method, free=list(free), covariance=C.tolist(), sigma0=self.sigma0)
                out.meta = {**out.meta, "calibration": cal}
        return out

    def save_model(self, path, provenance: dict | None = None):
        """Write the identified robot as a robot file with a ``calibration:`` block
        (docs/robot-file.md, "Saved models"); ``load_robot(path)`` gives the fitted model.

        ``provenance`` adds or overrides keys of the block (e.g. ``level``, ``options``).
        Returns the path.
        """

        refuse_input(path, self.inputs)
        return save_calibration(self, path, provenance)

    def to_dict(self) -> dict:
        d = {
            "method": self.method,
            "parameters": {n: {"estimate": float(e), "std": float(s), "nominal": float(v)}
                           for n, e, s, v in zip(self.names, self.estimate, self.std, self.nominal)},
            "n_parameters": len(self.names),
            "n_iterations": int(self.n_iterations),
            "converged": bool(self.converged),
            "chi2": float(self.chi2), "dof": int(self.dof), "sigma0": self.sigma0,
            "covariance_source": self.covariance_source,
            "covariance": np.asarray(self.covariance).tolist(),
            "theta": {n: float(v) for n, v in zip(self.all_names, self.theta)},
        }
        acc = self.accuracy or {}
        rm = {}
        if "train" in acc:
            rm["train"] = acc["train"].get("after", {}).get("rmse_mm")
            rm["train_before"] = acc["train"].get("before", {}).get("rmse_mm")
        if "validation" in acc:
            rm["validation"] = [v.get("after", {}).get("rmse_mm") for v in acc["validation"]]
        d["rmse_mm"] = rm
        d["accuracy"] = acc
        d.update({k: to_jsonable(v) for k, v in self.extra.items()})
        return d

    def table(self) -> Table:
        """Initial value, estimate and std of every estimated parameter
        (:func:`estcal.base.tables.parameter_table`): mm / mrad when the robot is known, else SI."""
        robot = getattr(self.problem, "robot", None)
        unit = si_unit if robot is None else (lambda n: display_unit(n, robot) if n in robot.params else ("SI", 1.0))
        return parameter_table(self, unit, title="")

    def summary(self) -> str:
        return (f"CalibrationResult(method={self.method!r}, {len(self.names)} parameters, "
                f"iterations={self.n_iterations}, converged={self.converged}, "
                f"sigma0={self.sigma0:.4g}, covariance={self.covariance_source})")

    def __str__(self) -> str:
        lines = [self.summary(), str(self.table())]
        acc = self.accuracy or {}
        if "train" in acc:
            b, a = acc["train"].get("before", {}), acc["train"].get("after", {})
            lines.append(f"train: RMSE {b.get('rmse_mm', float('nan')):.3f} mm -> {a.get('rmse_mm', float('nan')):.3f} mm")
        for i, v in enumerate(acc.get("validation", [])):
            lines.append(f"validation[{i}] {v.get('path', '')}: RMSE {v.get('before', {}).get('rmse_mm', float('nan')):.3f}"
                         f" mm -> {v.get('after', {}).get('rmse_mm', float('nan')):.3f} mm")
        return "\n".join(lines)


def score(problem, theta_before, theta_after, validation=(), train_errors=None) -> dict:
    """Accuracy before/after on the training terms and on each validation dataset.

    train_errors : the training point-error norms ``(before (N, k), after (N, k))`` in m when the caller
        has them from its own residuals (:func:`point_errors_from_rows`), instead of a kinematics pass."""
    robot = problem.robot
    out = {}
    t = problem.terms[0]
    if t.data.kind != "none":
        ba = ({"before": error_statistics(train_errors[0], None, t.data.n),
               "after": error_statistics(train_errors[1], None, t.data.n)} if train_errors is not None
              else _before_after(robot, theta_before, theta_after, t.data))
        out["train"] = {**ba, "path": t.data.where}
    vals = []
    for d in validation:
        vals.append({"path": d.where, **_before_after(robot, theta_before, theta_after, d)})
    if vals:
        out["validation"] = vals
    return out


def point_errors_from_rows(problem, e) -> np.ndarray | None:
    """The point-error norms (N, k) in m that :func:`pose_errors` returns for the training data, from the
    residual ``e`` of ``problem.evaluate`` when the problem's one term's method reads them off its rows
    (:meth:`estcal.methods.base.Method.point_errors`: the ``points`` and ``position`` methods) — the same
    numbers without a kinematics pass; None otherwise (the caller then runs :func:`score` as before)."""
    if len(problem.terms) != 1:
        return None
    t = problem.terms[0]
    return t.method.point_errors(t.data, e)


def _before_after(robot, theta_before, theta_after, data) -> dict:
    """``{"before": accuracy, "after": accuracy}``; on up to ``CHUNK / 2`` poses from one kinematics
    pass over both parameter vectors (:meth:`~estcal.kinematics.chain.SerialRobot.kinematics` with θ of
    shape (2, P): the same frames as two calls to 1e-12, at the overhead of one on a small file)."""
    if data.points is None and data.kind != "pose" or 2 * data.n > CHUNK:
        return {"before": accuracy(robot, theta_before, data), "after": accuracy(robot, theta_after, data)}
    kin = robot.kinematics(data.readings, np.stack([np.asarray(theta_before, float), np.asarray(theta_after, float)]),
                           data.context, jacobian=False)
    return {k: accuracy(robot, th, data, SimpleNamespace(**{f: getattr(kin, f)[w] for f in _fields(data)}))
            for w, (k, th) in enumerate((("before", theta_before), ("after", theta_after)))}
