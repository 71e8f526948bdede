"""Diagnose measured data: how accurate the robot's model is at new postures, which physical causes it names,
and what stays unexplained — one sparse Bayesian model that does both (docs/discrepancy.md).

:func:`diagnose`:

1. **The candidates** (:func:`estcal.discrepancy.terms.build_terms`): registration (free), every identifiable
   geometric parameter and every effect term of the library the data excite (compliance, backlash, link
   tilt, gear harmonics, encoder gain, drift — on the ``t`` column, or the row order of a file without one —,
   thermal expansion, user effects), each under an automatic-relevance prior.
2. **The model** (:func:`estcal.discrepancy.relevance.fit_relevance`): the precisions by type-II maximum
   likelihood (Tipping & Faul's fast sequential algorithm), relinearised by Gauss–Newton; the rows of a
   posture share a rigid error; each further session has its own measuring frame. Fitted (and its causes
   named, step 3) twice — the link frames' priors within 1 mm / 1 mrad and unbounded — and the bounded one
   kept unless the other's cross-validated error is lower by more than one standard error
   (:func:`_width_and_terms`).
3. **The causes** (:func:`estcal.discrepancy.relevance.select_terms`): a term is named when it survives, its
   Bayes factor is decisive (ln B ≥ 5), it survives in most cross-validation folds and it lowers the
   cross-validated error at new postures. Load terms (compliance, backlash, tilt) the evidence keeps stay in
   the model named or not; special terms (harmonics, gains, drift, thermal) enter only when named, and only
   if they pass the same tests again against the model with those load terms.
4. **How accurate** (:func:`estcal.discrepancy.budget.error_budget`): the nested cross-validation of the whole
   procedure by posture (and session with several), beside a time-blocked one; the repeatability floor;
   every validation file scored at its new postures once its measuring frame is registered on its rows at
   postures seen in training.

The result (:class:`estcal.discrepancy.result.DiagnosisResult`) holds the one model all of these describe.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from estcal.effects import make_effect
from estcal.estimate.result import pose_errors
from estcal.io.prepare import derive_approach, with_effect_context
from estcal.io.robotfile import load_robot, robot_to_dict
from estcal.methods import NoiseModel

from .relevance import _BASE
from .result import Cause, DiagnosisResult
from .terms import (WIDTH_AUTO, Candidate, build_terms, default_candidates, n_sessions as _n_sessions,
                    set_load_sides)
from .zeros import moved_zeros

__all__ = ["Candidate", "Cause", "DiagnosisResult", "diagnose", "default_candidates"]


# ------------------------------------------------------------------ data preparation
def _prepare_data(robot, data, validate, robot_spec, approach_from_order, session_time):
    """The robot (loaded, with one marker per measured point) and the data as the diagnosis reads them:
    sessions stacked, approach columns from the posture order, effect columns in the context, the acquisition
    time ``t`` (the row order of a file without a time column) from each session's first pose — or its mean
    with several sessions. Returns ``(robot, robot_spec, data, validate, sessions, time_source)``."""
    sessions = list(data) if isinstance(data, (list, tuple)) else None
    if sessions is not None:
        if not sessions:
            raise ValueError("diagnose: no dataset given")
        data = sessions[0]
    if isinstance(robot, (str, Path)):
        robot_spec = robot_spec or str(robot)
        robot = load_robot(robot, n_markers=data.n_points if data.kind in ("points",) else None)
    if data.kind == "points" and robot.n_markers == 0:
        # unknown points on the tool: markers initialised at the tool origin, estimated with the rest
        robot = load_robot(robot, n_markers=data.n_points)
    parts = sessions if sessions is not None else [data]
    source = "t column" if all("t" in d.context for d in parts) else "row order"
    stacked = sessions is not None and len(sessions) > 1
    if stacked:
        from estcal.sessions.data import stack_sessions

        prepared = []
        for d in sessions:
            d = derive_approach(d) if approach_from_order else d.subset(slice(None))
            _acquisition_time(d, source)
            if session_time:
                _session_time(d, centred=True)
            prepared.append(d)
        data = stack_sessions(prepared)
    else:
        data = derive_approach(data) if approach_from_order else data.subset(slice(None))
        if _n_sessions(data) > 1:  # stacked by the caller (a ``session`` column)
            _acquisition_time_each(data, source)
            if session_time:
                _session_time_each(data)
        else:
            _acquisition_time(data, source)
            if session_time:
                _session_time(data)
    validate = [derive_approach(d) if approach_from_order else d.subset(slice(None)) for d in validate]
    for d in validate:
        _acquisition_time(d, source)
        if session_time:
            _session_time(d, centred=stacked or _n_sessions(data) > 1)
    data = with_effect_context(robot, data)
    validate = [with_effect_context(robot, d) for d in validate]
    return robot, robot_spec, data, validate, (sessions if stacked else None), source


def _acquisition_time(d, source: str) -> None:
    """Without a ``t`` column the row order is the acquisition order (``source == "row order"``): ``t`` = the
    row index (in rows) — so that drift is a candidate and time-blocked folds follow the campaign."""
    if source == "row order" or "t" not in d.context:
        d.context["t"] = np.arange(d.n, dtype=float)


def _acquisition_time_each(data, source: str) -> None:
    if source == "row order" or "t" not in data.context:
        lab = np.asarray(data.columns["session"])
        t = np.zeros(data.n)
        for sv in np.unique(lab):
            m = np.flatnonzero(lab == sv)
            t[m] = np.arange(len(m), dtype=float)
        data.context["t"] = t


def _session_time_each(data) -> None:
    """:func:`_session_time` (centred) within each session of a dataset stacked with a ``session`` column."""
    lab = np.asarray(data.columns["session"])
    t = data.context["t"].copy()
    data.columns["t_abs"] = t.copy()
    for sv in np.unique(lab):
        m = lab == sv
        t[m] = t[m] - t[m].mean()
    data.context["t"] = t


def _session_time(d, centred: bool = False) -> None:
    """``t`` measured from the dataset's first pose (the absolute time kept in ``columns["t_abs"]``); with
    ``centred`` (several sessions fitted together) from the session's mean time, so that a drift, linear in
    ``t`` and zero at t = 0, has no mean within a session and cannot explain an offset between sessions."""
    d.columns["t_abs"] = d.context["t"].copy()
    d.context["t"] = d.context["t"] - (d.context["t"].mean() if centred else d.context["t"].min())


def _errors(robot, theta, datasets) -> list:
    """Point-error norms (m) of every dataset, one (M, k) array each (:func:`pose_errors`)."""
    return [pose_errors(robot, theta, d)[0] for d in datasets]


def _rmse_max(errors):
    """(RMSE, max) in mm of the point-error norms of :func:`_errors`; ``(None, None)`` for none."""
    if not errors:
        return None, None
    e = np.concatenate([x.reshape(-1) for x in errors])
    return float(np.sqrt(np.mean(e ** 2)) * 1e3), float(e.max() * 1e3)


def _scores(robot, theta, datasets):
    return _rmse_max(_errors(robot, theta, datasets))


def _train_rmse(final, data, frames, zeros=None) -> float:
    """The training RMSE (mm) of the point-error norms, every session's rows at its own measuring frame and joint
    zeros (``frames``: ``{session: (6 + k,) increment of the base and of the zeros ``zeros[session]``}``; the
    model's parameters are the first session's)."""
    from .relevance import _session_labels, session_theta

    if not frames or not all(n in final.params.names for n in _BASE):
        return _scores(final, final.params.values, [data])[0]
    lab = _session_labels(data)
    errors = []
    for s in dict.fromkeys(lab.tolist()):
        theta = final.params.values
        if s in frames:
            theta = session_theta(final, theta, frames[s], (zeros or {}).get(s) or ())
        errors.append(pose_errors(final, theta, data.subset(np.flatnonzero(lab == s)))[0])
    return _rmse_max(errors)[0]


# ------------------------------------------------------------------ main
def diagnose(robot, data, validate=(), effects=None, k_folds: int = 5, noise=None, rng=0, robot_spec=None,
             geometric: str = "sparse", session_time: bool = True, approach_from_order: bool = True,
             posture_tol=(1e-3, 1e-3), budget: bool = True, time_blocks: bool = True, ident_tol: float = 1e-4,
             regroup_tol: float = 1e-3, register_zeros: bool = True,
             geometric_width: float | str | None = "auto") -> DiagnosisResult:
    """Diagnose what the geometric model of ``robot`` gets wrong on ``data`` (module docstring).

    Parameters
    ----------
    robot : SerialRobot or robot spec (built-in name, .yaml, .urdf).
    data : Dataset (position / points / pose), or a list of datasets — one per session, fitted together, each
        session's measuring frame registered.
    validate : datasets scored with the model at their new postures (never used for a decision); each is
        another session: its frame is registered on its rows at postures the training measured — and, with
        ``register_zeros``, every joint zero those rows show moved since training (:mod:`estcal.discrepancy.zeros`).
    effects : registered effect names to consider (default: every registered effect; ``()``: geometry only).
    k_folds : folds of the cross-validation — grouped by posture, and by session with several sessions.
    noise : measurement noise (any form of :meth:`estcal.methods.NoiseModel.parse`); its scale is fitted
        with the model either way (the relevance model's noise).
    rng : seed of the fold assignment.
    geometric : ``"sparse"`` (every identifiable geometric parameter under a relevance prior, the default),
        ``"full"`` (unpenalised) or ``"joint_offset"`` (the offsets only).
    session_time : measure ``t`` from each dataset's first pose (from its mean with several sessions).
    approach_from_order : infer ``approach_<joint>`` columns from the acquisition order (``t``, else the rows;
        recorded columns are kept), so that backlash by approach is a candidate beside backlash by the load.
    posture_tol : ``(tol_rad, tol_m)`` of the posture grouping.
    budget : compute the error budget (nested CV, time-blocked CV, region); without it the answer is the
        cross-validation of the model with the all-rows choices (said in ``answer["basis"]``).
    time_blocks : the time-blocked CV in the budget.
    ident_tol, regroup_tol : the geometric identifiability tolerance and the relative size below which an
        effect term regroups into geometry.
    register_zeros : test and register a validation file's moved joint zeros on its seen rows (False: its frame
        only).
    geometric_width : the widest prior standard deviation the evidence search moves a link frame's geometric
        parameter to, m for a length and rad for an angle (:mod:`estcal.discrepancy.terms`); ``"auto"`` (the
        default): 1 mm / 1 mrad (:data:`~estcal.discrepancy.terms.GEOMETRIC_WIDTH`) unless the unbounded
        model's cross-validated error is lower by more than one standard error (:func:`_width_and_terms`);
        None: unbounded.
    """
    from estcal.base.blas import single_thread_blas

    # one BLAS thread, as every estcal command runs: a threaded reduction changes the last bits of the evidence
    # search's sums, and on a few dozen rows that can flip a marginal term (TIAGo, 31 rows: 2.38 against 2.69 mm at
    # new postures with two threads) — the same call must give the same diagnosis on every machine
    with single_thread_blas():
        return _diagnose(robot, data, validate, effects, k_folds, noise, rng, robot_spec, geometric, session_time,
                         approach_from_order, posture_tol, budget, time_blocks, ident_tol, regroup_tol,
                         register_zeros, geometric_width)


def _diagnose(robot, data, validate, effects, k_folds, noise, rng, robot_spec, geometric, session_time,
              approach_from_order, posture_tol, budget, time_blocks, ident_tol, regroup_tol,
              register_zeros=True, geometric_width=WIDTH_AUTO) -> DiagnosisResult:
    from estcal.validation.groups import row_groups

    from .relevance import cv_rmse_mm, fit_relevance

    parts = data if isinstance(data, (list, tuple)) else [data]
    recorded = any(k.startswith("approach_") for d in parts for k in (*d.columns, *d.context))
    robot, robot_spec, data, validate, sessions, time_source = _prepare_data(
        robot, data, validate, robot_spec, approach_from_order, session_time)
    approach_source = "recorded" if recorded else (time_source if approach_from_order else None)
    nm = NoiseModel(known=False) if noise is None else NoiseModel.parse(noise, known=True)
    terms = build_terms(robot, data, nm, effects=effects, geometric=geometric, ident_tol=ident_tol,
                        regroup_tol=regroup_tol, geometric_width=None if geometric_width == WIDTH_AUTO
                        else geometric_width)
    tidx = terms.term_index()
    load = np.array([terms.terms[i].load if i >= 0 else True for i in tidx], bool)
    groups = row_groups(data.readings, robot.joint_types, data.columns.get("session"),
                        data.context["t"] if time_source == "t column" else None, posture_tol)
    kind = "session" if len(groups.sessions) > 1 else "posture"
    folds = groups.folds(kind, k_folds, rng)
    time_folds = groups.folds("time", k_folds) if time_blocks else None
    terms, first, sel, width = _width_and_terms(terms, data, nm, load, folds, k_folds, time_folds,
                                                geometric_width == WIDTH_AUTO)
    fit = first if np.array_equal(sel.include, load) else fit_relevance(
        terms, data, nm, include=sel.include, system0=first.system, start=first.sparse.alpha)
    b = None
    if budget:
        from .budget import error_budget

        b = error_budget(terms, fit, data, groups, sel, k_folds, rng, time_blocks)
    return _result(robot, robot_spec, data, validate, sessions, nm, terms, fit, sel, groups, b, time_source,
                   approach_from_order, session_time, cv_rmse_mm(sel.cv), approach_source, register_zeros, width)


def _first_fit(terms, data, nm, load):
    """The relevance model with the load terms the evidence keeps (before naming), the load's side of every
    posture set again at the fitted geometry and the model refitted where one changed."""
    from .relevance import fit_relevance

    first = fit_relevance(terms, data, nm, include=load)
    if any(k.startswith("load_side_") for k in data.context) and set_load_sides(
            terms.robot, data, first.system.theta):
        # the load's side of a posture near zero load, at the fitted geometry rather than the nominal one: once,
        # afresh (the rigid error per posture estimated with the wrong sides would stay in the whitening)
        first = fit_relevance(terms, data, nm, include=load)
    return first


def _load_sides(data, sides=None) -> dict:
    """The ``load_side_<joint>`` context columns of ``data`` (a copy); with ``sides``, set to those first."""
    if sides is not None:
        for k in [k for k in data.context if k.startswith("load_side_")]:
            del data.context[k]
        data.context.update({k: v.copy() for k, v in sides.items()})
    return {k: v.copy() for k, v in data.context.items() if k.startswith("load_side_")}


def _width_and_terms(terms, data, nm, load, folds, k_folds, time_folds, choose: bool):
    """The model before its final fit: ``(terms, first fit, selection, width record)``. With ``choose`` the link
    frames' prior width is chosen by Breiman's one-standard-error rule (Breiman, Friedman, Olshen & Stone 1984,
    §3.4.3; Hastie, Tibshirani & Friedman 2009, *The Elements of Statistical Learning*, §7.10): the model whose
    link frames' priors stay within :data:`~estcal.discrepancy.terms.GEOMETRIC_WIDTH` — the stronger prior, the
    simpler model — unless the unbounded model's cross-validated error is lower by more than one standard error.
    Each is fitted and its causes named on the same folds; the errors compared are the selected models' CV mean
    squared point errors, the standard error the unbounded one's over the folds.

    Why a choice: on a few dozen postures the evidence lets a link frame's prior grow as wide as they allow, and
    the frames fitted so carry the training postures' structured error to others (TIAGo at the other session's
    new postures, ``experiments/tiago_disjoint.md``: 3.46 → 2.81 mm by this rule on the set of halvings
    declared before it, the bound kept on 67 of 72 halvings); a nominal model off by about the bound or more is
    misfitted with it and the misfit named as causes (a simulated PUMA 560 with 1 mm / 1 mrad errors: a gear
    harmonic and a backlash) — which its CV error shows (0.95 mm with the bound, 0.09 without), so the
    unbounded model is kept. The choice is made once on all rows: the error budget's nested CV replays the
    naming in every outer fold, not this choice."""
    import dataclasses

    from .relevance import fold_mse, select_terms
    from .terms import GEOMETRIC_WIDTH

    bounded = dataclasses.replace(terms, geometric_width=GEOMETRIC_WIDTH) if choose else None
    if bounded is not None and not np.any(bounded.alpha_min() > 0):
        bounded = None  # no link frame under a prior (geometric="full" / "joint_offset"): nothing to choose
    # each model from the same load sides, set again at its own fitted geometry (_first_fit): giving the bounded
    # model the unbounded one's fitted sides saves a fit (0.6 s of a two-session diagnosis) but scored 2.43 mm
    # against 2.37 on the TIAGo study's development halvings
    sides0 = _load_sides(data)
    runs = []
    for t in (terms,) if bounded is None else (terms, bounded):
        _load_sides(data, sides0)
        first = _first_fit(t, data, nm, load)
        _check_folds(first.system, folds, k_folds)
        sel = select_terms(t, first.system, folds, start=first.sparse.alpha, time_folds=time_folds)
        runs.append((t, first, sel, _load_sides(data)))
    if bounded is None:
        return (*runs[0][:3], None)
    (mse_u, se_u), (mse_b, _) = (fold_mse(r[2].cv["sq"], r[2].cv["n"]) for r in runs)
    if not np.isfinite(se_u):
        se_u = float("inf")  # one fold: no spread to judge the unbounded model's gain by; the bound is kept
    keep = runs[1] if mse_b <= mse_u + se_u else runs[0]
    _load_sides(data, keep[3])
    record = {"rule": "one standard error", "bound_si": GEOMETRIC_WIDTH, "bounded": keep is runs[1],
              "cv_bounded_mm": float(np.sqrt(mse_b) * 1e3), "cv_unbounded_mm": float(np.sqrt(mse_u) * 1e3),
              "cv_unbounded_plus_se_mm": float(np.sqrt(mse_u + se_u) * 1e3)}
    return (*keep[:3], record)


def _check_folds(system, folds, k) -> None:
    """Every fold (and every fold of a fold, the nested CV's) must leave more rows than unpenalised parameters."""
    from estcal.identify.select import UnidentifiableError

    per_pose = len(system.t) / max(len(np.unique(system.pose)), 1)
    least = min(len(f.train) for f in folds) * (k - 1) / k * per_pose
    if least <= system.n_free:
        raise UnidentifiableError(f"the cross-validation folds leave about {least:.0f} rows for {system.n_free} "
                                  f"unpenalised parameters (registration, sessions' frames, geometry with "
                                  f"geometric='full'): give more postures, fewer folds, or the default geometry")


# ------------------------------------------------------------------ the result
def _final_robot(terms, fit):
    """The model as a robot: the registration robot with the effects whose terms the model keeps (every other
    candidate is at zero — pruned — and left out), at the fitted values. Returns ``(robot, kept terms)``."""
    vals = dict(zip(terms.robot.params.names, fit.theta))
    kept = [t for t in terms.terms if any(vals[n] != 0.0 for n in t.names)]
    rb = terms.base
    for t in kept:
        rb = rb.add_effect(make_effect(t.effect, rb, joints=t.joints or None, **dict(t.options)))
    return rb.with_values(np.array([vals[n] for n in rb.params.names])), kept


def _display(name, robot, time_unit: str) -> tuple[float, str]:
    """(factor from SI, unit) to print an estimate of parameter ``name`` (effects: mrad, mm, ‰, ppm …)."""
    from estcal.base.units import display_unit

    kinds = dict(zip(robot.params.names, robot.params.kinds))
    if kinds.get(name) != "effect":
        unit, factor = display_unit(name, robot)
        return factor, unit
    head = name.split("_")[0]
    prismatic = any(name.endswith(j) for j, t in zip(robot.joint_names, robot.joint_types) if t == "prismatic")
    ang = "mm" if prismatic else "mrad"
    table = {"compliance": (1e3, "mm/N" if prismatic else "mrad/(N·m)"), "backlash": (1e3, ang),
             "tilt": (1e3, "mrad/(N·m)"), "encgain": (1e3, "‰"), "drift": (1e3, f"{ang}/{time_unit}"),
             "thermal": (1e6, "ppm/K" if time_unit == "K" else f"ppm/{time_unit}")}
    if head.startswith("harmonic"):
        return 1e3, "mrad"
    return table.get(head, (1.0, "SI"))


def _together(causes, data) -> list[str]:
    """What two named load causes of one joint mean together: a compliance ``c`` and a backlash by the load's side
    ``b`` of the opposite sign give ``δq = c·τ − |b|·sign τ = c·sign τ·(|τ| − |b|/c)`` beyond ``|τ| = |b|/c`` —
    a compliance that starts past a dead zone (friction or a preload holds the joint below it), not a free play."""
    by = {}
    for c in causes:
        if len(c.joints) == 1 and c.options.get("by", "load") == "load":
            by.setdefault(c.joints[0], {})[c.effect] = c
    out = []
    for j, e in by.items():
        if {"joint_compliance", "backlash"} <= set(e):
            cv = e["joint_compliance"].parameters[f"compliance_{j}"]["estimate"]
            bv = e["backlash"].parameters[f"backlash_{j}"]["estimate"]
            if cv > 0 > bv:
                out.append(f"{j}: compliance and a negative backlash by the load's side together are a compliance "
                           f"beyond a dead zone of |τ| ≈ {abs(bv) / cv:.2g} N·m (friction or a preload holds the "
                           "joint below it)")
    return out


def _cause(term, rec, fit, robot, system_names, explained, time_unit) -> Cause:
    """A named :class:`Cause` from its term, its naming record and the model's posterior."""
    pen = system_names[fit.system.n_free:]
    params = {}
    for n in term.names:
        j = pen.index(n)
        est, sd = float(fit.sparse.mean[j] + 0.0), float(np.sqrt(max(fit.sparse.cov[j, j], 0.0)))
        f, unit = _display(n, robot, time_unit)
        params[n] = {"estimate": est, "std": sd, "unit": unit, "display": [est * f, sd * f, unit]}
    return Cause(term.effect, list(term.joints), dict(term.options), params, rec["ln_bf"], rec["folds"],
                 rec["k_folds"], rec["cv_with_mm"], rec["cv_without_mm"], float(explained), term.load)


def _result(robot, robot_spec, data, validate, sessions, nm, terms, fit, sel, groups, budget, time_source,
            approach_from_order, session_time, cv_all_rows, approach_source=None,
            register_zeros: bool = True, width=None) -> DiagnosisResult:
    """The :class:`DiagnosisResult` of the fit: the answer, the causes, one validation figure per file."""
    from .relevance import refit

    final, kept = _final_robot(terms, fit)
    tidx = terms.term_index()
    system = fit.system
    time_unit = "s" if time_source == "t column" else "row"
    geo_only = tidx < 0

    def ss(inc):
        f = refit(system, None, inc, fit.sparse.alpha)
        r = system.t - system.F @ f.free - system.P @ f.mean
        return float(r @ r)

    ss_geo = ss(geo_only)
    causes = []
    recs = {r["term"]: r for r in sel.records}
    active = fit.sparse.active & fit.include
    named = []
    for i in sel.named:
        t = terms.terms[i]
        m = tidx == i
        if not np.any(active[m]):
            # the model refitted with every named cause prunes this one: a cause the model does not carry is not
            # printed with 0 ± 0 (the evidence search is not convex; the forward step's model kept it)
            others = [terms.terms[k].label for k in sel.named if k != i]
            recs[t.label].update(named=False, reason="withdrawn after naming: pruned by the evidence of the model "
                                 f"with the other named causes ({', '.join(others)})")
            continue
        named.append(i)
        frac = max(ss_geo - ss(geo_only | m), 0.0) / max(ss_geo, 1e-300)
        causes.append(_cause(t, recs[t.label], fit, terms.robot, system.names, frac, time_unit))
    train_mm = (_train_rmse(final, data, fit.frames, terms.session_zeros)
                if data.kind in ("position", "points", "pose") else None)
    b = budget.to_dict() if budget is not None else None
    names, C = _covariance(terms, fit)
    load_joints = sorted({j for t in kept if t.effect in ("joint_compliance", "backlash")
                          and t.options.get("by") != "approach" for j in t.joints})
    sides = _training_load_sides(final, data, load_joints) if validate else {}
    vals = [_validation(final, data, d, robot.joint_types, budget, (names, C), sides, register_zeros)
            for d in validate]
    answer = {"expected_mm": b["expected_mm"] if b else cv_all_rows,
              "bound95_mm": b["bound95_mm"] if b else None,
              "basis": b["expected_basis"] if b else "CV of the model chosen on all rows (no budget: optimistic)",
              "repeatability_mm": b["repeatability_mm"] if b else None, "time": (b or {}).get("time") or {}}
    geo_cols = [n for n, a in zip(terms.penalised, active) if a and n in set(terms.geometric)]
    kept_unnamed = [t.label for t in kept if t.load and t.label not in {terms.terms[i].label for i in named}]
    terms_d = {"n_free": len(terms.free), "geometric_mode": terms.geometric_mode,
               "geometric": {"considered": len(terms.geometric),
                             "kept": len(geo_cols) if terms.geometric_mode != "full" else len(terms.geometric)},
               "effects_considered": len(terms.terms), "effects_kept": len(kept),
               "kept": [t.label for t in kept], "kept_unnamed": kept_unnamed,
               "tested": [{k: v for k, v in r.items()} for r in sel.records],
               "regrouped": terms.regrouped, "candidates": [t.to_dict() for t in terms.terms],
               "together": _together(causes, data)}
    re_ = {}
    if system.psi is not None:
        re_ = {"sigma_weighted": float(np.sqrt(fit.sparse.noise_var)),
               "sigma_mm": float(np.median(system.sigma[system.kind == 0]) * np.sqrt(system.s2) * 1e3),
               "translation_mm": float(np.sqrt(np.sum(system.psi[:3])) * 1e3),
               "rotation_mrad": float(np.sqrt(np.sum(system.psi[3:])) * 1e3),
               "psi_si": system.psi.tolist()}
    model = {"robot": getattr(robot, "name", None), "robot_spec": robot_spec, "n_markers": int(robot.n_markers),
             "gravity": final.gravity.tolist(), "lumped_masses": terms.lumped,
             "effects": [e.to_dict() for e in final.effects],
             "theta": dict(zip(final.params.names, map(float, final.params.values))),
             "free": list(terms.free) + [n for n in terms.penalised if n in set(geo_cols)
                                         or any(n in t.names for t in kept)],
             "noise": nm.to_dict(), "geometric_level": terms.geometric_mode,
             "geometric_width": terms.geometric_width, "geometric_width_choice": width,
             "approach_from_order": bool(approach_from_order),
             "session_time": ("centred" if _n_sessions(data) > 1 else True) if session_time else False,
             "data_preparation": {"approach_from_order": bool(approach_from_order),
                                  "session_time": ("centred" if _n_sessions(data) > 1 else True) if session_time
                                  else False, "time_source": time_source},
             "session_frames": {str(s): dict(_frame_dict(v, terms.session_zeros.get(s), fit, s, final),
                                            name=_session_name(sessions, s)) for s, v in fit.frames.items()},
             "residual": {"rmse_mm": train_mm}}
    try:  # the nominal robot itself, so the fit needs no robot file to be simulated again
        model["robot_dict"] = robot_to_dict(robot)
    except ValueError:
        pass
    verdict = _verdict(causes, answer)
    res = DiagnosisResult(answer, causes, {"train_mm": train_mm, "cv_mm": b["model_mm"] if b else cv_all_rows,
                                           "validation": vals}, terms_d, b,
                          {"n_rows": data.n, "n_postures": groups.n_postures, "n_sessions": len(groups.sessions),
                           "time_source": time_source, "approach_source": approach_source, "folds": "session" if len(groups.sessions) > 1 else "posture",
                           "validation_registers": "frame and moved joint zeros" if register_zeros else "frame",
                           "k_folds": len(sel.cv["sq"])},
                          model, nm.to_dict(), re_, verdict, terms.lumped, robot=final, covariance=C,
                          covariance_names=names, sigma0=float(np.sqrt(fit.sparse.noise_var)),
                          train_data=list(sessions) if sessions else data, validation_data=list(validate),
                          fit_data=data)
    return res


def _zero_unit(robot, joint) -> str:
    """The display unit of a joint zero (values shown ×1e3 from SI): mm for a prismatic joint, else mrad."""
    return "mm" if robot.joint_types[robot.joint_names.index(joint)] == "prismatic" else "mrad"


def _session_name(sessions, s) -> str:
    """The name of session label ``s`` (0, 1, … in the order given): its file's stem, else the label."""
    from estcal.sessions.data import session_name

    try:
        return session_name(sessions[int(s)], int(s)) if sessions else str(s)
    except (IndexError, TypeError, ValueError):
        return str(s)


def _frame_dict(delta, zeros=None, fit=None, s=None, final=None) -> dict:
    """A session's frame increment (6 + k,) as rotation (mrad) and translation (mm), and its joint zeros
    ``zeros`` (k names) as ``{joint: [value, std, unit]}`` (mrad, or mm for a prismatic joint; the std from the
    model's covariance of its frame columns)."""
    d = np.asarray(delta, float)
    out = {"translation_mm": (d[:3] * 1e3).tolist(), "rotation_mrad": float(np.linalg.norm(d[3:6]) * 1e3)}
    if zeros:
        from .zeros import zero_parameters

        joint_of = {n: j for j, n in zero_parameters(final)}
        cols = fit.system.frame_of[s][6:]
        sd = np.sqrt(np.maximum(np.diag(fit.sparse.free_cov)[cols], 0.0))
        out["zeros"] = {joint_of[n]: [float(v * 1e3), float(e * 1e3), _zero_unit(final, joint_of[n])]
                        for n, v, e in zip(zeros, d[6:], sd)}
    return out


def _covariance(terms, fit):
    """The posterior covariance (SI) of the registration and of every kept penalised parameter, with their
    cross-covariance (``c = F⁺(y − Φw)``: Cov(c, w) = −F⁺Φ Σ_w)."""
    sp = fit.sparse
    nf = len(terms.free)
    keep_f = sp.extra.get("free_kept", np.ones(fit.system.n_free, bool))
    act = np.flatnonzero(sp.active & fit.include)
    names = list(terms.free) + [terms.penalised[j] for j in act]
    C = np.zeros((len(names), len(names)))
    C[:nf, :nf] = sp.free_cov[:nf, :nf]
    C[nf:, nf:] = sp.cov[np.ix_(act, act)]
    if "F_pinv" in sp.extra:
        full = np.zeros((fit.system.n_free, sp.cov.shape[0]))
        full[keep_f] = -(sp.extra["F_pinv"] @ (sp.extra["Phi"] * sp.extra["Phi_scale"])) @ sp.cov
        C[:nf, nf:] = full[:nf][:, act]
        C[nf:, :nf] = C[:nf, nf:].T
    return names, C


def _validation(final, data, d, joint_types, budget, cov, load_sides=None, register_zeros: bool = True) -> dict:
    """One validation file's figure: the model's RMSE at its new-posture rows, its measuring frame registered on
    its rows at postures the training measured (six parameters of the base frame, the model held), with the
    prediction at its postures and the region's coverage when the budget ran, and the share of its rows that
    load a kept compliance or backlash on the side of zero no training row did (``load_sides``:
    :func:`_training_load_sides`)."""
    from estcal.estimate import calibrate_lsq
    from estcal.methods import Problem
    from estcal.validation import posture_groups, rmse_se_mm, seen_postures

    from .stages import measured_points

    seen = seen_postures(data.readings, d.readings, joint_types)
    theta = final.params.values.copy()
    reg_ok = False
    moved = {"rotation_mrad": 0.0, "translation_mm": 0.0}
    pts = measured_points(d)
    min_rows = 1 if pts.shape[1] >= 3 or d.kind == "pose" else 3
    zeros = []
    if seen.sum() >= min_rows and all(n in final.params.names for n in _BASE) and (~seen).any():
        ds = d.subset(np.flatnonzero(seen))
        prob = Problem(final, [(None, ds, NoiseModel(known=False))])
        res = calibrate_lsq(prob, "lm", free=list(_BASE), check=False)
        zeros = moved_zeros(final, res.theta, ds, _BASE) if register_zeros else []
        if zeros:
            res = calibrate_lsq(prob, "lm", free=list(_BASE) + [z["parameter"] for z in zeros], check=False)
            for z in zeros:
                k = final.params.index(z["parameter"])
                z["value"] = float(res.theta[k] - final.params.values[k])
                z["display"] = [z["value"] * 1e3, z["std"] * 1e3, _zero_unit(final, z["joint"])]
        ib = final.params.indices(list(_BASE))
        delta = res.theta[ib] - theta[ib]
        theta = res.theta
        reg_ok = True
        from estcal.kinematics.transforms import rpy_to_matrix

        R0, R1 = rpy_to_matrix(final.params.values[ib[3:]]), rpy_to_matrix(theta[ib[3:]])
        ang = float(np.arccos(np.clip((np.trace(R1 @ R0.T) - 1) / 2, -1, 1)))
        moved = {"rotation_mrad": ang * 1e3, "translation_mm": float(np.linalg.norm(delta[:3]) * 1e3)}
    new = ~seen if seen.any() and (~seen).any() else np.ones(d.n, bool)
    dn = d.subset(np.flatnonzero(new))
    err = pose_errors(final, theta, dn)[0]
    out = {"path": str(d.where), "rmse_mm": float(np.sqrt(np.mean(err ** 2)) * 1e3),
           "rmse_se_mm": rmse_se_mm(err, posture_groups(dn.readings, joint_types)), "n_new": int(new.sum()),
           "n_seen": int(seen.sum()), "registered": reg_ok, "frame_moved": moved, "zeros_moved": zeros,
           "predicted_mm": None,
           "coverage": None, **_unseen_load_sides(final, dn, load_sides or {})}
    if budget is not None:
        from .budget import coverage_at, predicted_at, reach_at

        e, S = _model_points(final, theta, dn, cov, data.n)
        out["predicted_mm"] = predicted_at(budget, S)
        out.update(coverage_at(budget, e, S))
        out.update(reach_at(budget, data.readings, dn.readings, final.joint_names))
    return out


def _training_load_sides(final, data, joints) -> dict:
    """``{joint: (a positive load seen, a negative load seen, the zero tolerance)}`` of the training rows, for the
    joints of a kept compliance or backlash by the load — computed once for every validation file."""
    if not joints:
        return {}
    ji = [final.joint_names.index(j) for j in joints]
    tt = final.gravity_torques(data.readings, final.params.values, data.context)[:, ji]
    eps = 1e-9 * np.maximum(np.abs(tt).max(0), 1e-300)  # a numerically zero torque has no side
    return {j: (bool((tt[:, k] > eps[k]).any()), bool((tt[:, k] < -eps[k]).any()), float(eps[k]))
            for k, j in enumerate(joints)}


def _unseen_load_sides(final, dn, sides) -> dict:
    """``{"load_side_unseen": share of the rows of dn, "load_side_joints": [...]}``: the rows whose gravity torque
    on a joint of ``sides`` (:func:`_training_load_sides`) has the sign no training row had. There the model
    carries a deflection learnt on one side of zero load across it — a dead zone, or a backlash that was not a
    candidate because the training load never changed sign — untested by any cross-validation."""
    if not sides or not dn.n:
        return {"load_side_unseen": 0.0, "load_side_joints": []}
    joints = list(sides)
    tv = final.gravity_torques(dn.readings, final.params.values, dn.context)[:, [final.joint_names.index(j)
                                                                               for j in joints]]
    unseen = np.zeros(dn.n, bool)
    which = []
    for k, j in enumerate(joints):
        pos, neg, eps = sides[j]
        m = ((tv[:, k] > eps) & (not pos)) | ((tv[:, k] < -eps) & (not neg))
        if m.any():
            unseen |= m
            which.append(j)
    return {"load_side_unseen": float(unseen.mean()), "load_side_joints": which}


def _model_points(final, theta, d, cov, n_train):
    """(errors (n, 3), leverages N·J C Jᵀ (n, 3, 3)) of the model at the measured points of ``d``: ``cov`` the
    model's ``(names, covariance)``, N its number of training rows (the budget's unit of leverage)."""
    from estcal.methods import Problem

    from .stages import measured_points, predicted_points

    names, C = cov
    e = (measured_points(d) - predicted_points(final, theta, d)).reshape(-1, 3)
    rows = Problem(final, [(None, d, NoiseModel(known=False))]).evaluate(theta)
    J = rows.H[rows.kind == 0][:, final.params.indices(names)].reshape(-1, 3, len(names))
    return e, np.einsum("nip,pq,njq->nij", J, C, J) * n_train


def _verdict(causes, answer) -> str:
    names = "; ".join(c.label for c in causes) if causes else "no cause named"
    return f"{names}. Expected error at new postures {answer['expected_mm']:.3g} mm ({answer['basis']})."
