"""The error budget: how accurate the diagnosis's model is where it was not fitted, and why.

Every figure is a cross-validated RMSE (mm) of the point-error norms over held-out groups of rows
(:class:`estcal.validation.groups.Groups`): postures — and, with two sessions or more, the session too
(each fold trains on the other sessions and registers the held-out session's frame on its rows at seen
postures) — and contiguous blocks of acquisition time.

==========================  ==========================================================================
``nominal_mm``              the registration alone (base frame and measured points; nominal geometry)
``geometry_mm``             + the geometric parameters under their relevance priors (no effect)
``model_mm``                the diagnosis's model — the **nested** CV of its whole procedure: every
                            fold chooses its special terms (the naming tests of
                            :mod:`estcal.discrepancy.relevance`) on its training rows only and is
                            scored at its held-out rows (Varma & Simon 2006: a CV that chooses and
                            scores its own choice is optimistic)
``bound95_mm``              95 % of the held-out point errors are below it (the conformal quantile,
                            Barber et al. 2021)
``time``                    the same model by time-blocked CV (contiguous blocks of the acquisition
                            time in every session; ``time_source``: the ``t`` column or the row order);
                            when it is worse than ``model_mm`` by more than the two standard errors
                            together the error grows over the campaign, and the budget predicts for
                            later use with it (``expected_mm``, ``expected_basis``)
``repeatability_mm``        the floor from repeated postures (:func:`estcal.validation.repeatability_floor`)
``expected_mm``             the answer to "how accurate at new postures": ``model_mm``, or the
                            time-blocked figure when the two disagree
==========================  ==========================================================================

The prediction at target postures (:func:`predicted_at`) and the 95 % region (:func:`region_at`) come from
the nested held-out errors: ``E|e|² = a + b·v`` with ``v = N·tr(J C Jᵀ)`` the prediction variance of the fold
model in units of one training row (:func:`estcal.discrepancy.prediction.variance_model`), so targets
farther from the training postures than the CV's held-out ones are predicted larger.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.validation.groups import Fold

from .prediction import (beyond_leverage, conformal_threshold, predicted_rmse_at, region_coverage, region_scores,
                         region_sigma, slope_upper, variance_model)
from .relevance import cross_validate, cv_rmse_mm, fold_mse, held_out_errors, select_terms

__all__ = ["Budget", "error_budget", "budget_lines", "point_errors", "point_leverage", "predicted_at", "coverage_at",
           "reach_at"]


@dataclass
class Budget:
    """What :func:`error_budget` measured (mm; module docstring). ``folds`` the fold kind (``"posture"`` or
    ``"session"``) and their number ``k_folds``; ``decisions`` the special terms each outer fold named;
    ``region`` the 95 % region's variance model; ``extra`` what :func:`predicted_at` / :func:`region_at` need."""

    nominal_mm: float
    geometry_mm: float
    model_mm: float
    model_se_mm: float
    bound95_mm: float | None
    time: dict
    repeatability_mm: float | None
    repeatability_reason: str | None
    expected_mm: float
    expected_basis: str
    folds: str
    k_folds: int
    n_postures: int
    n_rows: int
    n_sessions: int
    decisions: list
    region: dict
    extrapolation: dict
    extra: dict = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        keys = ("nominal_mm", "geometry_mm", "model_mm", "model_se_mm", "bound95_mm", "time", "repeatability_mm",
                "repeatability_reason", "expected_mm", "expected_basis", "folds", "k_folds", "n_postures",
                "n_rows", "n_sessions", "decisions", "region", "extrapolation")
        return {k: getattr(self, k) for k in keys}


def point_errors(system, e, rows) -> np.ndarray:
    """(n_points, 3) the position part of a residual ``e`` (m) at the system ``rows``: 3 rows per point."""
    return np.asarray(e)[system.kind[rows] == 0].reshape(-1, 3)


def point_leverage(system, fit, rows) -> np.ndarray:
    """(n_points, 3, 3) the fit's prediction covariance (m²) at the measured points of the system ``rows``
    (:meth:`estcal.estimate.sparse.SparseFit.prediction_cov` per point)."""
    pos = rows[system.kind[rows] == 0].reshape(-1, 3)
    keep = fit.extra.get("free_kept", np.ones(system.n_free, bool))
    out = np.zeros((len(pos), 3, 3))
    for i, r in enumerate(pos):
        C = fit.prediction_cov(system.P[r], system.F[np.ix_(r, np.flatnonzero(keep))])
        out[i] = C * np.outer(system.sigma[r], system.sigma[r])
    return out


def _inner(groups, fold: Fold, kind, k, rng) -> list:
    """The inner folds of an outer fold's training rows, in the rows of the whole data."""
    sub = groups.subset(fold.train)
    return [Fold(fold.train[f.test], fold.train[f.train], fold.train[f.register]) for f in sub.folds(kind, k, rng)]


def _nested(terms, system, groups, folds, kind, k, rng, start, time_blocks=True):
    """The nested CV of the diagnosis's procedure: per outer fold the naming tests on its training rows
    (inner folds of the same kind), the model fitted there, scored at the held-out rows (registered when its
    session is held out). Returns (point errors (n, 3), leverages (n, 3, 3), per-fold squared sums and
    counts, the special terms each fold named, reach (n,) of each held-out point's row)."""
    errs, levs, sq, cnt, decisions, reach = [], [], [], [], [], []
    from estcal.validation import extrapolation_distance

    R = groups.readings
    for f in folds:
        sel = select_terms(terms, system, _inner(groups, f, kind, k, rng), rows=system.rows_of(f.train), start=start,
                           name_load=False, time_folds=_inner(groups, f, "time", k, rng) if time_blocks else None,
                           final_cv=False)
        e = held_out_errors(system, sel.fit, f.test, f.register)
        rt = system.rows_of(f.test)
        ep = point_errors(system, e, rt)
        errs.append(ep)
        lev = point_leverage(system, sel.fit, rt) * len(f.train)
        levs.append(lev)
        sq.append(float(np.sum(ep ** 2)))
        cnt.append(len(ep))
        decisions.append([terms.terms[i].label for i in sel.named])
        d = extrapolation_distance(R[f.train], R[f.test]).max(1) if R is not None else np.zeros(len(f.test))
        per_row = dict(zip(f.test.tolist(), d.tolist()))
        reach.append(np.array([per_row[p] for p in system.pose[rt][system.kind[rt] == 0][::3]]))
    return (np.concatenate(errs), np.concatenate(levs), np.array(sq), np.array(cnt), decisions,
            np.concatenate(reach))


def _rmse_se(sq, cnt) -> tuple[float, float]:
    """Pooled RMSE (mm) and its standard error over folds (δ-method of the fold mean squared errors)."""
    mse, se_mse = fold_mse(sq, cnt)
    rm = float(np.sqrt(mse))
    return rm * 1e3, se_mse / (2 * max(rm, 1e-300)) * 1e3


def _region(e, S) -> dict:
    """The 95 % region of a new posture from the nested held-out errors ``e`` (n, 3) and their leverages
    ``S`` (n, 3, 3): Σ = b·S + τ² I₃ by maximum likelihood (τ² at least 5 % of the held-out variance per
    coordinate), the slope's upper bound beyond the farthest held-out leverage, the conformal threshold."""
    floor = 0.05 * float(np.mean(np.asarray(e) ** 2))
    a, b = variance_model(e, S, tau2_floor=floor)
    b_far = slope_upper(e, S, b, tau2_floor=floor)
    region = {"level": 0.95, "tau_mm": float(np.sqrt(a / 3.0) * 1e3), "scale": float(b),
              "scale_far": None if not np.isfinite(b_far) else float(b_far),
              "leverage_max_m2": float(np.trace(S, axis1=-2, axis2=-1).max()) if len(e) else None,
              "variance_model": {"a_mm2": float(a * 1e6), "b": float(b)}}
    d2 = region_scores(e, region_sigma(region, S), 0.0)
    region.update(threshold_d2=conformal_threshold(d2, 0.95), n_points=int(len(d2)))
    return region


def error_budget(terms, fit, data, groups, selection, k: int = 5, rng=0, time_blocks: bool = True) -> Budget:
    """The budget of the diagnosis's model (module docstring): ``terms`` and ``fit`` (the all-rows
    :class:`~estcal.discrepancy.relevance.RelevanceFit`), ``groups`` of ``data``'s rows, ``selection`` the
    all-rows :class:`~estcal.discrepancy.relevance.Selection`."""
    from estcal.validation import repeatability_floor

    from .stages import measured_points

    system = fit.system
    kind = "session" if len(groups.sessions) > 1 else "posture"
    folds = groups.folds(kind, k, rng)
    start = fit.sparse.alpha
    tidx = terms.term_index()
    geo_only = tidx < 0
    nominal = cross_validate(system, folds, np.zeros(len(tidx), bool), start)
    geometry = cross_validate(system, folds, geo_only, start)
    e, S, sq, cnt, decisions, reach = _nested(terms, system, groups, folds, kind, k, rng, start, time_blocks)
    model_mm, model_se = _rmse_se(sq, cnt)
    norms = np.linalg.norm(e, axis=1)
    bound = conformal_threshold(norms, 0.95) * 1e3
    bound = float(bound) if np.isfinite(bound) else None  # too few held-out points for a 95 % bound
    time = _time_cv(system, groups, selection.include, k, start, model_mm, model_se) if time_blocks else {}
    pts = measured_points(data)
    rep = repeatability_floor(pts, groups.posture, groups.session,
                              zero_jacobians=_zero_jacobians(terms, fit, data, pts.shape[1]))
    rep_mm = None if rep is None else next((rep[key] for key in ("registered_zeros_mm", "registered_mm", "raw_mm")
                                            if rep.get(key) is not None), None)
    expected, basis = model_mm, f"nested {'session- and ' if kind == 'session' else ''}posture-grouped CV"
    if time.get("disagrees"):
        expected, basis = time["model_mm"], "time-blocked CV (the error grows over the campaign: later use)"
    return Budget(cv_rmse_mm(nominal), cv_rmse_mm(geometry), model_mm, model_se, bound, time, rep_mm,
                  None if rep is not None else "no posture is measured twice", float(expected), basis, kind,
                  len(folds), groups.n_postures, groups.n, len(groups.sessions), decisions, _region(e, S),
                  {"cv_reach_max": float(reach.max()) if reach.size else 0.0,
                   "fraction_outside": float(np.mean(reach > 0)) if reach.size else 0.0},
                  {"held_out": e, "leverage": S, "n_train": groups.n})


def _zero_jacobians(terms, fit, data, k: int):
    """(N, k, 3, z) the derivative of every row's k measured points with respect to the joint zeros the model
    registers per session (:attr:`~estcal.discrepancy.terms.Terms.session_zeros`), at the fitted parameters; None
    when it registers none or the rows are not points (the repeatability floor then registers the frames only)."""
    from estcal.methods import NoiseModel, Problem

    zeros = sorted({n for z in terms.session_zeros.values() for n in z})
    if not zeros or data.kind not in ("points", "position"):
        return None
    ev = Problem(terms.robot, [(None, data, NoiseModel(known=False))]).evaluate(fit.theta, jacobian=True)
    rows = np.flatnonzero(np.asarray(ev.kind) == 0)
    rows = rows[np.argsort(ev.pose[rows], kind="stable")]  # by row, then point, then axis
    if len(rows) != data.n * k * 3:
        return None
    return ev.H[np.ix_(rows, terms.robot.params.indices(zeros))].reshape(data.n, k, 3, len(zeros))


def _time_cv(system, groups, include, k, start, model_mm, model_se) -> dict:
    """The model (the all-rows terms) by time-blocked CV, and whether it disagrees with the posture-grouped
    figure (worse by more than both standard errors together)."""
    folds = groups.folds("time", k)
    if len(folds) < 2:
        return {}
    cv = cross_validate(system, folds, include, start)
    rm, se = _rmse_se(cv["sq"], cv["n"])
    gap = rm - model_mm
    return {"source": groups.time_source, "k_folds": len(folds), "model_mm": rm, "model_se_mm": se,
            "disagrees": bool(gap > np.hypot(se, model_se) if np.isfinite(se) and np.isfinite(model_se) else False),
            "nested": False}


def predicted_at(budget: Budget, S) -> float:
    """Expected RMSE (mm) at points whose leverage (N·J C Jᵀ, m²) is ``S`` (n, 3, 3): √mean(a + b·tr S)."""
    vm = budget.region["variance_model"]
    return predicted_rmse_at(vm["a_mm2"] * 1e-6, vm["b"], S, budget.region.get("leverage_max_m2")) * 1e3


def coverage_at(budget: Budget, e, S) -> dict:
    """The 95 % region applied to errors ``e`` (n, 3) with leverages ``S``: share inside, share beyond the
    farthest held-out leverage."""
    return {"coverage": region_coverage(budget.region, e, S), "beyond_cv_leverage": beyond_leverage(budget.region, S)}


def reach_at(budget, train_readings, readings, joint_names) -> dict:
    """How far the rows ``readings`` extrapolate against what the nested CV tried: ``{"reach_max": the farthest any
    joint goes beyond the training rows' range, in units of that range, "reach_joint": that joint,
    "beyond_cv_reach": share of the rows going farther than any held-out row of the nested CV went beyond its
    fold's training range}`` — where the prediction and the region are untested (they are calibrated on the
    held-out errors; on TIAGo a row 2.4 ranges beyond scored 8.1 mm for a prediction of 3.3)."""
    from estcal.validation import extrapolation_distance

    d = extrapolation_distance(train_readings, readings)
    if not d.size:
        return {"reach_max": 0.0, "reach_joint": None, "beyond_cv_reach": 0.0}
    cv = (budget["extrapolation"] if isinstance(budget, dict) else budget.extrapolation)["cv_reach_max"]
    return {"reach_max": float(d.max()), "reach_joint": joint_names[int(np.argmax(d.max(0)))],
            "beyond_cv_reach": float(np.mean(d.max(1) > cv + 1e-9))}


def budget_lines(b: dict) -> list[str]:
    """The budget as text lines (details of ``estcal diagnose``; the answer comes first elsewhere)."""
    fold = "session- and posture-grouped" if b["folds"] == "session" else "posture-grouped"
    rep = "—" if b["repeatability_mm"] is None else f"{b['repeatability_mm']:.3f}"
    why = f"   ({b['repeatability_reason']})" if b.get("repeatability_reason") else ""
    out = [f"error budget ({fold} {b['k_folds']}-fold CV, {b['n_postures']} postures, {b['n_rows']} rows; mm at "
           f"new postures):",
           f"  registration only          {b['nominal_mm']:8.3f}",
           f"  + geometry                 {b['geometry_mm']:8.3f}",
           f"  + effects (the model)      {b['model_mm']:8.3f} ± {b['model_se_mm']:.3f}  (nested: every fold makes "
           f"its own choices)",
           f"  repeatability floor        {rep:>8}{why}"]
    if b["geometry_mm"] < b["model_mm"]:
        # read before any validation file (UR10, 16 poses: 3.77 against 4.09 ± 0.39 mm; its 7 new poses then score
        # 4.06 mm with the geometry alone and 5.47 with the model)
        out.append(f"  the geometry alone scores lower at new postures than the model ({b['geometry_mm']:.3f} against "
                   f"{b['model_mm']:.3f} ± {b['model_se_mm']:.3f} mm): the load terms the evidence keeps may not carry "
                   f"to new postures on these data — `--effects none` fits the geometry alone")
    t = b.get("time") or {}
    if t:
        out.append(f"  time-blocked ({t['source']})  {t['model_mm']:8.3f} ± {t['model_se_mm']:.3f}  "
                   + ("— worse than by posture: the error grows over the campaign" if t["disagrees"]
                      else "— agrees with the posture-grouped figure"))
    return out
