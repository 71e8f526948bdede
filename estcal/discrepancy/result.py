"""The diagnosis's result: one model, one figure per question, the answer first.

:class:`DiagnosisResult` holds the one model the diagnosis recommends — the model its table, budget, JSON,
report, ``--save-model``, ``estcal compensate`` and ``estcal export`` all read — and prints the answer first:
the expected error at new postures with its 95 % bound, the named causes with their gains, what stays
unexplained, each validation file's one figure. Details follow.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.atomic import refuse_input
from estcal.base.jsonio import write_json

__all__ = ["Cause", "DiagnosisResult", "cause_label", "plain"]


def plain(v):
    """``v`` with numpy scalars and arrays turned into Python numbers and lists (JSON-ready)."""
    if isinstance(v, dict):
        return {k: plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def cause_label(effect: str, joints=(), options=None) -> str:
    """The words a named cause prints for ``effect`` on ``joints`` with ``options`` ("backlash (by approach)
    of arm_6_joint"): for a term of the model whether it is named or not."""
    options = options or {}
    j = ", ".join(joints) if joints else "the arm"
    order, by = options.get("orders"), options.get("by")
    name = effect.replace("_", " ") + (f" (order {', '.join(map(str, order))})" if order else "") + \
        (f" (by {by})" if by and by != "auto" else "")
    return f"{name} of {j}"


@dataclass
class Cause:
    """A named cause: ``effect`` on ``joints`` (empty: the whole arm) with ``options``.

    parameters : ``{name: {"estimate", "std", "unit", "display": [value, std, unit]}}`` (SI; display in mm,
        mrad … as the unit of the parameter says)
    ln_bf : the log Bayes factor of the model with the term against the model without it
    folds / k_folds : cross-validation folds whose own fit keeps the term
    cv_with_mm / cv_without_mm : the cross-validated RMSE at new postures with and without the term;
        ``gain_mm`` their difference
    explained_fraction : the share of the geometry-only model's training residual (sum of squares) the term
        removes when it alone is added to the geometry (named causes that overlap can each explain much)
    load : a load term (kept in the model by relevance, named or not)
    """

    effect: str
    joints: list
    options: dict
    parameters: dict
    ln_bf: float
    folds: int
    k_folds: int
    cv_with_mm: float
    cv_without_mm: float
    explained_fraction: float
    load: bool = True

    @property
    def gain_mm(self) -> float:
        return float(self.cv_without_mm - self.cv_with_mm)

    @property
    def label(self) -> str:
        return cause_label(self.effect, self.joints, self.options)

    def to_dict(self) -> dict:
        return plain({"effect": self.effect, "joints": list(self.joints), "options": self.options,
                      "parameters": self.parameters, "ln_bf": self.ln_bf, "folds": self.folds,
                      "k_folds": self.k_folds, "cv_with_mm": self.cv_with_mm, "cv_without_mm": self.cv_without_mm,
                      "gain_mm": self.gain_mm, "explained_fraction": self.explained_fraction, "load": self.load})

    def describe(self) -> str:
        vals = ", ".join(f"{v['display'][0]:.3g} ± {v['display'][1]:.2g} {v['display'][2]}".rstrip()
                         for v in self.parameters.values())
        return (f"{self.label}: {vals} — ln B {self.ln_bf:.1f}, kept in {self.folds}/{self.k_folds} folds, lowers "
                f"the error at new postures by {self.gain_mm:.2f} mm, explains {100 * self.explained_fraction:.0f} % of "
                f"the geometric residual")

@dataclass
class DiagnosisResult:
    """What :func:`estcal.discrepancy.diagnose` found (``to_dict()`` for the JSON).

    answer : ``{"expected_mm", "bound95_mm", "basis", "repeatability_mm", "time": {…}}`` — the expected RMSE
        at new postures (the budget's ``expected_mm``), 95 % of points below ``bound95_mm``
    causes : the named :class:`Cause` list
    accuracy : ``{"train_mm", "cv_mm", "validation": [one dict per file: path, rmse_mm (its new postures,
        its frame registered on its seen ones), rmse_se_mm (its standard error over those postures,
        :func:`estcal.validation.rmse_se_mm`), n_new, n_seen, registered, frame_moved, predicted_mm,
        coverage]}`` — one validation figure per file
    terms : what was considered, kept, tested (``tested``: every naming test), regrouped
    budget : the error budget (:class:`estcal.discrepancy.budget.Budget` as a dict) or None
    data : rows, postures, sessions, the time source
    model : the model as plain data (every parameter value, effects, gravity, preparation): the input of
        ``estcal simulate --from-fit`` and of the saved model
    random_effect : the noise of the rows within a posture and the rigid error of a posture (the model error)
    """

    answer: dict
    causes: list
    accuracy: dict
    terms: dict
    budget: dict | None
    data: dict
    model: dict
    noise: dict
    random_effect: dict
    verdict: str
    lumped_masses: bool = False
    report_files: list = field(default_factory=list)
    robot: object = field(default=None, repr=False)
    covariance: object = field(default=None, repr=False)
    covariance_names: list = field(default_factory=list, repr=False)
    sigma0: float = float("nan")
    train_data: object = field(default=None, repr=False)
    validation_data: list = field(default_factory=list, repr=False)
    fit_data: object = field(default=None, repr=False)  # the rows as the diagnosis prepared them (stacked, timed)

    @property
    def named(self) -> list[tuple[str, tuple]]:
        return [(c.effect, tuple(c.joints)) for c in self.causes]

    def to_dict(self) -> dict:
        return plain({"answer": self.answer, "causes": [c.to_dict() for c in self.causes], "verdict": self.verdict,
                      "accuracy": self.accuracy, "terms": self.terms, "budget": self.budget, "data": self.data,
                      "model": self.model, "noise": self.noise, "random_effect": self.random_effect,
                      "lumped_masses": self.lumped_masses, "report_files": self.report_files})

    def _inputs(self) -> list:
        meta = getattr(self.robot, "meta", None) or {}
        train = self.train_data if isinstance(self.train_data, list) else [self.train_data]
        return [getattr(d, "path", None) for d in [*train, *self.validation_data] if d is not None] + \
            [meta.get("robot_file"), meta.get("urdf")]

    def to_json(self, path) -> Path:
        refuse_input(path, self._inputs())
        return write_json(path, self.to_dict())

    def save_model(self, path, provenance: dict | None = None):
        """Write the model (geometry + the effects it keeps, at the estimate) as a robot file with a
        ``calibration:`` block (docs/robot-file.md, "Saved models")."""
        from estcal.io.savedmodel import save_diagnosis

        refuse_input(path, self._inputs())
        return save_diagnosis(self, path, provenance)

    def prepare(self, data):
        """``data`` prepared as the diagnosis prepared its own (approach columns, effect context, time)."""
        from estcal.io.prepare import prepare_data

        return prepare_data(self.robot, data, self.model.get("data_preparation"))

    def figures(self) -> dict:
        """The figures ``{file name: Figure}``: the partial joint residuals of the model's geometry alone (its
        effects set to zero) and of the model (:func:`estcal.discrepancy.analysis.residual_figures`), and the
        error budget's bars."""
        out = {}
        if self.robot is not None and self.fit_data is not None:
            from estcal.methods import NoiseModel, Problem

            from .analysis import residual_analysis, residual_figures

            rb = self.robot
            theta = rb.params.values
            geo = np.where(np.array([k == "effect" for k in rb.params.kinds]), 0.0, theta)
            problem = Problem(rb, [(None, self.fit_data, NoiseModel.parse(self.noise) if self.noise else
                                    NoiseModel(known=False))])
            tau = rb.gravity_torques(self.fit_data.readings, geo, self.fit_data.context)
            analysis = residual_analysis(problem, geo, False, len(self.covariance_names), {"tau": tau})
            out = residual_figures(problem, geo, analysis, tau=tau, title=rb.name,
                                   extended=(problem, theta) if rb.effects else None)
        if self.budget:
            from estcal.plots.budget import budget_figure

            out["budget.png"] = budget_figure(self.budget)
        return out

    # ------------------------------------------------------------------ text
    def __str__(self) -> str:
        return "\n".join(self.answer_lines() + [""] + self.detail_lines())

    def answer_lines(self) -> list[str]:
        """The first screen: how accurate at new postures, why, what is left, each validation file."""
        a, d = self.answer, self.data
        bound = (f"95 % of points within {a['bound95_mm']:.2f} mm" if a.get("bound95_mm") is not None
                 else "too few held-out points for a 95 % bound (19 needed)")
        out = [f"Expected error at new postures: {a['expected_mm']:.2f} mm RMS, {bound} ({a['basis']}; "
               f"{d['n_postures']} postures, {d['n_sessions']} session{'s' if d['n_sessions'] > 1 else ''})"]
        t = a.get("time") or {}
        if t:
            src = "the t column" if t["source"] == "t column" else "the row order (no t column: rows taken as " \
                                                                   "acquired in file order)"
            out.append(f"  later in the campaign (time-blocked CV, time from {src}): {t['model_mm']:.2f} mm — "
                       + ("worse: the error grows over the campaign, so the figure above is the time-blocked one"
                          if t["disagrees"] else "agrees"))
        if self.causes:
            out.append("Named causes (value ± std; evidence; gain at new postures; share of the geometric residual):")
            out += [f"  {c.describe()}" for c in self.causes]
            out += [f"  together, {n}" for n in self.terms.get("together", [])]
            src = d.get("approach_source")
            if src and any(c.options.get("by") == "approach" for c in self.causes):
                out.append("  approach: the side each joint moved from into its posture, " + (
                    "as recorded in the approach_<joint> columns" if src == "recorded" else
                    "from the order of the t column" if src == "t column" else
                    "from the row order (no t column: rows taken as acquired in file order)")
                    + " (--no-approach-from-order leaves backlash by approach out)")
        elif not self.terms.get("effects_considered"):
            out.append("Named causes: none considered — no effect term is a candidate (--effects none, or none "
                       "excitable on these data): the geometric model alone")
        else:
            out.append("Named causes: none — no term passes every test (docs/discrepancy.md, 'Naming')")
        for sf in (self.model.get("session_frames") or {}).values():
            moved = [f"{j} {v[0]:+.1f} ± {v[1]:.1f} {v[2]}" for j, v in (sf.get("zeros") or {}).items()
                     if abs(v[0]) > 3 * v[1]]
            if moved:
                out.append(f"Session {sf.get('name', '')}: joint zeros moved since the first session — "
                           + ", ".join(moved) + " (registered with its measuring frame, as an encoder homed "
                           "elsewhere at start-up; the others within three deviations)")
        rep = a.get("repeatability_mm")
        out.append(f"Unexplained: {a['expected_mm']:.2f} mm RMS at new postures remains with this model; "
                   + (f"repeatability floor {rep:.2f} mm" if rep is not None else
                      "repeatability floor unknown (no posture is measured twice)"))
        for v in self.accuracy.get("validation", []):
            out.append("Validation " + _validation_line(v))
        left = self.data.get("left_out") or []
        if left:
            rows = "; ".join(f"{r['file']} line {r['line']} ({r['kind']})" for r in left[:6])
            out.append(f"Left out: {len(left)} row(s) the data screening flags — {rows}"
                       + (" …" if len(left) > 6 else "") + " (--keep-all fits them; `estcal check` says why)")
        return out

    def detail_lines(self) -> list[str]:
        t, acc = self.terms, self.accuracy
        g = t["geometric"]
        width = _width_text(t["geometric_mode"], self.model.get("geometric_width"),
                            self.model.get("geometric_width_choice"))
        out = [f"model: {t['n_free']} registration parameters free; {g['kept']} of {g['considered']} geometric "
               f"parameters and {t['effects_kept']} of {t['effects_considered']} effect terms kept by the "
               f"evidence ({t['geometric_mode']} geometry{width}); training RMSE {acc['train_mm']:.3f} mm"]
        re_ = self.random_effect
        if re_:
            out.append(f"residual within a posture {re_['sigma_mm']:.3f} mm; a posture's rigid error (model error) "
                       f"{re_['translation_mm']:.2f} mm, {re_['rotation_mrad']:.2f} mrad RMS")
        kept = [r for r in t.get("kept_unnamed", [])]
        if kept:
            out.append("kept, not named (load terms the evidence keeps): " + ", ".join(kept))
        unscored = [r["term"] for r in t.get("tested", []) if not r["named"] and r["reason"].startswith("not scored")]
        for r in t.get("tested", []):
            if not r["named"] and r["term"] not in unscored:
                out.append(f"not named: {r['term']} — {r['reason']}")
        if unscored:
            out.append(f"not scored: {len(unscored)} further candidate terms (the search stops at the first step where "
                       f"none passes; the JSON's terms.tested lists them)")
        if t.get("regrouped"):
            out.append("regrouped into geometry (not separable on these data): "
                       + ", ".join(r["term"] for r in t["regrouped"]))
        if self.budget:
            from .budget import budget_lines

            out += budget_lines(self.budget)
        return out


def _width_text(mode: str, w, choice=None) -> str:
    """The link frames' prior bound on the model line (``model["geometric_width"]``) and, when the one-standard-
    error rule chose it (``model["geometric_width_choice"]``), the two cross-validated errors it compared."""
    if mode == "full":
        return ""
    text = "" if w is None else f", link frames' priors within {w * 1e3:g} mm / {w * 1e3:g} mrad"
    if choice:
        b = choice["bound_si"] * 1e3
        text = (f"{text or ', link frames unbounded'} — by the one-standard-error rule: CV "
                f"{choice['cv_bounded_mm']:.2f} mm within {b:g} mm / {b:g} mrad, {choice['cv_unbounded_mm']:.2f} "
                f"unbounded (+1 SE: {choice['cv_unbounded_plus_se_mm']:.2f})")
    return text


def _validation_line(v: dict) -> str:
    se = f" ± {v['rmse_se_mm']:.2f}" if v.get("rmse_se_mm") is not None else ""
    s = f"{v['path']}: {v['rmse_mm']:.2f}{se} mm at its {v['n_new']} new-posture rows"
    if v.get("registered"):
        fm = v["frame_moved"]
        s += (f" (measuring frame registered on its {v['n_seen']} rows at seen postures: moved {fm['rotation_mrad']:.2f} "
              f"mrad, {fm['translation_mm']:.2f} mm")
        zs = v.get("zeros_moved") or []
        if zs:
            s += "; " + ", ".join(f"{z['joint']}'s zero moved by {z['display'][0]:+.1f} ± {z['display'][1]:.1f} "
                                  f"{z['display'][2]}" for z in zs) + " since training, registered there too"
        s += ")"
    elif v["n_seen"]:
        s += f" ({v['n_seen']} rows at seen postures, too few to register the frame: scored in the training frame)"
    else:
        s += " (no posture in common with the training rows: scored in the training frame)"
    if v.get("predicted_mm") is not None:
        s += f"; predicted {v['predicted_mm']:.2f}"
    if v.get("coverage") is not None:
        s += f", {100 * v['coverage']:.0f} % inside the 95 % region"
    if v.get("load_side_unseen"):
        s += (f" — {100 * v['load_side_unseen']:.0f} % of its rows load {', '.join(v['load_side_joints'])} on the side "
              f"of zero no training row did: the model carries its load terms across zero load there, untested")
    if v.get("beyond_cv_reach"):
        s += (f" — {100 * v['beyond_cv_reach']:.0f} % of its rows extrapolate farther than the cross-validation tried "
              f"({v['reach_joint']}: {v['reach_max']:.2g}× its training range): the prediction is untested there")
    return s
