"""One entry for the identifiable set: :func:`select_identifiable` (GECARO App. III).

Every decision "which of these parameters can be estimated" in estcal goes through
:func:`select_identifiable`: the calibration levels (:func:`estcal.estimate.levels.select_free`),
the refusal of an unidentifiable free set (:func:`check_identifiable`), the experiment design's
base set (:func:`estcal.design.model.identifiable_subset`), the diagnosis's data-level set
(:mod:`estcal.discrepancy.geometric`), the GECARO analysis (:func:`estcal.identify.core.identifiable`)
and the simulated test problems. It scans the unit-norm columns of a weighted observation matrix
in priority order (:func:`estcal.identify.core.sequential_rank`) with a *named* tolerance:

* :data:`~estcal.identify.core.STRUCTURAL_TOL` (1e-10, default) — structural rank: is the column a
  combination of the kept ones, to round-off?
* :data:`~estcal.identify.core.DATA_TOL` (1e-4) — data-level identifiability: can noisy data
  estimate it with a usable variance?

The source is a :class:`~estcal.methods.problem.Problem` (its weighted rows at its values, or at the
design geometry of a saved model; on large data the triangular factor of
:mod:`estcal.methods.reduced`, which has the same column geometry) or a matrix with its column names.
"""
from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

import scipy.linalg as sla

from estcal.base.errors import InputError
from estcal.io.savedmodel import design_values
from estcal.kinematics.parameters import summarize_names, unknown_name_message
from estcal.methods.reduced import CHUNK_POSES, reduce_system, use_chunks

from .core import EPS, STRUCTURAL_TOL, format_relation, resolve_priorities, sequential_rank
from .priorities import scan_priorities

__all__ = ["Selection", "select_identifiable", "check_identifiable", "UnidentifiableError", "identifiable",
           "IdentifiabilityResult", "expand_patterns", "observation_matrix", "reduced_observation_matrix"]


class UnidentifiableError(InputError):
    """The free parameters are not all identifiable from these data."""


@dataclass
class Selection:
    """Outcome of :func:`select_identifiable` (and of the calibration levels).

    identifiable : chosen parameters, in the order of the given names (parameter-vector order)
    no_effect : parameters whose column is zero on these data
    regrouped : {dropped name: {kept name: β}} — the kept parameter absorbs β·Δη_dropped
    rejected : independent parameters refused by the ``accept`` test (e.g. an information criterion)
    condition_number : of the column-scaled observation matrix of the chosen set
    tol : the tolerance the scan used; r_diag : |R_jj| (sine to the span of the kept columns) by name
    level, criterion, theta : set by the calibration levels (level name, criterion, linearisation point)
    """

    identifiable: list
    no_effect: list = field(default_factory=list)
    regrouped: dict = field(default_factory=dict)
    rejected: list = field(default_factory=list)
    condition_number: float = float("nan")
    tol: float = STRUCTURAL_TOL
    r_diag: dict = field(default_factory=dict, repr=False)
    analysed: list = field(default_factory=list, repr=False)  # the names scanned, in the given order
    level: str = ""
    criterion: str = "structural"
    theta: np.ndarray | None = field(default=None, repr=False)

    @property
    def dropped(self) -> list:
        """Every analysed parameter not chosen (no effect, regrouped, rejected), in the given order."""
        keep = set(self.identifiable)
        return [n for n in self.analysed if n not in keep]

    def to_dict(self) -> dict:
        return {"level": self.level, "criterion": self.criterion, "n_identifiable": len(self.identifiable),
                "identifiable": list(self.identifiable), "no_effect": list(self.no_effect),
                "regrouped": {k: dict(v) for k, v in self.regrouped.items()}, "rejected": list(self.rejected),
                "condition_number": float(self.condition_number)}

    def regroup_label(self, name: str) -> str:
        """``name`` followed by the dropped parameters it absorbs (readable regrouping)."""
        terms = [(d, b) for d, rel in self.regrouped.items() for k, b in rel.items() if k == name]
        terms.sort(key=lambda t: -float(f"{abs(t[1]):.9g}"))  # ties to 9 digits: the scan order, not round-off
        parts = [f"{b:+.3g}·{d}" for d, b in terms]
        if not parts:
            return name
        shown = " ".join(parts[:3]) + (" …" if len(parts) > 3 else "")
        return f"{name} [{shown}]"


def select_identifiable(source, candidates=None, *, names: Sequence[str] | None = None, priorities=None,
                        rules: str = "gecaro", tol: float = STRUCTURAL_TOL, zero_tol: float = STRUCTURAL_TOL,
                        theta=None, order=None, accept=None) -> Selection:
    """The identifiable subset of ``candidates`` (GECARO App. III; module docstring).

    Parameters
    ----------
    source : a :class:`~estcal.methods.problem.Problem`, or an observation matrix ``W`` (M, c) whose
        columns are ``names``.
    candidates : for a Problem, names or patterns to consider (default: its free parameters); the
        method's own unknowns (plane, normal) are always included.
    priorities, rules : the order of the scan — higher priority first, ties in the given order
        (for a Problem: GECARO's rules ``"gecaro"`` or ``"order"`` overridden by ``priorities``,
        :func:`estcal.identify.analysis.scan_priorities`; for a matrix: ``priorities`` as
        :func:`estcal.identify.core.resolve_priorities` takes them, default the given order).
        ``order`` (column indices) gives the scan order directly; columns not listed are not analysed.
    tol : :data:`~estcal.identify.core.STRUCTURAL_TOL` or :data:`~estcal.identify.core.DATA_TOL`.
    zero_tol : relative column norm below which a parameter has no effect (structural by default).
    theta : linearisation point of a Problem (default: its values — the design values of a saved model).
    accept : ``accept(j, u) -> bool`` refuses an independent column (``rejected``).

    Returns
    -------
    Selection — ``identifiable`` in the order of the names.
    """
    if hasattr(source, "params"):
        W, names, order = _problem_matrix(source, candidates, priorities, rules, theta)
    else:
        W = np.asarray(source, float)
        names = list(names if names is not None else range(W.shape[1]))
        if W.ndim != 2 or W.shape[1] != len(names):
            raise ValueError(f"W has shape {W.shape} but {len(names)} names were given")
        if order is None and priorities is not None:
            prio = resolve_priorities(names, priorities)
            order = [i for i in np.argsort(-prio, kind="stable") if prio[i] > 0]
    return _scan(W, list(names), order, tol, zero_tol, accept)


def check_identifiable(A, names) -> float:
    """Raise :class:`UnidentifiableError` naming the parameters of ``A``'s columns (the weighted free
    columns of a fit, or their triangular factor) that have no effect or depend on the others —
    :func:`select_identifiable` with the structural tolerance, in the given order. Returns the
    condition number of the column-scaled ``A``."""
    sel = select_identifiable(A, names=list(names))
    if sel.no_effect:
        raise UnidentifiableError(
            f"parameters without effect on these measurements: {sel.no_effect}. Fix them (remove from --free) — "
            f"run `estcal identifiable` to see the identifiable set")
    if sel.regrouped:
        dep = list(sel.regrouped)
        raise UnidentifiableError(
            f"{len(dep)} of the {len(sel.identifiable) + len(dep)} free parameters are not identifiable from these "
            f"data (linearly dependent columns; e.g. {dep}). Fix or regroup them — "
            f"`estcal identifiable` lists an identifiable set")
    return sel.condition_number


def _scan(W, names, order, tol, zero_tol, accept) -> Selection:
    scan = sequential_rank(W, tol, order, zero_tol=zero_tol, accept=accept)
    kept, norms = scan.kept, scan.norms
    regrouped = {}
    if kept and scan.dependent:
        dep = list(scan.dependent)
        # every dependent column at once: one least-squares solve with as many right-hand sides
        betas, *_ = np.linalg.lstsq(W[:, kept] / norms[kept], W[:, dep] / norms[dep], rcond=None)
        for i, j in enumerate(dep):
            beta = betas[:, i]
            coef = beta * norms[j] / norms[kept]  # unscaled: w_j = Σ coef_k w_k
            regrouped[names[j]] = {names[kept[m]]: float(c) for m, c in enumerate(coef) if abs(beta[m]) > 1e-6}
    cond = float("nan")
    if kept:
        s = np.linalg.svd(W[:, kept] / norms[kept], compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    scanned = range(W.shape[1]) if order is None else order
    return Selection([names[i] for i in sorted(kept)], [names[i] for i in scan.no_effect], regrouped,
                     [names[i] for i in scan.rejected], cond, tol,
                     {names[i]: float(scan.r_diag[i]) for i in scanned}, [names[i] for i in sorted(scanned)])


def _problem_matrix(problem, candidates, priorities, rules, theta):
    """``(W, names, order)`` of a Problem: its weighted rows at ``theta`` (a saved model at its design
    geometry), the candidates plus the method's unknowns in vector order, the priority order."""
    if theta is None:  # a saved model: the structure of its design (estcal.io.savedmodel.design_values)
        dv = design_values(problem.robot)
        if dv is not None:
            th = problem.params.values.copy()
            th[problem.params.indices(problem.robot.params.names)] = dv
            problem = problem.with_values(th)
    pv = problem.params
    names = pv.free_names if candidates is None else expand_patterns(pv.names, candidates)
    extras = [n for n, k in zip(pv.names, pv.kinds) if k == "other" and n not in names]
    names = [n for n in pv.names if n in set(names) | set(extras)]
    ck = use_chunks(problem)
    if ck is not None:  # large data: the R factor, built chunk by chunk (same column geometry, bounded memory)
        W, names, _ = reduced_observation_matrix(problem, names, theta, chunk=ck)
    else:
        W, names = observation_matrix(problem, names, theta)
    prio = scan_priorities(problem, names, priorities, rules)
    return W, names, [i for i in np.argsort(-prio, kind="stable") if prio[i] > 0]


def expand_patterns(names: Sequence[str], patterns) -> list[str]:
    """Names matching any of ``patterns`` (fnmatch; a comma-separated string is split), in ``names`` order.

    A wildcard pattern may match nothing (so one candidate list serves Khalil, DH and URDF
    robots); an explicit name that does not exist, or a list matching nothing, is an error.
    """
    if isinstance(patterns, str):
        patterns = [p.strip() for p in patterns.split(",") if p.strip()]
    out = []
    for p in patterns:
        hit = [n for n in names if fnmatch.fnmatchcase(n, p)]
        if not hit and not any(ch in p for ch in "*?["):
            raise ValueError(unknown_name_message(p, names))
        out += hit
    if not out:
        raise ValueError(f"patterns {list(patterns)} match no parameter. This model has {len(names)} parameters: "
                         f"{summarize_names(names)}")
    keep = set(out)
    return [n for n in names if n in keep]


def reduced_observation_matrix(problem, names: Sequence[str] | None = None, theta=None,
                               chunk: int | None = None):
    """``(R, names, n_rows)``: the triangular factor of ``W`` (``W = Q R``) built ``chunk`` poses at a
    time (R ← qr([R; W_chunk])), so that memory stays O(chunk · P) whatever the number of poses.

    Every quantity :func:`estcal.identify.core.identifiable` computes — column norms, the
    sequential QR's ``|R_jj|``, regrouping coefficients, singular values — is invariant under
    ``W → QᵀW``, so the analysis of R is that of W (tested to 1e-10 in
    ``tests/test_memory.py``). Single-term problems with a splittable dataset only; the factor
    is the leading block of :func:`estcal.methods.reduced.reduce_system`'s (QR of ``[W b]``)."""
    names = list(problem.params.free_names if names is None else names)
    R, _, _, m = reduce_system(problem, theta, problem.params.indices(names), chunk or CHUNK_POSES)
    return R, names, m


def observation_matrix(problem, names: Sequence[str] | None = None, theta=None):
    """Weighted observation matrix ``W = H/σ`` (rows of all terms) and its column names."""
    rows = problem.evaluate(theta)
    pv = problem.params
    names = list(pv.free_names if names is None else names)
    W = rows.H[:, pv.indices(names)] / rows.sigma[:, None]
    return W, names


@dataclass
class IdentifiabilityResult:
    """Outcome of :func:`identifiable` (see module docstring).

    Attributes
    ----------
    names : parameters analysed (priority > 0), in the given order.
    identifiable : base parameters (given order); ``no_effect``: zero columns;
    regrouped : list of ``{"parameter", "relation": {base: coefficient}, "formula"}`` —
        ``w_parameter = Σ coefficient · w_base``, so a change of ``parameter`` is absorbed
        by the base parameters as ``Δbase += coefficient · Δparameter``;
    relations : ``{base: "base + c1*p1 + …"}`` — what each base parameter estimates;
    excluded : priority-0 parameters (not analysed, not identified);
    condition_number : of the column-scaled ``W_b``;
    tau : numerical zero used; r_diag : ``|R_jj|`` of every analysed column (scaled);
    qr : the QR variant used; priorities : priority of every parameter;
    priorities_out : same with non-identifiable parameters set to 0 (GECARO's output matrix).
    beta, beta_base, beta_dependent : unscaled regrouping matrix, ``W[:, beta_dependent] =
        W[:, beta_base] @ beta`` (eq. [36]-[37]).
    """

    names: list
    identifiable: list
    no_effect: list
    regrouped: list
    relations: dict
    excluded: list
    condition_number: float
    tau: float
    r_diag: dict
    qr: str
    priorities: dict
    n_rows: int
    beta: np.ndarray | None = None
    beta_base: list = field(default_factory=list)
    beta_dependent: list = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    excitation: dict | None = None

    @property
    def n_parameters(self) -> int:
        return len(self.names)

    @property
    def n_identifiable(self) -> int:
        return len(self.identifiable)

    @property
    def priorities_out(self) -> dict:
        keep = set(self.identifiable)
        return {n: (p if n in keep else 0) for n, p in self.priorities.items()}

    def status(self, name: str) -> str:
        """``""`` identifiable, ``"0"`` no effect, ``"n"`` regrouped, ``"x"`` excluded (priority 0)."""
        if name in self.identifiable:
            return ""
        if name in self.no_effect:
            return "0"
        if name in self.excluded:
            return "x"
        if any(r["parameter"] == name for r in self.regrouped):
            return "n"
        raise KeyError(f"{name!r} is not a parameter of this analysis")

    @property
    def rank_gap(self) -> tuple[float, float]:
        """(smallest |R_jj| kept, largest |R_jj| rejected among non-zero columns)."""
        kept = [self.r_diag[n] for n in self.identifiable]
        dep = [self.r_diag[r["parameter"]] for r in self.regrouped]
        return (min(kept) if kept else float("nan"), max(dep) if dep else 0.0)

    def to_dict(self) -> dict:
        lo, hi = self.rank_gap
        d = {"n_parameters": self.n_parameters, "n_identifiable": self.n_identifiable,
             "identifiable": list(self.identifiable), "no_effect": list(self.no_effect),
             "regrouped": [dict(r) for r in self.regrouped], "relations": dict(self.relations),
             "excluded": list(self.excluded), "condition_number": self.condition_number,
             "tau": self.tau, "rank_gap": {"min_kept": lo, "max_rejected": hi}, "qr": self.qr,
             "n_rows": self.n_rows, "priorities": dict(self.priorities),
             "priorities_out": self.priorities_out, "r_diag": dict(self.r_diag)}
        d.update(self.meta)
        if self.excitation is not None:
            d["excitation"] = self.excitation
        return d

    def excitation_lines(self) -> list[str]:
        """The dataset excitation check as text lines (none without ``--data``): whether the data identify
        the same set as random configurations (GECARO's criterion), the two condition numbers, and the
        parameters that differ — one wording for ``str(result)`` and ``estcal identifiable``."""
        ex = self.excitation
        if not ex:
            return []
        lines = [f"excitation: same identifiable set as random configurations: {ex['same_set']} (condition "
                 f"number {ex['condition_number']:.4g} vs {ex['random_condition_number']:.4g} with random "
                 f"configurations)"]
        if ex["missing"]:
            lines.append(f"  not identifiable from these data: {', '.join(ex['missing'])}")
        if ex["extra"]:
            lines.append(f"  identifiable only from these data (suspicious: near-dependent columns): "
                         f"{', '.join(ex['extra'])}")
        return lines

    def __str__(self) -> str:
        lo, hi = self.rank_gap
        head = " ".join(f"{k}={v}" for k, v in self.meta.items() if isinstance(v, (str, int, float)))
        lines = [f"Identifiable parameters{(' (' + head + ')') if head else ''}: {self.n_identifiable} of "
                 f"{self.n_parameters} ({self.n_rows} rows, QR: {self.qr}, τ = {self.tau:.3g}, "
                 f"gap {lo:.3g} kept / {hi:.3g} rejected)",
                 f"  condition number of column-scaled W_b: {self.condition_number:.4g}",
                 f"  identifiable: {', '.join(self.identifiable)}",
                 f"  no effect (0): {', '.join(self.no_effect) or '—'}"]
        if self.regrouped:
            lines.append("  regrouped (n): " + ", ".join(r["parameter"] for r in self.regrouped))
            lines.append("  base parameters absorbing others:")
            for b, f in self.relations.items():
                lines.append(f"    {f}")
        if self.excluded:
            lines.append(f"  excluded (priority 0): {', '.join(self.excluded)}")
        lines += ["  " + line for line in self.excitation_lines()]
        return "\n".join(lines)


def identifiable(W, names: Sequence[str], priorities=None, pivoting: bool = False, tol_factor: float = 1.0,
                 tau_floor: float = STRUCTURAL_TOL, rel_coef_tol: float = 1e-9,
                 meta: dict | None = None, n_rows: int | None = None) -> IdentifiabilityResult:
    """Identifiable parameters of the observation matrix ``W`` (GECARO App. III).

    Parameters
    ----------
    W : (M, P) observation matrix (weighted rows), columns aligned with ``names``.
    names : parameter names.
    priorities : None (all equal: the given column order decides), an array of
        ints aligned with ``names``, or ``{name/pattern: int}``. Higher first;
        0 = do not identify (column dropped, reported as ``excluded``). Columns of
        equal priority keep their given order (stable sort).
    pivoting : use QR with column pivoting instead of the priority-ordered
        sequential QR (the base set then follows column norms, not priorities).
    tol_factor : multiplies τ = c·ε·max|R_jj| (eq. [34]).
    tau_floor : lower bound of τ on the unit-norm columns (default :data:`STRUCTURAL_TOL`,
        see module docstring); 0 gives eq. [34] exactly.
    rel_coef_tol : regrouping coefficients below this (relative to unit-norm columns) are dropped.

    The kept set is :func:`select_identifiable`'s (with ``τ``); this function adds GECARO's
    regrouping relations (eqs. [35]-[37]) and the alternative of QR with column pivoting.

    Returns
    -------
    IdentifiabilityResult
    """
    W = np.asarray(W, float)
    names = list(names)
    if W.ndim != 2 or W.shape[1] != len(names):
        raise ValueError(f"W has shape {W.shape} but {len(names)} names were given")
    if not np.all(np.isfinite(W)):
        bad = np.argwhere(~np.isfinite(W))[0]
        raise ValueError(f"observation matrix has a non-finite entry (row {bad[0]}, parameter {names[bad[1]]!r})")
    prio = resolve_priorities(names, priorities)
    excluded = [n for n, p in zip(names, prio) if p == 0]
    use = np.flatnonzero(prio > 0)
    cols = [names[i] for i in use]
    Wu = W[:, use]
    c = len(cols)
    M = W.shape[0] if n_rows is None else int(n_rows)  # W may be the R factor of a taller matrix
    if c == 0:
        raise ValueError("no parameter to analyse (all priorities are 0)")
    norms = np.linalg.norm(Wu, axis=0)
    tau = max(tol_factor * c * EPS, tau_floor)  # eq. [34] with the structural floor (module docstring)
    zero = norms <= tau * max(norms.max(), 1e-300)
    # Stable sort by decreasing priority among the non-zero columns.
    order = [i for i in np.argsort(-prio[use], kind="stable") if not zero[i]]
    Ws = Wu[:, order] / norms[order]
    r_diag = {n: 0.0 for n in cols}
    if pivoting:
        _, R, piv = sla.qr(Ws, mode="economic", pivoting=True)
        d = np.abs(np.diag(R))
        tau = tau * (d.max() if d.size else 0.0)
        rank = int(np.sum(d > tau))
        kept_pos = np.sort(piv[:rank])
        for pos, dv in zip(piv, d):
            r_diag[cols[order[pos]]] = float(dv)
        qr_name = "column-pivoted Householder QR (scipy), priorities ignored"
    else:  # the one entry: priority-ordered sequential QR, τ on the unit-norm columns
        sel = select_identifiable(Wu, names=cols, order=order, tol=tau, zero_tol=tau)
        keep = set(sel.identifiable)
        kept_pos = np.array([p for p, i in enumerate(order) if cols[i] in keep], int)
        r_diag.update({n: v for n, v in sel.r_diag.items()})
        qr_name = "sequential QR in priority order, no pivoting (GECARO App. III)"
    dep_pos = np.setdiff1d(np.arange(len(order)), kept_pos)
    base = [cols[order[p]] for p in kept_pos]
    dep = [cols[order[p]] for p in dep_pos]
    W1, W2 = Ws[:, kept_pos], Ws[:, dep_pos]
    regrouped, relations, beta = [], {b: b for b in base}, None
    if kept_pos.size:
        sv = np.linalg.svd(W1, compute_uv=False)
        cond = float(sv[0] / sv[-1])
    else:
        cond = float("inf")
    if dep_pos.size and kept_pos.size:
        # eqs. [35]-[37]: QR of [W1 W2], β = R1⁻¹ R2 (scaled columns), then back to units.
        _, R = np.linalg.qr(np.hstack([W1, W2]))
        b = kept_pos.size
        beta_s = sla.solve_triangular(R[:b, :b], R[:b, b:])
        n1 = norms[[order[p] for p in kept_pos]]
        n2 = norms[[order[p] for p in dep_pos]]
        beta = beta_s * n2[None, :] / n1[:, None]  # unscaled: W2 = W1 β
        terms: dict[str, dict] = {bn: {} for bn in base}
        for k, dn in enumerate(dep):
            rel = {base[i]: float(beta[i, k]) for i in range(b) if abs(beta_s[i, k]) > rel_coef_tol}
            regrouped.append({"parameter": dn, "relation": rel,
                              "formula": f"w[{dn}] = " + (" + ".join(f"{v:.6g}*w[{n}]" for n, v in rel.items())
                                                          or "0")})
            for bn, v in rel.items():
                terms[bn][dn] = v
        relations = {bn: format_relation(bn, t) for bn, t in terms.items()}
    # Report lists in the caller's order.
    pos = {n: i for i, n in enumerate(names)}
    base_sorted = sorted(base, key=pos.get)
    regrouped.sort(key=lambda r: pos[r["parameter"]])
    return IdentifiabilityResult(
        names=cols, identifiable=base_sorted, no_effect=[n for n, z in zip(cols, zero) if z],
        regrouped=regrouped, relations={b: relations[b] for b in base_sorted}, excluded=excluded,
        condition_number=cond, tau=float(tau), r_diag=r_diag, qr=qr_name,
        priorities={n: int(p) for n, p in zip(names, prio)}, n_rows=M, beta=beta, beta_base=base,
        beta_dependent=dep, meta=dict(meta or {}))
