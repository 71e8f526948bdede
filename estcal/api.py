"""The workflow functions of the Python API (``estcal.calibrate``, ``estcal.diagnose``).

Thin wrappers over the functions behind ``estcal calibrate`` and ``estcal diagnose``
(:func:`estcal.estimate.levels.run_calibration`, :func:`estcal.discrepancy.diagnose`) that
accept what a user has at hand — a robot name, robot file, URDF or robot object; a CSV path
or a :class:`~estcal.io.dataset.Dataset`; the noise as a number — and return the result
objects, which know how to save themselves (``result.save_model(path)``). Reference:
docs/api.md.
"""
from __future__ import annotations

import numbers
from pathlib import Path

__all__ = ["calibrate", "diagnose", "as_noise", "robot_and_data"]


def as_noise(noise=None, known: bool = False):
    """A :class:`estcal.methods.NoiseModel` from the forms ``noise=`` accepts.

    * ``None`` — the defaults (0.1 mm, 1 mrad), as relative weights;
    * a number — position std σ (m); orientation std σ / 0.1 m (rad), the CLI's ratio;
    * a pair ``(position m, orientation rad)``;
    * a mapping ``{"position": m, "orientation": rad, "scalar": m, "known": bool}``;
    * a ``NoiseModel`` (returned as is; ``known`` is then ignored).

    ``known``: the stds are trusted absolute values (covariance not rescaled by σ0²).
    """
    from estcal.methods import NoiseModel

    if isinstance(noise, NoiseModel):
        return noise
    if noise is None:
        return NoiseModel(known=known)
    if isinstance(noise, dict):
        bad = set(noise) - {"position", "orientation", "scalar", "known"}
        if bad:
            raise ValueError(f"noise: unknown key(s) {sorted(bad)}; use position (m), orientation (rad), "
                             f"scalar (m), known (bool)")
        d = {"known": known, **noise}
        d.setdefault("scalar", d.get("position", NoiseModel.position))
        return NoiseModel(**d)
    if isinstance(noise, (tuple, list)):
        if len(noise) != 2:
            raise ValueError(f"noise: expected (position m, orientation rad), got {noise!r}")
        p, r = float(noise[0]), float(noise[1])
        return NoiseModel(position=p, orientation=r, scalar=p, known=known)
    s = float(noise)
    if not s > 0:
        raise ValueError(f"noise: the position std must be > 0 m, got {noise!r}")
    return NoiseModel(position=s, orientation=s / 0.1, scalar=s, known=known)


def _n_points_of(path) -> int | None:
    from estcal.cli.common import count_point_columns

    k, _, has_quat = count_point_columns(path)
    return k if k and not has_quat else None


def robot_and_data(robot, data, validate=(), points: int | None = None, root=None, tip=None):
    """Resolve ``robot`` (spec or object) and ``data`` / ``validate`` (paths or Datasets) together:
    a robot gets one unknown marker per measured point (``points``: keep the first N)."""
    from estcal.io.dataset import Dataset, load_dataset
    from estcal.io.robotfile import load_robot

    if points is not None and (isinstance(points, bool) or not isinstance(points, numbers.Integral) or points < 1):
        raise ValueError(f"points must be an integer ≥ 1 (the first N measured points), got {points!r}")
    k = None
    if isinstance(data, Dataset):
        k = data.n_points if data.kind == "points" else None
    else:
        k = _n_points_of(data)
    if points is not None:
        k = points
    if k is not None and not isinstance(robot, str | Path) and getattr(robot, "n_markers", 0) == k:
        rob = robot
    else:
        rob = load_robot(robot, root=root, tip=tip, n_markers=k)

    def load(d):
        if isinstance(d, Dataset):
            return d.with_points(k) if k is not None and d.n_points > k else d
        return load_dataset(d, rob, points=k)

    return rob, load(data), [load(v) for v in validate]


def calibrate(robot, data, method: str = "lm", *, free=None, level: str = "full", selection: str | None = None,
              measure: str | None = None, validate=(), noise=None, known_noise: bool = False, regularize=None,
              points: int | None = None, root: str | None = None, tip: str | None = None, checks: bool = True,
              allow_ill_conditioned: bool = False, **options):
    """Estimate the robot's parameters from measurements — ``estcal calibrate`` in Python.

    Parameters
    ----------
    robot : SerialRobot, built-in name, robot file (.yaml, e.g. a saved model) or URDF (.urdf).
    data : Dataset or CSV path (joint columns + x,y,z / x1..zk / pose; docs/dataset.md).
    method : estimator — ``lm`` (default), ``gauss-newton``, ``iterated-lls``, ``scipy-lm``,
        ``gtsam``, ``isam2``, ``gtsam-timevarying``, ``kalman``, ``ukf``, ``mcmc``.
    free : parameter names or shell patterns to estimate (default: the identifiable set of ``level``).
    level : ``registration`` | ``joint_offset`` | ``full``.
    selection : ``structural`` (default) | ``aic`` | ``bic``.
    measure : measurement method name (default: from the data's columns).
    validate : datasets or paths scored before/after (never used for the fit).
    noise : measurement noise — see :func:`as_noise` (number = position std in m).
    known_noise : trust ``noise`` as absolute (covariance not rescaled by σ0²).
    regularize : ``None``, ``"loo"`` or a prior std (SI) toward the nominal joint model.
    points : use the first N measured points.
    root, tip : URDF links delimiting the chain.
    checks : the numerical refusals of ``estcal calibrate`` (docs/reliability.md, "Numerical
        refusals"): :class:`~estcal.base.errors.NumericalRefusal` (a ``ValueError``) when the
        degrees of freedom are ≤ 0, the poses are repeated or degenerate, the estimator did not
        converge or the problem is ill-conditioned; ``False`` returns whatever the estimator gives.
    allow_ill_conditioned : turn the rank, convergence and conditioning refusals into warnings
        (``result.extra["reliability"]``), as ``--allow-ill-conditioned``.
    **options : estimator options (``max_iter=50``, ``q=1e-6`` …); ``estcal estimators`` lists them.

    Returns
    -------
    CalibrationResult — ``estimate``, ``std``, ``covariance`` (SI), ``accuracy`` (mm / mrad),
    ``parameter(name)`` → (estimate, std), ``robot()``, ``save_model(path)``, ``to_json(path)``.
    """
    from estcal.estimate.levels import run_calibration

    rob, ds, vals = robot_and_data(robot, data, validate, points, root, tip)
    res, _, _ = run_calibration(rob, ds, measure=measure, estimator=method, free=free,
                                level=None if free is not None else level, selection=selection, validate=vals,
                                noise=as_noise(noise, known_noise), options=options, regularize=regularize,
                                checks=checks, allow_ill_conditioned=allow_ill_conditioned)
    return res


def diagnose(robot, data, *, validate=(), effects=None, noise=None, points: int | None = None,
             root: str | None = None, tip: str | None = None, urdf_chain_masses: bool = True, **kw):
    """What the geometric model gets wrong, and which effect explains it — ``estcal diagnose``.

    Parameters
    ----------
    robot, data, validate, points, root, tip : as in :func:`calibrate`.
    effects : effect names to try (default: every registered effect, docs/effects.md).
    noise : the known measurement noise, in the forms of :func:`as_noise` (a number is the position
        std in m), taken as known (likelihood-ratio tests, noise-floor test); None: unknown (F tests).
    urdf_chain_masses : for URDF robots, count the links after the last actuated joint in its mass.
    **kw : options of :func:`estcal.discrepancy.diagnose` (``k_folds``, ``alpha``, ``max_effects``,
        ``geometric``, ``approach_from_order``, ``report`` …).

    Returns
    -------
    DiagnosisResult — ``causes``, ``verdict``, ``rmse_mm``, ``robot`` (extended), ``save_model(path)``.
    """
    from estcal.discrepancy import diagnose as _diagnose

    rob, ds, vals = robot_and_data(robot, data, validate, points, root, tip)
    if urdf_chain_masses and rob.meta.get("urdf"):
        from estcal.discrepancy.masses import with_urdf_masses

        rob = with_urdf_masses(rob)
    if "robot_spec" not in kw and isinstance(robot, str | Path):
        kw["robot_spec"] = str(robot)
    nm = None if noise is None else as_noise(noise, known=True)
    return _diagnose(rob, ds, validate=vals, candidates=list(effects) if effects else None, noise=nm, **kw)
