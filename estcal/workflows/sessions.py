"""Calibration over several sessions with a repeatability model: ``estcal sessions``
(docs/repeatability.md).

:func:`sessions` loads one dataset per session (or one file with a ``session`` column), chooses
the free set (``level``, default ``full`` as every command, or ``free``), the parameters that vary
between sessions (``vary``: names / patterns among the free ones, ``"auto"`` — the REML
likelihood-ratio selection among the free offsets and base — or ``"none"``), fits the mixed model
(:func:`estcal.sessions.fit_sessions`) and scores new sessions against the new-session prediction
ellipsoids. ``run.fit.save_model(path)`` writes the population model as a saved model whose
covariance is that of a *new* session (population θ + between-session Q).
"""
from __future__ import annotations

import fnmatch
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from estcal.base.errors import EstcalWarning, InputError, NumericalRefusal
from estcal.workflows.inputs import (check_held_out, check_input_files, input_errors, load_datasets, robot_for_data,
                                     split_names, warn_datasets)

__all__ = ["SessionsRun", "sessions", "FORMULATIONS"]

FORMULATIONS = ("gls", "gtsam", "kalman")


@dataclass
class SessionsRun:
    """What :func:`sessions` computed.

    fit : the :class:`~estcal.sessions.fit.SessionFit`; names : the sessions' names;
    datasets / validation : the session and new-session datasets; vary_selection : the steps of
    the ``vary="auto"`` selection (or None); scores / recalibration : {file: …} per new session.
    """

    fit: object
    names: list
    datasets: list
    validation: list = field(default_factory=list)
    validate_labels: list = field(default_factory=list)
    vary_selection: dict | None = None
    scores: dict = field(default_factory=dict)
    recalibration: dict = field(default_factory=dict)
    robot_spec: str = ""

    def to_dict(self) -> dict:
        """``fit.to_dict()`` plus the selection steps, validation scores and recalibration curves (SI)."""
        out = self.fit.to_dict()
        if self.vary_selection is not None:
            out["vary_selection"] = [{"accepted": st["accepted"], "alpha_per_test": st["alpha_per_test"],
                                      "table": [{k: v for k, v in e.items() if k != "std"} for e in st["table"]]}
                                     for st in self.vary_selection["steps"]]
        out["validation"], out["recalibration"] = dict(self.scores), dict(self.recalibration)
        return out


def _free_set(prob, level, free):
    """(free names, linearisation point) of the stacked sessions."""
    from estcal.estimate.levels import LEVELS, select_free

    if free is None and level not in LEVELS:
        raise InputError(f"--level must be one of {', '.join(LEVELS)}, got {level!r}")
    try:
        with input_errors():
            if free is not None:
                return prob.with_free(free).params.free_names, prob.params.values
            sel = select_free(prob, level)
            return sel.identifiable, sel.theta
    except InputError as exc:
        raise InputError(f"--free/--level: {exc}") from exc


def _vary_names(vary, prob, free_names) -> list[str]:
    """The parameters named by ``vary`` (names or patterns; a name must be free, a pattern match one)."""
    if vary == "none":
        return []
    pats = split_names(vary, "--vary")
    try:
        with input_errors():
            prob.with_free(pats)  # ParameterError naming an unknown name / pattern
    except InputError as exc:
        raise InputError(f"--vary: {exc}") from exc
    wild = [p for p in pats if any(ch in p for ch in "*?[")]
    bad = [p for p in pats if p not in wild and p not in free_names]
    empty = [p for p in wild if not any(fnmatch.fnmatchcase(n, p) for n in free_names)]
    if bad or empty:
        what = f"{bad} are not free parameters" if bad else f"{empty} match no free parameter"
        raise InputError(f"--vary: {what} (a varying parameter must be estimated); the free set is "
                         f"{', '.join(free_names)}")
    return [n for n in free_names if n in pats or any(fnmatch.fnmatchcase(n, p) for p in wild)]


def sessions(robot, data, *, level: str = "full", free=None, vary: str = "auto", formulation: str = "gls",
             noise=None, validate=(), recalibrate: int = 0, alpha: float = 0.01, points: int | None = None,
             root=None, tip=None, column_map=None, drop_flagged: bool = False) -> SessionsRun:
    """Fit several sessions at once with per-session deviations — the job of ``estcal sessions``.

    ``data``: one dataset (path or Dataset) per session, or a file with a ``session`` column;
    ``noise``: a :class:`~estcal.methods.NoiseModel` (default 0.1 mm / 1 mrad, relative weights:
    a variance factor is estimated with Q by REML); ``recalibrate``: with ``validate``, the error
    on the rest of each new session after re-measuring k = 0…K poses. ``column_map``: the data's
    column map; ``drop_flagged``: leave out the rows the screening flags
    (:func:`estcal.workflows.check.screen`; their findings are warned either way).
    """
    from estcal.methods import NoiseModel, Problem
    from estcal.sessions import choose_vary, fit_sessions
    from estcal.sessions.data import session_name, split_sessions

    if formulation not in FORMULATIONS:
        raise InputError(f"--formulation must be gls, gtsam or kalman, got {formulation!r}")
    if recalibrate < 0:
        raise InputError("--recalibrate must be ≥ 0")
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    check_input_files([*items, *validate])
    rob, n_markers = robot_for_data(robot, items[0], points, root, tip, column_map)
    loaded = load_datasets(items, rob, n_markers, column_map)
    vals = load_datasets(validate, rob, n_markers, column_map)
    from estcal.workflows.check import screen

    loaded = screen(loaded, rob, drop_flagged)
    with input_errors():
        parts = [s for d in loaded for s in split_sessions(d)]
    warn_datasets(loaded + vals)
    check_held_out(loaded, [], "session")
    check_held_out(loaded, vals)
    names = [session_name(s, i) for i, s in enumerate(parts)]
    if len(set(names)) < len(names):
        names = [f"{n}#{i + 1}" for i, n in enumerate(names)]
    noise = noise or NoiseModel()
    prob = Problem(rob, [(None, s, noise) for s in parts], noise)
    free_names, theta0 = _free_set(prob, level, split_names(free))
    run = SessionsRun(None, names, parts, vals, [_label(v) for v in validate],
                      robot_spec=str(robot) if isinstance(robot, (str, Path)) else rob.name)
    try:
        if vary == "auto":
            if len(parts) < 2:
                warnings.warn("one session: no between-session information, --vary auto selects nothing",
                              EstcalWarning, stacklevel=2)
            cands = [n for n, k in zip(prob.params.names, prob.params.kinds) if n in free_names and k in ("offset", "base")]
            run.vary_selection = choose_vary(rob, parts, free_names, cands, noise=noise, alpha=alpha, theta=theta0)
            vary_names = run.vary_selection["vary"]
        else:
            vary_names = _vary_names(vary, prob, free_names)
        run.fit = fit_sessions(rob, parts, free_names, vary_names, noise=noise, formulation=formulation,
                               theta=theta0, session_names=names)
    except InputError:
        raise
    except ValueError as exc:
        raise NumericalRefusal(str(exc)) from exc
    if not run.fit.converged:
        warnings.warn(f"the session fit did not converge in {run.fit.n_iterations} iterations", EstcalWarning,
                      stacklevel=2)
    _score(run, recalibrate)
    return run


def _label(item) -> str:
    return str(getattr(item, "where", None) or getattr(item, "path", None) or item)


def _score(run, recalibrate: int) -> None:
    """New-session scores (RMSE, 95 % coverage and its binomial band) and recalibration curves."""
    from estcal.sessions import predict_session, recalibration_curve

    for label, d in zip(run.validate_labels, run.validation):
        key = Path(label).name
        with input_errors(f"{label}: "):
            sc = predict_session(run.fit, d)
        sc.pop("d2")
        run.scores[key] = sc
        if recalibrate:
            run.recalibration[key] = recalibration_curve(run.fit, d, range(0, min(recalibrate, d.n - 1) + 1))
