"""Calibration levels and the choice of the free (identifiable) parameter set.

A *level* names what is estimated — ``registration`` (base + markers, or the
tool frame), ``joint_offset`` (+ offsets) and ``full`` (+ geometry and tool) —
and :func:`select_free` reduces it to an identifiable set on the calibration
data only: columns of the weighted observation matrix in priority order
(markers and method unknowns, base, offsets, geometric, tool — GECARO's
"offsets before geometry before base/tool", with the registration set nested
first because the data frame is unknown); a column is kept when its component
orthogonal to the kept ones is not numerically zero (GECARO App. III, the shared
:func:`estcal.identify.core.sequential_rank` with the structural tolerance
:data:`~estcal.identify.core.STRUCTURAL_TOL` on unit-norm columns). Dropped columns are reported as *no
effect* or *regrouped* with ``a_j = Σ β_k a_k`` (β = R1⁻¹R2). ``criterion="aic"``
/ ``"bic"`` additionally prunes, greedily, candidates that do not lower the
information criterion of the linearised fit (opt-in).

:func:`run_calibration` is the Python entry point behind ``estcal calibrate``:
problem, base registration, free set, estimator, accuracy before/after.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["LEVELS", "Selection", "level_candidates", "select_free", "run_calibration"]

LEVELS = ("registration", "joint_offset", "full")

# --------------------------------------------------------------------------- selection
@dataclass
class Selection:
    """Outcome of :func:`select_free`.

    identifiable : chosen free parameters (estimation order)
    no_effect : candidates whose column is zero on these data
    regrouped : {dropped name: {kept name: β}} — the kept parameter absorbs β·Δη_dropped
    rejected : identifiable candidates not supported by the information criterion
    condition_number : of the column-scaled weighted observation matrix of the chosen set
    """

    level: str
    criterion: str
    identifiable: list
    no_effect: list = field(default_factory=list)
    regrouped: dict = field(default_factory=dict)
    rejected: list = field(default_factory=list)
    condition_number: float = float("nan")
    theta: np.ndarray | None = field(default=None, repr=False)  # linearisation point (full vector)

    def to_dict(self) -> dict:
        return {"level": self.level, "criterion": self.criterion, "n_identifiable": len(self.identifiable),
                "identifiable": list(self.identifiable), "no_effect": list(self.no_effect),
                "regrouped": {k: dict(v) for k, v in self.regrouped.items()}, "rejected": list(self.rejected),
                "condition_number": float(self.condition_number)}

    def regroup_label(self, name: str) -> str:
        """``name`` followed by the dropped parameters it absorbs (readable regrouping)."""
        terms = [(d, b) for d, rel in self.regrouped.items() for k, b in rel.items() if k == name]
        terms.sort(key=lambda t: -abs(t[1]))
        parts = [f"{b:+.3g}·{d}" for d, b in terms]
        if not parts:
            return name
        shown = " ".join(parts[:3]) + (" …" if len(parts) > 3 else "")
        return f"{name} [{shown}]"


def level_candidates(pv, level: str, pose_data: bool = False) -> list[list[str]]:
    """Candidate groups of a level, in priority order (the first group is the registration set)."""
    if level not in LEVELS:
        raise ValueError(f"unknown level {level!r}; choose one of {LEVELS}")
    kinds = dict(zip(pv.names, pv.kinds))
    markers = [n for n in pv.names if kinds[n] == "marker"]
    other = [n for n in pv.names if kinds[n] == "other"]  # unknowns added by the methods
    base = [n for n in pv.names if kinds[n] == "base"]
    tool = [n for n in pv.names if kinds[n] == "tool"]
    if markers:
        reg_tool = []
    else:
        reg_tool = [n for n in tool if n.startswith("tool_t") or pose_data]
    groups = [markers + other + base + reg_tool]
    if level in ("joint_offset", "full"):
        groups.append([n for n in pv.names if kinds[n] == "offset"])
    if level == "full":
        groups.append([n for n in pv.names if kinds[n] == "geometric"])
        groups.append([n for n in tool if n not in reg_tool])
    return groups


def _weighted_matrix(problem, theta):
    """``(A, b, M, bᵀb)``; on large data (A, b) = (R, Qᵀb) of :mod:`estcal.estimate.reduced` — the
    ordered QR below, the regrouping coefficients and the condition number are invariant under Qᵀ."""
    from estcal.estimate.lsq import _weighted
    from estcal.estimate.reduced import reduce_system, use_chunks

    ck = use_chunks(problem)
    if ck is not None:
        R, c, rss, m = reduce_system(problem, theta, np.arange(len(problem.params.names)), ck)
        return R, c, m, rss
    A, b = _weighted(problem.evaluate(theta), slice(None))
    return A, b, A.shape[0], float(b @ b)


def select_free(problem, level: str = "full", criterion: str = "structural", theta=None,
                groups: list[list[str]] | None = None, known_noise: bool | None = None,
                refine_registration: bool = True, exclude=()) -> Selection:
    """Identifiable free set of a level on the problem's (calibration) data.

    Parameters
    ----------
    problem : :class:`estcal.methods.Problem` (its data: the calibration file only)
    level : ``registration``, ``joint_offset`` or ``full`` (ignored when ``groups`` is given)
    criterion : ``structural`` (QR rank only), ``aic`` (+ Akaike's criterion, see module docstring)
        or ``bic`` (Schwarz: penalty ln M per parameter instead of 2)
    theta : linearisation point (default: the problem's values)
    groups : explicit candidate groups in priority order (first group = always-kept set)
    known_noise : AIC with absolute weights (default: from the problem's noise models)
    refine_registration : linearise at the fit of the first group (registration) for higher levels
    exclude : names reported as *no effect* without looking at their columns (e.g. the
        parameters a structural analysis on consistent simulated data found without effect)

    The scan is :func:`estcal.identify.core.sequential_rank` — QR without pivoting on the
    priority-sorted, unit-norm columns: ``|R_jj| ≤ STRUCTURAL_TOL`` marks a dependent column
    (GECARO App. III, with the priority order of §1.5 deciding which of dependent columns is kept).
    """
    if criterion not in ("structural", "aic", "bic"):
        raise ValueError(f"unknown selection criterion {criterion!r}; choose 'structural', 'aic' or 'bic'")
    pv = problem.params
    pose = any(t.data.kind == "pose" for t in problem.terms)
    if groups is None:
        groups = level_candidates(pv, level, pose)
    exclude = set(exclude)
    if exclude:
        groups = [[n for n in g if n not in exclude] for g in groups]
    theta = pv.values.copy() if theta is None else np.asarray(theta, float)
    A, b, M, rss = _weighted_matrix(problem, theta)
    norms = np.linalg.norm(A, axis=0)
    first = set(pv.indices(groups[0])) if groups and groups[0] else set()
    order = [pv.index(n) for g in groups for n in g]
    if known_noise is None:
        known_noise = all(t.noise.known for t in problem.terms)
    if refine_registration and len(groups) > 1 and first:
        # Linearise where the registration set fits the data: at the nominal point the
        # unknown markers sit at the tool origin, which creates dependencies (marker vs
        # last-joint placement) that vanish once the markers are located.
        from estcal.estimate.lsq import calibrate_lsq

        reg_sel = select_free(problem, groups=[groups[0]], theta=theta)
        if reg_sel.identifiable:
            try:
                r0 = calibrate_lsq(problem.with_values(theta), "lm", free=reg_sel.identifiable, check=False)
                theta = r0.theta
                A, b, M, rss = _weighted_matrix(problem, theta)
                norms = np.linalg.norm(A, axis=0)
            except (ValueError, np.linalg.LinAlgError):  # keep the given linearisation point
                pass
    from estcal.identify.core import STRUCTURAL_TOL, sequential_rank

    n_kept = 0
    pen = np.log(M) if criterion == "bic" else 2.0  # Akaike: 2 per parameter; Schwarz: ln M

    def aic(r, p):
        return r + pen * p if known_noise else M * np.log(max(r, 1e-300) / M) + pen * p

    def accept(i, u):
        # information criterion on the new orthonormal direction u: RSS drops by (uᵀb)²
        nonlocal rss, n_kept
        if criterion == "structural":
            return True
        r_new = rss - float(u @ b) ** 2
        if i not in first and not aic(r_new, n_kept + 1) < aic(rss, n_kept):
            return False
        rss, n_kept = r_new, n_kept + 1
        return True

    scan = sequential_rank(A, STRUCTURAL_TOL, order, accept=accept)
    kept, regrouped_idx = scan.kept, scan.dependent
    no_effect = [pv.names[i] for i in scan.no_effect]
    rejected = [pv.names[i] for i in scan.rejected]
    regrouped = {}
    if kept and regrouped_idx:
        Ak = A[:, kept] / norms[kept]
        for j in regrouped_idx:
            beta, *_ = np.linalg.lstsq(Ak, A[:, j] / norms[j], rcond=None)
            coef = beta * norms[j] / norms[kept]  # unscaled: a_j = Σ coef_k a_k
            rel = {pv.names[kept[m]]: float(c) for m, c in enumerate(coef) if abs(beta[m]) > 1e-6}
            regrouped[pv.names[j]] = rel
    cond = float("nan")
    if kept:
        s = np.linalg.svd(A[:, kept] / norms[kept], compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    no_effect = [n for n in pv.names if n in exclude] + no_effect
    # estimation order: the vector's own order (stable, readable tables)
    names = [pv.names[i] for i in sorted(kept)]
    return Selection(level, criterion, names, no_effect, regrouped, rejected, cond, theta)


def _saved_free_set(robot, problem, level, selection) -> list[str] | None:
    """The free set a saved model was identified with, when this calibration asks for the same
    level, criterion and measurement method.

    The structural selection (GECARO priorities and the QR of App. III) is meant for the
    *designed* geometry: at a calibrated one, zero lengths and right angles are off by the
    calibration errors (PUMA ``d_2`` = −0.95 mm, ``alpha_1`` = −π/2 + 1 mrad), the priorities
    change and near-dependent parameters (``beta_1`` of perpendicular axes, |R_jj| ~ 1e-5) pass
    the numerical-zero test — a recalibration would fit a set with condition number ~10⁵.
    The set identified at the design stays identifiable at the calibrated point."""
    cal = robot.meta.get("calibration") or {}
    saved = cal.get("free")
    if not saved or cal.get("level") != (level or "full") or \
            cal.get("selection_criterion", "structural") != (selection or "structural"):
        return None
    term = problem.terms[0]
    name = getattr(term.method, "name", None)
    if cal.get("measure") not in (None, name) or not all(n in problem.params for n in saved):
        return None
    return list(saved)


def run_calibration(robot, data, *, measure: str | None = None, estimator: str = "lm",
                    free: list[str] | None = None, level: str | None = "full", selection: str | None = None,
                    validate=(), noise=None, register: bool = True, options: dict | None = None,
                    regularize=None, checks: bool = False, allow_ill_conditioned: bool = False):
    """Python entry point of ``estcal calibrate`` (robot and datasets already loaded).

    ``regularize``: ``None`` (plain least squares), ``"loo"`` (Gaussian prior toward the
    nominal values on the joint-model parameters — geometric placements, offsets, gains,
    tool — with the width τ chosen by leave-one-pose-out CV on ``data``:
    :mod:`estcal.estimate.regularize`), or a fixed τ (SI). Base frame and unknown points are
    never penalised. Needs a least-squares estimator.

    ``checks``: run :mod:`estcal.estimate.checks` — raise
    :class:`~estcal.base.errors.NumericalRefusal` on degenerate data (dof ≤ 0, repeated
    poses, rank loss beyond the generic identifiable set) and, unless ``allow_ill_conditioned``,
    on non-convergence or a condition number above ``COND_MAX``; the figures and warnings go to
    ``result.extra["reliability"]``.

    Returns ``(result, selection, problem)``; ``selection`` is None when ``free`` is given.
    """
    from estcal.estimate import register_base
    from estcal.estimate.registry import get_estimator
    from estcal.methods import NoiseModel, Problem, get_method

    noise = noise or NoiseModel()
    if checks:  # before the registration and the QR of the selection: cheap refusals first
        from estcal.estimate.checks import refuse_repeated_early

        refuse_repeated_early(data)
    method = get_method(measure) if measure else None
    problem = Problem(robot, [(method, data, noise)], noise)
    pv = problem.params
    theta0 = pv.values.copy()
    base_free = True
    sel = None
    reused = free is None and _saved_free_set(robot, problem, level, selection)
    if reused:
        free = reused
    if free is not None:
        problem.with_free(free)  # raises ParameterError naming an unknown parameter / pattern
        # register only when the whole base frame is estimated: Kabsch moves all six
        # base parameters, and a fixed one must keep its given value
        fn = set(problem.with_free(free).params.free_names)
        base_free = all(f"base_{c}" in fn for c in ("tx", "ty", "tz", "rx", "ry", "rz"))
    if register and base_free and data.kind in ("position", "points", "pose") and "base_tx" in pv:
        theta0 = register_base(problem.robot, data, theta0)
        problem = problem.with_values(theta0)
    start = problem
    exclude = []
    if free is None:
        # Default: the full structural identifiable set (QR). Information-criterion
        # pruning (aic/bic) is greedy and can drop parameters whose effect only shows
        # jointly with others, so it is opt-in.
        crit = selection or "structural"
        exclude = _structural_no_effect(robot, problem, level, data) if method is not None else []
        sel = select_free(problem, level, crit, known_noise=noise.known, exclude=exclude)
        free = sel.identifiable
        start = problem.with_values(sel.theta)  # staged: start from the registration fit
    assessment = None
    if checks:
        from estcal.base.errors import NumericalRefusal
        from estcal.estimate.checks import precheck

        assessment = precheck(problem if sel is None else start, list(problem.with_free(free).params.free_names),
                              sel=sel, level=level or "full", allow_ill_conditioned=allow_ill_conditioned,
                              exclude=exclude)
        if assessment.refusals:
            raise NumericalRefusal("\n".join(assessment.refusals))
    est = get_estimator(estimator)
    options = dict(options or {})
    if options:
        from estcal.estimate.registry import check_options

        check_options(estimator, options)
    user_options = dict(options)
    reg_choice = None
    if regularize is not None:
        from estcal.estimate.lsq import LSQ_METHODS
        from estcal.estimate.regularize import choose_prior_std

        if estimator not in LSQ_METHODS:
            raise ValueError(f"regularize needs a least-squares estimator ({', '.join(LSQ_METHODS)}), "
                             f"not {estimator!r}")
        kinds = dict(zip(pv.names, pv.kinds))
        penalised = [n for n in free if kinds.get(n) not in ("base", "marker", "other")]
        if isinstance(regularize, str):
            if regularize != "loo":
                raise ValueError(f"unknown regularize {regularize!r}; use 'loo' or a prior std in SI units")
            reg_choice = choose_prior_std(start, free, penalised, theta=start.params.values)
            options["prior_std"] = reg_choice.prior_std
        else:
            tau = float(regularize)
            if not tau > 0:
                raise ValueError(f"regularize: the prior std must be > 0, got {regularize}")
            options["prior_std"] = {n: tau for n in penalised}
    res = est(start, free=free, validation=list(validate), **options)
    if reg_choice is not None:
        res.extra["regularization"] = reg_choice.to_dict()
    if start is not problem:
        from estcal.estimate.lsq import score

        res.accuracy = score(problem, theta0, res.theta, list(validate))
        res.nominal = theta0[problem.params.indices(res.names)]
    if sel is not None:
        res.extra["selection"] = sel.to_dict()
    elif reused:
        res.extra["selection"] = {"level": level or "full", "criterion": selection or "structural",
                                  "identifiable": list(free), "source": "the saved model's free set"}
    if user_options:
        res.extra["options"] = user_options
    if regularize is not None:
        res.extra["regularize"] = regularize
    res.extra.setdefault("measure", problem.terms[0].method.name)
    if options.get("robust"):
        res.extra["robust_report"] = robust_report(problem, res, options["robust"], options.get("robust_k"))
    if checks:
        from estcal.base.errors import NumericalRefusal
        from estcal.estimate.checks import postcheck

        assessment = assessment.merge(postcheck(problem, res, allow_ill_conditioned=allow_ill_conditioned))
        res.extra["reliability"] = assessment.to_dict()
        if assessment.refusals:
            raise NumericalRefusal("\n".join(assessment.refusals))
    res.extra["initial_guess"] = "nominal + base registration (Kabsch)" if (register and base_free and
                                                                           data.kind != "none") else "nominal"
    res.inputs = tuple(p for p in [getattr(data, "path", None), *(getattr(v, "path", None) for v in validate),
                                   robot.meta.get("robot_file"), robot.meta.get("urdf")] if p)
    return res, sel, problem


def robust_report(problem, res, kernel, k=None) -> dict:
    """:func:`estcal.estimate.robust.outlier_report` at the estimate — at each batch's state for the
    time-varying smoother (its poses were fitted by their own batch's parameters)."""
    from estcal.estimate.robust import check_kernel, group_norms, outlier_report

    kernel = check_kernel(kernel)
    traj = res.extra.get("trajectory")
    if res.method == "gtsam-timevarying" and traj is not None:
        fidx = problem.params.indices(res.names)
        est = np.asarray(traj["estimate"])
        r = dims = lines = None
        bs = int(traj["batch_size"])
        for b in range(est.shape[0]):
            th = res.theta.copy()
            th[fidx] = est[b]
            rb, db, lb, _ = group_norms(problem, th)
            if r is None:
                r, dims, lines = rb.copy(), db, lb
            r[b * bs:(b + 1) * bs] = rb[b * bs:(b + 1) * bs]
        return outlier_report(problem, res.theta, kernel, k, n_params=len(res.names), norms=(r, dims, lines))
    return outlier_report(problem, res.theta, kernel, k, n_params=len(res.names))


_DIRECT = ("position", "location", "pose", "points")


def _structural_no_effect(robot, problem, level, data) -> list[str]:
    """Parameters without effect for a constraint method (links, planes, distance).

    Their observation matrix on real data is evaluated where the constraints do not
    hold exactly, so columns that vanish at consistency (the base orientation for a
    point link, …) are small but not zero there. GECARO's analysis on simulated,
    consistent configurations (:func:`estcal.identify.identify`) finds them; they are
    removed from the candidates. Direct measures (position, location, points) need no
    such step.
    """
    mname = problem.terms[0].method.name
    if mname in _DIRECT or data.kind != "none":
        return []
    try:
        from estcal.identify import identify
    except ImportError:  # pragma: no cover - identify is part of the package
        return []
    cands = [n for g in level_candidates(problem.params, level) for n in g if n in robot.params]
    try:
        ref = identify(robot, mname, None, candidates=cands, check_excitation=False)
    except (ValueError, RuntimeError, np.linalg.LinAlgError):
        return []
    return [n for n in ref.no_effect if n in cands]
