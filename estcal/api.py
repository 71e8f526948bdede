"""The workflow functions of the Python API (``estcal.calibrate``, ``estcal.diagnose``).

The Python face of the workflows behind ``estcal calibrate`` and ``estcal diagnose``
(:mod:`estcal.workflows.calibrate`, :mod:`estcal.workflows.diagnose`): they accept what a user has
at hand — a robot name, robot file, URDF or robot object; a CSV path or a
:class:`~estcal.io.dataset.Dataset`; the noise as a number — and return the result objects, which
know how to save themselves (``result.save_model(path)``). Errors are those of
:mod:`estcal.base.errors` (a bad file: ``DatasetError``; a fit the data cannot support:
``NumericalRefusal``); this module never imports the command line. Reference: docs/api.md.
"""
from __future__ import annotations

import warnings

__all__ = ["calibrate", "diagnose", "as_noise", "robot_and_data", "to_api_words", "api_words"]


def as_noise(noise=None, known: bool = False):
    """A :class:`estcal.methods.NoiseModel` from the forms ``noise=`` accepts — the one rule of
    :meth:`estcal.methods.NoiseModel.parse` (docs/conventions.md, "Noise"):

    * ``None`` — the defaults (0.1 mm, 1 mrad), as relative weights;
    * a number — position std σ (m); orientation std σ / 0.1 m (rad), the CLI's ratio;
    * a pair ``(position m, orientation rad)``;
    * a mapping ``{"position": m, "orientation": rad, "scalar": m, "known": bool}``;
    * a ``NoiseModel`` (returned as is; ``known`` is then ignored).

    ``known``: the stds are trusted absolute values (covariance not rescaled by σ0²).
    """
    from estcal.methods import NoiseModel

    return NoiseModel.parse(noise, known=known)


def robot_and_data(robot, data, validate=(), points: int | None = None, root=None, tip=None):
    """Resolve ``robot`` (spec or object) and ``data`` / ``validate`` (paths or Datasets) together:
    a robot gets one unknown marker per measured point (``points``: keep the first N)."""
    from estcal.workflows.inputs import robot_and_data as resolve

    return resolve(robot, data, validate, points, root, tip)


def _estimator_and_measure(estimator, measure, method):
    """``method=`` is deprecated: it named the estimator or the measurement (dispatched by name)."""
    if method is None:
        return estimator, measure
    from estcal.base.errors import EstcalWarning, InputError
    from estcal.estimate.registry import estimator_names
    from estcal.methods import METHODS, get_method

    get_method("position")  # the optional measurement modules, so that METHODS is complete
    if method in estimator_names():
        warnings.warn(f"method= is deprecated; use estimator={method!r} (docs/conventions.md, 'One vocabulary')",
                      EstcalWarning, stacklevel=3)
        return method, measure
    if method in METHODS:
        if measure is not None and measure != method:
            raise InputError(f"method={method!r} (a measurement) but measure={measure!r} was also given")
        warnings.warn(f"method= is deprecated; use measure={method!r} (docs/conventions.md, 'One vocabulary')",
                      EstcalWarning, stacklevel=3)
        return estimator, method
    raise InputError(f"unknown method {method!r}: neither an estimator ({', '.join(estimator_names())}) nor a "
                     f"measurement ({', '.join(sorted(METHODS))}) — use estimator= or measure=")


def calibrate(robot, data, estimator: str = "lm", *, measure: str | None = None, free=None, level: str | None = None,
              selection: str | None = None, validate=(), noise=None, known_noise: bool = False, regularize=None,
              points: int | None = None, root: str | None = None, tip: str | None = None, checks: bool = True,
              allow_ill_conditioned: bool = False, drop_flagged: bool = True, method: str | None = None, **options):
    """Estimate the robot's parameters from measurements — ``estcal calibrate`` in Python.

    Parameters
    ----------
    robot : SerialRobot, built-in name, robot file (.yaml, e.g. a saved model) or URDF (.urdf).
    data : Dataset or CSV path (joint columns + x,y,z / x1..zk / pose; docs/dataset.md), or a list
        of them: several sessions fitted with one parameter set.
    estimator : ``lm`` (default), ``gauss-newton``, ``iterated-lls``, ``scipy-lm``,
        ``gtsam``, ``isam2``, ``gtsam-timevarying``, ``kalman``, ``ukf``, ``mcmc``.
    measure : what was measured (``position``, ``pose``, ``points``, ``point-link`` …; default: from
        the data's columns).
    free : parameter names or shell patterns to estimate (default: the identifiable set of ``level``).
    level : ``registration`` | ``joint_offset`` | ``full``; None (the default, as ``estcal calibrate``'s): ``full``,
        and when its fit is refused for its conditioning (no convergence, a condition number above the limit) the
        identifiable geometric parameters under relevance priors instead (``result.extra["default_model"]`` says
        so; docs/calibration.md, "When the full level is refused").
    selection : ``structural`` (default) | ``aic`` | ``bic``.
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
    drop_flagged : leave out (default) the rows the data screening flags — readings beyond the joint limits,
        outliers after a robust fit, swapped or ghost markers, copies — named with their residual and the
        least-squares fit with them in ``result.extra["left_out"]`` and one warning; ``False`` fits every row
        (``--keep-all``). Needs ``checks`` (docs/reliability.md, "Gross errors").
    method : deprecated — the estimator or the measurement, dispatched by name (warned).
    **options : estimator options (``max_iter=50``, ``q=1e-6`` …); ``estcal estimators`` lists them.

    Returns
    -------
    CalibrationResult — ``estimate``, ``std``, ``covariance`` (SI), ``accuracy`` (mm / mrad),
    ``parameter(name)`` → (estimate, std), ``robot()``, ``save_model(path)``, ``to_json(path)``.
    """
    from estcal.workflows.calibrate import calibrate as run

    estimator, measure = _estimator_and_measure(estimator, measure, method)
    with api_words():
        cal = run(robot, data, estimator=estimator, measure=measure, free=free,
                  level=None if free is not None else level, selection=selection, validate=list(validate),
                  noise=as_noise(noise, known_noise), regularize=regularize, options=options, points=points,
                  root=root, tip=tip, checks=checks, allow_ill_conditioned=allow_ill_conditioned,
                  drop_flagged=drop_flagged)
    return cal.result


#: the command line's words → the Python API's (docs/conventions.md, "One vocabulary"): a flag → its keyword
#: and how its value is written (``list``: ``--free a,b`` → ``free=['a', 'b']``; ``str``: quoted; ``raw``;
#: ``si``: not copied, the flag's unit is not the keyword's; None: a flag without value → the keyword that sets it)
API_WORDS = {"--free": ("free", "list"), "--level": ("level", "str"), "--selection": ("selection", "str"),
             "--estimator": ("estimator", "str"), "--measure": ("measure", "str"), "--points": ("points", "raw"),
             "--root": ("root", "str"), "--tip": ("tip", "str"), "--validate": ("validate", "raw"),
             "--regularize": ("regularize", "raw"), "--robust": ("robust", "str"), "--chain": ("chain", "raw"),
             "--allow-ill-conditioned": ("allow_ill_conditioned=True", None),
             "--known-noise": ("known_noise=True", None),
             "--noise-pos-mm": ("noise", "si"), "--noise-rot-mrad": ("noise", "si"),
             "--option": ("an estimator keyword", None)}
_FLAG = None
#: words that may follow a flag as its value although they carry no digit, '_', ',' or '.'
_CHOICES = {"full", "registration", "structural", "aic", "bic", "lm", "gtsam", "isam2", "kalman", "ukf", "mcmc",
            "position", "pose", "points", "huber", "cauchy", "loo"}


def to_api_words(text: str) -> str:
    """``text`` (a message of the workflows, written with the command line's flags) in the API's keywords:
    ``pass --allow-ill-conditioned`` → ``pass allow_ill_conditioned=True``, ``(--level joint_offset, --free …)``
    → ``(level='joint_offset', free=…)``."""
    import re

    global _FLAG
    if _FLAG is None:
        flags = "|".join(sorted((re.escape(f) for f in API_WORDS), key=len, reverse=True))
        _FLAG = re.compile(rf"(?<![\w-])({flags})(?![\w-])(:?)(?:[ =]([^\s;:()]+?)(?=[\s;:()]|[,.](?:\s|$)|$))?")

    def value_of(v):
        if v is None:
            return None
        if len(v) > 1 and v[0] == v[-1] and v[0] in "'\"":
            return v[1:-1]
        return v if (v == "…" or re.search(r"[\d_,.*]", v) or v in _CHOICES) else None

    def sub(m):
        word, how = API_WORDS[m.group(1)]
        colon, raw = m.group(2), m.group(3)
        value = None if colon else value_of(raw)
        rest = "" if value is not None or raw is None or colon else f" {raw}"
        if how is None:
            return word + colon + rest
        if colon:
            return word + colon + (f" {raw}" if raw else "")
        if value is None or value == "…" or how == "si":  # "si": the flag's milli-unit value is not the keyword's
            return f"{word}=…{rest}"
        if how == "list":
            return f"{word}={[v for v in value.split(',') if v]!r}{rest}"
        return (f"{word}={value!r}" if how == "str" else f"{word}={value}") + rest

    return _FLAG.sub(sub, text)


class api_words:
    """Errors raised inside the block speak the API's keywords (:func:`to_api_words`), not the command
    line's flags; the exception's type is kept."""

    def __enter__(self):
        return self

    def __exit__(self, typ, exc, tb):
        from estcal.base.errors import EstcalError

        if isinstance(exc, EstcalError) and exc.args and isinstance(exc.args[0], str):
            exc.args = (to_api_words(exc.args[0]),) + tuple(exc.args[1:])
        return False


def diagnose(robot, data, *, validate=(), effects=None, noise=None, points: int | None = None,
             root: str | None = None, tip: str | None = None, folds: int = 5, geometric: str = "sparse",
             budget: bool = True, seed: int = 0, urdf_chain_masses: bool = True, approach_from_order: bool = True,
             column_map=None, drop_flagged: bool = True, report=None, register_zeros: bool = True,
             geometric_width: float | str | None = "auto"):
    """How accurate the robot's model is at new postures, which physical causes it names, what stays
    unexplained — ``estcal diagnose`` (docs/discrepancy.md; the defaults are the command's).

    Parameters
    ----------
    robot, data, validate, points, root, tip : as in :func:`calibrate`; ``data`` may be a list of sessions
        (each session's measuring frame registered); each validation file is scored at its new postures,
        its frame registered on its rows at postures the training measured (with ``register_zeros``, the
        default, also every joint zero those rows show moved since training).
    effects : effect names to consider (default: every registered effect, docs/effects.md).
    noise : the measurement noise in the forms of :func:`as_noise` (the rows' relative weights; the model
        fits its scale).
    folds : cross-validation folds (by posture; by session too with several sessions); seed : their seed.
    geometric : ``"sparse"`` (every identifiable geometric parameter under a relevance prior), ``"full"``
        (unpenalised) or ``"joint_offset"``.
    geometric_width : the widest prior standard deviation of a link frame's parameter — m for a length, rad
        for an angle; ``"auto"`` (the default): 1 mm / 1 mrad unless the unbounded model's cross-validated
        error is lower by more than one standard error; None: unbounded. Joint offsets and the tool are not
        bounded (docs/discrepancy.md).
    budget : the error budget (nested and time-blocked cross-validation, the 95 % region).
    drop_flagged : leave out the rows the data screening flags (the default, as :func:`calibrate`'s; named in
        ``result.data["left_out"]`` and in the text); False fits every row.
    urdf_chain_masses, approach_from_order, column_map, report : as ``estcal diagnose``.

    Returns
    -------
    DiagnosisResult — ``answer`` (expected error at new postures and its 95 % bound), ``causes``,
    ``accuracy`` (one validation figure per file), ``robot`` (the model), ``save_model(path)``.
    """
    from estcal.workflows.diagnose import diagnose as run

    nm = None if noise is None else as_noise(noise, known=True)
    return run(robot, data, validate=list(validate), effects=effects, noise=nm, points=points, root=root, tip=tip,
               folds=folds, geometric=geometric, budget=budget, seed=seed, urdf_chain_masses=urdf_chain_masses,
               approach_from_order=approach_from_order, column_map=column_map, drop_flagged=drop_flagged,
               report=report, register_zeros=register_zeros, geometric_width=geometric_width)
