"""Identifiable (base) parameters of an observation matrix — GECARO Appendix III.

Given the stacked observation matrix ``W`` (rows: linearised measurement
equations, columns: parameters), :func:`identifiable` finds

* **no effect** — zero columns (GECARO Table 2 entries "0");
* **identifiable** (base) parameters — a maximal set of independent columns,
  chosen by priority (the earliest independent columns in priority order);
* **regrouped** parameters — the other columns (entries "n"), with the
  regrouping relations ``W2 = W1 β``, ``β = R1⁻¹ R2`` (eqs. [35]–[37]), i.e.
  each base parameter estimates ``η_b = η_1 + β η_2``;
* the condition number of the column-scaled ``W_b``.

Why a *sequential* QR without pivoting
--------------------------------------
GECARO sorts the columns by decreasing priority and keeps "the first ``b``
independent columns". QR with column pivoting reorders the columns by the
norm of their remaining part and therefore ignores the priorities (it is
offered as ``pivoting=True``, and the result says which was used). A plain Householder QR of a rank-deficient
matrix is not reliable either: after a dependent column the reflector is
built from round-off, and that random direction can absorb part of a later
independent column. So the default is the QR built column by column: column
``j`` (in priority order) is orthogonalised against the orthonormal basis of
the columns already *kept* (classical Gram–Schmidt, applied twice — "CGS2",
orthogonal to working precision); ``|R_jj|`` is the norm of what remains, the
distance of column j to the span of the kept higher-priority columns. Column
j is kept when ``|R_jj| > τ``. In exact arithmetic this is the R factor of the
QR of ``[W1 W2]`` (eq. [35]) with the dependent columns' diagonal zero.

Numerical zero and scaling
--------------------------
``τ = c · ε · max_j |R_jj|`` (eq. [34], c = number of columns, ε = machine
precision), multiplied by ``tol_factor`` (default 1), with a floor
``tau_floor·max|R_jj|`` (default 1e-10). Eq. [34] is the round-off level of
an *exactly* computed W. Ours is computed from configurations that satisfy
the method's constraint only to ~1e-15 m (numerical inverse model) and from
differences of nearly equal Jacobians (link methods: columns that vanish
exactly, like θ0's ``z × (P_j − P_i)``, come out at ~1e-15 relative), and a
dependent column is rebuilt from the kept ones with regrouping coefficients
up to ~10³, so its remainder is ~1e-12 rather than ~1e-15. On the Stanford
robot the gap between kept and rejected ``|R_jj|`` spans 1e-2 … 1e-14 for
every method; a floor of 1e-10 sits safely inside it, while pure eq. [34]
(``tau_floor=0``, ~1e-14) keeps spurious round-off columns. The result reports
τ and the gap (smallest kept / largest rejected ``|R_jj|``). The columns are scaled
to unit norm before the QR: parameters in metres, radians and (for gains)
per-unit have column norms that differ by orders of magnitude, and eq. [34]
compares ``|R_jj|`` across columns — without scaling, a perfectly independent
but small column (e.g. a length parameter seen through a short lever arm)
could fall below τ, and a dependent large column could stay above it. After
scaling ``|R_jj|`` is the sine of the angle between column j and the span of
the kept columns: dimensionless and comparable. Zero columns are detected
before scaling: ``‖w_j‖ ≤ max(c·ε, tau_floor)·max_k ‖w_k‖`` (eq. [34] applied to
column norms, same floor).
"""
from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import scipy.linalg as sla

__all__ = ["IdentifiabilityResult", "identifiable", "resolve_priorities", "format_relation", "sequential_rank",
           "RankScan", "STRUCTURAL_TOL", "DATA_TOL"]

EPS = np.finfo(float).eps

#: Structural rank: |R_jj| (sine of the angle between a unit-norm column and the span of the
#: kept ones) below which a column is dependent, and relative column norm below which a
#: parameter has no effect. The Jacobian is exact up to round-off, and the measured gap
#: between kept and rejected |R_jj| spans 1e-2 … 1e-14 (module docstring), so 1e-10 sits
#: inside it: used by :func:`identifiable`, ``estcal.estimate.levels.select_free`` and the
#: design and parallel-robot analyses.
STRUCTURAL_TOL = 1e-10
#: Data-level identifiability: a column whose independent part is below 1e-4 of its norm is
#: *not* estimable from noisy data even though it is structurally independent — its standard
#: deviation is amplified ≥ 10⁴ over a well-conditioned one and its estimate absorbs model
#: errors of the other parameters. A different decision from the structural rank (used by the
#: discrepancy diagnosis, ``estcal.discrepancy.geometric``, to fit only what the data pin down).
DATA_TOL = 1e-4


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
        if self.excitation:
            ex = self.excitation
            lines.append(f"  excitation check vs random configurations: same set = {ex['same_set']}, "
                         f"cond(data) = {ex['condition_number']:.4g}, cond(random) = "
                         f"{ex['random_condition_number']:.4g}")
            if ex["missing"]:
                lines.append(f"    identifiable with random poses but not with these data: {ex['missing']}")
            if ex["extra"]:
                lines.append(f"    identifiable only with these data (suspicious, near-dependent): {ex['extra']}")
        return "\n".join(lines)


def resolve_priorities(names: Sequence[str], priorities=None, default: int = 1) -> np.ndarray:
    """Priority of each name: ``priorities`` is None (all ``default``), an array aligned
    with ``names``, or a mapping ``{name or fnmatch pattern: int}`` (later entries win;
    names not matched get ``default``)."""
    names = list(names)
    if priorities is None:
        return np.full(len(names), default, int)
    if isinstance(priorities, Mapping):
        out = np.full(len(names), default, int)
        for key, val in priorities.items():
            if any(ch in key for ch in "*?["):
                hit = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, key)]
            else:
                hit = [i for i, n in enumerate(names) if n == key]
            out[hit] = int(val)
        return out
    arr = np.asarray(priorities, int).reshape(-1)
    if arr.size != len(names):
        raise ValueError(f"{arr.size} priorities for {len(names)} parameters")
    if np.any(arr < 0):
        raise ValueError("priorities must be ≥ 0 (0 = do not identify)")
    return arr


def format_relation(base: str, terms: Mapping[str, float], digits: int = 6) -> str:
    """``"base + 1*p - 0.2*q"`` (coefficients with ``digits`` significant digits)."""
    out = base
    for name, c in terms.items():
        out += f" {'-' if c < 0 else '+'} {abs(c):.{digits}g}*{name}"
    return out


@dataclass
class RankScan:
    """Outcome of :func:`sequential_rank`; indices are columns of the input matrix.

    kept : independent columns, in scan order; dependent : columns within ``tol`` of the span
    of the kept ones; no_effect : zero columns; rejected : independent columns refused by the
    ``accept`` test; r_diag : |R_jj| of every scanned column on the unit-norm scale (0 for zero
    columns); norms : column norms; Q : orthonormal basis of the kept columns (M, len(kept)).
    """

    kept: list
    dependent: list
    no_effect: list
    rejected: list
    r_diag: np.ndarray
    norms: np.ndarray
    Q: np.ndarray


def sequential_rank(W, tol: float = STRUCTURAL_TOL, order=None, *, zero_tol: float = STRUCTURAL_TOL,
                    accept=None) -> RankScan:
    """Priority-ordered QR without pivoting of the unit-norm columns of ``W`` (GECARO App. III).

    The one implementation of the rank scan behind every identifiability decision. Columns
    are visited in ``order`` (default: the given order; columns not listed are not scanned).
    A column with ``‖w_j‖ ≤ zero_tol · max_k ‖w_k‖`` has no effect. Otherwise it is scaled to
    unit norm and orthogonalised against the kept columns by classical Gram–Schmidt applied
    twice (CGS2, orthogonal to working precision — Giraud et al., *Numer. Math.* 101, 2005);
    the norm of the remainder ``|R_jj|`` is the sine of the angle between the column and the
    span of the kept ones. It is dependent when ``|R_jj| ≤ tol``, else it is kept — unless
    ``accept(j, u)`` (u: the new orthonormal direction) returns False (e.g. an information
    criterion, ``estcal.estimate.levels``).

    tol : the decision the caller makes. :data:`STRUCTURAL_TOL` (1e-10) is the structural
        rank — is the column a combination of the others, to round-off? :data:`DATA_TOL`
        (1e-4) is data-level identifiability — can the data estimate it with a usable
        variance? The two answer different questions, hence one named argument, not two
        functions.
    """
    W = np.asarray(W, float)
    M, c = W.shape
    order = range(c) if order is None else [int(i) for i in order]
    norms = np.linalg.norm(W, axis=0)
    scale = max(float(norms.max()) if c else 0.0, 1e-300)
    Q = np.empty((M, min(M, c)))
    k = 0
    kept, dependent, no_effect, rejected = [], [], [], []
    r_diag = np.zeros(c)
    for j in order:
        if norms[j] <= zero_tol * scale:
            no_effect.append(j)
            continue
        v = W[:, j] / norms[j]
        for _ in range(2):  # CGS2: re-orthogonalise once
            if k:
                v = v - Q[:, :k] @ (Q[:, :k].T @ v)
        r_diag[j] = float(np.linalg.norm(v))
        if r_diag[j] <= tol or k == Q.shape[1]:
            dependent.append(j)
            continue
        u = v / r_diag[j]
        if accept is not None and not accept(j, u):
            rejected.append(j)
            continue
        Q[:, k] = u
        k += 1
        kept.append(j)
    return RankScan(kept, dependent, no_effect, rejected, r_diag, norms, Q[:, :k])


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
    else:
        scan = sequential_rank(Ws, tau, zero_tol=0.0)  # unit columns: max|R_jj| = 1, τ absolute
        kept_pos = np.array(scan.kept, int)
        for pos, dv in enumerate(scan.r_diag):
            r_diag[cols[order[pos]]] = float(dv)
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
