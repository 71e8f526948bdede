"""Estimators by name, so the CLI and users pick one with a string.

Each entry is ``"module:function"``; the function has the signature
``f(problem, free=None, validation=(), **options) -> CalibrationResult``.
Modules are imported lazily so optional backends cost nothing until used.
"""
from __future__ import annotations

import importlib
import math

__all__ = ["ESTIMATORS", "get_estimator", "estimator_names", "estimator_options",
           "check_options"]

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


# Estimators whose ``**options`` are passed on to another function: the keys that one accepts.
_FORWARDS = {"estcal.estimate.mcmc:calibrate_mcmc": "estcal.estimate.mcmc:sample_posterior",
             "estcal.estimate.kalman:calibrate_ukf": "estcal.estimate.kalman:calibrate_kalman"}
# Arguments the calibration entry point fills itself (not user options).
_RESERVED = {"problem", "free", "validation", "method", "check", "theta0", "filter"}


def _resolve(target):
    if callable(target):
        return target
    mod, fn = target.split(":")
    return getattr(importlib.import_module(mod), fn)


def estimator_options(name: str) -> dict:
    """``{option: default}`` of the keyword options estimator ``name`` accepts (``--option KEY=VALUE``).

    Read from the estimator function's signature (and, for those that pass ``**options`` on, from
    the function receiving them); arguments the calibration fills itself (problem, free set,
    validation data, initial values) are not listed. Imports the estimator's backend.
    """
    import inspect

    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; choose one of {estimator_names()}")
    targets = [ESTIMATORS[name]]
    if isinstance(targets[0], str) and targets[0] in _FORWARDS:
        targets.append(_FORWARDS[targets[0]])
    out = {}
    for t in targets:
        try:
            f = _resolve(t)
        except (ImportError, AttributeError) as exc:
            raise ValueError(f"estimator {name!r} is not available ({exc})") from exc
        for p in inspect.signature(f).parameters.values():
            if p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL) or p.name in _RESERVED:
                continue
            out[p.name] = None if p.default is inspect.Parameter.empty else p.default
    return out


#: accepted values of numeric estimator options, by name (``--option KEY=VALUE``): counts are
#: integers ≥ 1, tolerances and scales are > 0; any other number must be finite
OPTION_RANGES = [
    ({"batch_size", "check_every", "lags", "max_iter", "max_steps", "min_steps", "n_walkers", "passes",
      "poses_per_factor", "chunk"}, (lambda v: v >= 1 and float(v).is_integer(), "an integer ≥ 1")),
    ({"burn_in", "final_updates", "seed"}, (lambda v: v >= 0 and float(v).is_integer(), "an integer ≥ 0")),
    ({"final_sigma", "init_scale", "proposal_scale", "relinearize_sigma", "relinearize_threshold", "robust_k",
      "target_ess", "tau_factor", "tol", "ukf_alpha", "noise_scale", "encoder_std", "prior_std"},
     (lambda v: math.isfinite(v) and v > 0, "a finite number > 0")),
    ({"q"}, (lambda v: math.isfinite(v) and v >= 0, "a finite number ≥ 0")),
    ({"level"}, (lambda v: 0 < v < 1, "a number strictly between 0 and 1")),
]


def check_options(name: str, options) -> None:
    """Raise ``ValueError`` naming the estimator and its valid keys when an option is unknown."""
    import difflib

    valid = estimator_options(name)
    bad = [k for k in (options or {}) if k not in valid]
    if bad:
        hint = difflib.get_close_matches(bad[0], list(valid), n=1)
        raise ValueError(f"estimator {name!r} has no option {bad[0]!r}"
                         f"{f' (did you mean {hint[0]!r}?)' if hint else ''}; valid keys: "
                         f"{', '.join(sorted(valid))} (see `estcal estimators`)")
    # a number where the default is a number (bools are not numbers here)
    for k, v in (options or {}).items():
        d = valid[k]
        if isinstance(d, (int, float)) and not isinstance(d, bool) and not (
                isinstance(v, (int, float)) and not isinstance(v, bool)):
            raise ValueError(f"estimator {name!r}, option {k!r}: expected a number (default {d!r}), got {v!r}")
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            rule = next((r for keys, r in OPTION_RANGES if k in keys), None)
            if not math.isfinite(v) or (rule is not None and not rule[0](v)):
                raise ValueError(f"estimator {name!r}, option {k}={v!r}: must be "
                                 f"{rule[1] if rule else 'a finite number'}")
