"""Least squares on large datasets in bounded memory: the problem reduced to a triangular factor.

The weighted system ``A = H_free/σ``, ``b = e/σ`` of M rows enters every least-squares
quantity only through ``AᵀA``, ``Aᵀb`` and ``bᵀb``: with ``[A b] = Q R̃`` (thin QR),
``min ‖A x − b‖² = min ‖R x − c‖² + const`` (R, c the blocks of R̃), the covariance is
``(RᵀR)⁻¹``, column norms and singular values of A are those of R, and the identifiable set
found by the ordered QR of :func:`estcal.estimate.levels.select_free` is the same. R̃ is
built ``chunk`` poses at a time — ``R̃ ← qr([R̃; A_k b_k])`` (TSQR, as stable as one QR of the
whole matrix) — so memory is O(chunk · P) instead of O(M · P): a 6-axis pose dataset of 10⁶
rows would need 2.6 GB for H alone.

Used automatically above :data:`CHUNK_POSES` poses (single-term problems of per-pose methods:
position, location, points — also with the row weights of iteratively reweighted robust fits,
:class:`estcal.estimate.robust.WeightedProblem`), or with ``chunk=N`` in
:func:`estcal.estimate.lsq.calibrate_lsq`. :class:`DenseSystem` and :class:`ReducedSystem` give
the least-squares solvers the same system either way.
"""
from __future__ import annotations

import numpy as np

from estcal.base.progress import progress

from .problem import Problem, Term

__all__ = ["CHUNK_POSES", "PER_POSE_METHODS", "chunkable", "subproblems", "evaluate_chunks", "reduce_system",
           "chunked_cost", "chi2_and_rows", "weighted", "DenseSystem", "ReducedSystem"]

#: poses per chunk (≈ 60 MB of Jacobian and kinematics for a 6-axis arm with 54 parameters)
CHUNK_POSES = 20_000

#: methods whose rows each come from one dataset row alone; others (links, plane normals,
#: distances) compare rows of a ``group`` / ``pair`` and must be processed together
PER_POSE_METHODS = ("position", "location", "pose", "points", "plane-known", "plane-unknown")


def weighted(rows, free):
    """``(A, b)`` = ``(H[:, free]/σ, e/σ)``: the weighted system of the rows ``rows``."""
    w = 1.0 / rows.sigma
    A = rows.H[:, free] * w[:, None]
    b = rows.e * w
    return A, b


def chunkable(problem) -> bool:
    terms = getattr(problem, "terms", None)
    return (bool(terms) and len(terms) == 1 and hasattr(terms[0].data, "subset")
            and getattr(terms[0].method, "name", "") in PER_POSE_METHODS)


def use_chunks(problem, chunk=None):
    """The chunk size to use: ``chunk`` when given, CHUNK_POSES for large chunkable problems, else None."""
    if chunk is not None:
        return int(chunk) if chunkable(problem) else None
    if chunkable(problem) and problem.terms[0].data.n > CHUNK_POSES:
        return CHUNK_POSES
    return None


def subproblems(problem, chunk: int):
    """Sub-problems of ``chunk`` consecutive poses (the same robot, method and noise)."""
    (t,) = problem.terms
    n = t.data.n
    for a in range(0, n, chunk):
        sub = Problem.__new__(Problem)
        sub.robot = problem.robot
        sub.terms = [Term(t.method, t.data.subset(np.arange(a, min(a + chunk, n))), t.noise)]
        yield sub


def evaluate_chunks(problem, theta, chunk: int, jacobian: bool = True):
    """``(first pose, rows)`` of every chunk, in order; a problem with ``row_scale`` (IRLS weights)
    has its rows' σ scaled by the matching slice, as its own ``evaluate`` would."""
    scale = getattr(problem, "row_scale", None)
    off = 0
    n = problem.terms[0].data.n
    # a bar on a terminal for passes over large data (quiet inside an outer bar, e.g. the LM iterations)
    with progress(total=-(-n // chunk), desc="poses" + (" (Jacobian)" if jacobian else ""), unit="chunk") as bar:
        for k, sub in enumerate(subproblems(problem, chunk)):
            rows = sub.evaluate(theta, jacobian=jacobian)
            if scale is not None:
                rows.sigma = rows.sigma * scale[off:off + rows.e.size]
            off += rows.e.size
            bar.update(1)
            yield k * chunk, rows
    if scale is not None and off != scale.size:
        raise ValueError(f"row weights for {scale.size} rows, the chunks have {off}")


def reduce_system(problem, theta, cols, chunk: int):
    """``(R, c, rss, m)``: triangular factor and ``c = Qᵀb`` of the weighted system of columns
    ``cols`` at ``theta``, ``rss = bᵀb`` and the number of rows ``m``."""
    p = len(cols)
    Rt = np.zeros((0, p + 1))
    rss, m = 0.0, 0
    for _, rows in evaluate_chunks(problem, theta, chunk):
        w = 1.0 / rows.sigma
        Ab = np.column_stack([rows.H[:, cols] * w[:, None], rows.e * w])
        rss += float(Ab[:, -1] @ Ab[:, -1])
        m += Ab.shape[0]
        Rt = np.linalg.qr(np.vstack([Rt, Ab]), mode="r")
    if Rt.shape[0] < p + 1:  # fewer rows than columns: pad (the rank check reports it)
        Rt = np.vstack([Rt, np.zeros((p + 1 - Rt.shape[0], p + 1))])
    return Rt[:p, :p], Rt[:p, p], rss, m


def _chi2_rows_chunked(problem, theta, chunk: int) -> tuple[float, int]:
    c, m = 0.0, 0
    for _, r in evaluate_chunks(problem, theta, chunk, False):
        c += float(np.sum((r.e / r.sigma) ** 2))
        m += r.e.size
    return c, m


def chunked_cost(problem, theta, chunk: int) -> float:
    """``Σ (e/σ)²`` without Jacobians, chunk by chunk."""
    return _chi2_rows_chunked(problem, theta, chunk)[0]


def chi2_and_rows(problem, theta) -> tuple[float, int]:
    """``(Σ (e/σ)², number of rows)`` at ``theta``: chunk by chunk on large data, else in one evaluation."""
    ck = use_chunks(problem) if getattr(problem, "terms", None) else None
    if ck is not None:
        return _chi2_rows_chunked(problem, theta, ck)
    r = problem.evaluate(theta, jacobian=False)
    return float(np.sum((r.e / r.sigma) ** 2)), int(r.e.size)


class DenseSystem:
    """The weighted data rows of the whole problem: ``A = H_free/σ``, ``b = e/σ`` (M × p)."""

    def __init__(self, problem, fidx):
        self.problem, self.fidx = problem, fidx
        self.m = 0
        self._trial = None  # (θ, rows) of the last trial evaluated with its Jacobian
        # (θ, residual e) of the first and the last linearisation: the fit's accuracy before and after
        # is read from them (estcal.estimate.result.point_errors_from_rows), not from another pass
        self.first = self.last = None

    def linear(self, theta):
        """``(A, b, bᵀb)`` at θ (reusing the trial's rows when the trial was accepted)."""
        if self._trial is not None and np.array_equal(self._trial[0], theta):
            rows = self._trial[1]
        else:
            rows = self.problem.evaluate(theta)
        self._trial = None
        self.last = (np.array(theta, float), rows.e)
        if self.first is None:
            self.first = self.last
        A, b = weighted(rows, self.fidx)
        self.m = rows.e.size
        return A, b, float(b @ b)

    def cost(self, theta, jacobian: bool) -> float:
        """``Σ (e/σ)²`` at a trial θ; with ``jacobian`` the rows are kept, so that an accepted
        step (the common case) needs no second forward-kinematics pass."""
        rows = self.problem.evaluate(theta, jacobian=jacobian)
        if jacobian:
            self._trial = (theta.copy(), rows)
        return float(np.sum((rows.e / rows.sigma) ** 2))


class ReducedSystem:
    """The same least-squares problem as its triangular factor ``(R, Qᵀb)``, built ``chunk`` poses
    at a time (this module): every quantity below is unchanged, the memory is
    O(chunk · p) instead of O(M · p)."""

    def __init__(self, problem, fidx, chunk: int):
        self.problem, self.fidx, self.chunk = problem, fidx, int(chunk)
        self.m = 0

    def linear(self, theta):
        R, c, rss, self.m = reduce_system(self.problem, theta, self.fidx, self.chunk)
        return R, c, rss

    def cost(self, theta, jacobian: bool) -> float:
        return chunked_cost(self.problem, theta, self.chunk)
