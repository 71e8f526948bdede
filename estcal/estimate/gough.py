"""A Gough–Stewart calibration in the shape the shared estimators take, and its result.

:class:`GoughProblem` gives :class:`~estcal.parallel.residuals.GoughResiduals` (the IK or FK
measurement model of :mod:`estcal.parallel`, layer 2) the interface of
:class:`estcal.methods.problem.Problem`, so that every estimator of the registry
(:mod:`estcal.estimate.registry`: LM, Gauss–Newton, gtsam, Kalman, emcee …) runs on a Gough
platform unchanged; :class:`GoughCalibrationResult` is their
:class:`~estcal.estimate.result.CalibrationResult` with the platform's parameters, table and saved
model. The job that loads, identifies, runs and checks convergence is
:func:`estcal.workflows.gough.calibrate_gough` (docs/parallel.md).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from estcal.base.atomic import atomic_write_text, refuse_input
from estcal.base.jsonio import to_jsonable
from estcal.base.tables import Table, parameter_table
from estcal.estimate.result import CalibrationResult
from estcal.io.savedmodel import calibration_block
from estcal.kinematics.parameters import ParameterVector
from estcal.methods.base import Method, NoiseModel, Rows
from estcal.methods.problem import Term
from estcal.parallel.gough import GoughPlatform
from estcal.parallel.residuals import DEFAULT_SIGMA, GoughResiduals

__all__ = ["GoughProblem", "GoughCalibrationResult"]


# ---------------------------------------------------------------- the Problem adapter
class _GoughMeasurement(Method):
    """The Gough residual rows as a measurement method: decorrelated rows (unit σ), so the shared
    estimators, which use only ``e/σ`` and ``H/σ``, see a proper weighted least-squares cost."""

    def __init__(self, residual: str):
        self.name = f"gough-{residual}"

    def rows(self, robot, theta, data, noise, jacobian: bool = True) -> Rows:
        r = data.residuals.whitened(np.asarray(theta, float)[:42], jacobian)
        return Rows(r.e, None if r.J is None else -r.J, np.ones(r.e.size), r.pose, r.kind)


class _GoughTermData:
    """Dataset-like view of the measurements: ``n`` poses, ``subset`` by pose (a Kalman step or a
    factor then evaluates only its own poses), ``kind = "none"`` (no serial-chain accuracy)."""

    kind = "none"

    def __init__(self, residuals: GoughResiduals):
        self.residuals = residuals
        self.n = residuals.n_poses
        self.path = residuals.data.path
        self.where = f"{residuals.data.source} (Gough {residuals.kind.upper()} residuals)"
        self.context: dict = {}

    def subset(self, idx) -> "_GoughTermData":
        return _GoughTermData(self.residuals.subset(idx))


class GoughProblem:
    """A Gough calibration with the interface of :class:`estcal.methods.problem.Problem`.

    ``evaluate(theta)`` returns :class:`estcal.methods.base.Rows` with ``e`` the decorrelated
    residuals (measured − predicted), ``H = −∂e/∂θ`` (= ∂predicted/∂θ), ``sigma = 1``.

    Parameters
    ----------
    residuals : :class:`~estcal.parallel.residuals.GoughResiduals` (the measurement model).
    params : the 42 named parameters, their current values and free mask
        (:meth:`GoughPlatform.parameter_vector`).
    """

    def __init__(self, residuals: GoughResiduals, params: ParameterVector):
        self.residuals = residuals
        self.robot = residuals.robot
        self._params = params
        self.terms = [Term(_GoughMeasurement(residuals.kind), _GoughTermData(residuals),
                           NoiseModel(known=residuals.absolute_sigma))]

    @property
    def params(self) -> ParameterVector:
        return self._params

    def evaluate(self, theta=None, jacobian: bool = True) -> Rows:
        theta = self._params.values if theta is None else np.asarray(theta, float)
        t = self.terms[0]
        r = t.method.rows(self.robot, theta, t.data, t.noise, jacobian)
        r.term = np.zeros(r.e.size, int)
        return r

    def with_free(self, names) -> "GoughProblem":
        return GoughProblem(self.residuals, self._params.with_free(names))

    def with_values(self, theta) -> "GoughProblem":
        return GoughProblem(self.residuals, self._params.with_values(theta))

    def __repr__(self) -> str:
        return (f"GoughProblem({self.robot.name!r}, {self.residuals.kind}, {self.residuals.n_poses} poses, "
                f"{int(self._params.free.sum())} free)")


# ---------------------------------------------------------------- the result
@dataclass(repr=False)
class GoughCalibrationResult(CalibrationResult):
    """A :class:`~estcal.estimate.result.CalibrationResult` of a Gough platform (the result protocol
    of :class:`estcal.base.result.Result`: ``to_dict``, ``to_json``, ``save_model``, ``table``;
    and ``robot()``), with

    residual : ``"ik"`` or ``"fk"``; model : 42 or 36;
    requested : the free parameters asked for — those found not identifiable at the initial
        values are kept there (``std`` None) and listed in ``identifiability``;
    theta_initial : (42,) initial parameters; fk_failures : poses whose FK failed at the estimate
        (FK residuals; their rows count as zero).

    ``accuracy["train"]`` holds the RMS residual before and after: leg readings (IK, mm) or
    platform position error norms (FK, mm, and orientation, mrad).
    """

    residual: str = "ik"
    model: int = 42
    requested: list = field(default_factory=list)
    theta_initial: np.ndarray | None = None
    identifiability: dict = field(default_factory=dict)
    fk_failures: int = 0
    nominal_robot: GoughPlatform | None = field(default=None, repr=False, compare=False)

    @property
    def parameters(self) -> dict:
        """``{name: {estimate, std, nominal}}`` (m) of every requested free parameter; ``nominal``
        is the initial value, ``std`` None for those not estimated (not identifiable)."""
        idx = {n: i for i, n in enumerate(self.all_names)}
        est = {n: float(s) for n, s in zip(self.names, self.std)}
        return {n: {"estimate": float(self.theta[idx[n]]), "std": est.get(n),
                    "nominal": float(self.theta_initial[idx[n]])} for n in self.requested}

    def robot(self, base_robot=None) -> GoughPlatform:
        """The platform at the estimate (``base_robot``'s limits, home pose and workspace)."""
        return (base_robot if base_robot is not None else self.nominal_robot).with_theta(self.theta)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["parameters"] = self.parameters
        d.update(names=list(self.names), residual=self.residual, model=int(self.model),
                 fk_failures=int(self.fk_failures), identifiability=to_jsonable(self.identifiability))
        return d

    def table(self) -> Table:
        """Initial value, estimate and standard deviation of every requested parameter, in mm
        (:func:`estcal.base.tables.parameter_table`; '—' for those not identifiable)."""
        p = self.parameters
        rows = SimpleNamespace(names=list(p), estimate=[v["estimate"] for v in p.values()],
                               std=[np.nan if v["std"] is None else v["std"] for v in p.values()],
                               nominal=[v["nominal"] for v in p.values()])
        return parameter_table(rows, lambda name: ("mm", 1e3), title="")

    def summary(self) -> str:
        after = (self.accuracy.get("train") or {}).get("after", {})
        rot = after.get("rmse_mrad")
        return (f"Gough calibration ({self.method}, {self.residual.upper()} residuals, Model {self.model}): "
                f"RMS {after.get('rmse_mm', float('nan')):.4g} mm" + ("" if rot is None else f" / {rot:.4g} mrad")
                + f", {self.n_iterations} iterations, {'converged' if self.converged else 'NOT converged'}")

    def __str__(self) -> str:
        rows = [self.summary(), str(self.table())]
        ide = self.identifiability
        lost = ide.get("no_effect", []) + [r["parameter"] for r in ide.get("regrouped", [])]
        if lost:
            rows.append(f"not identifiable (kept at initial value): {lost}")
        if not self.converged and self.extra.get("convergence", {}).get("note"):
            rows.append(self.extra["convergence"]["note"])
        return "\n".join(rows)

    def save_model(self, path, provenance: dict | None = None) -> Path:
        """Write the calibrated platform as a Gough robot file (``type: gough``, lengths in m) with
        a ``calibration:`` block (estimator, data, free names, covariance, σ0, RMS before/after);
        :func:`estcal.parallel.load_gough` of the file gives the calibrated platform."""
        import yaml

        refuse_input(path, self.inputs)
        res = self.problem.residuals
        noise = {"rho": res.sigma_rho or DEFAULT_SIGMA["rho"], "position": res.sigma_p or DEFAULT_SIGMA["position"],
                 "orientation": res.sigma_r or DEFAULT_SIGMA["orientation"], "known": res.absolute_sigma}
        tr = self.accuracy.get("train", {})
        rm = {"train": {"before": tr.get("before", {}).get("rmse_mm"), "after": tr.get("after", {}).get("rmse_mm")}}
        block = calibration_block(estimator=self.method, train=[res.data], free=self.names,
                                  covariance=self.covariance, noise=noise, sigma0=self.sigma0, rmse_mm=rm,
                                  residual=self.residual, model=int(self.model), converged=bool(self.converged),
                                  covariance_source=self.covariance_source, **(provenance or {}))
        d = self.robot().to_dict("m")
        d["calibration"] = to_jsonable(block)
        atomic_write_text(path, yaml.safe_dump(d, sort_keys=False))
        return Path(path)
