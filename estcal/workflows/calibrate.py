"""Batch calibration: ``estcal calibrate`` and ``estcal.calibrate`` (docs/calibration.md).

:func:`calibrate` takes what the user has at hand — a robot spec or object; one dataset (path or
:class:`~estcal.io.dataset.Dataset`) or several sessions fitted with one parameter set — and goes
through five steps:

1. **Robot** — :func:`estcal.io.robotfile.load_robot` (built-in name, robot file, URDF with
   ``root``/``tip``), with as many unknown markers as measured points. A Gough-platform robot
   file is calibrated by :func:`calibrate_gough` (:mod:`estcal.workflows.gough`).
2. **Measurement** — from the columns (``x,y,z`` → position of the tool origin; ``x1..zk`` → k
   points with unknown coordinates in the tool frame, ``points=N`` keeps the first N;
   ``x,y,z,qw..qz`` → pose), or a measurement named by ``measure`` (``position``, ``pose``,
   ``point-link`` …).
3. **Initial guess** — data in an unknown frame (points / poses) are first registered: the
   base transform is set by Kabsch/Horn (:func:`estcal.estimate.register_base`).
4. **Free set** — ``free`` (names or shell patterns) or ``level`` (``registration``,
   ``joint_offset``, ``full``), reduced to an identifiable set on the calibration data only
   (never the validation files) by :func:`estcal.estimate.levels.select_free` (QR in GECARO
   priority order at the robot's design structure; ``selection="aic"|"bic"`` adds greedy pruning).
   A saved model recalibrated at the level it was saved with fits its own free set.
5. **Estimation** — any estimator of :mod:`estcal.estimate.registry`, then accuracy before/after
   on the calibration data and on each validation dataset, and — with ``checks`` — the numerical
   refusals of docs/reliability.md.

Errors are typed (:mod:`estcal.base.errors`): bad input is an ``InputError`` (``DatasetError``,
``RobotFileError``, ``ParameterError``, ``UnidentifiableError`` …), a result the data cannot
support a ``NumericalRefusal``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError, NumericalRefusal
from estcal.estimate.levels import LEVELS, Selection, level_candidates, robust_report, select_free
from estcal.workflows.inputs import (check_held_out, check_input_files, input_errors, load_datasets, robot_for_data,
                                     split_names, warn_datasets)

__all__ = ["Calibration", "calibrate", "calibrate_gough", "run_calibration", "ROBUST_KERNELS"]

ROBUST_KERNELS = ("huber", "cauchy")


@dataclass
class Calibration:
    """What a calibration computed and from what.

    result : :class:`~estcal.estimate.result.CalibrationResult` (estimate, std, covariance in SI;
        accuracy in mm / mrad; ``extra`` records the robot, data, measure, estimator, noise)
    selection : the :class:`~estcal.estimate.levels.Selection` of the free set (None with ``free``)
    problem : the :class:`~estcal.methods.Problem` at the initial guess
    robot : the robot the data were fitted with (with its markers)
    validation : the validation datasets, scored in order
    data_label, validate_labels : how the data were named (file paths, " + " between sessions)
    """

    result: object
    selection: Selection | None
    problem: object
    robot: object
    validation: list = field(default_factory=list)
    data_label: str = ""
    validate_labels: list = field(default_factory=list)

    @property
    def measure(self) -> str:
        return self.problem.terms[0].method.name

    @property
    def estimator(self) -> str:
        return self.result.extra.get("estimator", self.result.method)


def _label(item) -> str:
    return str(getattr(item, "where", None) or getattr(item, "path", None) or item)


def _check_choices(estimator, measure, level, free, robust, regularize) -> None:
    from estcal.estimate.registry import estimator_names
    from estcal.methods import METHODS, get_method

    get_method("position")  # imports the optional measurement modules, so METHODS is complete
    if estimator not in estimator_names():
        raise InputError(f"unknown estimator {estimator!r}; choose one of {estimator_names()}")
    if measure is not None and measure not in METHODS:
        raise InputError(f"unknown measurement method {measure!r}; choose one of {sorted(METHODS)}")
    if free is not None and level is not None:
        raise InputError("give either --free or --level, not both")
    if level is not None and level not in LEVELS:
        hint = ""
        if level in ("structural", "aic", "bic"):  # a selection criterion given as a level: say where it goes
            hint = (f" — {level!r} is a selection criterion, not a level: --selection {level} (it prunes the "
                    f"identifiable set of --level, default full)")
        raise InputError(f"unknown --level {level!r}; choose one of {', '.join(LEVELS)}{hint}")
    if robust is None:
        return
    if robust not in ROBUST_KERNELS:
        raise InputError(f"--robust must be huber or cauchy, got {robust!r}")
    if estimator == "ukf":
        raise InputError("--robust: the UKF has no robust update here — use --estimator kalman (EKF with a robust "
                         "innovation weight) or a least-squares / factor-graph estimator")
    if estimator == "mcmc":
        raise InputError("--robust: MCMC samples the Gaussian likelihood and has no robust likelihood — use "
                         "--estimator lm --robust … to name the outliers, remove them, then sample")
    if regularize is not None:
        raise InputError("--robust with --regularize is not supported: choose one")


def calibrate(robot, data, *, estimator: str = "lm", measure: str | None = None, free=None,
              level: str | None = None, selection: str | None = None, validate=(), noise=None,
              regularize=None, robust: str | None = None, options: dict | None = None, points: int | None = None,
              root: str | None = None, tip: str | None = None, checks: bool = True,
              allow_ill_conditioned: bool = False, column_map=None, posture_tol=(1e-3, 1e-3),
              drop_flagged: bool = True) -> Calibration:
    """Calibrate ``robot`` on ``data`` — the job of ``estcal calibrate``.

    Parameters
    ----------
    robot : SerialRobot, built-in name, robot file (.yaml, e.g. a saved model) or URDF.
    data : a dataset (CSV path or :class:`~estcal.io.dataset.Dataset`) or a list of them: several
        sessions, fitted with one parameter set.
    estimator : estimator name (``estcal estimators``); measure : measurement name (default: from
        the columns). free : names / shell patterns (a list or a comma-separated string);
        level : ``registration`` | ``joint_offset`` | ``full`` (default ``full`` when ``free`` is
        not given). selection : ``structural`` (default) | ``aic`` | ``bic``.
    validate : datasets scored before/after, never used for a decision.
    noise : a :class:`~estcal.methods.NoiseModel` (default 0.1 mm / 1 mrad, relative weights).
    regularize : None, ``"loo"`` or a prior std (SI); robust : ``huber`` | ``cauchy``.
    options : estimator options (SI); ``{"chain": path}`` keeps an MCMC chain.
    points, root, tip, column_map : as the loader's (first N points, URDF chain, column map).
    drop_flagged : leave out (default) the rows that the data screening flags as defects — readings beyond
        the joint limits, outliers after a robust fit, swapped or ghost markers, copies
        (:func:`estcal.workflows.check.screen_rows`; docs/reliability.md, "Gross errors"); they are named
        in ``result.extra["left_out"]`` with their residual and the least-squares fit with them
        (:mod:`estcal.workflows.left_out`). ``False`` (``--keep-all``) fits every row; ``checks=False`` skips
        the screening.
    checks, allow_ill_conditioned : the numerical refusals (docs/reliability.md).
    posture_tol : ``(rad, m)``: validation rows whose readings agree with a calibration row within it are at
        *seen* postures; each validation score is split into ``seen`` / ``new`` (docs/real-data.md).
    """
    sessions = list(data) if isinstance(data, (list, tuple)) else [data]
    if not sessions:
        raise InputError("no calibration data given")
    free = split_names(free)
    options = dict(options or {})
    _check_choices(estimator, measure, level, free, robust, regularize)
    if options.get("chain") is not None and estimator != "mcmc":
        raise InputError(f"--chain stores an MCMC chain: it needs --estimator mcmc, not {estimator!r}")
    if robust is not None:
        options["robust"] = robust
    check_input_files([*sessions, *validate])
    rob, n_markers = robot_for_data(robot, sessions[0], points, root, tip, column_map)
    parts = load_datasets(sessions, rob, n_markers, column_map)
    originals, left = parts, []
    if checks:
        from estcal.workflows.check import screen_rows

        for part in parts:  # the cheap refusals before the screening's robust fit
            refuse_early(rob, part, measure, free, level, allow_ill_conditioned)
        parts, left = screen_rows(parts, rob, drop_flagged, warn_dropped=False)
    vals = load_datasets(validate, rob, n_markers, column_map)
    check_held_out(parts, [], "session")
    check_held_out(parts, vals)
    ds = parts[0]
    if len(parts) > 1:
        from estcal.sessions.data import stack_sessions

        with input_errors():
            ds = stack_sessions(parts)
    warn_datasets(parts + vals)
    try:
        res, sel, problem = _run(rob, ds, robot, estimator, measure, free, level, selection, vals, noise, options,
                                 regularize, checks, allow_ill_conditioned)
    except NumericalRefusal as exc:
        if not (getattr(exc, "kind", None) == "ill-conditioned" and level is None and free is None and regularize is None
                and robust is None and estimator in ("lm", "gauss-newton", "iterated-lls") and not options):
            raise
        res, sel, problem = _relevance_default(rob, ds, robot, estimator, measure, vals, noise, selection, exc)
    _seen_new(res, problem, ds, vals, tuple(posture_tol))
    if left:
        _report_left_out(res, left, originals, ds, problem, rob, vals, noise,
                         dict(measure=measure, free=free, level=level or "full", selection=selection))
    res.extra["measurement_noise"] = _noise_components(problem, res)
    out = Calibration(res, sel, problem, rob, vals, " + ".join(_label(s) for s in sessions),
                      [_label(v) for v in validate])
    res.extra.update(robot=robot if isinstance(robot, (str, Path)) else rob.name, data=out.data_label,
                     validate=out.validate_labels, measure=out.measure, estimator=estimator,
                     noise=problem.terms[0].noise.to_dict(), points=n_markers)
    res.extra["robot"] = str(res.extra["robot"])
    return out


def _relevance_default(rob, ds, spec, estimator, measure, vals, noise, selection, refusal):
    """The default calibration when the full level is refused for its conditioning (non-convergence, a condition
    number above the limit) — data that a regularised model supports: the identifiable geometric parameters under
    the diagnosis's relevance priors (:func:`estcal.discrepancy.relevance.fit_relevance` without effects, rows
    independent), the pruned ones held at their nominal values, then the chosen least-squares estimator with
    those priors (MAP). The refusal stays for data that support nothing: this fit is checked like any other,
    its conditioning with the priors. ``res.extra["default_model"]`` says why and what."""
    from estcal.discrepancy.relevance import fit_relevance
    from estcal.discrepancy.terms import build_terms
    from estcal.methods import NoiseModel

    nm = noise or NoiseModel()
    terms = build_terms(rob, ds, nm, effects=(), geometric="sparse")
    # grown from the best column: on data this ill-conditioned the full geometric start keeps near-collinear pairs
    # under wide priors (a PUMA in a tenth of its joint ranges: beta_3 +82 and offset_3 −98 mrad, σ0 0.47 — an
    # overfit), where the growing search keeps the parameters the data determine
    fit = fit_relevance(terms, ds, nm, rigid=False, ridge_start=False)
    sp = fit.sparse
    kept = [n for n, a in zip(terms.penalised, sp.active) if a]
    # the MAP of ‖b − Ax‖²/σ² + Σ α_j x_j² in calibrate_lsq's form: prior std 1/√(α_j σ²) of rows weighted by σ
    std = {n: float(1.0 / np.sqrt(a * sp.noise_var)) for n, a in zip(terms.penalised, sp.alpha) if np.isfinite(a)}
    res, sel, problem = _run(rob, ds, spec, estimator, measure, list(terms.free) + kept, None, None, vals, noise,
                             {"prior_std": std}, None, True, False)
    res.extra["default_model"] = {
        "reason": f"the full level was refused: {refusal}".split(". The numbers")[0],
        "model": "relevance priors (docs/calibration.md, 'When the full level is refused')",
        "kept": kept, "considered": list(terms.geometric), "prior_std": std}
    return res, sel, problem


def _report_left_out(res, left, originals, kept, problem, rob, vals, noise, choices) -> None:
    """``res.extra["left_out"]``: the rows the screening left out and the least-squares fit with them — the
    fit ``--keep-all`` gives with the default estimator, same measure, free set or level, selection and
    noise (:mod:`estcal.workflows.left_out`) —, warned in one line."""
    from estcal.workflows.left_out import left_out_report, warn_left_out

    def refit(data):
        return run_calibration(rob, data, estimator="lm", validate=vals, noise=noise, checks=False, **choices)[0]

    res.extra["left_out"] = left_out_report(left, originals, kept, problem, res, refit)
    warn_left_out(res.extra["left_out"])


def _noise_components(problem, res, max_rows: int = 20000) -> dict:
    """The noise std per measurement kind and axis of the measuring frame by REML from the residual of the
    fit (:func:`estcal.discrepancy.noise.measurement_noise`); above ``max_rows`` residual rows it is not
    estimated (the dense REML would dominate the run) and the output says so."""
    from estcal.discrepancy.noise import measurement_noise

    M = sum(len(t.data.readings) for t in problem.terms) * 6
    if M > 6 * max_rows:
        return {"estimated": f"not estimated: more than {max_rows} residual rows (estcal diagnose estimates it)"}
    try:
        return measurement_noise(problem, res.theta, list(res.names))
    except (ValueError, np.linalg.LinAlgError) as exc:  # reporting only
        return {"estimated": f"not estimated: {exc}"}


def _seen_new(res, problem, ds, vals, posture_tol=(1e-3, 1e-3)) -> None:
    """Each validation score split by posture: rows at postures of the calibration data (``seen``) and at
    new ones (``new``, inside / outside the calibration joint ranges), in ``res.accuracy["validation"][i]``;
    a validation made only of seen postures is warned about (docs/real-data.md)."""
    import warnings

    from estcal.base.errors import EstcalWarning
    from estcal.estimate.result import pose_errors
    from estcal.validation import validation_split

    accs = (res.accuracy or {}).get("validation", [])
    for v, acc in zip(vals, accs):
        pos, _ = pose_errors(problem.robot, res.theta, v)
        if pos is None:
            continue
        split = validation_split(ds.readings, v.readings, pos, problem.robot.joint_types, *posture_tol)
        acc.update({k: split[k] for k in ("seen", "new", "new_inside", "new_outside", "only_seen")})
        if split["warning"]:
            acc["warning"] = f"{v.where}: {split['warning']}"
            warnings.warn(acc["warning"], EstcalWarning, stacklevel=3)


def _run(rob, ds, spec, estimator, measure, free, level, selection, vals, noise, options, regularize, checks,
         allow_ill):
    """:func:`run_calibration` with the lower layers' failures named for the user."""
    from estcal.estimate.chainfile import ChainFileError
    from estcal.identify.select import UnidentifiableError
    from estcal.kinematics.parameters import ParameterError

    try:
        with input_errors():
            return run_calibration(rob, ds, measure=measure, estimator=estimator, free=free,
                                   level=level or "full", selection=selection, validate=vals, noise=noise,
                                   options=options, regularize=regularize, checks=checks,
                                   allow_ill_conditioned=allow_ill)
    except ChainFileError as exc:
        raise ChainFileError(f"--chain: {exc}") from exc
    except ParameterError as exc:
        raise ParameterError(f"--free: {exc}") from exc
    except UnidentifiableError as exc:
        hint = f"`estcal identifiable --robot {spec}` lists an identifiable set" if isinstance(spec, (str, Path)) \
            else "`estcal identifiable` lists an identifiable set"
        if free is not None:
            hint += "; or give --level instead of --free to let estcal choose one"
        raise UnidentifiableError(f"{exc}\n  ({hint})") from exc
    except (RuntimeError, np.linalg.LinAlgError) as exc:  # e.g. a backend's numerical failure
        text = str(exc).strip()
        if "Indeterminate" in text:
            near = " ".join(text.split()).split("(Symbol:")[-1].split(")")[0].strip() if "(Symbol:" in text else "?"
            raise NumericalRefusal(
                f"estimator {estimator!r}: gtsam found the linear system indeterminate near variable {near} — some "
                f"parameter combinations are not determined by the data (for gtsam-timevarying: a batch whose "
                f"poses, after robust down-weighting, leave directions fixed only by an extremely tight process "
                f"noise; raise --option q=… or --option batch_size=…)") from exc
        first = text.splitlines()[0] if text else type(exc).__name__
        raise InputError(f"estimator {estimator!r} failed: {first} — try another estimator (e.g. --estimator lm) "
                         f"or check the free set with `estcal identifiable`") from exc


def calibrate_gough(robot, data, *, estimator: str = "lm", free=None, residual: str = "ik", model: int = 42,
                    noise_pos: float | None = None, noise_rot: float | None = None, noise_leg: float | None = None,
                    options: dict | None = None):
    """A Gough platform's calibration (:func:`estcal.workflows.gough.calibrate_gough`) from its
    robot file and one measurement file; noises in SI; ``options`` are the estimator's."""
    from estcal.workflows.gough import calibrate_gough as _gough

    if isinstance(data, (list, tuple)):
        if len(data) > 1:
            raise InputError("several data files are not supported for Gough platforms: give one file")
        data = data[0]
    check_input_files([data])
    with input_errors():
        return _gough(robot, data, estimator=estimator, free=split_names(free), residual=residual, model=model,
                      sigma_p=noise_pos, sigma_r=noise_rot, sigma_rho=noise_leg, **(options or {}))


def is_gough(robot) -> bool:
    """True for a Gough-platform robot file or built-in name."""
    if not isinstance(robot, (str, Path)):
        return False
    from estcal.parallel import is_gough_file

    return is_gough_file(robot)


def _saved_free_set(robot, problem, level, selection) -> list[str] | None:
    """The free set a saved model was identified with, when this calibration asks for the same
    level, criterion and measurement method.

    The structural selection (GECARO priorities and the QR of App. III) is meant for the
    *designed* geometry: at a calibrated one, zero lengths and right angles are off by the
    calibration errors (PUMA ``d_2`` = −0.95 mm, ``alpha_1`` = −π/2 + 1 mrad), the priorities
    change and near-dependent parameters (``beta_1`` of perpendicular axes, |R_jj| ~ 1e-5) pass
    the numerical-zero test — a recalibration would fit a set with condition number ~10⁵.
    The set identified at the design stays identifiable at the calibrated point."""
    cal = robot.meta.get("calibration") or {}
    saved = cal.get("free")
    if not saved or cal.get("level") != (level or "full") or \
            cal.get("selection_criterion", "structural") != (selection or "structural"):
        return None
    term = problem.terms[0]
    name = getattr(term.method, "name", None)
    saved_measure = "pose" if cal.get("measure") == "location" else cal.get("measure")  # GECARO's word, saved before
    if saved_measure not in (None, name) or not all(n in problem.params for n in saved):
        return None
    return list(saved)


def run_calibration(robot, data, *, measure: str | None = None, estimator: str = "lm",
                    free: list[str] | None = None, level: str | None = "full", selection: str | None = None,
                    validate=(), noise=None, register: bool = True, options: dict | None = None,
                    regularize=None, checks: bool = False, allow_ill_conditioned: bool = False):
    """The calibration of loaded objects behind ``estcal calibrate`` and ``estcal.calibrate``.

    ``regularize``: ``None`` (plain least squares), ``"loo"`` (Gaussian prior toward the
    nominal values on the joint-model parameters — geometric placements, offsets, gains,
    tool — with the width τ chosen by leave-one-pose-out CV on ``data``:
    :mod:`estcal.estimate.regularize`), or a fixed τ (SI). Base frame and unknown points are
    never penalised. Needs a least-squares estimator.

    ``checks``: run :mod:`estcal.estimate.checks` — raise
    :class:`~estcal.base.errors.NumericalRefusal` on degenerate data (dof ≤ 0, repeated
    poses, rank loss beyond the generic identifiable set) and, unless ``allow_ill_conditioned``,
    on non-convergence or a condition number above ``COND_MAX``; the figures and warnings go to
    ``result.extra["reliability"]``.

    Returns ``(result, selection, problem)``; ``selection`` is None when ``free`` is given.
    """
    from estcal.estimate import register_base
    from estcal.estimate.registry import get_estimator
    from estcal.methods import NoiseModel, Problem, get_method

    noise = noise or NoiseModel()
    if checks:  # before the registration and the QR of the selection: cheap refusals first
        refuse_early(robot, data, measure, free, level, allow_ill_conditioned, noise)
    method = get_method(measure) if measure else None
    problem = Problem(robot, [(method, data, noise)], noise)
    pv = problem.params
    theta0 = pv.values.copy()
    base_free = True
    sel = None
    reused = free is None and _saved_free_set(robot, problem, level, selection)
    if reused:
        free = reused
    if free is not None:
        problem.with_free(free)  # raises ParameterError naming an unknown parameter / pattern
        # register only when the whole base frame is estimated: Kabsch moves all six
        # base parameters, and a fixed one must keep its given value
        fn = set(problem.with_free(free).params.free_names)
        base_free = all(f"base_{c}" in fn for c in ("tx", "ty", "tz", "rx", "ry", "rz"))
    if register and base_free and data.kind in ("position", "points", "pose") and "base_tx" in pv:
        theta0 = register_base(problem.robot, data, theta0)
        problem = problem.with_values(theta0)
    start = problem
    exclude = []
    if free is None:
        # Default: the full structural identifiable set (QR). Information-criterion
        # pruning (aic/bic) is greedy and can drop parameters whose effect only shows
        # jointly with others, so it is opt-in.
        crit = selection or "structural"
        exclude = _structural_no_effect(robot, problem, level, data) if method is not None else []
        sel = select_free(problem, level, crit, known_noise=noise.known, exclude=exclude)
        free = sel.identifiable
        start = problem.with_values(sel.theta)  # staged: start from the registration fit
    assessment = None
    if checks:
        from estcal.estimate.checks import precheck

        assessment = precheck(problem if sel is None else start, list(problem.with_free(free).params.free_names),
                              sel=sel, level=level or "full", allow_ill_conditioned=allow_ill_conditioned,
                              exclude=exclude, priors=bool((options or {}).get("prior_std")))
        if assessment.refusals:
            raise NumericalRefusal("\n".join(assessment.refusals))
    est = get_estimator(estimator)
    options = dict(options or {})
    if options:
        from estcal.estimate.registry import check_options

        check_options(estimator, options)
    user_options = dict(options)
    reg_choice = _prior(start, free, estimator, regularize, options)
    res = est(start, free=free, validation=list(validate), **options)
    if reg_choice is not None:
        res.extra["regularization"] = reg_choice.to_dict()
    if start is not problem:
        from estcal.estimate.result import score

        res.accuracy = score(problem, theta0, res.theta, list(validate))
        res.nominal = theta0[problem.params.indices(res.names)]
    _record(res, problem, sel, reused and free, level, selection, user_options, regularize, options)
    if checks:
        from estcal.estimate.checks import postcheck

        assessment = assessment.merge(postcheck(problem, res, allow_ill_conditioned=allow_ill_conditioned))
        res.extra["reliability"] = assessment.to_dict()
        if assessment.refusals:
            exc = NumericalRefusal("\n".join(assessment.refusals))
            exc.kind = "ill-conditioned"  # the fit ran; its conditioning or convergence is what failed
            raise exc
    res.extra["initial_guess"] = "nominal + base registration (Kabsch)" if (register and base_free and
                                                                           data.kind != "none") else "nominal"
    res.inputs = tuple(p for p in [getattr(data, "path", None), *(getattr(v, "path", None) for v in validate),
                                   robot.meta.get("robot_file"), robot.meta.get("urdf")] if p)
    return res, sel, problem


def refuse_early(robot, data, measure=None, free=None, level=None, allow_ill_conditioned=False, noise=None):
    """The refusals made before any registration, screening or QR of ``data``
    (:func:`estcal.estimate.checks.refuse_repeated_early`): identical rows always; too few distinct
    postures for the parameters generic poses identify when the default free set is fitted and a
    rank loss would be refused (not with ``free`` or ``allow_ill_conditioned``)."""
    from estcal.estimate.checks import refuse_repeated_early
    from estcal.methods import NoiseModel, Problem, get_method

    problem = None
    if not free and not allow_ill_conditioned:
        noise = noise or NoiseModel()
        problem = Problem(robot, [(get_method(measure) if measure else None, data, noise)], noise)
        if problem.terms[0].method.name not in _DIRECT:
            problem = None
    refuse_repeated_early(data, problem, level or "full")


def _prior(start, free, estimator, regularize, options) -> object:
    """``options["prior_std"]`` from ``regularize`` (None, "loo" or a prior std in SI) on the
    joint-model parameters of ``free``; returns the leave-one-pose-out choice (or None)."""
    if regularize is None:
        return None
    from estcal.estimate.lsq import LSQ_METHODS
    from estcal.estimate.regularize import choose_prior_std

    if estimator not in LSQ_METHODS:
        raise InputError(f"regularize needs a least-squares estimator ({', '.join(LSQ_METHODS)}), "
                         f"not {estimator!r}")
    pv = start.params
    kinds = dict(zip(pv.names, pv.kinds))
    penalised = [n for n in free if kinds.get(n) not in ("base", "marker", "other")]
    if isinstance(regularize, str):
        if regularize != "loo":
            raise InputError(f"unknown regularize {regularize!r}; use 'loo' or a prior std in SI units")
        choice = choose_prior_std(start, free, penalised, theta=start.params.values)
        options["prior_std"] = choice.prior_std
        return choice
    tau = float(regularize)
    if not tau > 0:
        raise InputError(f"regularize: the prior std must be > 0, got {regularize}")
    options["prior_std"] = {n: tau for n in penalised}
    return None


def _record(res, problem, sel, reused, level, selection, user_options, regularize, options) -> None:
    """What decided the fit, in ``res.extra``: selection, options, prior, measure, robust report."""
    if sel is not None:
        res.extra["selection"] = sel.to_dict()
    elif reused:
        res.extra["selection"] = {"level": level or "full", "criterion": selection or "structural",
                                  "identifiable": list(reused), "source": "the saved model's free set"}
    if user_options:
        res.extra["options"] = user_options
    if regularize is not None:
        res.extra["regularize"] = regularize
    res.extra.setdefault("measure", problem.terms[0].method.name)
    if options.get("robust"):
        res.extra["robust_report"] = robust_report(problem, res, options["robust"], options.get("robust_k"))


_DIRECT = ("position", "location", "pose", "points")


def _structural_no_effect(robot, problem, level, data) -> list[str]:
    """Parameters without effect for a constraint method (links, planes, distance).

    Their observation matrix on real data is evaluated where the constraints do not
    hold exactly, so columns that vanish at consistency (the base orientation for a
    point link, …) are small but not zero there. GECARO's analysis on simulated,
    consistent configurations (:func:`estcal.identify.identify`) finds them; they are
    removed from the candidates. Direct measures (position, location, points) need no
    such step.
    """
    mname = problem.terms[0].method.name
    if mname in _DIRECT or data.kind != "none":
        return []
    try:
        from estcal.identify import identify
    except ImportError:  # pragma: no cover - identify is part of the package
        return []
    cands = [n for g in level_candidates(problem.params, level) for n in g if n in robot.params]
    try:
        ref = identify(robot, mname, None, candidates=cands, check_excitation=False)
    except (ValueError, RuntimeError, np.linalg.LinAlgError):
        return []
    return [n for n in ref.no_effect if n in cands]
