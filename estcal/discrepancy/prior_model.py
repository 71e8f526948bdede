"""The MAP group-prior model: a prior instead of a level — ``estcal diagnose --geometric prior``.

The recommended procedure of :func:`estcal.discrepancy.diagnose` makes two discrete choices — the
geometric level and the named effects — and on tens of real postures both change from split to split
(docs/real-data.md, "A prior instead of a level"). This model makes neither:

* **the terms**: registration (base frame, markers / unknown tool) free; the structurally identifiable
  geometric candidates (``full``: :func:`estcal.identify.select.select_identifiable` on the model's
  columns at the registration fit) and every per-joint ``joint_compliance``, ``backlash`` and
  ``link_tilt`` candidate the data can excite (:func:`estcal.discrepancy.diagnose.default_candidates`,
  no families) — penalised: the gravity load along each joint's axis and across it;
* **the prior**: every penalised parameter ``θ_j ~ N(nominal_j, τ_j²)``, by default with one width per
  parameter — automatic relevance determination (MacKay 1994; Tipping 2001): the evidence switches off
  the terms the data do not support, one by one — or (``widths="group"``) one width per group of like
  parameters (lengths, angles, joint offsets, each kind of effect;
  :func:`estcal.estimate.regularize.prior_groups`); the widths by type-II maximum likelihood — the
  evidence of the linearised model (MacKay 1992, *Neural Comput.* 4:415; Bishop 2006 eq. 3.86) —
  alternating with the MAP fit (:func:`estcal.estimate.regularize.fit_group_prior`). Measured at new
  postures (docs/real-data.md, "A prior instead of a level"): on TIAGo the tilt terms and the widths per
  parameter each lower the error on 5 of 6 posture-disjoint halvings;
* **the widths' criterion** of the command (``CRITERION``): the evidence's widths times one common
  multiplier chosen by leave-one-posture-out CV (``evidence+cv``; ``criterion="evidence"`` for the evidence
  alone, the default of :func:`prior_fit` and :func:`fit_prior`);
* **several sessions**: in :func:`diagnose_prior` each further session's measuring frame is registered by the
  fit (``session_frames="per-session"``, the default; ``"one"``: one frame for all, as every other
  ``--geometric`` choice); in :func:`fit_prior` with ``per_session="registration"``. Either way a rigid
  transform by alternation (:func:`estcal.discrepancy.stages.fit_stage_sessions`).

For accuracy at new postures the recommended command is ``estcal diagnose S1 S2 --geometric prior
--residual-model gp-joints --folds 10`` (docs/real-data.md, "The recommended command for new postures").

Nothing is chosen from the data but the widths, so the nested prediction of the error budget is the
posture-grouped CV of this fit with the widths refitted on every fold's training rows
(:class:`estcal.discrepancy.prediction.Procedure` with ``fit=``). A term of this model is not a named
cause: its amplitude is shrunk, not tested.

When the data excite no effect term (every gravity load zero, or of one sign for backlash without
approach columns), the model is the geometric prior alone, with a warning — still a model with a
prior on the geometry; its note says so.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, fields

import numpy as np

from estcal.base.errors import EstcalWarning
from estcal.discrepancy.diagnose import (DiagnosisResult, _attach_budget, _geometric_model, _Model, _n_sessions,
                                         _noise_components, _prepare_data, _result, _scores, default_candidates)
from estcal.discrepancy.geometric import geometric_candidates, gravity_ready, weighted_system
from estcal.discrepancy.residual import residual_choice
from estcal.discrepancy.stages import FittedStage, fit_stage, fit_stage_sessions, measured_points
from estcal.estimate.regularize import fit_group_prior, prior_groups
from estcal.identify.select import select_identifiable
from estcal.methods import NoiseModel, Problem
from estcal.validation import grouped_folds, posture_groups

__all__ = ["EFFECTS", "WIDTHS", "WIDTH_CHOICES", "width_groups", "prior_model", "prior_fit", "fit_prior", "prior_summary",
           "diagnose_auto", "SESSION_FRAMES", "CRITERION",
           "width_line", "diagnose_prior", "PriorDiagnosisResult"]

#: the candidate effects of the prior model (the diagnosis's per-joint candidates of these kinds): the gravity
#: load along each joint's axis (compliance, backlash) and across it (link tilt, docs/effects.md)
EFFECTS = ("joint_compliance", "backlash", "link_tilt")
#: one prior width per parameter by default (automatic relevance determination; "group": one per kind)
WIDTHS = "parameter"
WIDTH_CHOICES = ("parameter", "group")
#: the widths' criterion of ``estcal diagnose --geometric prior`` and ``auto`` (the evidence's widths times one
#: multiplier by leave-one-posture-out CV; docs/real-data.md, "The recommended command for new postures")
CRITERION = "evidence+cv"
#: the measuring frames of several sessions under ``--geometric prior``
SESSION_FRAMES = ("per-session", "one")

#: SI unit of an effect group's parameters on a (revolute, prismatic) joint (estcal/effects/library.py)
_EFFECT_UNITS = {"compliance": ("rad/(N·m)", "m/N"), "backlash": ("rad", "m"), "tilt": ("rad/(N·m)", "rad/(N·m)")}
_GROUP_UNITS = {"length": "m", "angle": "rad", "offset": "rad", "offset_length": "m", "gain": "1"}


def prior_model(robot, data, noise, effects=EFFECTS):
    """``(problem, free, penalised)`` at the registration fit: the robot with the candidate effects added,
    the registration parameters free, the structurally identifiable geometric candidates and the effect
    parameters penalised (module docstring)."""
    rb0, theta, reg, _ = fit_stage(robot, data, noise, "nominal")
    rb, _ = gravity_ready(rb0, theta, robot.params.values)
    for c in default_candidates(rb, data, effects=list(effects), families=False) if effects else []:
        # per-joint terms only: when no joint qualifies the screening offers the effect on the whole arm, whose
        # torques are then zero (no gravity) or of one sign (backlash) — nothing the data excite
        if c.joints:
            rb = rb.add_effect(c.make(rb))
    problem = Problem(rb, [(None, data, noise)])
    cands = geometric_candidates(rb)
    _, A, _ = weighted_system(problem, rb.params.values, cands)
    geo = select_identifiable(A, names=cands).identifiable
    eff = [n for n, k in zip(rb.params.names, rb.params.kinds) if k == "effect"]
    free = list(dict.fromkeys(list(reg) + geo + eff))
    penalised = [n for n in free if n not in set(reg)]
    return problem, free, penalised


def prior_fit(noise, criterion: str = "evidence", effects=EFFECTS, widths: str = WIDTHS):
    """The model's fit as a callable ``fit(robot, data) -> FittedStage`` — what
    :func:`~estcal.discrepancy.stages.fit_stage_sessions` and the budget's ``Procedure(fit=…)`` replay on any
    rows: :func:`prior_model` and :func:`~estcal.estimate.regularize.fit_group_prior` on those rows only (the
    widths included). The fitted result carries its widths (``extra["fold_decision"]``); the last
    :class:`~estcal.estimate.regularize.GroupPrior` is ``fit.last``."""

    def fit(robot, data):
        problem, free, pen = prior_model(robot, data, noise, effects)
        gp = fit_group_prior(problem, free, pen, width_groups(pen, widths), criterion=criterion)
        gp.result.extra["fold_decision"] = {"widths_si": gp.to_dict()["widths"],
                                            "sigma0": float(gp.sigma0),
                                            "effective_parameters": _effective(gp)}
        fit.last = gp
        return FittedStage(problem.robot, gp.result.theta, free, gp.result)

    fit.last = None
    return fit


def width_groups(penalised, widths: str):
    """The prior groups: ``"group"`` — one width per kind of parameter (:func:`prior_groups`); ``"parameter"``
    — one width per parameter (automatic relevance determination: MacKay 1994, *ASHRAE Trans.* 100:1053;
    Tipping 2001, *JMLR* 1:211), the evidence then shrinks each term separately."""
    if widths not in WIDTH_CHOICES:
        raise ValueError(f"widths must be one of {WIDTH_CHOICES}, got {widths!r}")
    return {n: n for n in penalised} if widths == "parameter" else None


def fit_prior(robot, data, noise, criterion: str = "evidence", per_session=None, effects=EFFECTS, n_alt: int = 3,
              widths: str = WIDTHS):
    """The model of the module docstring on ``data`` → ``(FittedStage, GroupPrior)``; with ``per_session =
    "registration"``, every session after the first gets a rigid transform onto the first (the alternation of
    :func:`estcal.discrepancy.stages.fit_stage_sessions`, ``n_alt`` rounds)."""
    fit = prior_fit(noise, criterion, effects, widths)
    fs = fit_stage_sessions(robot, data, noise, "named", per_session=per_session, n_iter=n_alt, fit=fit)
    return fs, fit.last


def _effective(gp) -> float:
    return float(gp.result.extra["prior"]["effective_parameters"])


def _group_unit(group, names, robot) -> tuple[str, str]:
    """``(SI unit, display unit)`` of a prior group; an effect group over revolute and prismatic joints has
    two units for its one width (both listed); a group of one parameter (``widths="parameter"``) has the unit
    of that parameter's kind."""
    if group not in _GROUP_UNITS and group not in _EFFECT_UNITS and len(names) == 1:
        group = prior_groups(robot, names)[names[0]]
    if group in _GROUP_UNITS:
        si = _GROUP_UNITS[group]
        return si, {"m": "mm", "rad": "mrad", "1": ""}[si]
    if group not in _EFFECT_UNITS:
        return "SI", "SI"
    types = dict(zip(robot.joint_names, robot.joint_types))
    si = list(dict.fromkeys(_EFFECT_UNITS[group][types.get(n.split("_", 1)[1]) == "prismatic"] for n in names))
    return " | ".join(si), " | ".join("m" + u for u in si)


def prior_summary(gp, robot, n_free: int) -> dict:
    """The prior model's figures as plain data: every group's width in SI and display units (mm, mrad,
    mrad/(N·m) …: SI × 1000, ``display_unit``) with its number of parameters, σ0 (the fitted scale of the
    weighted residual, 1 = the noise model), the effective number of parameters ``tr(Σ HᵀWH)``, the log
    evidence and the effect terms of the model."""
    d = gp.to_dict()
    members = {}
    for n, g in gp.groups.items():
        members.setdefault(g, []).append(n)
    widths = {}
    per_parameter = all(members[g] == [g] for g in d["widths"])
    for g, w in d["widths"].items():
        si, disp = _group_unit(g, members[g], robot)
        factor = 1.0 if disp == "SI" else 1e3
        widths[g] = {"width": w, "unit": si, "width_display": w * factor, "display_unit": disp,
                     "n_parameters": len(members[g])}
        if per_parameter:
            widths[g]["kind"] = prior_groups(robot, members[g])[g]
    effects = {}
    for e in robot.effects:
        effects.setdefault(e.name, []).extend(getattr(e, "joints", None) or [])
    return {"model": f"MAP, a nominal-centred Gaussian prior per {'parameter' if per_parameter else 'parameter group'} "
                     "(docs/real-data.md, 'A prior instead of a level')",
            "criterion": d["criterion"], "widths_per": "parameter" if per_parameter else "group", "widths": widths,
            "sigma0": d["sigma0"], "log_evidence": d["log_evidence"],
            "rounds": d["rounds"], "n_parameters": int(n_free), "n_penalised": d["n_penalised"],
            "effective_parameters": _effective(gp),
            "effects": [{"effect": k, "joints": list(v)} for k, v in effects.items()]}


def width_line(prior: dict) -> str:
    """The widths of :func:`prior_summary` as one text line (display units); with one width per parameter, per
    kind of parameter the range of its widths and how many the evidence switched off (below 1 % of the kind's
    largest: the term is held at its nominal value)."""
    if prior.get("widths_per") != "parameter":
        return ", ".join(f"{g} {w['width_display']:.3g} {w['display_unit']}".rstrip()
                         for g, w in prior["widths"].items())
    kinds = {}
    for w in prior["widths"].values():
        kinds.setdefault((w["kind"], w["display_unit"]), []).append(w["width_display"])
    parts = []
    for (kind, unit), v in kinds.items():
        v = np.asarray(v)
        off = int(np.sum(v < 1e-2 * v.max()))
        span = f"{v[0]:.2g}" if v.size == 1 else f"{v.min():.2g}–{v.max():.2g}"
        line = f"{kind} ×{v.size} {span} {unit}".rstrip()
        parts.append(line + (f" ({off} off)" if off else ""))
    return ", ".join(parts)


@dataclass
class PriorDiagnosisResult(DiagnosisResult):
    """A :class:`~estcal.discrepancy.diagnose.DiagnosisResult` whose extended model is the prior model, with its
    summary ``prior`` (:func:`prior_summary` + training and CV RMSE) in the text and the JSON."""

    prior: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dict(super().to_dict(), prior=self.prior)

    def __str__(self) -> str:
        lines = super().__str__().split("\n")
        p = self.prior
        extra = [f"  prior model: {p['n_parameters']} parameters ({p['n_penalised']} under the prior, "
                 f"{p['effective_parameters']:.1f} effective), σ0 {p['sigma0']:.3g}, training RMSE "
                 f"{p['train_rmse_mm']:.3f} mm — the 'extended' rows below",
                 f"  widths ({p['criterion']}): {width_line(p)}"]
        if p["effects"]:
            extra.append("  effect terms under the prior: " + "; ".join(
                f"{e['effect']} ({len(e['joints'])} joints)" for e in p["effects"]))
        for sv, r in ((p.get("session_frames") or {}).get("sessions") or {}).items():
            extra.append(f"  session {sv} registered onto the first: {r['rotation_mrad']:.2f} mrad, "
                         f"{np.linalg.norm(r['translation_mm']):.2f} mm (the model is in the first session's frame; "
                         f"validation files are scored in it)")
        if p.get("note"):
            extra.append(f"  note: {p['note']}")
        return "\n".join(lines[:1] + extra + lines[1:])

    def save_model(self, path, provenance: dict | None = None):
        """The saved model (geometry + every effect term at the MAP estimate) with the prior's widths in its
        calibration block."""
        keep = ("model", "criterion", "widths_per", "widths", "sigma0", "effective_parameters")
        return super().save_model(path, dict(provenance or {}, prior={k: self.prior[k] for k in keep}))


def _once_per_rows(fit):
    """``fit`` (:func:`prior_fit`) fitting each set of rows once: the diagnosis's CV and the budget's outer folds
    are the same posture-grouped folds (the same groups, ``k`` and seed), so the budget's fits of the model on
    their training rows — and on all rows — are those already made (half the command's CPU time on TIAGo)."""
    done = {}

    def once(robot, data):
        key = (id(robot), data.readings.tobytes(), measured_points(data).tobytes(),
               tuple((k, np.asarray(v).tobytes()) for k, v in sorted(data.context.items())))
        if key not in done:
            done[key] = fit(robot, data)
            once.last = fit.last
        return done[key]

    once.last = None
    return once


def _cv(robot, data, fit, folds) -> tuple[float, float]:
    """(RMSE, max) in mm of the point-error norms at the held-out postures of ``folds``, the model (and its
    widths) refitted on each fold's training rows."""
    meas = measured_points(data)
    err = np.zeros(meas.shape[:2])
    for test in folds:
        fs = fit(robot, data.subset(np.setdiff1d(np.arange(data.n), test)))
        err[test] = np.linalg.norm(meas[test] - fs.predict(data.subset(test)), axis=-1)
    return float(np.sqrt(np.mean(err ** 2)) * 1e3), float(err.max() * 1e3)


def diagnose_prior(robot, data, validate=(), candidates=None, k_folds: int = 5, noise=None, rng=0, robot_spec=None,
                   geometric: str = "prior", approach_from_order: bool = False, session_time: bool = True,
                   posture_tol=(1e-3, 1e-3), budget: bool = False, residual_model: str | None = None,
                   criterion: str = CRITERION, effects=EFFECTS, ident_tol: float = 1e-4, cv_max_iter: int = 30,
                   alpha=None, max_effects=None, widths: str = WIDTHS, fit=None,
                   session_frames: str = "per-session"):
    """:func:`estcal.discrepancy.diagnose` with the MAP group-prior model as the recommended model
    (``geometric="prior"``; module docstring): no forward selection — ``candidates``, ``alpha`` and
    ``max_effects`` are not used, and candidates given are refused.

    The ``geometric`` rows of the result are the ``full`` geometric fit (as the default diagnosis's), the
    ``extended`` rows the prior model: training RMSE, posture-grouped CV (the widths refitted on each fold)
    and validation (``seen`` / ``new`` postures). ``result.prior``: :func:`prior_summary` plus the training
    and CV RMSE (mm). With ``budget`` (or ``residual_model="gp"``) the error budget's nested prediction
    refits the model, its widths included, on every outer fold's training rows. Returns a
    ``DiagnosisResult`` (with ``prior``); saved, compensated and exported like any diagnosis model. ``fit``:
    the model's fit (:func:`prior_fit` made once per rows) when the caller has one with fits already made on
    these rows (:func:`diagnose_auto`'s level choice, the same folds). ``session_frames``: with several
    sessions, ``"per-session"`` (default) gives every session after the first its own rigid registration of
    the measuring frame, fitted with the model by alternation
    (:func:`~estcal.discrepancy.stages.fit_stage_sessions`) in every fit — all rows, each CV fold, each outer
    fold of the budget — and the model is the first session's frame (validation files are scored in it);
    ``"one"``: one measuring frame for all.
    """
    if geometric != "prior":
        raise ValueError(f"diagnose_prior fits the prior model (geometric='prior'), got {geometric!r}")
    if candidates:
        raise ValueError(f"the prior model keeps every excitable {', '.join(effects)} term under its prior "
                         "and selects no effect: give no candidates (docs/real-data.md, 'A prior instead of a level')")
    robot, robot_spec, data, validate, sessions = _prepare_data(robot, data, validate, robot_spec,
                                                                approach_from_order, session_time)
    nm = NoiseModel(known=False) if noise is None else NoiseModel.parse(noise, known=True)
    groups = posture_groups(data.readings, robot.joint_types, *posture_tol)
    folds = grouped_folds(groups, k_folds, rng)
    # the reference: the full geometric fit and its residual analysis, as the default diagnosis reports them
    geo, gdropped, lumped, tau, analysis, _ = _geometric_model(robot, data, nm, None, ident_tol, "full", folds,
                                                               cv_max_iter)
    analysis["geometric_level"] = "full"
    width_groups([], widths)  # refuse an unknown choice before any fit
    if session_frames not in SESSION_FRAMES:
        raise ValueError(f"session_frames must be one of {SESSION_FRAMES}, got {session_frames!r}")
    per = "registration" if session_frames == "per-session" and _n_sessions(data) > 1 else None
    fit = fit or _once_per_rows(prior_fit(nm, criterion, effects, widths))
    sfit = _sessions_fit(fit, nm, per)
    fs = sfit(robot, data)
    gp = fit.last
    # every row in the first session's frame: the one robot model describes them all (nothing moves with one frame)
    data_c = fs.common_data(data)
    problem = Problem(fs.robot, [(t.method, data_c, t.noise) for t in geo.problem.terms])
    final = _Model(problem, fs.theta.copy(), list(fs.free), float(gp.result.chi2), _effective(gp),
                   _cv(robot, data, sfit, folds), gp.result)
    res = _result(robot, robot_spec, data, validate, sessions, nm, geo, final, [], [], [], analysis, gdropped,
                  lumped, "prior", approach_from_order, session_time)
    if per:  # the training figures of the model with each session's registration
        tr = _scores(fs.robot, fs.theta, [data_c])
        res.rmse_mm["extended"]["train"], res.max_mm["extended"]["train"] = tr
        res.model["residual"].update(rmse_mm=tr[0], max_mm=tr[1])
    prior = dict(prior_summary(gp, fs.robot, len(fs.free)), train_rmse_mm=res.rmse_mm["extended"]["train"],
                 cv_rmse_mm=final.cv[0], note=None, session_frames=_session_frames(fs, per))
    if not prior["effects"]:
        prior["note"] = (f"the data excite no {' or '.join(effects)} term (every gravity torque is zero, or of one "
                         f"sign for backlash without approach columns): the prior is on the geometry alone")
        warnings.warn(f"--geometric prior: {prior['note']}", EstcalWarning, stacklevel=2)
    out = PriorDiagnosisResult(**{f.name: getattr(res, f.name) for f in fields(res)}, prior=prior)
    out.verdict = _verdict(out, prior)
    # REML treats the fit's parameters as unpenalised, which the prior model's are not (its 50-odd terms would
    # take the residual's degrees of freedom): the noise components of the geometric fit's residual
    out.measurement_noise = _noise_components(geo)
    out.figure_inputs = (geo.problem, geo.theta, analysis, tau, robot.name, (final.problem, final.theta))
    if budget or residual_model:
        _budget(out, robot, data, nm, fit, k_folds, rng, posture_tol, residual_model, per)
    return out




def _sessions_fit(fit, nm, per):
    """``fit`` (one frame) with each further session's rigid registration fitted by alternation when ``per``
    (:func:`~estcal.discrepancy.stages.fit_stage_sessions`, its default rounds — as the budget runs it, so the
    shared fits of the alternation are made once per rows); ``fit`` itself otherwise."""
    if not per:
        return fit

    def sessions_fit(robot, data):
        return fit_stage_sessions(robot, data, nm, "named", per_session=per, fit=fit)

    return sessions_fit


def _session_frames(fs, per) -> dict:
    """``{"frames": "per-session" | "one", "sessions": {label: {"rotation_mrad", "translation_mm"}}}``: each
    further session's registration onto the first (rotation angle and translation)."""
    out = {"frames": "per-session" if per else "one", "sessions": {}}
    for sv, (R, t, _) in fs.sessions.items():
        ang = float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
        label = str(int(sv)) if isinstance(sv, (int, float, np.number)) and float(sv).is_integer() else str(sv)
        out["sessions"][label] = {"rotation_mrad": ang * 1e3, "translation_mm": (np.asarray(t) * 1e3).tolist()}
    return out


def diagnose_auto(robot, data, validate=(), k_folds: int = 5, noise=None, rng=0, robot_spec=None,
                  approach_from_order: bool = False, session_time: bool = True, posture_tol=(1e-3, 1e-3),
                  budget: bool = False, residual_model: str | None = None, criterion: str = CRITERION,
                  widths: str = WIDTHS, **kw):
    """``estcal diagnose --geometric auto``: the level chosen by posture-grouped CV among the MAP prior model
    and the levels ``joint_offset``, ``aic``, ``full`` — the prior model preferred, a level taken only when its
    CV error is lower by more than one standard error (:func:`estcal.discrepancy.prediction.choose_level`,
    :mod:`estcal.discrepancy.prediction` says why). The prior model chosen: :func:`diagnose_prior`, its causes
    not named; a level chosen: :func:`estcal.discrepancy.diagnose` at that level (``kw``: its further options,
    the candidates among them). Either way the error budget's nested prediction replays the same choice, the
    prior model among the candidates, in every outer fold (a fold that chooses a level names its causes with
    the diagnosis's selector; when the prior model was chosen on all rows there is none, and such a fold fits
    the level alone). The CV of every candidate is in ``analysis["geometric_level_cv_mm"]`` and in the verdict.
    """
    from estcal.discrepancy.diagnose import diagnose
    from estcal.discrepancy.prediction import PRIOR, Procedure, choose_level

    rb, spec, d, _, _ = _prepare_data(robot, data, validate, robot_spec, approach_from_order, session_time)
    nm = NoiseModel(known=False) if noise is None else NoiseModel.parse(noise, known=True)
    width_groups([], widths)  # refuse an unknown choice before any fit
    fit = _once_per_rows(prior_fit(nm, criterion, EFFECTS, widths))
    groups = posture_groups(d.readings, rb.joint_types, *posture_tol)
    level, cv = choose_level(rb, d, nm, groups, k_folds, rng, fits={PRIOR: fit})
    common = dict(validate=validate, k_folds=k_folds, noise=noise, rng=rng, robot_spec=spec,
                  approach_from_order=approach_from_order, session_time=session_time, posture_tol=posture_tol)
    gp = residual_choice(residual_model)[0]
    if level == PRIOR:
        if kw.get("candidates"):
            raise ValueError("--geometric auto chose the prior model, which selects no effect: give no candidates")
        res = diagnose_prior(rb, data, **common, criterion=criterion, widths=widths, fit=fit, session_frames="one")
        proc = Procedure(level="auto", prior_fit=fit, gp=gp, k_inner=k_folds)
        effects = ()
    else:
        res = diagnose(rb, data, geometric=level, **common, **kw)
        effects = tuple((c.effect, list(c.joints), dict(c.options or {})) for c in res.causes)
        proc = Procedure(level="auto", select_effects=res.selector, effects=() if res.selector else effects,
                         gp=gp, k_inner=k_folds, prior_fit=fit)
    res.analysis["geometric_level_cv_mm"] = {c: v["cv_mm"] for c, v in cv.items()}
    res.analysis["geometric_choice"] = {"chosen": level, "cv": cv}
    res.verdict += (" Chosen by --geometric auto (posture-grouped CV, mm, the prior model preferred within one "
                    "standard error): " + ", ".join(f"{c} {v['cv_mm']:.3g} ± {v['se_mm']:.2g}" for c, v in cv.items())
                    + f" → {level}.")
    if budget or residual_model:
        # the rows as prepared here (several sessions stacked), which the diagnosis prepared alike
        _attach_budget(res, rb, d, nm, proc, level, effects, k_folds, rng, posture_tol, residual_model)
    return res


def _verdict(res, prior) -> str:
    g, x = res.rmse_mm["geometric"], res.rmse_mm["extended"]
    per = "one width per parameter" if prior.get("widths_per") == "parameter" else "one width per group"
    how = "the evidence" if prior.get("criterion") != "evidence+cv" else "the evidence, scaled by posture-grouped CV"
    frames = prior.get("session_frames") or {}
    reg = f", {len(frames['sessions'])} further session(s) registered" if frames.get("sessions") else ""
    s = (f"Prior model (MAP, {prior['n_penalised']} parameters under nominal-centred priors, {per} "
         f"by {how}{reg}; no cause is named: a term of this model is shrunk, not tested). RMSE train "
         f"{g['train']:.3g} → {x['train']:.3g} mm, CV {g['cv']:.3g} → {x['cv']:.3g} mm")
    if g["validation"] is not None:
        s += f", validation {g['validation']:.3g} → {x['validation']:.3g} mm"
    return s + " (geometric: the full level)."


def _budget(res, robot, data, nm, fit, k_folds, rng, posture_tol, residual_model, per=None) -> None:
    """The error budget of the prior model: its nested prediction refits the model, widths included (and each
    session's registration with ``per``), on every outer fold's training rows (the folds of the diagnosis's
    CV: ``fit`` returns those fits again)."""
    from estcal.discrepancy.prediction import Procedure

    proc = Procedure(level="full", fit=fit, label="prior",
                     gp=residual_choice(residual_model)[0], k_inner=k_folds)
    _attach_budget(res, robot, data, nm, proc, "full", (), k_folds, rng, posture_tol, residual_model, per)
