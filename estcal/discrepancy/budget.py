"""The error budget: where the error at new postures goes, by posture-grouped cross-validation.

Every figure is a cross-validated RMSE (mm) of the point-error norms over the same rows,
with folds that never split a posture (:func:`estcal.validation.grouped_folds`): the
twin of a held-out row measured in another session is never in training. Each fold
refits every stage from scratch (registration, the geometric level's own selection,
the named effects, the residual GP).

=========================  ==============================================================
``nominal_mm``             registration only: base frame and unknown points/tool fitted,
                           nominal geometry
``geometric_mm``           the chosen geometric level (``full``, ``aic``, ``joint_offset``)
``named_mm``               + the named effects (equal to ``geometric_mm`` when none)
``structured_unnamed_mm``  the RMSE reduction a Gaussian process on the named model's
                           residual still achieves (:mod:`estcal.discrepancy.residual`,
                           the better of the joint and Cartesian spaces); 0 when none
``unstructured_mm``        what is left after it: ``named_mm − structured_unnamed_mm``
``repeatability_mm``       the floor from repeated postures after removing what the model
                           treats as per-session: a rigid registration of each session
                           (raw when one session), and with a per-session measured point
                           (``per_session="registration+points"``) that point too
                           (:func:`estcal.validation.repeatability_floor`); ``None`` with
                           ``repeatability_reason`` when no posture repeats or the
                           per-session point cannot be told from the frame
``predicted_validation_mm`` the expected RMSE at new postures of the recommended model
                           (named, or named + GP): the **nested** CV of the procedure that
                           recommends it — every outer fold chooses the level, the causes
                           and the GP on its training rows only and scores its own choice
                           (:mod:`estcal.discrepancy.prediction`)
=========================  ==============================================================

With a :class:`~estcal.discrepancy.prediction.Procedure` the stages are those of the procedure
replayed in each fold (``geometric_mm``: the level each fold chose; ``named_mm``: the causes each
fold named), so every figure is the error of what the tool would do, not of one choice made on
all rows. A procedure with its own fit (``Procedure.fit``, e.g. the MAP group-prior model of
:mod:`estcal.discrepancy.prior_model`) puts that model in the named row (``model``: its name) and
refits it, with every decision it makes (the prior widths), on each fold's training rows; ``decisions``
records per fold what it decided (``fit``). A procedure whose level choice has the prior model among its
candidates (``Procedure.prior_fit``) fits, in a fold that chooses it, the prior model in the named row and
the ``full`` level in the geometric one (``decisions[i].level``: ``"prior"``).

``region`` is the 95 % prediction region of a new posture (b × θ covariance + τ², the
conformal threshold from the nested held-out points) and ``region.variance_model``
the line ``E|e|² = a + b·tr Σ_θ`` of the nested held-out errors; :func:`region_at` applies the
region to validation rows and :func:`predicted_at` predicts the RMSE at target postures from their
joint readings alone — larger than ``predicted_validation_mm`` where they lie farther from the
training postures than the CV's held-out ones (:mod:`estcal.discrepancy.prediction`).

The reduction is a plain difference of RMSEs (not a quadrature split): the budget reads
"the GP would take the error from 2.6 to 2.4 mm". Folds are few on real data (tens of
postures), so the per-fold RMSEs are reported and their spread gives the uncertainty of
``predicted_validation_mm`` (``predicted_validation_se_mm``, the standard error over folds).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.discrepancy.prediction import (GP_GAIN, PRIOR, Procedure, beyond_leverage, choose_level,
                                           conformal_threshold, predicted_rmse_at, region_coverage, region_scores, region_sigma,
                                           slope_upper, variance_model)
from estcal.discrepancy.residual import SPACES, fit_residual_model, residual_choice, residual_correction
from estcal.discrepancy.stages import (STAGES, FittedStage, fit_stage, fit_stage_sessions, measured_points,
                                       point_covariance, predicted_points)
from estcal.methods import NoiseModel
from estcal.validation import (DEFAULT_TOL_M, DEFAULT_TOL_RAD, extrapolation_distance, grouped_folds, n_postures,
                               posture_groups, repeatability_floor, rmse_mm)

__all__ = ["ErrorBudget", "FittedStage", "error_budget", "diagnosis_budget", "budget_lines", "predicted_at",
           "region_at", "reach_at", "fit_stage", "fit_stage_sessions", "predicted_points", "measured_points",
           "point_covariance", "STAGES"]


@dataclass
class ErrorBudget:
    """Result of :func:`error_budget` (mm; see the module docstring for each entry)."""

    nominal_mm: float
    geometric_mm: float
    named_mm: float
    structured_unnamed_mm: float
    unstructured_mm: float
    repeatability_mm: float | None
    predicted_validation_mm: float
    predicted_validation_se_mm: float
    recommended: str
    unnamed: dict
    per_fold_mm: dict
    gp_mm: dict
    repeatability: dict | None
    n_postures: int
    n_rows: int
    k_folds: int
    level: str
    effects: list
    residual_model: object = None
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("nominal_mm", "geometric_mm", "named_mm", "structured_unnamed_mm",
                                           "unstructured_mm", "repeatability_mm", "predicted_validation_mm",
                                           "predicted_validation_se_mm", "recommended", "unnamed", "per_fold_mm",
                                           "gp_mm", "repeatability", "n_postures", "n_rows", "k_folds", "level")}
        d["effects"] = [{"effect": e[0], "joints": list(e[1])} for e in self.effects]
        d["cross_validation"] = "posture-grouped"
        d.update({k: v for k, v in self.extra.items() if not k.startswith("fitted")})
        return d

    def lines(self) -> list[str]:
        """The budget as text lines (the ``diagnose`` output)."""
        return budget_lines(self.to_dict())

    def __str__(self) -> str:
        return "\n".join(self.lines())


def budget_lines(b: dict) -> list[str]:
    """Text lines of a budget dict (:meth:`ErrorBudget.to_dict`)."""
    rep = "—" if b["repeatability_mm"] is None else f"{b['repeatability_mm']:.3f}"
    why = f"   ({b['repeatability_reason']})" if b.get("repeatability_reason") else ""
    top = ", ".join(f"{k} {v:.2f}" for k, v in list(b["unnamed"].get("relevance", {}).items())[:3])
    return [f"error budget (posture-grouped {b['k_folds']}-fold CV, {b['n_postures']} postures, {b['n_rows']} rows; mm):",
            f"  nominal (registration)   {b['nominal_mm']:8.3f}",
            f"  geometric ({b['level']:<12}) {b['geometric_mm']:8.3f}",
            f"  {(b['model'] + ' model') if b.get('model') else '+ named effects':<24} {b['named_mm']:8.3f}",
            f"  structured, unnamed      {b['structured_unnamed_mm']:8.3f}   "
            f"(GP over {b['unnamed'].get('space', '-')}: {top or '-'})",
            f"  unstructured             {b['unstructured_mm']:8.3f}",
            f"  repeatability floor      {rep:>8}{why}",
            f"  predicted at new postures {b['predicted_validation_mm']:7.3f} ± {b['predicted_validation_se_mm']:.3f}"
            f"  ({b['recommended']}; {'nested CV: every fold makes its own choices' if b.get('nested') else 'CV'})"
            ] + _region_lines(b)


def _region_lines(b: dict) -> list[str]:
    r = b.get("region")
    if not r:
        return []
    far = f" ({r['scale_far']:.3g} beyond the farthest held-out leverage)" if r.get("scale_far") is not None else ""
    out = [f"  95 % region at a new posture: {r.get('scale', 1.0):.3g}{far}·N·J C_θ Jᵀ + ({r['tau_mm']:.2f} mm)² I, "
           f"d² ≤ {r['threshold_d2']:.3g} (conformal from the held-out points; χ²₃ {r['chi2_d2']:.3g} covers "
           f"{100 * r['nested_coverage_chi2']:.0f} %)"]
    for v in b.get("validation", []):
        pred = f" (predicted at its postures {v['predicted_mm']:.3f})" if v.get("predicted_mm") is not None else ""
        if v.get("beyond_cv_leverage"):
            pred += f" — {100 * v['beyond_cv_leverage']:.0f} % of them beyond the CV's farthest leverage"
        if v.get("beyond_cv_reach"):
            pred += (f" — {100 * v['beyond_cv_reach']:.0f} % of its rows extrapolate farther than the CV tried "
                     f"({v['reach_joint']}: {v['reach_max']:.2g}× its training range, CV "
                     f"{b['extrapolation']['cv_reach_max']:.2g}×): the prediction is untested there")
        out.append(f"  validation {v['path']}: RMSE {v['rmse_mm']:.3f} mm{pred}, inside the region "
                   f"{100 * v['coverage']:.0f} % of {v['n_points']} points")
    if b.get("validation") and b.get("training_sessions") == 1:
        out.append("  (one training session: the region has no session-to-session term, so the points of another "
                   "session fall outside it more often than 5 %; train on several sessions to include it)")
    return out


def _fold_rmse(sq_rows, folds):
    return [float(np.sqrt(np.mean(sq_rows[f])) * 1e3) for f in folds]


def _inner_gp_gains(robot, data, noise, level, effects, folds, spaces, cfg) -> dict:
    """{space: (held-out MSE after the GP ÷ without it, its one-standard-error margin)} over the posture-grouped
    ``folds`` of ``data``: the named model and the GP refitted on each fold's training rows (the GP from its
    default start: hyperparameters fitted on rows that include the held-out ones would leak them) — the GP
    decision of the procedure, made on these rows only."""
    meas = measured_points(data)
    base, after = [], {sp: [] for sp in spaces}
    for test in folds:
        train = np.setdiff1d(np.arange(data.n), test)
        dtr, dte = data.subset(train), data.subset(test)
        stage = "named" if effects else "geometric"
        fs = fit_stage_sessions(robot, dtr, noise, stage, level, effects, cfg["per_session"], max_iter=cfg["max_iter"],
                                fit=cfg["fit"])
        held = meas[test] - fs.predict(dte)
        base.append(float(np.sum(held ** 2)))
        r_tr = fs.residual_common(dtr)
        for sp in spaces:
            gp = fit_residual_model(sp, fs.robot, fs.theta, dtr.readings, r_tr, dtr.context, 0, cfg["rng"])
            corr = residual_correction(gp, fs.robot, fs.theta, dte.readings, dte.context)
            after[sp].append(float(np.sum((held - fs.rotate_to_session(dte, corr)) ** 2)))
    return _gains(np.array(base), {sp: np.array(v) for sp, v in after.items()})


def _gains(base, after: dict) -> dict:
    """{space: (Σ after / Σ base, one standard error of the per-fold gain relative to Σ base)}."""
    tot = max(float(base.sum()), 1e-300)
    out = {}
    for sp, a in after.items():
        d = base - a
        se = float(d.std(ddof=1) * np.sqrt(len(d)) / tot) if len(d) > 1 else float("inf")
        out[sp] = (float(a.sum() / tot), se)
    return out


def _inner_gp_choice(rule: str, spaces, gains) -> str | None:
    """:func:`_gp_choice` on the inner CV's gains (``gains()``, computed only when the rule leaves a choice: not
    for ``never``, nor for ``always`` among one space)."""
    if rule == "never":
        return None
    if rule == "always" and len(spaces) == 1:
        return spaces[0]
    return _gp_choice(rule, gains())


def _gp_choice(rule: str, gains: dict) -> str | None:
    """The space of the recommended GP (None: no GP) by the procedure's rule (:mod:`.prediction`): ``always``
    the best space; ``cv`` the best space only when it lowers the held-out RMSE by ≥ 5 % and its gain
    exceeds one standard error over the folds (the one-standard-error rule of the levels)."""
    if rule == "never" or not gains:
        return None
    best = min(gains, key=lambda sp: gains[sp][0])
    ratio, se = gains[best]
    return best if rule == "always" or (ratio <= GP_GAIN ** 2 and 1.0 - ratio > se) else None


def _outer_fold(robot, data, noise, test, proc, cfg, gps_all):
    """One outer fold of the nested CV: the procedure's decisions on the training rows only (level, causes,
    GP), every stage refitted there, scored at the held-out postures. ``cfg``: groups, folds options,
    per_session, spaces, max_iter, rng, nested, the final decisions (used when not nested)."""
    n = data.n
    train = np.setdiff1d(np.arange(n), test)
    dtr, dte = data.subset(train), data.subset(test)
    meas = measured_points(dte)
    per, mi = cfg["per_session"], cfg["max_iter"]
    lv = cfg["level"]
    if cfg["nested"] and proc.level == "auto":
        lv = choose_level(robot, dtr, noise, cfg["groups"][train], proc.k_inner, cfg["rng"], per, max_iter=mi,
                          fits=proc.candidates())[0]
    # the prior model chosen as the level: its own fit, the full level as the budget's geometric stage
    fold_fit, geo_lv = (proc.prior_fit, "full") if lv == PRIOR else (proc.fit, lv)
    fits = {"nominal": fit_stage_sessions(robot, dtr, noise, "nominal", per_session=per, max_iter=mi),
            "geometric": fit_stage_sessions(robot, dtr, noise, "geometric", geo_lv, per_session=per, max_iter=mi)}
    eff = ([] if lv == PRIOR else proc.effects_for(train, fits["geometric"].free)) if cfg["nested"] \
        else list(cfg["effects"])
    fits["named"] = (fit_stage_sessions(robot, dtr, noise, "named", geo_lv, eff, per, max_iter=mi, fit=fold_fit)
                     if eff or fold_fit is not None else fits["geometric"])
    out = {"held": {st: meas - fs.predict(dte) for st, fs in fits.items()}, "gp": {}, "level": lv,
           "effects": [[e[0], list(e[1])] for e in eff]}
    if fold_fit is not None:  # what the procedure's own fit decided on this fold's rows (e.g. the prior widths)
        out["fit"] = fits["named"].result.extra.get("fold_decision")
    fs = fits["named"]
    r_tr = fs.residual_common(dtr)
    gps = {}
    for sp in cfg["spaces"]:
        gps[sp] = fit_residual_model(sp, fs.robot, fs.theta, dtr.readings, r_tr, dtr.context, 0, cfg["rng"],
                                     start=gps_all[sp])
        corr = residual_correction(gps[sp], fs.robot, fs.theta, dte.readings, dte.context)
        out["gp"][sp] = out["held"]["named"] - fs.rotate_to_session(dte, corr)
    if cfg["nested"]:
        space = _inner_gp_choice(proc.gp, cfg["spaces"], lambda: _inner_gp_gains(
            robot, dtr, noise, geo_lv, eff, grouped_folds(cfg["groups"][train], proc.k_inner, cfg["rng"]),
            cfg["spaces"], dict(cfg, fit=fold_fit)))
    else:
        space = cfg["gp_space"]
    out["gp_space"] = space
    out["rec"] = out["gp"][space] if space else out["held"]["named"]
    # the parameter covariance only: a GP's variance is the same everywhere far from its data, and a fold
    # may choose a GP where the final model does not (the variance model's a holds what the GP leaves)
    # × the number of training rows: the leverage in units of one training row (the metric of the identification
    # Jacobian, the same whatever the number of rows of the fit; prediction.py)
    out["S"] = point_covariance(fs, dte) * len(train)
    # how far each held-out row goes beyond its fold's training ranges (0 inside: inside_ranges)
    out["reach"] = extrapolation_distance(dtr.readings, dte.readings).max(1)
    return out


def error_budget(robot, data, noise=None, *, level: str = "full", effects=(), procedure=None, groups=None,
                 sessions=None, k_folds: int = 5, rng=0, tol_rad: float = DEFAULT_TOL_RAD,
                 tol_m: float = DEFAULT_TOL_M, spaces=SPACES, residual_model: str | None = None,
                 gp_restarts: int = 1, max_iter: int = 60, per_session: str | None = None,
                 nested: bool = True) -> ErrorBudget:
    """The error budget of the module docstring on ``data`` (all sessions stacked).

    Parameters
    ----------
    robot : nominal robot; data : Dataset (position, points or pose rows; a ``session`` column
        marks sessions, see :func:`estcal.sessions.stack_sessions`).
    noise : NoiseModel for the fits (default: unknown, 0.2 mm / 0.2 mrad starting scale).
    level, effects : the geometric level (``"auto"``: :func:`~estcal.discrepancy.prediction.choose_level`)
        and the named effects (``(name, joints, options)``) of the recommended model — the procedure's
        decisions on all rows; ``level="prior"`` (or ``"auto"`` choosing it): the procedure's ``prior_fit``,
        the MAP prior model, is the recommended model (no named effects; the geometric stage is ``full``).
    procedure : the :class:`~estcal.discrepancy.prediction.Procedure` that made them, replayed on every
        outer fold (default: the level as given — ``auto`` is chosen again in every fold — the effects
        fixed, the GP as ``residual_model`` says).
    groups : posture labels (default: :func:`estcal.validation.posture_groups` with ``tol_rad``, ``tol_m``).
    sessions : session labels (default: the ``session`` column, else one session).
    k_folds : posture-grouped folds (capped at the number of postures).
    spaces : residual GP spaces tried (``joints``, ``cartesian``).
    residual_model : ``"gp"`` makes named + GP the recommended model (``procedure.gp = "always"``) and
        returns the GP fitted on all rows in ``residual_model``; ``"gp-joints"`` / ``"gp-cartesian"``: the GP of
        that space only (``spaces`` is then that space).
    per_session : ``"registration"`` / ``"registration+points"``: every stage with a rigid registration
        of each session (and a per-session change of the measured points), see :func:`fit_stage_sessions`.
    nested : replay the procedure's decisions in every outer fold (the honest prediction); False: the
        decisions on all rows are kept in every fold (the CV of the chosen model, optimistic by the
        selection).
    """
    noise = noise or NoiseModel(position=2e-4, orientation=2e-4, known=False)
    gp_rule, gp_spaces = residual_choice(residual_model)
    if gp_spaces != SPACES:  # a residual model of one named space; "gp" leaves the caller's spaces
        spaces = gp_spaces
    n = data.n
    g = posture_groups(data.readings, robot.joint_types, tol_rad, tol_m) if groups is None else np.asarray(groups)
    if sessions is None:
        sessions = data.columns.get("session", np.zeros(n))
    if level == PRIOR and (procedure is None or procedure.prior_fit is None):
        raise ValueError("level 'prior' needs a Procedure with prior_fit (the MAP prior model's fit)")
    proc = procedure or Procedure(level=level, effects=tuple(tuple(e) for e in effects),
                                  gp=gp_rule, k_inner=k_folds)
    levels_cv = None
    if level == "auto":
        level, levels_cv = choose_level(robot, data, noise, g, proc.k_inner, rng, per_session, max_iter=max_iter,
                                        fits=proc.candidates())
    # the prior model chosen as the level: its own fit and no named effects; the full level as the geometric stage
    chose_prior = level == PRIOR
    final_fit, model = (proc.prior_fit, proc.label or PRIOR) if chose_prior else (proc.fit, proc.label)
    if chose_prior:
        effects, level = (), "full"
    folds = grouped_folds(g, k_folds, rng)
    meas = measured_points(data)
    stage = "named" if effects else "geometric"
    final = fit_stage_sessions(robot, data, noise, stage, level, effects, per_session, max_iter=max_iter, fit=final_fit)
    r_all = final.residual_common(data)
    gps_all = {sp: fit_residual_model(sp, final.robot, final.theta, data.readings, r_all, data.context, gp_restarts,
                                      rng) for sp in spaces}
    cfg = {"groups": g, "per_session": per_session, "max_iter": max_iter, "rng": rng, "nested": nested,
           "spaces": spaces, "level": PRIOR if chose_prior else level,
           "effects": effects, "gp_space": None, "fit": final_fit}
    if not nested:  # the decision on all rows first: the folds keep it
        cfg["gp_space"] = _inner_gp_choice(proc.gp, spaces, lambda: _inner_gp_gains(
            robot, data, noise, level, effects, grouped_folds(g, proc.k_inner, rng), spaces, cfg))
    held = {st: np.zeros_like(meas) for st in STAGES}
    held_gp = {sp: np.zeros_like(meas) for sp in spaces}
    rec = np.zeros_like(meas)
    S = np.zeros(meas.shape + (3,))
    reach = np.zeros(n)  # how far held-out rows go beyond their fold's training ranges (the farthest joint)
    decisions = []
    for test in folds:
        o = _outer_fold(robot, data, noise, test, proc, cfg, gps_all)
        for st in STAGES:
            held[st][test] = o["held"][st]
        for sp in spaces:
            held_gp[sp][test] = o["gp"][sp]
        rec[test], S[test], reach[test] = o["rec"], o["S"], o["reach"]
        decisions.append({"level": o["level"], "effects": o["effects"], "gp": o["gp_space"],
                          **({"fit": o["fit"]} if "fit" in o else {})})
    # the GP decision on all rows: the outer folds' held-out residuals with and without each space's GP
    fsq = lambda h: np.array([np.sum(h[f] ** 2) for f in folds])  # noqa: E731
    ratios = _gains(fsq(held["named"]), {sp: fsq(held_gp[sp]) for sp in spaces})
    gp_space = cfg["gp_space"] if not nested else _gp_choice(proc.gp, ratios if proc.gp != "never" else {})
    return _assemble(robot, data, g, sessions, folds, held, held_gp, rec, S, reach, final, gps_all, gp_space,
                     ratios, level, effects, levels_cv, decisions, per_session, nested, model)


def _assemble(robot, data, g, sessions, folds, held, held_gp, rec, S, reach, final, gps_all, gp_space, ratios,
              level, effects, levels_cv, decisions, per_session, nested, model=None) -> ErrorBudget:
    """The :class:`ErrorBudget` from the outer folds' held-out residuals (module docstring)."""
    sq = {k: np.sum(v ** 2, axis=-1) for k, v in held.items()}  # (N, k) squared norms
    rm = {k: rmse_mm(np.sqrt(v)) for k, v in sq.items()}
    sq_gp = {sp: np.sum(v ** 2, axis=-1) for sp, v in held_gp.items()}
    gp_mm = {sp: rmse_mm(np.sqrt(v)) for sp, v in sq_gp.items()}
    best = min(gp_mm, key=gp_mm.get) if gp_mm else None
    structured = max(rm["named"] - gp_mm[best], 0.0) if best else 0.0
    unnamed = {}
    if best:
        gp = gps_all[best]
        names = gp.joint_names if best == "joints" else gp.input_names
        unnamed = {"space": best, "relevance": gp.relevance,
                   "length_scales": dict(zip(names, np.asarray(gp.length_scales).tolist()))}
    pred_sq = np.sum(rec ** 2, axis=-1)
    per_fold = {k: _fold_rmse(v, folds) for k, v in sq.items()}
    if best:
        per_fold["gp"] = _fold_rmse(sq_gp[best], folds)
    per_fold["recommended"] = _fold_rmse(pred_sq, folds)
    pf = np.array(per_fold["recommended"])
    se = float(pf.std(ddof=1) / np.sqrt(len(pf))) if len(pf) > 1 else float("nan")
    # the recommended model's CV error inside / outside the fold's training joint ranges (extrapolation)
    # and the farthest a held-out row went beyond its fold's training range (in ranges): the nested prediction
    # has seen extrapolation up to there, not beyond (region_at flags validation rows that go farther)
    outside = reach > 0
    in_out = {"cv_inside_mm": rmse_mm(np.sqrt(pred_sq[~outside])), "cv_outside_mm": rmse_mm(np.sqrt(pred_sq[outside])),
              "fraction_outside": float(outside.mean()), "cv_reach_max": float(reach.max()) if reach.size else 0.0}
    region = _region(rec, S)
    rep_mm, rep_reason, rep = _repeatability(data, g, sessions, final, per_session)
    label = (model or ("named" if effects else "geometric")) + (" + GP" if gp_space else "")
    extra = {"fitted_robot": final.robot, "fitted_theta": final.theta, "fitted": final, "per_session": per_session,
             "fitted_readings": data.readings,  # the training readings (not serialised: "fitted…")
             # one session: the nested held-out errors hold nothing of what changes from one session to the next
             "training_sessions": int(np.unique(np.asarray(sessions)).size),
             "extrapolation": in_out, "region": region, "nested": bool(nested), "decisions": decisions,
             "gp_space": gp_space, "gp_held_out_ratio": {sp: {"mse_ratio": r, "se": e} for sp, (r, e) in ratios.items()}}
    if levels_cv:
        extra["levels_cv"] = levels_cv
    if model:  # a procedure's own model (e.g. prior) in the named row
        extra["model"] = model
    if rep_reason:
        extra["repeatability_reason"] = rep_reason
    return ErrorBudget(rm["nominal"], rm["geometric"], rm["named"], float(structured), float(rm["named"] - structured),
                       rep_mm, rmse_mm(np.sqrt(pred_sq)), se, label, unnamed, per_fold, gp_mm, rep, n_postures(g),
                       data.n, len(folds), level, [tuple(e) for e in effects],
                       gps_all[gp_space] if gp_space else None, extra)


def _repeatability(data, g, sessions, final, per_session):
    """``(repeatability_mm, reason it is None or None, the floor's dict)``: the spread of repeated postures
    after removing exactly what the model treats as per-session (:func:`estcal.validation.repeatability_floor`)
    — a rigid registration of every session (also with one frame for all, the floor's usual reading); with
    ``per_session="registration+points"`` also each session's own measured point on the tool, for a model whose
    sessions measure different points differs at the same posture by far more than its repeatability."""
    lab = np.asarray(sessions)
    points = per_session == "registration+points" and len(np.unique(lab)) > 1
    R_tool = None
    if points:
        R_tool = final.tool_rotations(data)
    rep = repeatability_floor(measured_points(data), g, lab, tool_rotations=R_tool)
    if rep is None:
        return None, "no posture is measured twice", None
    if points:
        return rep["registered_points_mm"], rep["registered_points_reason"], rep
    return (rep["registered_mm"] if rep["registered_mm"] is not None else rep["raw_mm"]), None, rep


def _region(e, S) -> dict:
    """The 95 % region of a new posture from the nested held-out errors ``e`` and their model covariances ``S``:
    Σ = b·S + τ² I₃ fitted by maximum likelihood (S: N·J C_θ Jᵀ; ``E|e|² = a + b·tr S``, τ² = a/3, at least 5 %
    of the held-out variance per coordinate; :func:`~estcal.discrepancy.prediction.variance_model`), beyond the
    farthest held-out leverage with the slope's upper bound (:func:`~estcal.discrepancy.prediction.slope_upper`),
    the conformal threshold of the scores."""
    floor = 0.05 * float(np.mean(np.asarray(e) ** 2))
    a, b = variance_model(e, S, tau2_floor=floor)
    tau2 = a / 3.0
    b_far = slope_upper(e, S, b, tau2_floor=floor)
    region = {"level": 0.95, "tau_mm": float(np.sqrt(tau2) * 1e3), "scale": float(b),
              "scale_far": None if not np.isfinite(b_far) else float(b_far),
              "leverage_max_m2": float(np.trace(np.asarray(S), axis1=-2, axis2=-1).max()) if np.size(e) else None,
              "variance_model": {"a_mm2": float(a * 1e6), "b": float(b)}}
    d2 = region_scores(e, region_sigma(region, S), 0.0)
    region.update({"threshold_d2": conformal_threshold(d2, 0.95), "chi2_d2": 7.814727903251178,
                   "nested_coverage_chi2": float(np.mean(d2 <= 7.814727903251178)), "n_points": int(d2.size)})
    return region


def _model_at(budget, data, errors: bool = True):
    """Errors (…, 3; None without ``errors``) of the budget's recommended model (the final fit + its GP's mean)
    at the rows of ``data`` and their parameter covariances J C_θ Jᵀ × N (…, 3, 3; N training rows). Without ``errors`` only the
    joint readings, the context and the number of points of ``data`` are used — never its measurements."""
    fs = budget.extra["fitted"]
    S = point_covariance(fs, data) * budget.n_rows
    if not errors:
        return None, S
    e = measured_points(data) - fs.predict(data)
    if budget.residual_model is not None:
        mean = residual_correction(budget.residual_model, fs.robot, fs.theta, data.readings, data.context)
        e = e - fs.rotate_to_session(data, mean)
    return e, S


def region_at(budget, data) -> dict:
    """The budget's 95 % prediction region applied to ``data`` (rows not used by the fit, e.g. a validation
    file): ``{"coverage": share of the points inside, "n_points", "rmse_mm", "predicted_mm",
    "beyond_cv_leverage": share of the points farther than any held-out point of the nested CV}`` with the
    recommended model's Σ (θ covariance of the final fit, scaled, + τ²; :func:`_region`)
    and the conformal threshold; ``predicted_mm`` is :func:`predicted_at` of its postures."""
    e, S = _model_at(budget, data)
    region = budget.extra["region"]
    return {"coverage": region_coverage(region, e, S), "n_points": int(np.prod(e.shape[:2])),
            "rmse_mm": rmse_mm(np.linalg.norm(e, axis=-1)), "predicted_mm": _predicted(budget, S),
            "beyond_cv_leverage": beyond_leverage(region, S), **reach_at(budget, data.readings)}


def reach_at(budget, readings) -> dict:
    """How far the rows ``readings`` extrapolate against what the budget's nested CV tried: ``{"reach_max":
    the farthest any joint goes beyond the training rows' range, in units of that range, "reach_joint": that
    joint, "beyond_cv_reach": share of the rows going farther than any held-out row of the nested CV went
    beyond its fold's training range}``. The prediction and the region are calibrated on the held-out errors
    (:func:`_region`): past that reach they extrapolate the variance model too. On TIAGo a halving whose new
    postures turn arm_3 2.4 ranges beyond the training range (the CV: 0.9) scores 8.1 mm for a prediction of
    3.3 — while halvings flagged for a few rows a little beyond stay predicted within 30 % (docs/real-data.md,
    "A prior instead of a level"): a flag that the prediction is untested there, not a proof that it fails."""
    d = extrapolation_distance(budget.extra["fitted_readings"], readings)
    cv = budget.extra["extrapolation"]["cv_reach_max"]
    if not d.size:
        return {"reach_max": 0.0, "reach_joint": None, "beyond_cv_reach": 0.0}
    j = int(np.argmax(d.max(0)))
    return {"reach_max": float(d.max()), "reach_joint": budget.extra["fitted_robot"].joint_names[j],
            "beyond_cv_reach": float(np.mean(d.max(1) > cv + 1e-9))}


def predicted_at(budget, targets) -> float:
    """Expected RMSE (mm) of the recommended model at the target postures ``targets`` (a Dataset: its joint
    readings, context and number of points are used, never its measurements): √mean(a + b·tr Σ_θ) with the
    variance model of the nested CV (:func:`~estcal.discrepancy.prediction.variance_model`) — larger than
    ``predicted_validation_mm`` where the targets lie farther from the training postures than the CV's
    held-out postures did."""
    return _predicted(budget, _model_at(budget, targets, errors=False)[1])


def _predicted(budget, S) -> float:
    vm = budget.extra["region"]["variance_model"]
    return predicted_rmse_at(vm["a_mm2"] * 1e-6, vm["b"], S) * 1e3


def diagnosis_budget(robot, diagnosis, **kw) -> ErrorBudget:
    """The error budget of a :class:`~estcal.discrepancy.diagnose.DiagnosisResult`: its training data as it
    prepared them, its geometric level and its named causes (``kw`` as :func:`error_budget`)."""
    effects = [(c.effect, list(c.joints), dict(c.options or {})) for c in diagnosis.causes]
    level = diagnosis.analysis.get("geometric_level", "full")
    return error_budget(robot, diagnosis.train_data, kw.pop("noise", None), level=level, effects=effects, **kw)
