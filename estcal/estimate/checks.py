"""Honest results: refuse degenerate data, flag ill-conditioned or implausible estimates.

A least-squares fit always returns numbers; whether they mean anything depends on
the data. These checks run around :func:`estcal.workflows.calibrate.run_calibration`
(``checks=True``, what ``estcal calibrate`` does) and are documented, with their
thresholds and tests, in ``docs/reliability.md``:

Before the estimation (:func:`precheck`)

* **degrees of freedom** — ``dof = rows − p ≤ 0``: σ0 is undefined and every
  standard deviation would be a guess. Always a refusal.
* **repeated poses** — the number of distinct joint configurations is reported;
  when they carry fewer rows than parameters, a refusal names the repeated lines.
* **rank loss beyond the identifiable set** — the free set chosen on these data is
  compared with the set the same method identifies on *generic* poses (uniform
  within the joint limits, same robot, same linearisation point, consistent
  measurements). Parameters identifiable in general but not on these data mean
  the poses are degenerate (a singular wrist, one joint never moved, …); the
  estimator would otherwise silently fit a smaller set.

After the estimation (:func:`postcheck`)

* **convergence** — an estimator that stopped on its iteration limit;
* **conditioning** — the condition number of the column-scaled, weighted
  observation matrix of the free parameters at the estimate, above
  :data:`COND_MAX`. Good designs of the robots shipped with estcal give 90–250
  (PUMA position / points / pose, TIAGo mocap: ``docs/reliability.md``); a
  wrist held 0.1 mrad from its singularity gives ~10⁶. A relative data error δ
  can move the column-scaled parameters by up to ``cond · δ``.
* **plausibility** — an estimate that moved from its initial value by more than
  :data:`SHIFT_MULTIPLE` times its scale: the prior std when a prior is used
  (MAP, Kalman, MCMC with ``prior_std``), otherwise :data:`NOMINAL_SCALE` (10 mm,
  10 mrad, 1 % of gain) — calibration corrects millimetres and milliradians, and a
  larger move usually means a wrong model or an unidentifiable direction. Base
  frame, markers and method unknowns are exempt (their initial values are
  registrations or placeholders). A warning, never a refusal.

Non-convergence and conditioning are refusals unless ``allow_ill_conditioned``
(``--allow-ill-conditioned``); then they are reported as warnings.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.base.errors import NumericalRefusal
from estcal.identify.select import UnidentifiableError
from estcal.io.dataset import dataset_from_arrays
from estcal.methods.problem import Problem
from estcal.methods.reduced import chi2_and_rows, reduce_system, use_chunks, weighted

from .levels import select_free

__all__ = ["Assessment", "COND_MAX", "NOMINAL_SCALE", "SHIFT_MULTIPLE", "precheck",
           "postcheck", "distinct_poses", "refuse_repeated_early", "generic_identifiable", "structure_key",
           "scaled_condition"]

#: refusal threshold on the condition number of the column-scaled weighted observation matrix
COND_MAX = 1e4
#: plausible size of a calibration correction (m, rad, or relative for gains)
NOMINAL_SCALE = 0.01
#: warn when |estimate − initial| exceeds this many scales (prior std or NOMINAL_SCALE)
SHIFT_MULTIPLE = 3.0
_EXEMPT_KINDS = ("base", "marker", "other")


@dataclass
class Assessment:
    """What the checks found: ``refusals`` (fatal), ``warnings`` and the measured figures."""

    refusals: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    figures: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"refusals": list(self.refusals), "warnings": list(self.warnings),
                "thresholds": {"cond_max": COND_MAX, "nominal_scale": NOMINAL_SCALE,
                               "shift_multiple": SHIFT_MULTIPLE},
                **self.figures}

    def merge(self, other: "Assessment") -> "Assessment":
        return Assessment(self.refusals + other.refusals, self.warnings + other.warnings,
                          {**self.figures, **other.figures})


def _lines(data, idx, most: int = 6) -> str:
    lines = getattr(data, "lines", None)
    ln = [int(lines[i]) if lines is not None else int(i) + 2 for i in idx]
    return ", ".join(map(str, ln[:most])) + (" …" if len(ln) > most else "")


def distinct_poses(readings, decimals: int = 12) -> tuple[int, np.ndarray]:
    """Number of distinct joint configurations and, per pose, the index of its first copy."""
    r = np.round(np.asarray(readings, float), decimals)
    _, first, inv = np.unique(r, axis=0, return_index=True, return_inverse=True)
    return int(first.size), first[inv.reshape(-1)]


def refuse_repeated_early(data, problem=None, level: str = "full") -> None:
    """The cheap refusals made before any registration, selection or QR of the data.

    * data whose distinct joint configurations cannot fix even the base frame (fewer than 3, or
      fewer rows than its 6 parameters);
    * with ``problem`` (the default free set of ``level``, refusals not turned into warnings): repeated
      rows whose distinct configurations carry no more equations than the parameters the same
      measurement identifies on generic poses (:func:`generic_identifiable`, cached per robot
      structure) — the later checks would refuse them (no degrees of freedom, repeated poses or
      rank loss), after a QR of every row.

    ``np.unique`` on the readings: ~1 s for 10⁶ rows, where the QR of the full check would take
    minutes. Raises :class:`NumericalRefusal` naming the repeated lines."""
    if data.kind == "none" or data.n == 0:
        return
    R = np.ascontiguousarray(data.readings, float) + 0.0  # + 0.0: -0.0 and 0.0 are one value
    keys = R.view(np.dtype((np.void, R.dtype.itemsize * R.shape[1]))).ravel()
    _, first_idx, inv = np.unique(keys, return_index=True, return_inverse=True)  # bit-identical rows
    n_distinct, first = int(first_idx.size), first_idx[inv.reshape(-1)]
    per_pose = 6 if data.kind == "pose" else 3 * max(data.n_points, 1)
    rep = np.flatnonzero(first != np.arange(data.n))
    if n_distinct < 3 or n_distinct * per_pose <= 6:
        raise NumericalRefusal(
            f"{data.where}: only {n_distinct} distinct joint configuration(s) among {data.n} poses (repeated lines "
            f"{_lines(data, rep)}): a fit needs at least 3 distinct poses to place the base frame "
            f"— refused before any estimation; measure distinct poses (estcal design proposes them)")
    if problem is None or not rep.size or data.kind not in ("position", "points", "pose"):
        return  # without repeated rows there are at most a few poses here: the full checks are cheap
    gen = generic_identifiable(problem, level, problem.params.values)
    need = len(gen.identifiable) if gen is not None else 0
    if n_distinct * per_pose <= need:
        raise NumericalRefusal(
            f"{data.where}: only {n_distinct} distinct joint configuration(s) among {data.n} poses (repeated lines "
            f"{_lines(data, rep)}) carry at most {n_distinct * per_pose} independent equations, where the {level} "
            f"level identifies {need} parameters on generic poses — refused before any estimation; measure at least "
            f"{need // per_pose + 1} distinct poses (estcal design proposes them), or estimate fewer parameters "
            f"(--level joint_offset, --free …)")


def scaled_condition(A) -> float:
    """Condition number of ``A`` with unit-norm columns (zero columns: ``inf``)."""
    n = np.linalg.norm(A, axis=0)
    if A.shape[1] == 0:
        return 1.0
    if np.any(n == 0):
        return float("inf")
    s = np.linalg.svd(A / n, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


#: generic poses: twice the equations the candidate parameters need, at least this many poses
GENERIC_ROWS_PER_PARAMETER = 2
GENERIC_POSES_MIN = 8
#: registration values (base, markers, tool, method unknowns) are rounded to this before the generic
#: check (m, rad): the structural rank is constant on open sets of them, and rounding lets every fold,
#: session or dataset of one robot share one computation
REGISTRATION_ROUNDING = 1e-3
_GENERIC_CACHE: dict = {}
_GENERIC_CACHE_MAX = 64


def generic_dataset(robot, data, theta, n: int, seed: int = 0):
    """Same kind of data on ``n`` uniform random poses, measured exactly at ``theta``."""
    rng = np.random.default_rng(seed)
    q = robot.random_readings(n, rng)
    # the data's context repeated (a layout of no rows, such as a header read before any row: none)
    ctx = {k: np.asarray(v)[np.arange(n) % data.n] for k, v in data.context.items()} if data.n else {}
    kin = robot.kinematics(q, theta[: robot.n_params] if theta.size > robot.n_params else theta, ctx,
                           jacobian=False)
    if data.kind == "pose":
        return dataset_from_arrays(data.joint_names, q, R=kin.R, p=kin.p, context=ctx)
    k = data.n_points
    pts = kin.points[:, :k] if robot.n_markers >= k else kin.p[:, None, :]
    return dataset_from_arrays(data.joint_names, q, points=pts, context=ctx)


def _elements(elems) -> list:
    return [(e.kind, e.axis, e.param) for e in elems]


def structure_key(problem, theta, n: int, extra=()) -> str:
    """sha256 of what decides the generic identifiable set of ``problem`` at ``theta``: the robot's
    chain (links, constant frames, motions, joint types and limits, couplings, masses, effects),
    its parameter names and kinds, the linearisation point, the measurement (method, kind, points,
    joints, the context of the ``n`` generic poses) and ``extra`` (the selection's arguments)."""
    import hashlib

    robot, t = problem.robot, problem.terms[0]
    h = hashlib.sha256()

    def put(*xs):
        for x in xs:
            h.update(np.ascontiguousarray(x).tobytes() if isinstance(x, np.ndarray) else repr(x).encode())
            h.update(b"|")

    pv = problem.params
    put(type(robot).__name__, tuple(pv.names), tuple(pv.kinds), np.asarray(theta, float), n, extra)
    for attr in ("joint_types", "limits", "offset_idx", "gain_idx", "marker_idx", "gravity", "payload_mass",
                 "payload_com", "coupling", "convention"):
        v = getattr(robot, attr, None)
        put(np.asarray(v) if isinstance(v, np.ndarray) else v)
    for ln in getattr(robot, "links", ()):
        put(ln.label, np.asarray(ln.const, float), _elements(ln.before), ln.joint, ln.joint_kind,
            np.asarray(ln.joint_axis, float), ln.joint_param, _elements(ln.after), float(ln.mass),
            np.asarray(ln.com, float))
    for e in getattr(robot, "effects", ()):
        put(type(e).__qualname__, sorted((k, v.tolist() if isinstance(v, np.ndarray) else v)
                                         for k, v in vars(e).items() if not callable(v)))
    put(getattr(t.method, "name", None), t.data.kind, t.data.n_points, tuple(t.data.joint_names))
    for k in sorted(t.data.context):
        put(k, np.asarray(t.data.context[k])[np.arange(n) % t.data.n])
    return h.hexdigest()


def generic_identifiable(problem, level, theta, exclude=(), groups=None, exact: bool = False):
    """The selection the same method makes on generic poses (see module docstring), or None when
    the data are not direct measurements (links, planes: their analysis is ``estcal identifiable``).

    Structural identifiability belongs to the robot and the measurement, not to the data: it is
    computed once per content (:func:`structure_key`; an in-process cache) on as few uniform random
    poses as give twice the equations the candidates need (at least :data:`GENERIC_POSES_MIN`), at
    ``theta`` with its registration values rounded to :data:`REGISTRATION_ROUNDING` (``exact``: not rounded —
    a regrouping that holds exactly at ``theta``, such as a base axis along a joint axis at −90°, is then
    seen)."""
    if len(problem.terms) != 1:
        return None
    t = problem.terms[0]
    if t.data.kind not in ("position", "points", "pose"):
        return None
    one = Problem.__new__(Problem)  # one pose tells the rows per pose (no pass over large data)
    one.robot, one.terms = problem.robot, [type(t)(t.method, t.data.subset([0]), t.noise)]
    rows_per_pose = max(1, len(one.evaluate(theta, jacobian=False).e))
    pv = problem.params
    n = max(GENERIC_POSES_MIN, int(np.ceil(GENERIC_ROWS_PER_PARAMETER * len(pv.names) / rows_per_pose)))
    th = np.asarray(theta, float).copy()
    reg = np.array([k in _EXEMPT_KINDS or k == "tool" for k in pv.kinds])
    if not exact:
        th[reg] = np.round(th[reg] / REGISTRATION_ROUNDING) * REGISTRATION_ROUNDING
    key = structure_key(problem, th, n, (level, None if groups is None else [list(g) for g in groups],
                                         sorted(exclude)))
    if key in _GENERIC_CACHE:
        return _GENERIC_CACHE[key]
    try:
        gen = Problem(problem.robot, [(t.method, generic_dataset(problem.robot, t.data, th, n), t.noise)], t.noise)
        out = select_free(gen, level, "structural", theta=th, refine_registration=False, exclude=exclude,
                          groups=groups)
    except (ValueError, np.linalg.LinAlgError, AttributeError, IndexError):
        out = None
    if len(_GENERIC_CACHE) >= _GENERIC_CACHE_MAX:
        _GENERIC_CACHE.pop(next(iter(_GENERIC_CACHE)))
    _GENERIC_CACHE[key] = out
    return out


def precheck(problem, free, *, sel=None, level="full", allow_ill_conditioned: bool = False,
             exclude=(), priors: bool = False) -> Assessment:
    """Checks before estimating ``free`` (see module docstring). ``priors``: every free parameter that is not
    registration has a proper prior (a MAP fit): a pair that regroups is then determined by the priors, not
    refused (the conditioning is checked on the fit with its prior rows)."""
    out = Assessment()
    pv = problem.params
    t = problem.terms[0]
    data = t.data
    theta = sel.theta if (sel is not None and sel.theta is not None) else pv.values
    m = chi2_and_rows(problem, theta)[1]
    p = len(free)
    out.figures.update(rows=int(m), n_parameters=int(p), dof=int(m - p))
    n_distinct = None
    if data.kind != "none" or data.n:
        n_distinct, first = distinct_poses(data.readings)
        out.figures.update(n_poses=int(data.n), distinct_poses=n_distinct)
    per_pose = m / max(data.n, 1)
    if m - p <= 0:
        need = int(np.floor(p / max(per_pose, 1e-300))) + 1
        out.refusals.append(
            f"{data.where}: {data.n} poses give {m} equations for {p} free parameters (degrees of freedom "
            f"{m - p} ≤ 0): σ0 and every standard deviation would be undefined. Measure at least {need} "
            f"distinct poses, or estimate fewer parameters (--level joint_offset, --free …)")
        return out
    if n_distinct is not None and n_distinct < data.n and n_distinct * per_pose <= p:
        rep = np.flatnonzero(first != np.arange(data.n))
        out.refusals.append(
            f"{data.where}: only {n_distinct} distinct joint configuration(s) among {data.n} poses (repeated "
            f"lines {_lines(data, rep)}); {n_distinct} distinct pose(s) carry {int(n_distinct * per_pose)} independent "
            f"equations for {p} parameters. Repeating a pose averages noise but identifies nothing new — "
            f"measure distinct poses (estcal design proposes them)")
        return out
    gen = None
    if sel is not None:
        gen = generic_identifiable(problem, level, np.asarray(theta, float), exclude=exclude)
    elif data.kind in ("position", "points", "pose") and not priors:
        gen = generic_identifiable(problem, level, np.asarray(theta, float), groups=[list(free)])
        here = select_free(problem, groups=[list(free)], theta=theta, refine_registration=False)
        if gen is not None and len(here.identifiable) < len(gen.identifiable):
            exact = generic_identifiable(problem, level, np.asarray(theta, float), groups=[list(free)], exact=True)
            if exact is not None and len(exact.identifiable) < p:
                raise UnidentifiableError(regrouping_message(exact, free))
        if gen is not None and len(here.identifiable) == len(gen.identifiable) and len(gen.identifiable) < p:
            raise UnidentifiableError(regrouping_message(gen, free))
        sel = here
    if gen is not None:
        here = list(sel.identifiable) + list(sel.rejected)  # aic/bic pruning is a choice, not a rank loss
        lost = [n for n in gen.identifiable if n not in here]
        out.figures.update(identifiable_here=len(here), identifiable_generic=len(gen.identifiable))
        if len(here) < len(gen.identifiable):
            msg = (f"{data.where}: these poses identify {len(here)} parameters where the same "
                   f"measurement on generic poses identifies {len(gen.identifiable)} — degenerate data (a "
                   f"joint near a singularity or barely moved, too few distinct poses); lost: "
                   f"{', '.join(lost[:8])}{' …' if len(lost) > 8 else ''}. Measure poses spread over the "
                   f"joint ranges (estcal design), or pass --allow-ill-conditioned to fit the smaller set")
            (out.warnings if allow_ill_conditioned else out.refusals).append(msg)
    return out


def regrouping_message(sel, free) -> str:
    """A ``--free`` set whose parameters regroup on any poses (``sel``: the selection on generic poses),
    in the words of ``estcal identifiable`` (no effect (0), regrouped (n), the base parameter's formula)."""
    lost = [n for n in free if n not in sel.identifiable]
    parts = []
    for n in lost:
        rel = sel.regrouped.get(n) if hasattr(sel, "regrouped") else None
        if n in getattr(sel, "no_effect", ()):
            parts.append(f"{n} has no effect (0) on this measurement")
        elif rel:
            kept = ", ".join(f"{k} ({b:+.4g})" for k, b in rel.items())
            formula = " and ".join(f"{k} {'+' if b >= 0 else '-'} {abs(b):.4g}*{n}" for k, b in rel.items())
            parts.append(f"{n} is regrouped (n), absorbed by {kept}: only {formula} is identifiable")
        else:
            parts.append(f"{n} is regrouped (n)")
    keep = [n for n in free if n in sel.identifiable]
    return (f"--free {','.join(free)}: {'; '.join(parts)} — on any poses, by the robot's structure and the "
            f"measurement (as `estcal identifiable` reports), not because of these data. Estimate the base "
            f"parameter alone (--free {','.join(keep) or '…'}), or let estcal choose the set (--level)")


def postcheck(problem, res, *, allow_ill_conditioned: bool = False) -> Assessment:
    """Checks of a :class:`~estcal.estimate.result.CalibrationResult` (see module docstring)."""
    out = Assessment()
    pv = problem.params
    fidx = pv.indices(res.names)
    try:
        ck = use_chunks(problem)
        if ck is not None:  # large data: the triangular factor has A's singular values
            A = reduce_system(problem, res.theta, fidx, ck)[0]
        else:
            A, _ = weighted(problem.evaluate(res.theta), fidx)
        prior_rows = (res.extra.get("prior") or {}).get("std", {})
        if prior_rows:  # a MAP fit: its prior rows are equations too (the conditioning of AᵀA + diag(1/τ²))
            P = np.zeros((len(prior_rows), A.shape[1]))
            for k, (n, sd) in enumerate(prior_rows.items()):
                P[k, list(res.names).index(n)] = 1.0 / sd
            A = np.vstack([A, P])
        cond = scaled_condition(A)
    except (ValueError, np.linalg.LinAlgError):
        cond = float("nan")
    out.figures.update(condition_number=cond, converged=bool(res.converged))
    bad = []
    if not res.converged and res.method == "mcmc":
        bad.append(f"the MCMC chain did not reach its target effective sample size in {res.n_iterations} steps "
                   f"(extend it: --chain FILE with a larger --option max_steps=N continues a stored chain)")
    elif not res.converged:
        bad.append(f"the estimator {res.method!r} did not converge in {res.n_iterations} iterations")
    if not cond <= COND_MAX:
        bad.append(f"the condition number of the column-scaled observation matrix at the estimate is "
                   f"{cond:.3g} > {COND_MAX:g}: some parameter combinations are barely determined by these "
                   f"poses")
    if bad:
        msg = ("; ".join(bad) + ". The numbers would not be trustworthy — measure better-spread poses, fix the "
               "weakest parameters (`estcal identifiable`), or pass --allow-ill-conditioned to see the result "
               "anyway")
        (out.warnings if allow_ill_conditioned else out.refusals).append(msg)
    kinds = dict(zip(pv.names, pv.kinds))
    prior = (res.extra.get("prior") or {}).get("std", {})
    # a kept parameter absorbs β·Δ of each parameter regrouped into it: its plausible scale grows
    # to NOMINAL_SCALE·√(1 + Σβ²) (e.g. PUMA offset_3 absorbs 49·d_4 — 49 rad per metre)
    grow = {}
    for rel in ((res.extra.get("selection") or {}).get("regrouped") or {}).values():
        for k, b in rel.items():
            grow[k] = grow.get(k, 1.0) + float(b) ** 2
    moved = []
    for n, e, v in zip(res.names, np.asarray(res.estimate), np.asarray(res.nominal)):
        if kinds.get(n) in _EXEMPT_KINDS:
            continue
        s = float(prior[n]) if n in prior else NOMINAL_SCALE * np.sqrt(grow.get(n, 1.0))
        if abs(e - v) > SHIFT_MULTIPLE * s:
            moved.append((abs(e - v) / s, n))
    if moved:
        moved.sort(reverse=True)
        out.warnings.append(
            f"{len(moved)} estimate(s) moved more than {SHIFT_MULTIPLE:g}× their scale ({NOMINAL_SCALE * 1e3:g} "
            f"mm / mrad, grown by the regrouping coefficients, or the prior std) from the initial value: "
            + ", ".join(f"{n} ({r:.0f}×)" for r, n in moved[:6]) + (" …" if len(moved) > 6 else "")
            + " — check the robot model and the units of the data")
    out.figures["moved"] = [n for _, n in moved]
    return out
