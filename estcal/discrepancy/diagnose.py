"""Diagnose measured data: where the geometric model fails, which physical effect explains it, and the gain.

Workflow of :func:`diagnose` (docs/discrepancy.md):

1. **Geometric fit** — registration, then every identifiable base, marker/tool,
   joint-offset and link parameter (:func:`~estcal.discrepancy.geometric.fit_geometric`);
   no joint gains (an encoder gain error is a candidate effect, so it gets named).
2. **Residual analysis** — partial joint residuals against joint angles, gravity
   torques, their sign, time/temperature, workspace position; χ² against the
   noise; harmonics (:mod:`estcal.discrepancy.analysis`); figures from :meth:`DiagnosisResult.figures`.
3. **Candidates** — every registered effect (:mod:`estcal.effects`, users add
   theirs with :func:`~estcal.effects.register_effect`) on every joint it applies
   to (harmonic orders 1, 2, 3 as separate candidates; drift with ``t0`` = first
   time stamp; thermal expansion when a time/temperature column exists).
4. **Forward selection** — at each step every candidate is screened by the exact
   least-squares gain of its columns projected orthogonally to the current
   model's columns (the model is linear in the effect parameters; the projection
   also gives the identifiability check: a column whose orthogonal part is below
   ``regroup_tol`` of its norm *regroups* into parameters already in the model,
   so the effect cannot be "found"). The best ``n_refit`` are refitted by
   Levenberg–Marquardt; the best by BIC is accepted when

   * ΔBIC < 0, with BIC = χ² + p ln M (known noise) or M ln(RSS/M) + p ln M;
   * its significance test passes at the family-wise level ``alpha``
     (Bonferroni over the candidates screened at this step): likelihood ratio
     Δχ² ~ χ²_k when the noise is known, the nested F test
     F = (ΔRSS/k) / (RSS₁/(M − p₁)) ~ F(k, M − p₁) otherwise;
   * it explains at least ``min_explained`` of the residual left above the noise
     floor (χ² − dof with known noise; the whole residual otherwise), so a
     significant but marginal proxy of an out-of-library error is not named;
   * the k-fold cross-validated RMSE decreases.

5. **Output** — :class:`DiagnosisResult`: named causes with joints, parameter
   estimates ± std, ΔBIC, the fraction of the geometric residual variance each
   explains, and RMSE / max of the geometric and extended models on the training
   data, in cross-validation and on validation data.

References: Schwarz (1978) for BIC; the nested F test (e.g. Seber & Lee,
*Linear Regression Analysis*, §4.3); GECARO App. III for the QR identifiability.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from estcal.base.atomic import refuse_input
from estcal.base.jsonio import write_json
from estcal.base.progress import progress
from estcal.effects import EFFECTS, make_effect
from estcal.effects.library import across_axis_moments
from estcal.estimate import calibrate_lsq
from estcal.estimate.result import pose_errors
from estcal.io.prepare import derive_approach, prepare_data, with_effect_context
from estcal.io.robotfile import load_robot, robot_to_dict
from estcal.io.savedmodel import save_diagnosis
from estcal.methods import NoiseModel, Problem
from estcal.validation import grouped_folds, posture_groups

from .analysis import residual_analysis, residual_figures
from .geometric import fit_geometric, geometric_candidates, gravity_ready, orthonormal_basis, weighted_system
from .stability import (TIME_EFFECTS, LinearCandidates, cause_key, fold_selections, folds_naming,
                        information_criterion, joint_votes, significance, stable_selection)

__all__ = ["Candidate", "Cause", "DiagnosisResult", "diagnose", "default_candidates", "cross_validate"]


@dataclass
class Candidate:
    """One candidate extension: registered effect ``effect`` on ``joints`` with ``options``."""

    effect: str
    joints: list | None = None
    options: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        j = ",".join(self.joints) if self.joints else "arm"
        o = "".join(f"[{k}={v}]" for k, v in self.options.items() if k in ("orders", "scope"))
        return f"{self.effect}{o}({j})"

    def make(self, robot):
        return make_effect(self.effect, robot, joints=self.joints, **self.options)

    def make_names(self, robot) -> list:
        """Parameter names this candidate would add (empty if it cannot be built)."""
        try:
            return list(self.make(robot).param_names)
        except (ValueError, TypeError):
            return []

    def to_dict(self) -> dict:
        return {"effect": self.effect, "joints": self.joints, "options": _plain(self.options)}


def _n_sessions(data) -> int:
    """Sessions stacked in ``data`` (its ``session`` column; 1 without one)."""
    lab = data.columns.get("session")
    return 1 if lab is None else len(np.unique(lab))


def _is_family(entry) -> bool:
    """A screening-table entry for one effect over several joints."""
    return bool(entry.get("joints")) and len(entry["joints"]) > 1


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def default_candidates(robot, data, effects: Sequence[str] | None = None, harmonic_orders=(1, 2, 3),
                       families: bool = True):
    """Candidates from the effect registry for ``robot`` and ``data``.

    Per joint for effects that take joints and, with ``families``, the whole
    family once more as one candidate over all its eligible joints (a compound
    effect — e.g. every joint a little compliant — appears as several weak
    per-joint terms, each below the significance threshold, whose sum is not:
    the group's likelihood-ratio test with k degrees of freedom finds it). Once
    for whole-arm effects (those that refuse a joint list); thermal expansion in
    both forms, whole arm and links only (``scope``). Time/temperature effects
    only when the data have the column they need; gravity effects only on joints
    the data load. With ``effects=None``, the registered effects that
    are screened by default (``link_tilt`` is not: ask for it by name).
    """
    # effects that ask not to be screened by default (a new kind, measured on request: ``link_tilt``)
    names = [n for n, f in EFFECTS.items() if getattr(f, "screened_by_default", True)] if effects is None \
        else list(effects)
    unknown = [e for e in names if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; registered: {', '.join(sorted(EFFECTS))} (docs/effects.md)")
    ctx = data.context
    tau = None
    if any(n in ("joint_compliance", "backlash") for n in names):
        tau = robot.gravity_torques(data.readings, context=ctx)
        big = max(float(np.abs(tau).max()), 1e-300)
    m_across = None
    if "link_tilt" in names:
        m_across = np.linalg.norm(across_axis_moments(robot, data.readings, context=ctx)[0], axis=-1)  # (N, n)
    out = []
    # several sessions: time runs from each session's mean (_prepare_data), so a time effect is zero there
    # and never shifts one session against another
    t_zero = 0.0 if _n_sessions(data) > 1 else (float(np.min(ctx["t"])) if "t" in ctx else 0.0)
    for name in names:
        if name == "drift":
            if "t" not in ctx:
                continue
            opts = {"t0": t_zero}  # 0 with session time
        elif name == "thermal_expansion":
            if "temperature" in ctx:
                opts = {"reference": float(np.mean(ctx["temperature"]))}
            elif "t" in ctx:
                opts = {"t_reference": t_zero}
            else:
                continue
            out.append(Candidate(name, None, opts))
            out.append(Candidate(name, None, dict(opts, scope="links")))
            continue
        else:
            opts = {}
        variants = [dict(opts, orders=[k]) for k in harmonic_orders] if name == "gear_harmonic" else [opts]
        per_joint = []
        for ji, j in enumerate(robot.joint_names):
            if name == "backlash" and "approach_" + j in ctx:
                if not np.any(ctx["approach_" + j]):
                    continue
            elif name in ("joint_compliance", "backlash") and tau is not None:
                # a torque that is numerically zero (vertical axis) or of constant sign (backlash)
                # gives a column that is noise or an offset: not a candidate
                t = tau[:, ji]
                if np.abs(t).max() <= 1e-9 * big:
                    continue
                if name == "backlash" and "approach_" + j not in ctx and (np.all(t > 0) or np.all(t < 0)):
                    continue
            elif name == "link_tilt" and np.abs(m_across[:, ji]).max() <= 1e-9 * max(float(m_across.max()), 1e-300):
                continue  # no moment across this axis (no mass beyond it, or no gravity)
            for o in variants:
                try:
                    Candidate(name, [j], o).make(robot)
                except (ValueError, TypeError):
                    continue
                per_joint.append(Candidate(name, [j], o))
        if per_joint:
            out += per_joint
            if families:
                for o in variants:
                    js = [c.joints[0] for c in per_joint if c.options == o]
                    if len(js) > 1:
                        out.append(Candidate(name, js, o))
        else:
            try:
                Candidate(name, None, opts).make(robot)
                out.append(Candidate(name, None, opts))
            except (ValueError, TypeError):
                continue
    return out


@dataclass
class Cause:
    """A named non-geometric effect accepted by the selection."""

    effect: str
    joints: list
    parameters: dict  # name -> {"estimate", "std"}
    delta_bic: float
    test: str
    statistic: float
    p_value: float
    explained_fraction: float  # of the geometric model's residual (weighted RSS)
    explained_excess_fraction: float  # of the residual above the noise floor left at this step
    cv_rmse_mm_before: float
    cv_rmse_mm_after: float
    options: dict = field(default_factory=dict)
    alternatives: list = field(default_factory=list)  # competing candidates within ΔBIC 10
    folds_naming: int | None = None  # posture-grouped folds whose selection names it too (stability rule)
    k_folds: int | None = None

    def to_dict(self) -> dict:
        return _plain({"alternatives": self.alternatives, "effect": self.effect, "joints": list(self.joints), "parameters": self.parameters,
                       "delta_bic": self.delta_bic, "test": self.test, "statistic": self.statistic,
                       "p_value": self.p_value, "explained_fraction": self.explained_fraction,
                       "explained_excess_fraction": self.explained_excess_fraction,
                       "cv_rmse_mm_before": self.cv_rmse_mm_before, "cv_rmse_mm_after": self.cv_rmse_mm_after,
                       "options": self.options, "folds_naming": self.folds_naming, "k_folds": self.k_folds})

    def describe(self) -> str:
        ps = ", ".join(f"{n} = {v['estimate']:.4g} ± {v['std']:.2g}" for n, v in self.parameters.items())
        j = ", ".join(self.joints) if self.joints else "whole arm"
        s = (f"{self.effect} on {j}: {ps}; ΔBIC {self.delta_bic:.1f}, {self.test} p = {self.p_value:.2g}, "
             f"explains {100 * self.explained_fraction:.0f}% of the geometric residual")
        if self.k_folds:
            s += f"; named in {self.folds_naming} of {self.k_folds} posture-grouped folds"
        if self.alternatives:
            s += "; hard to tell from " + ", ".join(f"{a['candidate']} (ΔBIC +{a['delta_bic_difference']:.1f})"
                                                  for a in self.alternatives)
        return s


@dataclass
class DiagnosisResult:
    """What :func:`diagnose` found. ``to_dict()`` has at least the keys ``causes``,
    ``verdict`` and ``rmse_mm`` ({``geometric``, ``extended``} × {``train``, ``cv``, ``validation``})."""

    causes: list
    verdict: str
    rmse_mm: dict
    max_mm: dict
    analysis: dict
    steps: list
    noise: dict
    geometric_free: list
    geometric_dropped: list
    model: dict
    geometric_model: dict
    lumped_masses: bool
    report_files: list = field(default_factory=list)
    located: list = field(default_factory=list)  # structure located on a joint but not named
    robot: object = field(default=None, repr=False)  # the extended robot at the estimate
    geometric_robot: object = field(default=None, repr=False)
    # the final joint fit, for save_model: covariance (SI) of ``covariance_names``, σ0, the data
    covariance: object = field(default=None, repr=False)
    covariance_names: list = field(default_factory=list, repr=False)
    sigma0: float = float("nan")
    train_data: object = field(default=None, repr=False)
    validation_data: list = field(default_factory=list, repr=False)
    # the error budget (estcal.discrepancy.budget, posture-grouped CV) when asked for, and its residual GP
    budget: dict | None = None
    residual_model: object = field(default=None, repr=False)
    # the stability rule (causes named in most posture-grouped folds) and the REML noise per kind and axis
    stability: dict | None = None
    measurement_noise: dict | None = None
    # the diagnosis's cause selection on any subset of its rows (linearised; the nested prediction replays it)
    selector: object = field(default=None, repr=False)
    # what :meth:`figures` draws from: (geometric problem, θ, analysis, gravity torques, title, extended fit)
    figure_inputs: tuple = field(default=None, repr=False)

    def figures(self) -> dict:
        """The residual figures, ``{file name: matplotlib Figure}``
        (:func:`estcal.discrepancy.analysis.residual_figures`), and the error budget's when computed;
        written by ``--report DIR``."""
        out = {}
        if self.figure_inputs is not None:
            problem, theta, analysis, tau, title, extended = self.figure_inputs
            out = residual_figures(problem, theta, analysis, tau=tau, title=title, extended=extended)
        if self.budget:
            from estcal.plots.budget import budget_figure

            out["budget.png"] = budget_figure(self.budget)
        return out

    def save_model(self, path, provenance: dict | None = None):
        """Write the identified robot (geometry + named effects at the joint estimate) as a
        robot file with a ``calibration:`` block (docs/robot-file.md, "Saved models")."""

        refuse_input(path, self._inputs())
        return save_diagnosis(self, path, provenance)

    def _inputs(self) -> list:
        meta = getattr(self.robot, "meta", None) or {}
        return [getattr(d, "path", None) for d in [self.train_data, *self.validation_data] if d is not None] + \
            [meta.get("robot_file"), meta.get("urdf")]

    def prepare(self, data):
        """``data`` prepared as the diagnosis prepared its own: approach columns from the posture
        order (if used), effect columns moved into the context, session time. Score new data
        with ``self.robot`` (extended) or ``self.geometric_robot`` after this."""
        return prepare_data(self.robot, data, {k: self.model.get(k) for k in ("approach_from_order",
                                                                                "session_time")})

    def score(self, data) -> dict:
        """RMSE / max (mm) of the geometric and extended models on ``data`` (prepared first),
        every measured point, plus the RMSE of each point separately."""
        d = self.prepare(data)
        out = {}
        for lab, r in (("geometric", self.geometric_robot), ("extended", self.robot)):
            pos, _ = pose_errors(r, r.params.values, d)
            out[lab] = {"rmse_mm": float(np.sqrt(np.mean(pos ** 2)) * 1e3), "max_mm": float(pos.max() * 1e3),
                        "rmse_mm_per_point": (np.sqrt(np.mean(pos ** 2, axis=0)) * 1e3).tolist()}
        return out

    @property
    def named(self) -> list[tuple[str, tuple]]:
        return [(c.effect, tuple(c.joints)) for c in self.causes]

    def to_dict(self) -> dict:
        return _plain({"causes": [c.to_dict() for c in self.causes], "verdict": self.verdict,
                       "rmse_mm": self.rmse_mm, "max_mm": self.max_mm, "noise": self.noise,
                       "geometric_free": self.geometric_free, "geometric_dropped": self.geometric_dropped,
                       "lumped_masses": self.lumped_masses, "steps": self.steps, "analysis": self.analysis,
                       "model": self.model, "geometric_model": self.geometric_model, "located": self.located,
                       "report_files": self.report_files, "budget": self.budget, "stability": self.stability,
                       "measurement_noise": self.measurement_noise})

    def to_json(self, path) -> Path:

        refuse_input(path, self._inputs())
        return write_json(path, self.to_dict())

    def __str__(self) -> str:
        def f(x):
            return "   –  " if x is None else f"{x:6.3f}"

        lines = [f"Diagnosis: {self.verdict}"]
        for c in self.causes:
            lines.append("  cause: " + c.describe())
        for d in (self.stability or {}).get("not_kept", []):
            lines.append(f"  not kept: {d['candidate']} — named on all rows but in only {d['folds_naming']} of "
                         f"{self.stability['k_folds']} posture-grouped folds")
        for d in self.located:
            lines.append(f"  located, not named: {d['shape']} of {', '.join(d['joints'])} "
                         f"({100 * d['explained_fraction']:.0f}% of the geometric residual)")
        lines.append(f"  {'RMSE (mm)':<12}{'train':>8}{'CV':>8}{'valid':>8}   max: train / valid")
        for k in ("geometric", "extended"):
            r, m = self.rmse_mm[k], self.max_mm[k]
            lines.append(f"  {k:<12}{f(r['train']):>8}{f(r['cv']):>8}{f(r['validation']):>8}   "
                         f"{f(m['train'])} / {f(m['validation'])}")
        lines += self._cv_note()
        vp = self.rmse_mm.get("validation_postures") or {}
        for part in ("seen", "new") if vp else ():
            d = vp[part]
            lines.append(f"  valid at {part} postures ({d['n_rows']} rows): geometric {f(d['geometric']).strip()}, "
                         f"extended {f(d['extended']).strip()} mm"
                         + (" — memory, not accuracy at new postures" if part == "seen" and d["n_rows"] else ""))
        nf = self.analysis.get("noise_floor", {})
        if nf:
            s = f"  geometric fit: χ²/dof = {nf['chi2_per_dof']:.3g}"
            if nf.get("noise_known"):
                s += f" (p = {nf['p_value']:.2g}; {'at' if nf['at_noise_floor'] else 'above'} the noise floor)"
            lines.append(s)
        if self.analysis.get("strongest"):
            s = ", ".join(f"{d['joint']}~{d['feature']} R²={d['r2']:.2f}" for d in self.analysis["strongest"][:4])
            lines.append(f"  strongest residual structures: {s}")
        if self.measurement_noise:
            from estcal.discrepancy.noise import noise_lines

            lines += ["  " + ln for ln in noise_lines(self.measurement_noise)]
        if self.budget:
            from estcal.discrepancy.budget import budget_lines

            lines += ["  " + ln for ln in budget_lines(self.budget)]
        return "\n".join(lines)

    def _cv_note(self) -> list[str]:
        """The line that tells the table's CV from the budget's: the table's "extended" CV refits the named
        causes on every fold (they were chosen on all rows, so it is optimistic by that choice); the
        budget's nested CV replays the choice on each fold's training rows, the figure to expect at new
        postures. Said when causes were named and the budget ran nested."""
        b = self.budget or {}
        if not (self.causes and b.get("nested") and b.get("named_mm") is not None and not b.get("model")):
            return []
        worse = b["named_mm"] >= b["geometric_mm"]
        return [f"  (CV: the causes above refitted on every fold; each fold choosing its own causes — the nested CV "
                f"of the error budget, what to expect at new postures — gives {b['named_mm']:.3f} mm against "
                f"{b['geometric_mm']:.3f} mm geometric" + (": choosing causes from these data does not lower the error "
                                                          "at new postures)" if worse else ")")]


# ------------------------------------------------------------------ helpers
def cross_validate(problem, theta, free, folds, max_iter: int = 30):
    """k-fold cross-validated point errors: refit ``free`` on k−1 folds (LM from ``theta``),
    predict the held-out poses. Returns ``(rmse_mm, max_mm)`` over every held-out point."""
    term = problem.terms[0]
    data = term.data
    sq = []
    for test in folds:
        train = np.setdiff1d(np.arange(data.n), test)
        sub = Problem(problem.robot.with_values(theta), [(term.method, data.subset(train), term.noise)])
        res = calibrate_lsq(sub, "lm", free=free, check=False, max_iter=max_iter)
        pos, _ = pose_errors(sub.robot, res.theta, data.subset(test))
        sq.append(pos.reshape(-1))
    e = np.concatenate(sq)
    return float(np.sqrt(np.mean(e ** 2)) * 1e3), float(e.max() * 1e3)


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


def _seen_new(data, validate, errors: dict, joint_types) -> dict:
    """The validation RMSE of both models split by posture (:func:`estcal.validation.validation_split`):
    rows at postures of the training data (``seen``: memory) and at new postures (``new``: accuracy
    where the model was not fitted), ``{"seen" | "new": {"n_rows", "geometric", "extended"},
    "only_seen"}``; a validation made only of seen postures is warned about (docs/real-data.md).
    ``errors``: ``{"geometric" | "extended": _errors(model, validate)}``, computed once by the caller."""
    import warnings

    from estcal.base.errors import EstcalWarning
    from estcal.validation import validation_split

    R = np.vstack([d.readings for d in validate])
    splits = {k: validation_split(data.readings, R, np.vstack([e.reshape(len(e), -1) for e in es]), joint_types)
              for k, es in errors.items()}
    out = {part: {"n_rows": splits["geometric"][part]["n_rows"],
                  **{k: splits[k][part]["rmse_mm"] for k in splits}} for part in ("seen", "new")}
    out["only_seen"] = splits["geometric"]["only_seen"]
    if splits["geometric"]["warning"]:
        warnings.warn(f"validation: {splits['geometric']['warning']}", EstcalWarning, stacklevel=4)
    return out


def _regrouping(A, names_a, E, names_e) -> dict:
    """How a regrouped effect's columns are absorbed: ``{effect parameter: {model parameter: β}}``
    from :func:`estcal.identify.identifiable` (GECARO eq. [36]-[37]) with the model's parameters first."""
    try:
        from estcal.identify import identifiable
    except ImportError:  # pragma: no cover - the identification module is optional here
        return {}
    W = np.c_[A, E]
    names = list(names_a) + list(names_e)
    prio = np.r_[np.full(len(names_a), 2), np.ones(len(names_e), int)]
    try:
        res = identifiable(W, names, prio, tau_floor=1e-3)
    except Exception:  # noqa: BLE001 - reporting only
        return {}
    out = {r["parameter"]: {k: float(v) for k, v in sorted(r["relation"].items(), key=lambda kv: -abs(kv[1]))[:4]}
           for r in res.regrouped if r["parameter"] in names_e}
    out.update({n: {} for n in res.no_effect if n in names_e})
    return out


def _fit(problem, theta, free, max_iter=100):
    return calibrate_lsq(problem.with_values(theta), "lm", free=free, check=False, max_iter=max_iter)


# ------------------------------------------------------------------ main
@dataclass
class _Model:
    """The model of the current step of the forward selection: its problem, estimate, free set, the
    weighted residual sum of squares, its number of parameters, its cross-validated (RMSE, max) and fit."""

    problem: object
    theta: np.ndarray
    free: list
    rss: float
    p: int
    cv: tuple
    res: object


@dataclass
class _Rules:
    """The rules of every selection step (the diagnose options they come from)."""

    known: bool
    M: int
    folds: list
    alpha: float
    min_explained: float
    n_refit: int
    regroup_tol: float
    cv_max_iter: int


def diagnose(robot, data, validate=(), candidates=None, k_folds: int = 5, noise=None, alpha: float = 0.01,
             max_effects: int = 3, min_explained: float = 0.3, n_refit: int = 3, regroup_tol: float = 1e-3,
             ident_tol: float = 1e-4, free=None, rng=0, robot_spec=None,
             cv_max_iter: int = 30, verbose: bool = False, geometric: str = "full",
             session_time: bool = True, approach_from_order: bool = False,
             families: bool = True, posture_tol=(1e-3, 1e-3), budget: bool = False,
             residual_model: str | None = None, stability: bool = True) -> DiagnosisResult:
    """Diagnose what the geometric model of ``robot`` gets wrong on ``data``.

    Parameters
    ----------
    robot : SerialRobot or robot spec (built-in name, .yaml, .urdf).
    data : Dataset (position / points / pose) of the robot's joints, or a list of datasets,
        one per session (approach directions and session time per session; fitted
        together, see :func:`estcal.sessions.data.stack_sessions`).
    validate : datasets scored with both models (not used for any decision).
    candidates : list of :class:`Candidate`, of registered effect names, or None
        (every registered effect on every joint, :func:`default_candidates`).
    k_folds : folds of the cross-validation, grouped by posture: rows whose readings agree within
        ``posture_tol`` (rad, m) — the same posture in another session or twice in one file — are
        held out together (:func:`estcal.validation.grouped_folds`; docs/real-data.md).
    posture_tol : ``(tol_rad, tol_m)`` of the posture grouping.
    budget : also compute the error budget (:func:`estcal.discrepancy.budget.error_budget`: nominal,
        geometric, named, structured-unnamed and unstructured RMSE, repeatability floor and
        ``predicted_validation_mm``, all by posture-grouped CV with ``k_folds``) into ``result.budget``.
    residual_model : ``"gp"``: the budget's residual Gaussian process becomes part of the recommended
        model (``result.residual_model``; docs/real-data.md).
    stability : keep a named cause only when the selection on the training rows of more than half of the
        posture-grouped folds names it too (:mod:`estcal.discrepancy.stability`; ``result.stability`` and
        each cause's ``folds_naming``).
    noise : measurement noise, any form of :meth:`estcal.methods.NoiseModel.parse` — a float is the
        position std σ (m) with orientation σ / 0.1 m (rad) — taken as known (a NoiseModel keeps
        its own ``known``). None: unknown (relative weights, F tests).
    alpha : family-wise significance level of each selection step.
    max_effects : most effects named.
    min_explained : least fraction of the residual above the noise floor an effect
        must explain to be named.
    n_refit : candidates refitted nonlinearly per step (best linearised gains).
    regroup_tol : relative size below which an effect column counts as regrouped
        into the model's parameters (not identifiable).
    ident_tol : relative numerical zero of the geometric identifiable set.
    geometric : ``full`` (every identifiable geometric parameter, default), ``aic``
        (those an Akaike criterion supports) or ``joint_offset``; see
        :func:`~estcal.discrepancy.geometric.fit_geometric`. ``auto``: the one of the
        three with the lowest cross-validated RMSE on ``data`` (the one-standard-error rule); the
        command's ``--geometric auto`` (:func:`estcal.discrepancy.prior_model.diagnose_auto`, through
        :func:`estcal.diagnose`) has the MAP prior model among the candidates too, preferred.
    approach_from_order : infer ``approach_<joint>`` columns from the posture order
        (:func:`~estcal.io.prepare.derive_approach`) for data and validation
        data, so that backlash is tested against the approach direction.
    session_time : measure ``t`` from the first pose of each dataset (drift and
        warm-up are session effects; a validation file from another day then
        starts at its own t = 0). The absolute time stays in ``columns["t_abs"]``.
    free : explicit geometric free set (default: identifiable geometric parameters).
    rng : seed of the fold assignment.
    families : also screen each joint effect as one family over all its joints
        (see :func:`default_candidates`); tried only at steps where no single-joint
        or whole-arm candidate is accepted.
    robot_spec : how to reload the nominal robot (stored in the fit for
        :func:`estcal.discrepancy.feedback.simulate_from_fit`).
    """
    robot, robot_spec, data, validate, sessions = _prepare_data(robot, data, validate, robot_spec,
                                                                approach_from_order, session_time)
    # the one rule of every noise= (NoiseModel.parse): a number σ is taken as known
    nm = NoiseModel(known=False) if noise is None else NoiseModel.parse(noise, known=True)
    known = bool(nm.known)

    # 1. geometric model
    groups = posture_groups(data.readings, robot.joint_types, *posture_tol)
    folds = grouped_folds(groups, k_folds, rng)
    requested = geometric
    geometric, level_cv = _geometric_level(robot, data, nm, groups, k_folds, rng, geometric)
    # 2. residual analysis (with the geometric fit)
    geo, gdropped, lumped, tau, analysis, n_rows = _geometric_model(robot, data, nm, free, ident_tol, geometric,
                                                                    folds, cv_max_iter)
    problem, theta_g = geo.problem, geo.theta
    if level_cv:
        analysis["geometric_level_cv_mm"] = level_cv

    # 3.-4. forward selection of effects
    rules = _Rules(known, n_rows, folds, alpha, min_explained, n_refit, regroup_tol, cv_max_iter)
    cands = _candidates(candidates, problem.robot, data, families)
    causes, steps, final, first = _forward_selection(geo, cands, rules, max_effects, verbose)
    lc = _linear_candidates(geo, first, rules, max_effects, data) if first else None
    stab = None
    if stability and causes and lc is not None:  # 4b. causes that survive a new split
        causes, final, stab = _stability(geo, causes, final, lc, groups, rules, rng)
    causes, located = _locate_harmonic_series(causes)

    # 5. output
    result = _result(robot, robot_spec, data, validate, sessions, nm, geo, final, causes, located, steps, analysis,
                     gdropped, lumped, geometric, approach_from_order, session_time, stab)
    result.stability, result.measurement_noise = stab, _noise_components(final)
    if stability and lc is not None:
        result.selector = _selector(lc, groups, k_folds, rng)
    result.figure_inputs = (problem, theta_g, analysis, tau, robot.name,
                            (final.problem, final.theta) if causes else None)
    if budget or residual_model:
        _error_budget(result, robot, data, nm, requested, geometric, k_folds, rng, posture_tol, residual_model,
                      causes)
    return result


def _geometric_model(robot, data, nm, free, ident_tol, level, folds, cv_max_iter):
    """Steps 1–2 of the module docstring: ``(model, dropped parameters, lumped masses, gravity torques (N, n),
    residual analysis, number of weighted rows)`` of the geometric fit at ``level`` (with the masses the
    gravity-driven candidates need) and its k-fold CV on ``folds``."""
    problem, gres, gfree, gdropped = fit_geometric(robot, data, nm, free=free, tol=ident_tol, level=level)
    theta_g = gres.theta.copy()
    grobot, lumped = gravity_ready(problem.robot, theta_g, robot.params.values)
    problem = Problem(grobot, [(t.method, t.data, t.noise) for t in problem.terms])
    b, _, _ = weighted_system(problem, theta_g, gfree)
    geo = _Model(problem, theta_g, list(gfree), float(b @ b), len(gfree),
                 cross_validate(problem, theta_g, gfree, folds, cv_max_iter), gres)
    tau = grobot.gravity_torques(data.readings, theta_g, data.context)
    analysis = residual_analysis(problem, theta_g, bool(nm.known), geo.p, {"tau": tau})
    analysis.update(lumped_masses=lumped, geometric_level=level)
    return geo, gdropped, lumped, tau, analysis, len(b)


def _error_budget(result, robot, data, nm, requested, geometric, k_folds, rng, posture_tol, residual_model,
                  causes) -> None:
    """The error budget of the diagnosis (:func:`estcal.discrepancy.budget.error_budget`) into ``result.budget``
    and its residual Gaussian process into ``result.residual_model``. Its prediction is the nested CV of the
    diagnosis itself: every outer fold chooses the level (when ``auto``) and the causes (the stability rule,
    linearised) on its training rows only (:mod:`estcal.discrepancy.prediction`)."""
    from estcal.discrepancy.prediction import Procedure
    from estcal.discrepancy.residual import residual_choice

    effects = [(c.effect, list(c.joints), dict(c.options or {})) for c in causes]
    proc = Procedure(level="auto" if requested == "auto" else geometric, effects=tuple(effects),
                     select_effects=result.selector, gp=residual_choice(residual_model)[0],
                     k_inner=k_folds)
    _attach_budget(result, robot, data, nm, proc, geometric, effects, k_folds, rng, posture_tol, residual_model)


def _attach_budget(result, robot, data, nm, proc, level, effects, k_folds, rng, posture_tol, residual_model,
                   per_session=None) -> None:
    """The error budget of ``proc`` (:func:`estcal.discrepancy.budget.error_budget`, the recommended model's
    ``level`` and ``effects`` on all rows) into ``result.budget``, its residual GP into
    ``result.residual_model``, and with validation data the 95 % region at their rows beside their RMSE — for
    the default diagnosis and the prior model's (:mod:`estcal.discrepancy.prior_model`) alike."""
    from estcal.discrepancy.budget import error_budget, region_at

    b = error_budget(robot, data, nm, level=level, effects=effects, procedure=proc, k_folds=k_folds, rng=rng,
                     tol_rad=posture_tol[0], tol_m=posture_tol[1], residual_model=residual_model,
                     per_session=per_session)
    result.budget = b.to_dict()
    result.residual_model = b.residual_model
    if result.validation_data:
        result.budget["validation"] = [dict(region_at(b, d), path=str(d.where)) for d in result.validation_data]


def _linear_candidates(geo, table, rules, max_effects, data) -> LinearCandidates:
    """The selection linearised at the all-rows geometric estimate (:mod:`.stability`): every geometric
    column and the columns of every candidate the first screening could test."""
    from .stability import drift_free_of_offsets

    names = geometric_candidates(geo.problem.robot)
    b, A, rows = weighted_system(geo.problem, geo.theta, names)
    ok = [e for e in table if e["status"] == "ok"]
    blocks = [e["_E"] for e in ok]
    sess = data.columns.get("session")
    if sess is not None and len(np.unique(sess)) > 1:  # a drift never explains an offset between sessions
        rs = np.asarray(sess)[rows.pose]
        blocks = [drift_free_of_offsets(E, rs, rows.kind, rows.sigma) if e["effect"] in TIME_EFFECTS else E
                  for e, E in zip(ok, blocks)]
    params = [list(e["_obj"][3]) for e in ok]
    robot = geo.problem.robot
    fam = {}
    for i, e in enumerate(ok):
        if _is_family(e):  # the joint of each column of a family (a family is reduced as it is named)
            c = e["_obj"][0]
            owner = {n: j for j in c.joints for n in Candidate(c.effect, [j], c.options).make_names(robot)}
            fam[i] = [owner.get(n) for n in params[i]]
    return LinearCandidates(b, A, list(names), rows.sigma, rows.pose, rows.kind == 0, [e["candidate"] for e in ok],
                            [_is_family(e) for e in ok], blocks, params, rules.known, rules.alpha,
                            rules.min_explained, max_effects, rules.n_refit, rules.regroup_tol,
                            {e["candidate"]: (e["effect"], list(e["joints"] or []), dict(e["_obj"][0].options))
                             for e in ok}, fam)


def _stability(geo, causes, final, lc, groups, rules, rng):
    """``(kept causes, final model, stability record)``: a cause is kept when the linearised selection on the
    training rows of more than half of the posture-grouped folds names it too (:func:`.stability.folds_naming`);
    the model is refitted without the others and kept only if its grouped CV is still lower than the
    geometric model's."""
    k = len(rules.folds)
    sel = fold_selections(lc, groups, rules.folds, k, rng, free=geo.free)
    for c in causes:
        c.folds_naming, c.k_folds = folds_naming(c.effect, c.joints, sel), k
    kept = [c for c in causes if c.folds_naming > k / 2]
    if len(kept) < len(causes):
        final = _refit_kept(geo, kept, rules) if kept else geo
        if kept and not final.cv[0] < geo.cv[0]:
            kept, final = [], geo
    stab = {"rule": "named on all rows and in more than half of the posture-grouped folds (selection on each "
                    "fold's training rows, linearised at the all-rows geometric estimate)",
            "k_folds": k, "folds_naming": joint_votes(sel), "kept": [cause_key(c) for c in kept],
            "not_kept": [{"candidate": cause_key(c), "folds_naming": c.folds_naming} for c in causes if c not in kept]}
    return kept, final, stab


def _refit_kept(geo, kept, rules) -> _Model:
    """The geometric model plus the kept causes only, refitted jointly (and cross-validated)."""
    rob = geo.problem.robot.with_values(geo.theta)
    names = []
    for c in kept:
        eff = make_effect(c.effect, rob, joints=list(c.joints) or None, **dict(c.options or {}))
        rob = rob.add_effect(eff)
        names += list(eff.param_names)
    prob = Problem(rob, [(t.method, t.data, t.noise) for t in geo.problem.terms])
    res = _fit(prob, rob.params.values, geo.free + names)
    for c in kept:
        c.parameters = {n: {"estimate": float(res.parameter(n)[0]), "std": float(res.parameter(n)[1])}
                        for n in c.parameters}
    return _Model(prob, res.theta.copy(), geo.free + names, float(res.chi2), geo.p + len(names),
                  cross_validate(prob, res.theta, geo.free + names, rules.folds, rules.cv_max_iter), res)


def _selector(lc, groups, k, rng):
    """The diagnosis's cause selection and stability rule on any subset of its rows (linearised): the
    :class:`~estcal.discrepancy.prediction.Procedure` the nested prediction replays on its outer folds."""
    g = np.asarray(groups)

    def select(rows, free):
        return stable_selection(lc, g[np.asarray(rows)], k, rng, rows=rows, free=free)

    return select


def _noise_components(model) -> dict:
    """The REML noise std per measurement kind and axis of the measuring frame of the final model."""
    from estcal.discrepancy.noise import measurement_noise

    try:
        return measurement_noise(model.problem, model.theta, model.free)
    except (ValueError, np.linalg.LinAlgError) as exc:  # reporting only: say why instead of failing the diagnosis
        return {"estimated": f"not estimated: {exc}"}


def _prepare_data(robot, data, validate, robot_spec, approach_from_order, session_time):
    """The robot (loaded, with one marker per measured point) and the data as the diagnosis reads them:
    sessions stacked, approach columns from the posture order, effect columns in the context, ``t``
    from each session's first pose. Returns ``(robot, robot_spec, data, validate, sessions)``;
    ``sessions`` is the list of datasets when several were stacked, else None."""
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
    stacked = sessions is not None and len(sessions) > 1
    if stacked:
        # several sessions (one dataset each): approach directions and session time are
        # per session, then the sessions are fitted together (a ``session`` column records them)
        from estcal.sessions.data import stack_sessions

        parts = []
        for d in sessions:
            d = derive_approach(d) if approach_from_order else d.subset(slice(None))
            if session_time:
                _session_time(d, centred=True)
            parts.append(d)
        data = stack_sessions(parts)
    if approach_from_order:
        if not stacked:
            data = derive_approach(data)
        validate = [derive_approach(d) for d in validate]
    data = with_effect_context(robot, data)
    validate = [with_effect_context(robot, d) for d in validate]
    if session_time:
        for d in validate:
            _session_time(d, centred=stacked or _n_sessions(data) > 1)
        if not stacked and _n_sessions(data) > 1:  # stacked by the caller (a ``session`` column)
            _session_time_each(data)
        elif not stacked:
            _session_time(data)
    return robot, robot_spec, data, validate, (sessions if stacked else None)


def _session_time_each(data) -> None:
    """:func:`_session_time` (centred) within each session of a dataset stacked with a ``session`` column."""
    if "t" not in data.context:
        return
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
    ``t`` and zero at t = 0, has no mean within a session and cannot explain an offset between sessions —
    that is the repeatability's part (docs/real-data.md)."""
    if "t" in d.context:
        d.columns["t_abs"] = d.context["t"].copy()
        d.context["t"] = d.context["t"] - (d.context["t"].mean() if centred else d.context["t"].min())


def _geometric_level(robot, data, noise, groups, k_folds, rng, geometric):
    """``(level, {level: CV RMSE mm})``: ``geometric`` itself, or for ``"auto"`` the level of ``joint_offset``,
    ``aic`` and ``full`` that posture-grouped CV and the one-standard-error rule choose
    (:func:`estcal.discrepancy.prediction.choose_level`: the simplest level within one standard error of
    the lowest CV error)."""
    if geometric != "auto":
        return geometric, {}
    from estcal.discrepancy.prediction import choose_level

    level, cv = choose_level(robot, data, noise, groups, k_folds, rng)
    return level, {lv: v["cv_mm"] for lv, v in cv.items()}


def _candidates(candidates, robot, data, families) -> list:
    """The candidate effects: every registered one (None), or the given candidates and effect names."""
    if candidates is None:
        return default_candidates(robot, data, families=families)
    cands = []
    for c in candidates:
        if isinstance(c, Candidate):
            cands.append(c)
        elif isinstance(c, str):
            cands += default_candidates(robot, data, effects=[c], families=families)
        else:
            cands.append(Candidate(*c))
    return cands


def _forward_selection(geo: _Model, cands, rules: _Rules, max_effects: int, verbose: bool):
    """Add one effect per step while one passes every test (module docstring, steps 3-4).

    Returns ``(causes, steps, final, first)``: the named causes with the estimates of the final joint fit,
    the record of every step, the final model and the first step's screening table (every candidate's
    columns at the geometric estimate, for the stability rule)."""
    cur, causes, steps, used, first = geo, [], [], set(), None
    for step in range(max_effects):
        table = _screen(cur, cands, used, rules, step)
        first = table if first is None else first
        ok = sorted((e for e in table if e["status"] == "ok"), key=lambda e: e["delta_bic_linear"])
        accepted, refits = _refit_and_test(cur, ok, rules)
        steps.append(_step_record(step, cur, cands, used, table, ok, accepted, rules))
        if verbose:
            print(f"step {step + 1}: " + ", ".join(f"{e['candidate']} ΔBIC {e['delta_bic']:.1f} "
                                                   f"p {e['p_value']:.2g} {e.get('rejected')}"
                                                   for _, e, _ in refits))
        if accepted is None:
            break
        cur = _add_cause(cur, accepted, refits, causes, used, geo.rss)
    for c in causes:  # estimates of the final (jointly fitted) model, not those of the step that added each
        c.parameters = {n: {"estimate": float(cur.res.parameter(n)[0]), "std": float(cur.res.parameter(n)[1])}
                        for n in c.parameters}
    return causes, steps, cur, first


def _screen(cur: _Model, cands, used, rules: _Rules, step: int) -> list[dict]:
    """Every candidate not in the model yet, linearised at the current estimate: its columns projected
    orthogonally to the model's; regrouped (not identifiable) when they vanish there, else the
    linear least-squares gain and ΔBIC."""
    b, A, _ = weighted_system(cur.problem, cur.theta, cur.free)
    Q = orthonormal_basis(A)
    b_perp = b - Q @ (Q.T @ b)
    table = []
    for c in progress(cands, desc=f"diagnose: step {step + 1}, candidate effects", unit="effect"):
        c = _remaining(c, cur.problem.robot, used)
        if c is None:
            continue
        entry = {"candidate": c.label, "effect": c.effect, "joints": c.joints}
        try:
            eff = c.make(cur.problem.robot)
            rob = cur.problem.robot.with_values(cur.theta).add_effect(eff)
            prob = Problem(rob, [(t.method, t.data, t.noise) for t in cur.problem.terms])
            names = list(eff.param_names)
            _, E, _ = weighted_system(prob, rob.params.values.copy(), names)
        except Exception as exc:  # an effect that cannot run on these data (missing column …)
            entry.update(status="skipped", reason=str(exc))
            table.append(entry)
            continue
        En = np.linalg.norm(E, axis=0)
        Ep = E - Q @ (Q.T @ E)
        rel = np.linalg.norm(Ep, axis=0) / np.maximum(En, 1e-300)
        sv = np.linalg.svd(Ep / np.maximum(En, 1e-300), compute_uv=False)
        if np.any(En == 0) or rel.min() < rules.regroup_tol or sv.min() < rules.regroup_tol * sv.max():
            entry.update(status="regroups", orthogonal_fraction=float(min(rel.min(), sv.min() / sv.max())
                                                                      if En.all() else 0.0),
                         relation=_regrouping(A, cur.free, E, names))
            table.append(entry)
            continue
        x, *_ = np.linalg.lstsq(Ep, b_perp, rcond=None)
        r = b_perp - Ep @ x
        rss1 = float(r @ r)
        k = len(names)
        entry.update(status="ok", k=k, rss_linear=rss1, _E=E,
                     delta_bic_linear=information_criterion(rss1, rules.M, cur.p + k, rules.known)
                     - information_criterion(cur.rss, rules.M, cur.p, rules.known),
                     _obj=(c, rob, prob, names))
        table.append(entry)
    return table


def _remaining(c, robot, used):
    """The candidate as it can still be added: None when it is in the model; a family reduced to its
    joints not yet in the model (≥ 2), so that the rest of a compound effect is still searched
    after some of its joints were named singly."""
    if c.label in used:
        return None
    have = set(robot.params.names)
    if c.joints and len(c.joints) > 1:
        rest = [j for j in c.joints if not have.intersection(Candidate(c.effect, [j], c.options).make_names(robot))]
        if len(rest) < 2:
            return None
        c = Candidate(c.effect, rest, c.options)
        return None if c.label in used else c
    if c.joints and have.intersection(c.make_names(robot)):
        return None  # already in the model as part of an accepted family
    return c


def _refit_and_test(cur: _Model, ok, rules: _Rules):
    """Refit the best linearised candidates nonlinearly and test them in order of ΔBIC: the first
    that lowers BIC, is significant at α / (candidates tested), explains enough of the excess
    residual and lowers the cross-validated RMSE is accepted. Single-joint and whole-arm
    candidates first; a family (one effect over several joints) only when none of them is
    accepted, so that a compound effect of weak per-joint terms is found without a family
    absorbing a single-joint cause. Returns ``(accepted or None, refits)``."""
    n_tested = max(len(ok), 1)
    accepted, refits = None, []
    for group in ([e for e in ok if not _is_family(e)], [e for e in ok if _is_family(e)]):
        if accepted is not None:
            break
        refits = sorted((_refit(cur, e, rules) for e in group[:rules.n_refit]), key=lambda t: t[0])
        n_cv = 0
        for dbic, e, res in refits:
            reasons, cv_e, n_cv = _rejections(cur, e, res, dbic, n_tested, n_cv, rules)
            e["rejected"] = reasons
            if not reasons:
                accepted = (e, res, cv_e)
                break
    return accepted, refits


def _refit(cur: _Model, e, rules: _Rules):
    """``(ΔBIC, entry, fit)`` of the model with the candidate's parameters, refitted nonlinearly."""
    c, rob, prob, names = e["_obj"]
    res = _fit(prob, rob.params.values, cur.free + names)
    rss1 = float(res.chi2)
    k = len(names)
    dbic = (information_criterion(rss1, rules.M, cur.p + k, rules.known)
            - information_criterion(cur.rss, rules.M, cur.p, rules.known))
    tname, stat, pval = significance(cur.rss, rss1, k, rules.M, cur.p + k, rules.known)
    e.update(rss=rss1, delta_bic=dbic, test=tname, statistic=stat, p_value=pval)
    return dbic, e, res


def _rejections(cur: _Model, e, res, dbic, n_tested, n_cv, rules: _Rules):
    """``(reasons, cv, n_cv)``: why the refitted candidate is not named (empty: it is), its
    cross-validated (RMSE, max) when it was cross-validated (at most two per step)."""
    c, rob, prob, names = e["_obj"]
    excess = cur.rss - (max(rules.M - cur.p, 0) if rules.known else 0.0)
    frac_excess = (cur.rss - e["rss"]) / excess if excess > 0 else 0.0
    e["explained_excess_fraction"] = float(frac_excess)
    reasons, cv_e = [], None
    if not dbic < 0:
        reasons.append("ΔBIC ≥ 0")
    if not e["p_value"] < rules.alpha / n_tested:
        reasons.append(f"p = {e['p_value']:.2g} ≥ α/{n_tested}")
    if not frac_excess >= rules.min_explained:
        reasons.append(f"explains {100 * frac_excess:.0f}% < {100 * rules.min_explained:.0f}% of the excess")
    if not reasons and n_cv < 2:
        n_cv += 1
        cv_e = cross_validate(prob, res.theta, cur.free + names, rules.folds, rules.cv_max_iter)
        e["cv_rmse_mm"] = cv_e[0]
        if not cv_e[0] < cur.cv[0]:
            reasons.append(f"CV RMSE {cv_e[0]:.4g} ≥ {cur.cv[0]:.4g} mm")
    elif not reasons:
        reasons.append("not cross-validated (limit)")
    return reasons, cv_e, n_cv


def _step_record(step, cur: _Model, cands, used, table, ok, accepted, rules: _Rules) -> dict:
    """What one step tried (the 12 best linearised candidates), what regroups, what was accepted."""
    return {"step": step + 1, "rss_before": cur.rss, "n_candidates": len(cands) - len(used),
            "n_tested": len(ok), "alpha_per_test": rules.alpha / max(len(ok), 1),
            "table": [{k: _plain(v) for k, v in e.items() if not k.startswith("_")}
                      for e in sorted(table, key=lambda e: e.get("delta_bic_linear", np.inf))[:12]],
            "regroups": {e["candidate"]: _plain(e.get("relation", {})) for e in table if e["status"] == "regroups"},
            "accepted": accepted[0]["candidate"] if accepted else None}


def _add_cause(cur: _Model, accepted, refits, causes, used, rss_geometric) -> _Model:
    """Name the accepted effect (with its competing explanations) and return the extended model."""
    e, res, cv_e = accepted
    c, rob, prob, names = e["_obj"]
    used.add(c.label)
    params = {n: {"estimate": float(res.parameter(n)[0]), "std": float(res.parameter(n)[1])} for n in names}
    cause = Cause(c.effect, list(c.joints or []), params, float(e["delta_bic"]), e["test"], float(e["statistic"]),
                  float(e["p_value"]), (cur.rss - e["rss"]) / rss_geometric, float(e["explained_excess_fraction"]),
                  cur.cv[0], cv_e[0], _plain(c.options))
    # Competing explanations: refitted candidates whose BIC is within 10 of the accepted one
    # (Kass & Raftery: a BIC difference above 10 is very strong evidence).
    cause.alternatives = [{"candidate": o["candidate"], "delta_bic_difference": float(o["delta_bic"] - e["delta_bic"])}
                          for _, o, _ in refits if o is not e and o["delta_bic"] - e["delta_bic"] < 10]
    causes.append(cause)
    return _Model(prob, res.theta.copy(), cur.free + names, float(e["rss"]), cur.p + len(names), cv_e, res)


def _locate_harmonic_series(causes):
    """``(causes, located)``: a gear harmonic is one order of the joint angle. When several orders of
    the same joint are selected, the data describe a smooth function of that angle that the
    harmonics only approximate term by term (a Fourier series of, e.g., a quadratic error): the
    joint is located, but no library mechanism is named for it."""
    located, groups = [], {}
    for c in causes:
        if c.effect == "gear_harmonic":
            groups.setdefault(tuple(c.joints), []).append(c)
    for joints, cs in groups.items():
        if len(cs) > 1:
            orders = sorted(k for c in cs for k in c.options.get("orders", []))
            located.append({"joints": list(joints), "shape": f"smooth function of the joint angle (harmonic "
                                                             f"orders {', '.join(map(str, orders))} all needed)",
                            "explained_fraction": float(sum(c.explained_fraction for c in cs)),
                            "terms": [c.to_dict() for c in cs]})
            causes = [c for c in causes if c not in cs]
    return causes, located


def _result(robot, robot_spec, data, validate, sessions, nm, geo: _Model, final: _Model, causes, located, steps,
            analysis, gdropped, lumped, geometric, approach_from_order, session_time, stability=None) -> DiagnosisResult:
    """The :class:`DiagnosisResult`: RMSE / max of both models on the training data, in cross-validation
    and on the validation data, the verdict, and the two models as plain data."""
    gr, xr = geo.problem.robot, final.problem.robot
    tr_g, tr_x = _scores(gr, geo.theta, [data]), _scores(xr, final.theta, [data])
    # the validation errors once per model: the pooled scores, each file's and the seen / new split
    err_g, err_x = _errors(gr, geo.theta, validate), _errors(xr, final.theta, validate)
    va_g, va_x = _rmse_max(err_g), _rmse_max(err_x)
    rmse = {"geometric": {"train": tr_g[0], "cv": geo.cv[0], "validation": va_g[0]},
            "extended": {"train": tr_x[0], "cv": final.cv[0], "validation": va_x[0]}}
    mx = {"geometric": {"train": tr_g[1], "cv": geo.cv[1], "validation": va_g[1]},
          "extended": {"train": tr_x[1], "cv": final.cv[1], "validation": va_x[1]}}
    if validate:
        rmse["validation_each"] = {"geometric": [_rmse_max([e])[0] for e in err_g],
                                   "extended": [_rmse_max([e])[0] for e in err_x],
                                   "paths": [d.where for d in validate]}
        rmse["validation_postures"] = _seen_new(data, validate, {"geometric": err_g, "extended": err_x},
                                                gr.joint_types)
    final_floor = residual_analysis(final.problem, final.theta, bool(nm.known), final.p)["noise_floor"]
    analysis["noise_floor_extended"] = final_floor
    verdict = _verdict(causes, analysis["noise_floor"], final_floor, steps, rmse, bool(nm.known), located,
                       (stability or {}).get("not_kept", []), (stability or {}).get("k_folds"))
    model = {"robot": getattr(robot, "name", None), "robot_spec": robot_spec, "n_markers": int(robot.n_markers),
             "gravity": gr.gravity.tolist(), "lumped_masses": lumped,
             "effects": [e.to_dict() for e in xr.effects],
             "theta": dict(zip(xr.params.names, map(float, final.theta))),
             "free": final.free, "noise": nm.to_dict(), "geometric_level": geometric,
             "approach_from_order": bool(approach_from_order),
             "session_time": ("centred" if _n_sessions(data) > 1 else True) if session_time else False,
             "residual": {"rmse_mm": tr_x[0], "max_mm": tr_x[1], "chi2_per_dof": final_floor["chi2_per_dof"]}}
    gmodel = {"theta": dict(zip(gr.params.names, map(float, geo.theta))), "free": geo.free,
              "residual": {"rmse_mm": tr_g[0], "max_mm": tr_g[1],
                           "chi2_per_dof": analysis["noise_floor"]["chi2_per_dof"]}}
    try:  # the nominal robot itself, so the fit needs no robot file to be simulated again
        model["robot_dict"] = robot_to_dict(robot)
    except ValueError:  # a robot the file format cannot express: the fit names it by robot_spec
        pass
    # the last accepted joint fit (the geometric fit when nothing was named) gives the covariance
    result = DiagnosisResult(causes, verdict, rmse, mx, analysis, steps, nm.to_dict(), geo.free, gdropped, model,
                             gmodel, lumped, robot=xr.with_values(final.theta),
                             geometric_robot=gr.with_values(geo.theta), covariance=np.asarray(final.res.covariance),
                             covariance_names=list(final.res.names), sigma0=float(final.res.sigma0),
                             train_data=list(sessions) if sessions else data, validation_data=list(validate))
    result.located = located
    return result


def _verdict(causes, floor_g, floor_x, steps, rmse, known, located=(), unstable=(), k_folds=None) -> str:
    def gain():
        g, x = rmse["geometric"], rmse["extended"]
        s = f"RMSE train {g['train']:.3g} → {x['train']:.3g} mm, CV {g['cv']:.3g} → {x['cv']:.3g} mm"
        if g["validation"] is not None:
            s += f", validation {g['validation']:.3g} → {x['validation']:.3g} mm"
        return s

    loc = ""
    if located:
        loc = " " + " ".join(
            f"A {d['shape']} of {', '.join(d['joints'])} is located (explains "
            f"{100 * d['explained_fraction']:.0f}% of the geometric residual) but no library mechanism fits it: "
            f"that part of the residual is not explained by the modelled effects." for d in located)
    if unstable:
        loc += " Not kept: " + ", ".join(f"{d['candidate']} (named on all rows, in {d['folds_naming']} of {k_folds} "
                                         f"posture-grouped folds)" for d in unstable) + " — a cause must survive a new split."
    if not causes and located:
        return f"No cause named. {gain()} with an empirical joint-angle correction.{loc}"
    if not causes and unstable:
        return f"No cause named.{loc}"
    if not causes:
        if known and floor_g.get("at_noise_floor"):
            return (f"No significant non-geometric effect: the geometric model fits at the noise floor "
                    f"(χ²/dof = {floor_g['chi2_per_dof']:.3g}, p = {floor_g['p_value']:.2g}); no cause named.")
        best = None
        for e in (steps[0]["table"] if steps else []):
            if "delta_bic" in e:
                best = e
                break
        s = "No candidate effect of the library explains the residual; no cause named"
        if known:
            s += f" (the geometric fit is above the noise floor, χ²/dof = {floor_g['chi2_per_dof']:.3g})"
        if best is not None:
            s += (f"; best candidate {best['candidate']} rejected: "
                  f"{'; '.join(best.get('rejected', [])) or 'not significant'}")
        return s + ". The residual is not explained by the modelled effects."
    names = "; ".join(f"{c.effect} of {', '.join(c.joints) if c.joints else 'the arm'}" for c in causes)
    s = f"Named cause(s): {names}. {gain()}.{loc}"
    if known:
        if floor_x.get("at_noise_floor"):
            s += f" The extended model fits at the noise floor (χ²/dof = {floor_x['chi2_per_dof']:.3g})."
        else:
            s += (f" A residual above the noise floor remains unexplained (χ²/dof = "
                  f"{floor_x['chi2_per_dof']:.3g}).")
    return s
