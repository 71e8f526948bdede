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
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

__all__ = ["resolve_priorities", "format_relation", "sequential_rank", "RankScan", "STRUCTURAL_TOL", "DATA_TOL",
           "EPS"]

EPS = np.finfo(float).eps

#: Structural rank: |R_jj| (sine of the angle between a unit-norm column and the span of the
#: kept ones) below which a column is dependent, and relative column norm below which a
#: parameter has no effect. The Jacobian is exact up to round-off, and the measured gap
#: between kept and rejected |R_jj| spans 1e-2 … 1e-14 (module docstring), so 1e-10 sits
#: inside it: the default of :func:`estcal.identify.select.select_identifiable`, the one entry
#: for the identifiable set.
STRUCTURAL_TOL = 1e-10
#: Data-level identifiability: a column whose independent part is below 1e-4 of its norm is
#: *not* estimable from noisy data even though it is structurally independent — its standard
#: deviation is amplified ≥ 10⁴ over a well-conditioned one and its estimate absorbs model
#: errors of the other parameters. A different decision from the structural rank (used by the
#: discrepancy diagnosis, ``estcal.discrepancy.geometric``, to fit only what the data pin down).
DATA_TOL = 1e-4


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
