r"""Gough–Stewart platform calibration: load, check, run a shared estimator, return a result.

The measurement model — IK or FK residuals with per-pose noise covariance and analytic
Jacobians — is :class:`estcal.parallel.residuals.GoughResiduals` (docs/parallel.md).
:class:`estcal.estimate.gough.GoughProblem` gives it the interface of :class:`estcal.methods.problem.Problem`
(``params``, ``evaluate(θ) -> Rows``, ``with_free``, ``with_values``, one per-pose splittable
term), so the estimators of the shared registry (:mod:`estcal.estimate.registry`) run on it
unchanged: :data:`ESTIMATORS` lists those that can, the others are refused with the reason.

``converged`` is honest for every estimator: it is the estimator's own test *and*, for the
point estimators, first-order optimality checked here — a Gauss–Newton step from the estimate
on the estimator's own cost (data, plus its Gaussian prior when it uses one, with the robust
weights when a kernel is set) moves no parameter by more than :data:`STEP_TOL_SIGMA` of its
standard deviation or :data:`STEP_TOL_M`. A single-pass Kalman filter or UKF is therefore
reported as not converged when its estimate is not yet at the optimum (their default,
``passes=None``, iterates the passes until they converge).
The MCMC posterior mean is not a stationary point of the cost; its flag is the sampler's
(effective sample size and autocorrelation time, :mod:`estcal.estimate.mcmc`).

Functions here load, check, run and return; they never print. Bad input raises
:class:`~estcal.base.errors.InputError` naming the file or option, data that cannot support an
estimate :class:`~estcal.base.errors.NumericalRefusal`; warnings are
:class:`~estcal.base.errors.EstcalWarning`.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.errors import EstcalWarning, InputError, NumericalRefusal
from estcal.base.jsonio import write_json
from estcal.estimate._common import prior_std_vector
from estcal.estimate.lsq import prior_arrays
from estcal.estimate.registry import check_options, get_estimator
from estcal.estimate.gough import GoughCalibrationResult, GoughProblem
from estcal.estimate.result import CalibrationResult
from estcal.identify.select import identifiable
from estcal.kinematics.parameters import ParameterVector
from estcal.parallel._rot import make_T, so3_exp
from estcal.parallel.daney import daney_initial_theta, generate_random_poses
from estcal.parallel.data import GoughData, load_gough_data, simulate_gough_data
from estcal.parallel.gough import GoughPlatform, load_gough, split_pose
from estcal.parallel.residuals import GoughResiduals
from estcal.simulate import ErrorModel
from estcal.simulate.core import simulation_noise

__all__ = ["ESTIMATORS", "GoughProblem", "GoughCalibrationResult", "calibrate_gough", "identifiable_gough",
           "simulate_gough", "GoughSimulation", "save_gough_data", "STEP_TOL_SIGMA", "STEP_TOL_M"]

#: Shared estimators that run on a Gough platform (each tested against ``lm`` in
#: tests/test_parallel_calibration.py).
ESTIMATORS = ("lm", "gauss-newton", "iterated-lls", "scipy-lm", "gtsam", "isam2", "kalman", "ukf", "mcmc")

#: Shared estimators refused for a Gough platform, with the reason.
REFUSED = {
    "gtsam-timevarying": "it estimates parameters drifting over time, and Gough measurements carry no time "
                         "(the platform parameters are constants); use kalman, isam2 or lm",
}

#: Convergence test (module docstring): the Gauss–Newton step from the estimate moves no
#: parameter by more than this fraction of its standard deviation …
STEP_TOL_SIGMA = 0.01
#: … or by more than this length (m): every Gough parameter is a length; 0.1 nm is far below
#: any metrology and above the rounding of the FK solution (1e-13 m on the leg lengths).
STEP_TOL_M = 1e-10

_LSQ = ("lm", "gauss-newton", "iterated-lls", "scipy-lm")


def _warn(msg: str) -> None:
    warnings.warn(msg, EstcalWarning, stacklevel=3)


# ---------------------------------------------------------------- checks and helpers
def _check_estimator(name: str, options: dict) -> None:
    if name in REFUSED:
        raise InputError(f"estimator {name!r} is not available for Gough platforms: {REFUSED[name]}")
    if name not in ESTIMATORS:
        raise InputError(f"estimator {name!r} is not available for Gough platforms; choose one of "
                         f"{', '.join(ESTIMATORS)}")
    if "backend" in options:
        raise InputError("calibrate_gough: option 'backend' is gone — Gough calibration always runs the shared "
                         "estimators of estcal.estimate")
    if "validation" in options:
        raise InputError("calibrate_gough: held-out validation data are not supported for Gough platforms")
    check_options(name, options)
    if name in ("kalman", "ukf") and np.any(np.asarray(options.get("q", 0.0), float) != 0):
        raise InputError(f"estimator {name!r}: process noise q > 0 models parameters drifting over time; "
                         "Gough measurements carry no time (the platform parameters are constants): use q = 0")


def _initial_theta(robot: GoughPlatform, theta0, initial: str, daney_results) -> np.ndarray:
    if theta0 is not None:
        th = np.asarray(theta0, float).reshape(-1)
        if th.shape != (42,) or not np.all(np.isfinite(th)):
            raise InputError(f"theta0 must be 42 finite values (m), got shape {th.shape}")
        return th.copy()
    if initial == "nominal":
        return robot.theta
    if initial == "daney":
        if not daney_results:
            raise InputError("initial='daney' needs daney_results (see estcal.parallel.daney.calibrate_leg_daney)")
        return daney_initial_theta(robot, daney_results)
    raise InputError(f"initial must be 'nominal' or 'daney', got {initial!r}")


def _free_parameters(robot: GoughPlatform, model: int, theta: np.ndarray, free) -> ParameterVector:
    pv = robot.parameter_vector(model).with_values(theta)
    if free is None:
        return pv
    pv = pv.with_free(free)
    if model == 36 and any(n.startswith("drho") for n in pv.free_names):
        raise InputError(f"Model 36 keeps the leg offsets fixed; free {list(free)} selects "
                         f"{[n for n in pv.free_names if n.startswith('drho')]} (use model=42)")
    return pv


def _identify(W: np.ndarray, names: Sequence[str]) -> dict:
    """Identifiability of the columns of the whitened Jacobian ``W``: the shared
    :func:`estcal.identify.select.identifiable` (GECARO App. III, sequential QR in parameter order)."""
    out = identifiable(W, list(names)).to_dict()
    for g in out["regrouped"]:
        g.setdefault("combination", dict(g["relation"]))
    return out


def _accuracy(residuals: GoughResiduals, theta: np.ndarray) -> dict:
    """RMS / mean / max residual (mm; FK also mrad) at ``theta``: leg readings (IK) or platform
    position and orientation error norms (FK, poses whose FK failed left out and counted)."""
    r = residuals.raw(theta, jacobian=False)
    n = residuals.n_poses
    ok = ~r.fk_failed
    if residuals.kind == "ik":
        a = np.abs(r.e)
        out = {"n_poses": n, "quantity": "leg reading"}
    else:
        e = r.e.reshape(n, 6)[ok]
        a = np.linalg.norm(e[:, :3], axis=1)
        rot = np.linalg.norm(e[:, 3:], axis=1)
        out = {"n_poses": int(ok.sum()), "quantity": "platform pose", "fk_failures": r.n_fk_failures}
        if rot.size:
            out.update(rmse_mrad=float(np.sqrt(np.mean(rot**2)) * 1e3), max_mrad=float(rot.max() * 1e3))
    if a.size:
        out.update(rmse_mm=float(np.sqrt(np.mean(a**2)) * 1e3), mean_mm=float(a.mean() * 1e3),
                   max_mm=float(a.max() * 1e3))
    return out


def _prior_of(name: str, problem, names, x0, options) -> tuple[np.ndarray, np.ndarray] | None:
    """``(1/τ, μ)`` of the Gaussian prior estimator ``name`` puts on the free parameters, if any."""
    ps = options.get("prior_std")
    if name in ("kalman", "ukf", "isam2"):
        P0 = options.get("P0")
        if P0 is not None:
            P0 = np.asarray(P0, float)
            tau = P0 if P0.ndim == 1 else np.sqrt(np.diag(P0))
        else:
            tau = prior_std_vector(problem, names, ps)
        return 1.0 / tau, np.asarray(x0, float)
    if name == "gtsam" and (options.get("use_prior") or ps is not None):
        return 1.0 / prior_std_vector(problem, names, ps), np.asarray(x0, float)
    if name in _LSQ and ps is not None:
        return prior_arrays(names, ps, options.get("prior_mean"), x0)
    return None


def _max_step_sigma(res: CalibrationResult, name: str, options: dict) -> float:
    """Largest ``|δ_j| / max(σ_j, STEP_TOL_M/STEP_TOL_SIGMA)`` of the Gauss–Newton step ``δ`` from
    the estimate on the estimator's own cost (module docstring): ≤ STEP_TOL_SIGMA at an optimum."""
    # estimate.robust imports scipy.stats (0.4 s): only when a calibration is checked
    from estcal.estimate.robust import check_kernel, kernel_threshold, kernel_weight

    problem = res.problem
    fidx = problem.params.indices(res.names)
    rows = problem.evaluate(res.theta)
    e, A = rows.e / rows.sigma, rows.H[:, fidx] / rows.sigma[:, None]
    kernel = check_kernel(options.get("robust"))
    if kernel is not None:  # IRLS fixed point: the kernel's weight of each pose's residual norm
        g = np.linalg.norm(e.reshape(-1, 6), axis=1)
        w = np.repeat(np.sqrt(kernel_weight(kernel, g, kernel_threshold(kernel, 6, options.get("robust_k")))), 6)
        e, A = e * w, A * w[:, None]
    prior = _prior_of(name, problem, res.names, res.nominal, options)
    if prior is not None:
        winv, mu = prior
        e = np.r_[e, -winv * (res.estimate - mu)]
        A = np.r_[A, np.diag(winv)]
    step = np.linalg.lstsq(A, e, rcond=None)[0]
    scale = np.maximum(np.nan_to_num(np.asarray(res.std, float)), STEP_TOL_M / STEP_TOL_SIGMA)
    return float(np.max(np.abs(step) / scale)) if step.size else 0.0


def _convergence(res: CalibrationResult, name: str, options: dict) -> dict:
    step = _max_step_sigma(res, name, options)
    own = bool(res.converged)
    out = {"estimator": own, "max_step_sigma": step}
    if name == "mcmc":
        out.update(converged=own, test="the sampler's (effective sample size, autocorrelation time)")
        if not own:
            out["note"] = "the MCMC chain has not reached its target effective sample size (raise max_steps)"
        return out
    ok = own and step <= STEP_TOL_SIGMA
    out.update(converged=ok, test=f"the estimator's and a Gauss–Newton step ≤ {STEP_TOL_SIGMA} σ "
                                  f"(or {STEP_TOL_M:g} m) from the estimate")
    if not ok:
        hint = " (leave passes unset: the passes go on until converged)" if name in ("kalman", "ukf") else ""
        out["note"] = (f"not converged: the {name} estimate is {step:.3g} σ from the optimum of its cost"
                       + ("" if own else f"; {name} reports no convergence") + hint)
    return out


# ---------------------------------------------------------------- calibration
def _load(robot, data) -> tuple[GoughPlatform, GoughData, tuple]:
    inputs = tuple(str(x) for x in (robot, data) if isinstance(x, (str, Path)) and Path(str(x)).is_file())
    robot = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    data = data if isinstance(data, GoughData) else load_gough_data(data)
    return robot, data, inputs


def _result(res: CalibrationResult, robot, residuals, requested, theta_init, ide, model, inputs, conv):
    """The shared estimator's result as a :class:`GoughCalibrationResult`."""
    base = {f.name: getattr(res, f.name) for f in fields(CalibrationResult)}
    after = _accuracy(residuals, res.theta)
    base.update(converged=conv["converged"], inputs=inputs,
                accuracy={"train": {"before": _accuracy(residuals, theta_init), "after": after,
                                    "path": residuals.data.source}})
    base["extra"] = dict(res.extra, convergence=conv)
    return GoughCalibrationResult(**base, residual=residuals.kind, model=model, requested=list(requested),
                                  theta_initial=np.asarray(theta_init, float).copy(), identifiability=ide,
                                  fk_failures=int(after.get("fk_failures", 0)), nominal_robot=robot)


def calibrate_gough(
    robot: GoughPlatform | str | Path | Mapping,
    data: GoughData | str | Path,
    estimator: str = "lm",
    residual: str = "ik",
    model: int = 42,
    free: Sequence[str] | None = None,
    theta0: np.ndarray | None = None,
    initial: str = "nominal",
    daney_results: list | None = None,
    sigma_rho: float | None = None,
    sigma_p: float | None = None,
    sigma_r: float | None = None,
    method: str | None = None,
    **options: Any,
) -> GoughCalibrationResult:
    """Calibrate a Gough platform from measured poses and leg readings with a shared estimator.

    Parameters
    ----------
    robot : nominal platform (object, built-in name, robot file or dict).
    data : :class:`~estcal.parallel.data.GoughData` or a measurement file (CSV, NPZ, JSON).
    estimator : a name of :data:`ESTIMATORS` (the shared registry, :mod:`estcal.estimate.registry`);
        ``options`` are that estimator's (``estcal estimators``), e.g. ``passes=3`` for ``kalman``.
    residual : ``"ik"`` (leg readings predicted from the measured pose) or ``"fk"`` (pose predicted
        from the readings), docs/parallel.md.
    model : 42 (a, b, Δρ) or 36 (a, b; offsets fixed at their initial values).
    free : parameter names/patterns to estimate (default: the model's set).
    theta0 / initial : initial value: explicit (42,) vector, or ``"nominal"`` (the robot's values),
        or ``"daney"`` (the linear per-leg solutions ``daney_results``, a list of
        :class:`~estcal.parallel.daney.LegDaneyResult`).
    sigma_rho, sigma_p, sigma_r : noise std (m, m, rad); override those stored with the data.
        Without them the rows are weighted by :data:`~estcal.parallel.residuals.DEFAULT_SIGMA` and
        the covariance is scaled by χ²/(m − p).
    method : deprecated spelling of ``estimator``.

    Free parameters not identifiable at the initial value (QR of the whitened Jacobian) are kept
    at their initial value and reported with ``std`` None.
    """
    if method is not None:
        warnings.warn("calibrate_gough(method=...) is deprecated: use estimator=...", DeprecationWarning,
                      stacklevel=2)
        estimator = method
    _check_estimator(estimator, options)
    robot, data, inputs = _load(robot, data)
    theta_init = _initial_theta(robot, theta0, initial, daney_results)
    residuals = GoughResiduals(robot, data, residual, sigma_rho, sigma_p, sigma_r, theta_weights=theta_init)
    problem = GoughProblem(residuals, _free_parameters(robot, model, theta_init, free))
    requested = problem.params.free_names
    rows = problem.evaluate()
    ide = _identify(rows.H[:, problem.params.free_indices], requested)
    if ide["n_identifiable"] == 0:
        raise NumericalRefusal(f"{data.source}: none of the free parameters {requested} is identifiable from "
                               f"these poses")
    if ide["n_identifiable"] < len(requested):
        problem = problem.with_free(ide["identifiable"])
    res = get_estimator(estimator)(problem, **options)
    conv = _convergence(res, estimator, options)
    out = _result(res, robot, residuals, requested, theta_init, ide, model, inputs, conv)
    if out.fk_failures:
        _warn(f"{data.source}: the forward kinematics failed at {out.fk_failures} of {len(data)} poses at the "
              f"estimate; their residuals count as zero — check those poses before trusting this fit")
    return out


def identifiable_gough(
    robot: GoughPlatform | str | Path | Mapping,
    data: GoughData | str | Path | None = None,
    residual: str = "ik",
    model: int = 42,
    n_poses: int = 50,
    seed: int = 0,
    free: Sequence[str] | None = None,
) -> dict:
    """Identifiability of the Gough parameters (``estcal identifiable`` with a Gough robot).

    Uses the measured poses of ``data`` if given, else ``n_poses`` random workspace poses
    (noise-free, from ``seed``): the shared :func:`estcal.identify.select.identifiable` on the whitened
    Jacobian. Returns its dict (``n_parameters, n_identifiable, identifiable, no_effect, regrouped,
    condition_number`` …) plus ``robot``, ``model``, ``residual``, ``n_poses``.
    """
    robot = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    if data is None:
        data = simulate_gough_data(robot, n_poses, seed)
    elif not isinstance(data, GoughData):
        data = load_gough_data(data)
    problem = GoughProblem(GoughResiduals(robot, data, residual), _free_parameters(robot, model, robot.theta, free))
    rows = problem.evaluate()
    out = _identify(rows.H[:, problem.params.free_indices], problem.params.free_names)
    out.update({"robot": robot.name, "model": model, "residual": residual, "n_poses": len(data)})
    return out


# ---------------------------------------------------------------- simulation
def save_gough_data(data: GoughData, path) -> Path:
    """Write measurements as CSV (:meth:`GoughData.to_csv_text`), atomically."""
    return atomic_write_text(path, data.to_csv_text())


@dataclass
class GoughSimulation:
    """Output of :func:`simulate_gough` (``truth`` is JSON-ready)."""

    data: GoughData
    true_robot: GoughPlatform
    nominal_robot: GoughPlatform
    errors: dict
    true_T: np.ndarray
    true_rho: np.ndarray
    truth: dict

    def write(self, csv_path, truth_path=None, true_robot_path=None) -> Path:
        """Write the measurements CSV (:func:`load_gough_data` format), the ground truth JSON and
        the true robot file (YAML), when the paths are given."""
        save_gough_data(self.data, csv_path)
        if truth_path is not None:
            write_json(truth_path, dict(self.truth, dataset=str(csv_path)))
        if true_robot_path is not None:
            import yaml

            atomic_write_text(true_robot_path, yaml.safe_dump(self.true_robot.to_dict()))
        return Path(csv_path)

    def to_dict(self) -> dict:
        return self.truth


def _parameter_errors(pv: ParameterVector, errors, em, rng) -> dict:
    if errors is None or errors == "none":
        return {}
    if errors == "random":
        return {n: float(rng.normal(0.0, em.offset if k == "offset" else em.length)) for n, k in zip(pv.names, pv.kinds)}
    if isinstance(errors, Mapping):
        err = {str(k): float(v) for k, v in errors.items()}
        for n in err:
            pv.index(n)  # clear error for unknown names
        return err
    raise InputError(f"errors must be None, 'none', 'random' or a dict, got {errors!r}")


def simulate_gough(robot: GoughPlatform | str | Path | Mapping = "left_hand", n_poses: int = 50,
                   errors=None, error_std=None, noise=None, seed: int | None = 0,
                   T: np.ndarray | None = None) -> GoughSimulation:
    """Simulate a Gough calibration dataset: true robot = nominal + parameter errors, random
    workspace poses, noise on the measured poses and readings.

    Parameters
    ----------
    robot : nominal robot (object, built-in name, robot file, dict).
    n_poses : number of random workspace poses (ignored if ``T`` is given).
    errors : None / ``"none"`` (true = nominal), ``"random"`` (N(0, σ²) with ``error_std.length``
        for ``a_k, b_k`` and ``error_std.offset`` for ``drho_k``) or ``{name: δ}``.
    error_std : :class:`estcal.simulate.ErrorModel` or dict of its fields.
    noise : :class:`estcal.simulate.NoiseModel` or dict (default noise-free): ``position`` on each
        coordinate of the measured platform position, ``orientation`` on each rotation-vector
        component of its orientation, ``joint`` on each leg reading (Gaussian σ or uniform half-width).
    seed : seeds independent streams for errors, poses and noise.
    """
    nominal = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    noise = simulation_noise(noise)
    em = error_std if isinstance(error_std, ErrorModel) else ErrorModel(**(error_std or {}))
    r_err, r_pose, r_noise = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    pv = nominal.parameter_vector(42)
    err = _parameter_errors(pv, errors, em, r_err)
    theta = pv.values.copy()
    for n, v in err.items():
        theta[pv.index(n)] += v
    true = nominal.with_theta(theta)
    true.name = f"{nominal.name}_true"
    Tt = generate_random_poses(true, n_poses, r_pose) if T is None else np.asarray(T, float).reshape(-1, 4, 4)
    rho_t = true.leg_lengths(Tt)
    P, R = split_pose(Tt)
    Pm = P + noise.draw(noise.position, P.shape, r_noise)
    Rm = so3_exp(noise.draw(noise.orientation, P.shape, r_noise)) @ R
    rho_m = rho_t + noise.draw(noise.joint, rho_t.shape, r_noise)
    data = GoughData(make_T(Pm, Rm), rho_m, noise.std(noise.joint) or None, noise.std(noise.position) or None,
                     noise.std(noise.orientation) or None, "simulated")
    truth = {
        "robot": nominal.name, "n_poses": int(len(Tt)), "seed": seed,
        "errors": err, "true_parameters": dict(zip(pv.names, theta.tolist())),
        "nominal_parameters": dict(zip(pv.names, pv.values.tolist())),
        "noise": noise.to_dict(simulation=True) | {"meaning": {"position": "platform position, each coordinate (m)",
                                                "orientation": "rotation-vector component (rad)",
                                                "joint": "leg reading (m)"}},
        "error_std": em.to_dict(),
    }
    return GoughSimulation(data, true, nominal, err, Tt, rho_t, truth)
