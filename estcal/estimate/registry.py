"""Estimators by name, so the CLI and users pick one with a string.

Each entry is ``"module:function"``; the function has the signature
``f(problem, free=None, validation=(), **options) -> CalibrationResult``.
Modules are imported lazily so optional backends cost nothing until used.
"""
from __future__ import annotations

import importlib

__all__ = ["ESTIMATORS", "get_estimator", "register_estimator", "estimator_names"]

ESTIMATORS: dict[str, str] = {
    "lm": "estcal.estimate.lsq:calibrate_lsq",
    "gauss-newton": "estcal.estimate.lsq:calibrate_lsq",
    "iterated-lls": "estcal.estimate.lsq:calibrate_lsq",
    "scipy-lm": "estcal.estimate.lsq:calibrate_lsq",
    "gtsam": "estcal.estimate.factorgraph:calibrate_gtsam",
    "isam2": "estcal.estimate.factorgraph:calibrate_isam2",
    "gtsam-timevarying": "estcal.estimate.factorgraph:calibrate_timevarying",
    "kalman": "estcal.estimate.kalman:calibrate_kalman",
    "ukf": "estcal.estimate.kalman:calibrate_ukf",
    "mcmc": "estcal.estimate.mcmc:calibrate_mcmc",
}


def register_estimator(name: str, target) -> None:
    """Add an estimator: ``target`` is a callable or a ``"module:function"`` string."""
    ESTIMATORS[name] = target


def estimator_names() -> list[str]:
    return sorted(ESTIMATORS)


def get_estimator(name: str):
    """Callable ``f(problem, free=None, validation=(), **options)`` for ``name``."""
    try:
        target = ESTIMATORS[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; choose one of {estimator_names()}") from None
    if callable(target):
        return target
    mod, fn = target.split(":")
    try:
        f = getattr(importlib.import_module(mod), fn)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"estimator {name!r} is not available ({exc})") from exc
    if mod.endswith(".lsq"):
        return lambda problem, **kw: f(problem, method=name, **kw)
    return f
