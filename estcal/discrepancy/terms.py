"""The candidate model of the diagnosis: every term it may keep, and which of them a cause can be.

:func:`build_terms` starts from a registration (the base frame and the unknown points — or the tool — fitted
on the nominal geometry), then collects

* the **registration** parameters: unpenalised (``free``), always estimated;
* the **geometric** parameters the data identify (:func:`estcal.identify.select.select_identifiable` in
  GECARO's priority order, data-level tolerance): each under its own automatic-relevance prior
  (``geometric="sparse"``, the default), unpenalised (``"full"``: the classic calibration), or only the
  joint offsets (``"joint_offset"``). With ``geometric_width`` (:data:`GEOMETRIC_WIDTH`, 1 mm / 1 mrad, a
  machined arm's tolerance) the search moves a link frame's prior only to widths within it, or prunes it; it
  starts from one ridge width for the whole geometry (:func:`estcal.discrepancy.relevance.fit_relevance`), so
  a link frame ends within the bound, out, or — where no prior within the bound explains the data better — at
  that ridge width. The diagnosis's default (:data:`WIDTH_AUTO`) fits the model with the bound and without it
  and keeps the bounded one unless the unbounded one's cross-validated error is lower by more than one
  standard error (:func:`estcal.discrepancy.diagnose._width_and_terms`): on TIAGo's small halvings (14–31
  postures, new postures of the other session) the bound is kept on 67 of 72 and lowers the error (3.46 →
  2.81 mm on the set declared before the rule; experiments/tiago_disjoint.md), and a nominal model off by
  about the bound or more — whose misfit the bound would name as causes (simulated PUMA, 1 mm / 1 mrad
  errors, one point: a gear harmonic and a backlash on clean data) — shows it in its CV error and keeps the
  unbounded priors (tests/test_diagnose.py). Joint offsets, the tool and the registration are never bounded:
  a zero is wherever the homing put it, a tool wherever it was mounted;
* every **effect term** of the library the data excite (:func:`estcal.discrepancy.diagnose.default_candidates`,
  one term per effect and joint; whole-arm effects once): each a group of parameters under
  automatic-relevance priors. A term whose columns lie in the span of the registration and geometric
  columns *regroups* into them (its orthogonal part below ``regroup_tol`` of its norm): the data cannot tell
  it from geometry, so it is listed in ``regrouped`` and never a candidate.

Two kinds of effect term (measured on TIAGo at new postures in another session, docs/discrepancy.md):

* **load terms** — joint compliance, backlash, link tilt (:data:`LOAD_EFFECTS`): deflections under the
  gravity load the robot already carries, bounded by it wherever the posture goes. The evidence keeps
  the ones it finds relevant in the model, named or not (they lower the error at new postures from 5.7 to
  3.1 mm there);
* **special terms** — gear harmonics, encoder gains, drift, thermal expansion and any user effect:
  functions of the joint reading or of time that grow or oscillate beyond the data. Kept by relevance alone
  they raise that error to 8–10 mm (a harmonic of a joint seen over part of its range fits cancellations
  that explode beyond it), so a special term enters the model only when it is *named* — when it passes
  every test of :mod:`estcal.discrepancy.relevance`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from estcal.effects import EFFECTS, make_effect
from estcal.effects.library import across_axis_moments

__all__ = ["LOAD_EFFECTS", "GEOMETRIC_MODES", "GEOMETRIC_WIDTH", "WIDTH_AUTO", "Candidate", "default_candidates",
           "Term", "Terms", "build_terms", "n_sessions"]

#: the effects whose terms the evidence keeps without naming them (module docstring)
LOAD_EFFECTS = ("joint_compliance", "backlash", "link_tilt")
#: how the geometric parameters enter the model
GEOMETRIC_MODES = ("sparse", "full", "joint_offset")
#: a machined arm's link-frame tolerance (m for a length, rad for an angle): the bound the diagnosis tries by
#: default (:data:`WIDTH_AUTO`; module docstring)
GEOMETRIC_WIDTH = 1e-3
#: ``geometric_width`` of the diagnosis by default: :data:`GEOMETRIC_WIDTH` or unbounded, by the one-standard-error
#: rule on the cross-validated error (:func:`estcal.discrepancy.diagnose._width_and_terms`)
WIDTH_AUTO = "auto"


@dataclass
class Candidate:
    """One candidate extension: registered effect ``effect`` on ``joints`` with ``options``."""

    effect: str
    joints: list | None = None
    options: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        j = ",".join(self.joints) if self.joints else "arm"
        o = "".join(f"[{k}={v}]" for k, v in self.options.items() if k in ("orders", "scope", "by"))
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
        return {"effect": self.effect, "joints": self.joints, "options": dict(self.options)}


def n_sessions(data) -> int:
    """Sessions stacked in ``data`` (its ``session`` column; 1 without one)."""
    lab = data.columns.get("session")
    return 1 if lab is None else len(np.unique(lab))


def default_candidates(robot, data, effects: Sequence[str] | None = None, harmonic_orders=(1, 2, 3),
                       families: bool = False):
    """Candidates from the effect registry for ``robot`` and ``data``: per joint for effects that take joints
    (harmonic orders as separate candidates), once for whole-arm effects (thermal expansion in both forms,
    whole arm and links only); time effects only when the data have a time (``t`` in the context),
    gravity effects only on joints the data load (a torque that is numerically zero, or of one sign for
    backlash by the load, gives a column that is noise or an offset); backlash by approach on joints whose
    ``approach_<joint>`` column the data carry (not all zero). ``families``: also every
    joint effect once over all its eligible joints. ``effects=None``: every registered effect."""
    names = list(EFFECTS) if effects is None else list(effects)
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
    # several sessions: time runs from each session's mean, so a time effect is zero there and never shifts one
    # session against another
    t_zero = 0.0 if n_sessions(data) > 1 else (float(np.min(ctx["t"])) if "t" in ctx else 0.0)
    for name in names:
        if name == "drift":
            if "t" not in ctx:
                continue
            opts = {"t0": t_zero}
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
        if name == "gear_harmonic":
            variants = [dict(opts, orders=[k]) for k in harmonic_orders]
        elif name == "backlash":
            # the link rests on the side its load pushes it to, or where the motor left it (Backlash): both are
            # candidates when the data record the approach
            variants = [dict(opts, by="load"), dict(opts, by="approach")]
        else:
            variants = [opts]
        per_joint = []
        for ji, j in enumerate(robot.joint_names):
            ok = variants
            if name in ("joint_compliance", "backlash") and tau is not None:
                t = tau[:, ji]
                if np.abs(t).max() <= 1e-9 * big:
                    ok = [o for o in ok if o.get("by") == "approach"]
                elif name == "backlash" and (np.all(t > 0) or np.all(t < 0)):
                    ok = [o for o in ok if o.get("by") == "approach"]
            if name == "backlash":
                a = ctx.get("approach_" + j)
                if a is None or not np.any(a):
                    ok = [o for o in ok if o.get("by") != "approach"]
            elif name == "link_tilt" and np.abs(m_across[:, ji]).max() <= 1e-9 * max(float(m_across.max()), 1e-300):
                continue  # no moment across this axis (no mass beyond it, or no gravity)
            for o in ok:
                try:
                    eff = Candidate(name, [j], o).make(robot)
                except (ValueError, TypeError):
                    continue
                if name == "gear_harmonic" and robot.joint_types[ji] == "revolute" and (
                        np.ptp(data.readings[:, ji]) * abs(eff.gear_ratio[j]) * o["orders"][0] < np.pi):
                    # over less than half its period (of the phase: the reading times the gear ratio) a harmonic
                    # of order n is a quadratic in the angle that trades with the offset and the geometry, its
                    # continuation beyond the range unknown (TIAGo, 18 postures over 0.49 rad of arm_3: a 20 mrad
                    # third-order harmonic named, 6.25 mm at new postures)
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
class Term:
    """One candidate effect term: ``effect`` on ``joints`` (empty: the whole arm) with ``options``; its
    parameter ``names``; ``load`` for a load term (module docstring)."""

    effect: str
    joints: list
    options: dict
    names: list
    load: bool

    @property
    def label(self) -> str:
        j = ",".join(self.joints) if self.joints else "arm"
        o = "".join(f"[{k}={v}]" for k, v in self.options.items() if k in ("orders", "scope", "by"))
        return f"{self.effect}{o}({j})"

    def to_dict(self) -> dict:
        return {"effect": self.effect, "joints": list(self.joints), "options": dict(self.options),
                "parameters": list(self.names), "load": self.load}


@dataclass
class Terms:
    """What :func:`build_terms` returns.

    robot : the robot ready for gravity, with every candidate effect added (at zero, its nominal value)
    theta0 : (P,) the registration estimate (full parameter vector)
    nominal : (P,) the prior mean of every parameter (nominal geometry, zero effects)
    free : unpenalised names (registration; with ``geometric="full"`` the geometric ones too)
    geometric : the identifiable geometric names (penalised unless ``geometric="full"``)
    terms : the effect terms
    regrouped : ``[{"term", "orthogonal_fraction"}]`` of the terms that regroup into geometry
    geometric_mode : one of :data:`GEOMETRIC_MODES`; lumped : the robot has no masses (1 kg lumped per link)
    base : the same robot without the candidate effects (the model adds back those it keeps)
    session_zeros : ``{session: [zero parameter names]}`` — for every session after the first, the joint zeros
        registered with its frame (:func:`session_zero_names`)
    geometric_width : the widest prior standard deviation of a link frame's parameter (SI; None: unbounded)
    """

    robot: object
    theta0: np.ndarray
    nominal: np.ndarray
    free: list
    geometric: list
    terms: list
    regrouped: list = field(default_factory=list)
    geometric_mode: str = "sparse"
    lumped: bool = False
    base: object = None
    session_zeros: dict = field(default_factory=dict)
    geometric_width: float | None = None

    @property
    def penalised(self) -> list:
        geo = [] if self.geometric_mode == "full" else list(self.geometric)
        return geo + [n for t in self.terms for n in t.names]

    def alpha_min(self) -> np.ndarray:
        """(len(penalised),) the least prior precision the evidence search moves every penalised parameter to
        (``alpha_min`` of :func:`estcal.estimate.sparse.sparse_bayes`): ``1/geometric_width²`` for a link frame's
        parameter (kind ``geometric``), 0 (unbounded) for the joint offsets, the tool and the effect terms."""
        if self.geometric_width is None:
            return np.zeros(len(self.penalised))
        kinds = self.kinds()
        return np.array([self.geometric_width ** -2 if kinds.get(n) == "geometric" else 0.0 for n in self.penalised])

    def term_index(self) -> np.ndarray:
        """(len(penalised),) the index in ``terms`` of each penalised parameter (−1: geometric)."""
        owner = {n: i for i, t in enumerate(self.terms) for n in t.names}
        return np.array([owner.get(n, -1) for n in self.penalised], int)

    def kinds(self) -> dict:
        return dict(zip(self.robot.params.names, self.robot.params.kinds))


def set_load_sides(robot, data, theta) -> int:
    """Set the context columns ``load_side_<joint>`` (±1, the sign of the joint's gravity torque at the
    parameters ``theta``) of ``data`` in place, for every joint (backlash by the load reads them); returns
    the number of (row, joint) sides that changed. A posture whose load is near zero takes the side of the
    model it is evaluated with: at the registration fit the nominal geometry's, which the fitted geometry can
    contradict (a 7 mrad backlash on the wrong side at 2 of 50 postures doubles the residual)."""
    tau = robot.gravity_torques(data.readings, theta, data.context)
    changed = 0
    for ji, j in enumerate(robot.joint_names):
        side = np.where(tau[:, ji] >= 0, 1.0, -1.0)
        old = data.context.get(f"load_side_{j}")
        changed += int(len(side) if old is None else np.sum(old != side))
        data.context[f"load_side_{j}"] = side
    return changed


def build_terms(robot, data, noise, effects=None, geometric: str = "sparse", ident_tol: float = 1e-4,
                regroup_tol: float = 1e-3, geometric_width: float | None = None) -> Terms:
    """The candidate model of ``robot`` on ``data`` (module docstring).

    effects : registered effect names to consider (None: every registered effect) or ``()`` for none.
    geometric_width : the widest prior standard deviation of a link frame's parameter (m / rad; None: unbounded).
    """
    if geometric_width is not None and not (np.isfinite(geometric_width) and geometric_width > 0):
        raise ValueError(f"geometric_width must be a positive width (m / rad) or None, got {geometric_width!r}")
    from estcal.identify.select import select_identifiable

    from .geometric import geometric_candidates, gravity_ready, orthonormal_basis, weighted_system
    from .stages import fit_stage
    from estcal.methods import Problem

    if geometric not in GEOMETRIC_MODES:
        raise ValueError(f"geometric must be one of {GEOMETRIC_MODES}, got {geometric!r}")
    names = list(EFFECTS) if effects is None else list(effects)
    rb0, theta, reg, _ = fit_stage(robot, data, noise, "nominal")
    rb, lumped = gravity_ready(rb0, theta, robot.params.values)
    base = rb
    cands = list(default_candidates(rb, data, effects=names, families=False)) if names else []
    # one effect instance per kind and options over all its candidate joints: the same parameters as one per
    # joint, but the chain evaluates each kind once (a link tilt turns every other column with the points: eight
    # instances did it eight times)
    kinds_of = {}
    for c in cands:
        kinds_of.setdefault((c.effect, repr(sorted(c.options.items()))), []).append(c)
    for group in kinds_of.values():
        joints = [j for c in group for j in (c.joints or [])]
        rb = rb.add_effect(make_effect(group[0].effect, rb, joints=joints or None, **dict(group[0].options)))
    # the side each joint's load pushes it to, fixed at the registration fit (a context column of the data, in
    # place) and updated once at the fitted model (diagnose): backlash by the load's side would otherwise flip at
    # a posture whose load crosses zero as the geometry moves, and Gauss–Newton would jump back and forth
    if any(c.effect == "backlash" for c in cands):
        set_load_sides(rb, data, rb.params.values)
    problem = Problem(rb, [(None, data, noise)])
    theta0 = rb.params.values.copy()
    geo = geometric_candidates(rb)
    kinds = dict(zip(rb.params.names, rb.params.kinds))
    if geometric == "joint_offset":
        geo = [n for n in geo if kinds[n] in ("base", "marker", "offset") or (kinds[n] == "tool" and rb.n_markers == 0)]
    free = list(reg)
    # the registration first: a geometric parameter the registration can stand in for (a last joint's offset
    # turning a tool point on its axis, which the tool's own translation moves too) is not a candidate — its
    # remainder would be a sliver of noise, and a relevance prior lets such a sliver grow without bound
    order = free + [n for n in geo if n not in set(free)]
    _, A, _ = weighted_system(problem, theta0, order)
    ident = select_identifiable(A, names=order, tol=ident_tol).identifiable
    geometric_names = [n for n in ident if n not in set(free)]
    # effect terms that regroup into the registration and geometric columns are not candidates
    _, A, _ = weighted_system(problem, theta0, free + geometric_names)
    Q = orthonormal_basis(A)
    terms, regrouped = [], []
    # the registration moved only the base and the points: every other parameter is still nominal (effects 0)
    nominal = theta0.copy()
    every = [n for n, k in zip(rb.params.names, rb.params.kinds) if k == "effect"]
    _, E_all, _ = weighted_system(problem, theta0, every)  # one evaluation for every candidate's columns
    col = {n: i for i, n in enumerate(every)}
    for c in cands:
        pn = Candidate(c.effect, c.joints, c.options).make_names(rb)
        if not pn:
            continue
        E = E_all[:, [col[n] for n in pn]]
        En = np.linalg.norm(E, axis=0)
        if np.any(En == 0):
            regrouped.append({"term": c.label, "orthogonal_fraction": 0.0})
            continue
        Ep = E - Q @ (Q.T @ E)
        frac = float(np.min(np.linalg.norm(Ep, axis=0) / En))
        if frac < regroup_tol:
            regrouped.append({"term": c.label, "orthogonal_fraction": frac})
            continue
        terms.append(Term(c.effect, list(c.joints or []), dict(c.options), pn, c.effect in LOAD_EFFECTS))
    if geometric == "full":
        free = free + geometric_names
    zeros = session_zero_names(problem, theta0, data, ident_tol)
    return Terms(rb, theta0, nominal, free, geometric_names, terms, regrouped, geometric, lumped, base, zeros,
                 geometric_width)


def session_zero_names(problem, theta, data, tol: float = 1e-4) -> dict:
    """``{session: [zero parameter names]}`` of every session after the first that measures at least
    :data:`~estcal.discrepancy.zeros.MIN_POSTURES` postures another session measured too: the joint zeros its
    rows identify beside its measuring frame (the six base parameters first, then the joints in chain order, QR
    at the data tolerance ``tol``) — registered with that frame, since a joint homed at start-up reads a new
    session's postures with its zero moved (:mod:`estcal.discrepancy.zeros`). The shared postures measure the
    move whatever the geometry; without them a session's zeros would rest on the model alone. A joint whose
    axis the frame's own motion reproduces (a vertical first axis: the frame's yaw) is not among them."""
    from estcal.identify.select import select_identifiable
    from estcal.validation import posture_groups

    from .geometric import weighted_system
    from .relevance import _BASE
    from .zeros import MIN_POSTURES, zero_parameters

    lab = data.columns.get("session")
    zeros = [n for _, n in zero_parameters(problem.robot)]
    base = [n for n in _BASE if n in problem.robot.params.names]
    if lab is None or len(base) < 6 or not zeros:
        return {}
    order = base + zeros
    _, A, rows = weighted_system(problem, theta, order)
    lab = np.asarray(lab)
    session = lab[rows.pose]
    posture = posture_groups(data.readings, problem.robot.joint_types)
    out = {}
    for s in list(dict.fromkeys(lab.tolist()))[1:]:
        shared = np.intersect1d(posture[lab == s], posture[lab != s])
        if len(shared) < MIN_POSTURES:
            continue
        m = session == s
        ident = select_identifiable(A[m], names=order, tol=tol).identifiable
        out[s] = [n for n in zeros if n in set(ident)]
    return out

