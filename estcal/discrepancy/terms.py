"""The candidate model of the diagnosis: every term it may keep, and which of them a cause can be.

:func:`build_terms` starts from a registration (the base frame and the unknown points — or the tool — fitted
on the nominal geometry), then collects

* the **registration** parameters: unpenalised (``free``), always estimated;
* the **geometric** parameters the data identify (:func:`estcal.identify.select.select_identifiable` in
  GECARO's priority order, data-level tolerance): each under its own automatic-relevance prior
  (``geometric="sparse"``, the default), unpenalised (``"full"``: the classic calibration), or only the
  joint offsets (``"joint_offset"``);
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

import numpy as np

__all__ = ["LOAD_EFFECTS", "GEOMETRIC_MODES", "Term", "Terms", "build_terms"]

#: the effects whose terms the evidence keeps without naming them (module docstring)
LOAD_EFFECTS = ("joint_compliance", "backlash", "link_tilt")
#: how the geometric parameters enter the model
GEOMETRIC_MODES = ("sparse", "full", "joint_offset")


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
        o = "".join(f"[{k}={v}]" for k, v in self.options.items() if k in ("orders", "scope"))
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

    @property
    def penalised(self) -> list:
        geo = [] if self.geometric_mode == "full" else list(self.geometric)
        return geo + [n for t in self.terms for n in t.names]

    def term_index(self) -> np.ndarray:
        """(len(penalised),) the index in ``terms`` of each penalised parameter (−1: geometric)."""
        owner = {n: i for i, t in enumerate(self.terms) for n in t.names}
        return np.array([owner.get(n, -1) for n in self.penalised], int)

    def kinds(self) -> dict:
        return dict(zip(self.robot.params.names, self.robot.params.kinds))


def build_terms(robot, data, noise, effects=None, geometric: str = "sparse", ident_tol: float = 1e-4,
                regroup_tol: float = 1e-3) -> Terms:
    """The candidate model of ``robot`` on ``data`` (module docstring).

    effects : registered effect names to consider (None: every registered effect) or ``()`` for none.
    """
    from estcal.effects import EFFECTS
    from estcal.identify.select import select_identifiable

    from .diagnose import Candidate, default_candidates
    from .geometric import geometric_candidates, gravity_ready, orthonormal_basis, weighted_system
    from .stages import fit_stage
    from estcal.methods import Problem

    if geometric not in GEOMETRIC_MODES:
        raise ValueError(f"geometric must be one of {GEOMETRIC_MODES}, got {geometric!r}")
    names = list(EFFECTS) if effects is None else list(effects)
    rb0, theta, reg, _ = fit_stage(robot, data, noise, "nominal")
    rb, lumped = gravity_ready(rb0, theta, robot.params.values)
    base = rb
    cands = []
    for c in default_candidates(rb, data, effects=names, families=False) if names else []:
        eff = c.make(rb)
        rb = rb.add_effect(eff)
        cands.append(c)
    problem = Problem(rb, [(None, data, noise)])
    theta0 = rb.params.values.copy()
    geo = geometric_candidates(rb)
    kinds = dict(zip(rb.params.names, rb.params.kinds))
    if geometric == "joint_offset":
        geo = [n for n in geo if kinds[n] in ("base", "marker", "offset") or (kinds[n] == "tool" and rb.n_markers == 0)]
    _, A, _ = weighted_system(problem, theta0, geo)
    ident = select_identifiable(A, names=geo, tol=ident_tol).identifiable
    free = list(reg)
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
    return Terms(rb, theta0, nominal, free, geometric_names, terms, regrouped, geometric, lumped, base)

