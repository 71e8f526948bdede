"""Sparse Bayesian linear regression: automatic relevance determination by fast marginal likelihood.

The model (Tipping 2001, *JMLR* 1:211; MacKay 1994)::

    y = F c + Φ w + ε,     ε ~ N(0, σ² I),     w_j ~ N(0, 1/α_j),     c flat (unpenalised)

Every penalised column ``φ_j`` has its own prior precision ``α_j``; the precisions and the noise are chosen
by type-II maximum likelihood — the marginal likelihood (evidence) of ``y`` — and a column whose optimal
``α_j`` is infinite is pruned: the evidence decides what stays. The unpenalised columns ``F`` (a
registration: base frame, markers, session frames) are integrated out with a flat prior: the data and the
penalised columns are projected onto the orthogonal complement of ``F`` (the restricted likelihood,
Patterson & Thompson 1971), which leaves ``N − rank F`` degrees of freedom.

The search is Tipping & Faul's sequential algorithm (2003, *AISTATS*, "Fast marginal likelihood
maximisation for sparse Bayesian models"): with every other precision fixed the evidence is, as a function
of one ``α_j``,

    ℓ(α_j) = ½ [ log α_j − log(α_j + s_j) + q_j² / (α_j + s_j) ]     (their eq. 15)

with the "sparsity" ``s_j = φ_jᵀ C₋ⱼ⁻¹ φ_j`` and "quality" ``q_j = φ_jᵀ C₋ⱼ⁻¹ y`` of the column against the
model without it; its maximum is ``α_j = s_j² / (q_j² − s_j)`` when ``q_j² > s_j`` and ``α_j = ∞`` (pruned)
otherwise (their eq. 20). Each step takes the one action — add a column, re-estimate its precision, or
delete it — that raises the evidence most, so the model grows from empty and never holds more columns than
the data support; the noise is re-estimated (MacKay 1992's fixed point ``σ² = |y − Φμ|² / (N − Σγ)``)
between steps. ``s_j, q_j`` come from the Gram matrix ``ΦᵀΦ`` computed once, so a step costs O(M m²) for
``M`` candidate columns and ``m`` in the model (m ≤ a few tens here) — milliseconds for a calibration.

Why ARD prunes — and why it can keep a column that explains nothing physical: the evidence's sparsity acts
like a reweighted ℓ1 penalty (Wipf & Nagarajan 2008, *NIPS* 20), so among near-collinear columns it keeps
the fewest that fit; a column that absorbs structured model error is as "relevant" as a real cause. The
diagnosis therefore names a cause only on further evidence (:mod:`estcal.discrepancy.relevance`).

Shapes: ``Phi`` (N, M), ``y`` (N,), ``F`` (N, p). Columns are scaled to unit norm internally; precisions
are returned in the units of the columns given.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SparseFit", "Prepared", "sparse_bayes", "log_evidence_ard", "shared_precision"]

_LOG2PI = float(np.log(2.0 * np.pi))


@dataclass
class SparseFit:
    """Result of :func:`sparse_bayes` (column units as given).

    alpha : (M,) prior precision of every penalised column; ``inf`` for a pruned column
    mean : (M,) posterior mean of ``w`` (0 for pruned columns)
    cov : (M, M) posterior covariance of ``w`` (zero rows / columns for pruned ones)
    free : (p,) posterior mean of the unpenalised coefficients ``c`` (given the penalised ones)
    free_cov : (p, p) their posterior covariance (the penalised columns' uncertainty included)
    noise_var : σ², the fitted noise variance (the scale of the residual: model error included)
    log_evidence : log marginal (restricted) likelihood at the optimum
    gamma : (M,) ``1 − α_j Σ_jj``, how well each column is determined by the data (0 … 1; Σγ = effective
        number of penalised parameters, MacKay 1992)
    n_iter : sequential steps taken; converged : whether the last step's gain was below ``tol``
    dof : N − rank F (rows left after the unpenalised columns)
    """

    alpha: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    free: np.ndarray
    free_cov: np.ndarray
    noise_var: float
    log_evidence: float
    gamma: np.ndarray
    n_iter: int
    converged: bool
    dof: int
    extra: dict = field(default_factory=dict)

    @property
    def active(self) -> np.ndarray:
        """(M,) bool: the columns the evidence keeps."""
        return np.isfinite(self.alpha)

    @property
    def effective_parameters(self) -> float:
        return float(self.gamma.sum())

    def prediction_cov(self, Phi, F=None) -> np.ndarray:
        """(r, r) posterior covariance of ``F c + Φ w`` at new rows (noise excluded): with ``c = F⁺(y − Φw)``
        the prediction is ``F F⁺ y + (Φ − F F⁺Φ) w``, so its covariance is ``σ² F F⁺F⁺ᵀFᵀ + D Σ Dᵀ``,
        ``D = Φ − F F⁺Φ`` (the training rows' F⁺ and F⁺Φ kept in ``extra``)."""
        Phi = np.asarray(Phi, float)
        if F is None or not np.size(F) or "F_pinv" not in self.extra:
            return Phi @ self.cov @ Phi.T
        F = np.asarray(F, float)
        G = F @ self.extra["F_pinv"]
        D = Phi - G @ (self.extra["Phi"] * self.extra["Phi_scale"])
        return self.noise_var * (G @ G.T) + D @ self.cov @ D.T

    def predict(self, Phi, F=None):
        """Posterior mean of ``F c + Φ w`` at new rows (``F`` None: the penalised part only)."""
        out = np.asarray(Phi, float) @ self.mean
        if F is not None and np.size(F):
            out = out + np.asarray(F, float) @ self.free
        return out


def _project(F, *arrays):
    """The arrays with their components along the columns of ``F`` removed; ``rank F``; and the pivoted QR
    factorisation ``(Q (n, r), R (r, r), the r independent columns)`` of the column-scaled ``F`` (Businger &
    Golub's column pivoting, ``scipy.linalg.qr``) — its rank by the factor's diagonal, its pseudo-inverse on
    those columns."""
    if F is None or F.shape[1] == 0:
        return arrays, 0, None
    from scipy.linalg import qr

    nrm = np.linalg.norm(F, axis=0)
    nrm[nrm == 0] = 1.0
    Q, R, piv = qr(F / nrm, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    r = int(np.sum(d > 1e-10 * max(d.max(), 1e-300))) if d.size else 0
    Q = Q[:, :r]
    return tuple(a - Q @ (Q.T @ a) for a in arrays), r, (Q, R[:r, :r], piv[:r], nrm)


#: a penalised column whose part orthogonal to ``F`` and to one penalised column before it is at most this
#: fraction of its norm repeats that column on these rows (:func:`_repeats`)
REPEAT_TOL = 1e-6


def _repeats(G) -> tuple[np.ndarray, np.ndarray]:
    """``(repeats, rounding)``, (M,) bool each, from the Gram matrix ``G`` of the unit-norm columns projected off
    ``F``: the columns that repeat an earlier one — whose part orthogonal to it (and to ``F``) is at most
    :data:`REPEAT_TOL` of their norm, ``1 − cos² ≤ tol²`` — or that ``F`` alone spans (``rounding``: their
    projection at most ``tol``).

    Why: two columns one multiple of the other on the rows (a backlash by approach where every training
    posture was approached from one side is ± the joint's offset) leave the evidence flat along
    ``1/α_a + c²/α_b`` (it sees the columns only through the covariance ``σ²I + Σ_j φ_j φ_jᵀ / α_j``), so
    which of them takes the weight is decided by rounding — the same fit on these rows, and at rows where the
    columns differ (the other approach) predictions millimetres apart from a 1e-12 m change of the data. Such
    a column is never searched (:func:`sparse_bayes`): it keeps the precision its warm start gives it — in a
    cross-validation fold, the one the rows that told the columns apart gave it, so the split is the prior's
    (``w_b / w_a = c·α_a / α_b``) — or stays out, and the first of the pair (the geometry comes before the
    effects) takes the weight: the column order and the start decide, not the rounding.

    Only pairs: ``k`` columns in general position within a ``d``-dimensional subspace leave the evidence flat
    only when ``k > d(d+1)/2`` (their rank-one terms ``φ_j φ_jᵀ`` are then linearly dependent among the
    symmetric ``d × d`` matrices), so a column merely in the span of several others — every column, once the
    rows are fewer than the columns — is still a candidate."""
    d = np.diag(G).copy()
    rounding = d <= REPEAT_TOL ** 2
    s = np.sqrt(np.where(rounding, 1.0, d))
    C = G / np.outer(s, s)
    same = 1.0 - C * C <= REPEAT_TOL ** 2
    same &= ~rounding[:, None] & ~rounding[None, :]
    return rounding | np.triu(same, 1).any(axis=0), rounding


class _State:
    """The sequential search's state on the projected, unit-norm system (Gram form)."""

    def __init__(self, G, h, tt, n):
        self.G, self.h, self.tt, self.n = G, h, tt, n
        self.dG = np.diag(G).copy()
        M = len(h)
        self.alpha = np.full(M, np.inf)
        self.beta = 1.0
        self.logdet = 0.0  # log|Σ| of the last posterior
        self._cols = (None, None, None)

    def cols(self, A):
        """``(G[:, A], G[A][:, A])`` — the active set changes at adds and deletes only, while the posterior, the
        (s, q) and the residual of every step read these: gathered once per active set."""
        key = A.tobytes()
        if self._cols[0] != key:
            GA = self.G[:, A]
            # G[A][:, A] as the residual's product always read it (column-major: the same sums, to the bit)
            self._cols = (key, GA, self.G[A][:, A])
        return self._cols[1], self._cols[2]

    def posterior(self):
        """(active indices, Σ, μ) for the current precisions and noise (one Cholesky factor and its triangular
        inverse; ``self.logdet`` = log|Σ| from the factor)."""
        from scipy.linalg.lapack import dtrtri

        A = np.flatnonzero(np.isfinite(self.alpha))
        if A.size == 0:
            self.logdet = 0.0
            return A, np.zeros((0, 0)), np.zeros(0)
        H = self.beta * self.cols(A)[1]
        H.flat[:: len(A) + 1] += self.alpha[A]
        L = _cholesky(H)
        Li, _ = dtrtri(L, lower=1)
        Sig = Li.T @ Li
        mu = self.beta * (Sig @ self.h[A])
        self.logdet = -2.0 * float(np.sum(np.log(np.diag(L))))
        return A, Sig, mu

    def sq(self, A, Sig, mu):
        """(s, q) of every column against the model without it (Tipping & Faul eqs. 23–24)."""
        b = self.beta
        if A.size:
            GA = self.cols(A)[0]
            S = b * self.dG - b * b * np.sum((GA @ Sig) * GA, axis=1)
            Q = b * self.h - b * (GA @ mu)
        else:
            S = b * self.dG
            Q = b * self.h
        s, q = S.copy(), Q.copy()
        a = self.alpha[A]
        den = a - S[A]
        s[A] = a * S[A] / den
        q[A] = a * Q[A] / den
        return s, q

    def residual2(self, A, mu):
        if A.size == 0:
            return self.tt
        return float(self.tt - 2.0 * mu @ self.h[A] + mu @ (self.cols(A)[1] @ mu))

    def update_noise(self, A, Sig, mu):
        gamma = 1.0 - self.alpha[A] * np.diag(Sig) if A.size else np.zeros(0)
        r2 = max(self.residual2(A, mu), 1e-300)
        self.beta = max(self.n - float(gamma.sum()), 1e-6) / r2

    def log_evidence(self, A, Sig, mu) -> float:
        """log p(y | α, β) (Bishop 2006 eq. 3.86 with one precision per column; restricted to N − rank F rows)."""
        b = self.beta
        a = self.alpha[A]
        logdet_sig = self.logdet if A.size else 0.0
        E = 0.5 * b * self.residual2(A, mu) + 0.5 * float(np.sum(a * mu * mu))
        return float(0.5 * np.sum(np.log(a)) + 0.5 * self.n * np.log(b) - E + 0.5 * logdet_sig
                     - 0.5 * self.n * _LOG2PI)


def _cholesky(H):
    """Cholesky factor of ``H``; when two columns in the model are collinear to rounding and their precisions
    tiny, ``H`` can lose definiteness by rounding: a jitter of 1e-12 of its mean diagonal, grown tenfold until
    the factor exists (a prior of that size, far below any data's)."""
    try:
        return np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        eps = 1e-12 * max(float(np.mean(np.diag(H))), 1e-300)
        for _ in range(12):
            try:
                return np.linalg.cholesky(H + eps * np.eye(len(H)))
            except np.linalg.LinAlgError:
                eps *= 10.0
        raise


def _ell(alpha, s, q):
    """ℓ(α) of the module docstring (the log evidence gained by the column at precision α; 0 at α = ∞)."""
    out = 0.5 * (-np.log1p(s / alpha) + q * q / (alpha + s))
    return np.where(np.isfinite(alpha), out, 0.0)


def shared_precision(Phi, y, F=None, iters: int = 200, tol: float = 1e-8) -> tuple[float, float]:
    """``(α, σ²)``: one prior precision shared by every column of ``Phi`` (on unit-norm columns, as
    :func:`sparse_bayes` scales them) and the noise variance, by type-II maximum likelihood — ridge regression
    with its width chosen by the evidence, MacKay's fixed point (1992, *Neural Computation* 4:415, eqs. 4.9
    and 4.10 with one α)::

        γ = Σᵢ βλᵢ / (βλᵢ + α),    α = γ / |μ|²,    σ² = 1/β = |y − Φμ|² / (n − γ)

    (``λᵢ`` the eigenvalues of ``ΦᵀΦ`` after ``F`` is projected out, ``μ`` the posterior mean, ``n = N − rank
    F``). The full model's evidence optimum: a start for the sequential search that keeps every column and
    shrinks the directions the data do not determine, instead of growing from one column (:func:`sparse_bayes`'s
    ``start``: ``α ‖φ_j‖²`` in column units). ``α = ∞`` when the data carry no signal for the columns."""
    Phi = np.asarray(Phi, float)
    y = np.asarray(y, float)
    N, M = Phi.shape
    F = None if F is None else np.asarray(F, float).reshape(N, -1)
    nrm = np.linalg.norm(Phi, axis=0)
    (Pt, yt), rank_f, _ = _project(F, Phi / np.where(nrm > 0, nrm, 1.0), y)
    n = N - rank_f
    lam, V = np.linalg.eigh(Pt.T @ Pt)
    lam = np.maximum(lam, 0.0)
    z = V.T @ (Pt.T @ yt)
    tt = float(yt @ yt)
    beta = 1.0 / max(0.1 * tt / max(n, 1), 1e-300)
    alpha = 1.0
    for _ in range(iters):
        d = beta * lam + alpha
        m = beta * z / d  # the posterior mean in the eigenbasis
        gamma = float(np.sum(beta * lam / d))
        mm = float(m @ m)
        res = tt - 2 * float(m @ z) + float(np.sum(lam * m * m))
        if mm <= 1e-300 or gamma <= 1e-12:
            return np.inf, max(tt / max(n, 1), 1e-300)
        new_alpha = gamma / mm
        new_beta = max(n - gamma, 1e-12) / max(res, 1e-300)
        done = abs(new_alpha - alpha) <= tol * alpha and abs(new_beta - beta) <= tol * beta
        alpha, beta = new_alpha, new_beta
        if done:
            break
    return float(alpha), float(1.0 / beta)


def sparse_bayes(Phi, y, F=None, *, tol: float = 1e-6, max_iter: int | None = None, noise_var: float | None = None,
                 start=None, exclude=None, alpha_min=None, prepared=None) -> SparseFit:
    """Sparse Bayesian regression of ``y`` on the penalised columns ``Phi`` and the unpenalised ``F``.

    Parameters
    ----------
    Phi : (N, M) penalised columns (prior ``w_j ~ N(0, 1/α_j)``); y : (N,) data
    F : (N, p) unpenalised columns (flat prior), or None
    tol : stop when no single action raises the log evidence by more than ``tol`` (nats)
    max_iter : most sequential steps (default 20·M + 50)
    noise_var : a fixed noise variance σ² (None: estimated with the precisions)
    start : (M,) precisions to start from (a previous fit's ``alpha``: the warm start of a refit on other
        rows or at a new linearisation point); None: from the single best column. A column that repeats an
        earlier one on these rows (:func:`_repeats`) is never searched: it keeps its start's precision (the
        one rows that told them apart gave it) or, without one, stays out
    exclude : (M,) bool — columns held out of the model (α = ∞ throughout; for Bayes factors of a term)
    alpha_min : (M,) least precision of every column the search moves to (its widest prior, 1/α_min = the
        largest plausible square deviation; None: unbounded). ℓ(α) is unimodal, so the bounded optimum is the
        unbounded one clipped: a column the data would let grow without bound (a near-collinear set fitting each
        other's cancellations) is held at its plausible scale. It bounds the moves, not the start: a column
        ``start`` puts below it (a wider prior — the diagnosis starts link frames from a ridge fit's width) keeps
        that precision until a move within the bound, or its deletion, raises the evidence
    prepared : :class:`Prepared` of these ``Phi, y, F`` (then not read again): the column scaling, the projection
        off ``F`` and the Gram matrix, which depend on the rows only — a caller refitting one system with other
        columns excluded or other precisions (a cross-validation fold's candidates) computes them once

    Returns
    -------
    :class:`SparseFit`
    """
    pre = prepared if prepared is not None else Prepared(Phi, y, F)
    Phi, y, F, N, M = pre.Phi, pre.y, pre.F, pre.N, pre.M
    nrm, nrm_s, Pn, Q, G, h, yt = pre.nrm, pre.nrm_s, pre.Pn, pre.Q, pre.G, pre.h, pre.yt
    usable = nrm > 0
    if exclude is not None:
        usable &= ~np.asarray(exclude, bool)
    n = pre.n
    st = _State(G, h, float(yt @ yt), n)
    # a column that repeats an earlier one (_repeats) is never searched: held at its start's precision (the
    # precision the rows that did tell them apart gave it), or out
    held = usable & pre.repeats & ~pre.rounding  # (a column of rounding, F spans it alone, stays out)
    usable &= ~pre.repeats
    fixed = noise_var is not None
    st.beta = 1.0 / noise_var if fixed else 1.0 / max(0.1 * float(yt @ yt) / max(n, 1), 1e-300)
    amin = np.zeros(M) if alpha_min is None else np.broadcast_to(np.asarray(alpha_min, float), (M,)) / nrm_s ** 2
    if start is not None:
        a0 = np.asarray(start, float) / nrm_s ** 2  # precisions in the unit-norm coordinates (w_n = ‖φ‖ w)
        st.alpha = np.where((usable | held) & np.isfinite(a0), a0, np.inf)
    held &= np.isfinite(st.alpha)
    if not np.isfinite(st.alpha).any() and usable.any():
        score = np.where(usable, h * h / np.maximum(np.diag(G), 1e-300), -np.inf)
        j = int(np.argmax(score))
        S, Qj = st.beta * G[j, j], st.beta * h[j]
        st.alpha[j] = max(S * S / (Qj * Qj - S) if Qj * Qj > S else S, amin[j])  # a weak start: re-estimated or deleted
    max_iter = 20 * M + 50 if max_iter is None else int(max_iter)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        st, A, Sig, mu, it, converged = _search(st, usable, held, amin, tol, max_iter, fixed, start is not None, M)
        fit = _result(st, A, Sig, mu, nrm_s, Pn, y, F, Q, it, converged, pre)
        # what adding each column alone would gain (the held-out ones included): ℓ at its optimal precision — the
        # log Bayes factor of that column against this model with every other precision held (a cheap screen)
        s, q = st.sq(A, Sig, mu)
        theta = q * q - s
        out = np.isinf(st.alpha) & ~pre.repeats
        best = np.where(theta > 0, np.maximum(s * s / np.where(theta > 0, theta, 1.0), amin), np.inf)
        fit.extra["add_gain"] = np.where(out & (theta > 0), _ell(best, s, q), 0.0)
    return fit


class Prepared:
    """What :func:`sparse_bayes` computes from its rows alone (``prepared=``): column norms, the projection off
    ``F``, the Gram matrix and ``Φᵀy`` of the projected unit-norm columns, and ``F⁺`` when asked."""

    def __init__(self, Phi, y, F):
        self.Phi = np.asarray(Phi, float)
        self.y = np.asarray(y, float)
        self.N, self.M = self.Phi.shape
        self.F = None if F is None else np.asarray(F, float).reshape(self.N, -1)
        self.nrm = np.linalg.norm(self.Phi, axis=0)
        self.nrm_s = np.where(self.nrm > 0, self.nrm, 1.0)
        self.Pn = self.Phi / self.nrm_s
        (Pt, self.yt), rank_f, self.Q = _project(self.F, self.Pn, self.y)
        self.n = self.N - rank_f
        if self.n <= 0:
            raise ValueError(f"sparse_bayes: {self.N} rows and {rank_f} unpenalised columns leave no degree of "
                             f"freedom")
        self.G = Pt.T @ Pt
        self.h = Pt.T @ self.yt
        self.repeats, self.rounding = _repeats(self.G)
        self._Fp = self._FFt = None

    def F_pinv(self):
        """``F⁺`` on the independent columns of ``F`` (the pivoted QR of :func:`_project`; the others get 0)."""
        if self._Fp is None:
            Qf, Rf, cols, fn = self.Q
            Fp = np.zeros((self.F.shape[1], self.F.shape[0]))
            Fp[cols] = np.linalg.solve(Rf, Qf.T) / fn[cols, None]
            self._Fp = Fp
        return self._Fp

    def F_gram(self):
        """``F⁺ F⁺ᵀ`` (the free coefficients' covariance at unit noise, given the penalised ones)."""
        if self._FFt is None:
            Fp = self.F_pinv()
            self._FFt = Fp @ Fp.T
        return self._FFt


def _search(st, usable, held, amin, tol, max_iter, fixed, warm, M):
    """The sequential search (module docstring) from the state's precisions; returns
    ``(state, A, Σ, μ, steps, converged)``."""
    converged, it = False, 0
    A, Sig, mu = st.posterior()
    L = None  # the log evidence, computed when a batch needs the comparison
    for it in range(1, max_iter + 1):
        s, q = st.sq(A, Sig, mu)
        theta = q * q - s
        new_alpha = np.where(usable & (theta > 0), np.maximum(s * s / np.where(theta > 0, theta, 1.0), amin), np.inf)
        new_alpha[held] = st.alpha[held]
        gain = _ell(new_alpha, s, q) - _ell(st.alpha, s, q)
        gain = np.where(np.isfinite(gain), gain, -np.inf)
        j = int(np.argmax(gain)) if M else 0
        if not M or gain[j] <= tol:  # (no penalised column: the noise alone)
            if fixed:
                converged = True
                break
            beta0 = st.beta
            st.update_noise(A, Sig, mu)
            A, Sig, mu = st.posterior()
            L = None
            if abs(np.log(st.beta / beta0)) < 1e-6:
                converged = True
                break
            continue
        old = st.alpha.copy()
        # Many columns change at once from a warm start. Try every action that gains alone (each at its optimum
        # given the others: MacKay's simultaneous update, with Tipping & Faul's adds and deletes), then the
        # re-estimates only; keep a batch when the evidence rises, else take the single best action (Tipping &
        # Faul's step, which always raises it). The stopping rule is theirs either way: no single action gains.
        good = (gain > tol) & ~((old == new_alpha) | (np.isinf(old) & np.isinf(new_alpha)))
        refresh = good & np.isfinite(old) & np.isfinite(new_alpha)
        tries = [good] if warm else []  # from a warm start: everything at once first
        if refresh[j]:
            tries.append(refresh)
        took = False
        for batch in tries:
            if batch.sum() < 2:
                continue
            if L is None:
                L = st.log_evidence(A, Sig, mu)
            st.alpha[batch] = new_alpha[batch]
            if np.isfinite(st.alpha).any():
                A2, Sig2, mu2 = st.posterior()
                L2 = st.log_evidence(A2, Sig2, mu2)
                if L2 > L + tol:
                    A, Sig, mu, L = A2, Sig2, mu2, L2
                    took = True
                    break
            st.alpha = old.copy()
        if took:
            continue
        st.alpha[j] = new_alpha[j]
        if not fixed and it % 5 == 0:
            st.update_noise(*st.posterior())
        A, Sig, mu = st.posterior()
        L = None
    return st, A, Sig, mu, it, converged


def _result(st, A, Sig, mu, nrm_s, Pn, y, F, Q, it, converged, pre) -> SparseFit:
    M = len(nrm_s)
    alpha = np.full(M, np.inf)
    alpha[A] = st.alpha[A] * nrm_s[A] ** 2
    mean = np.zeros(M)
    mean[A] = mu / nrm_s[A]
    cov = np.zeros((M, M))
    cov[A[:, None], A] = Sig / np.outer(nrm_s[A], nrm_s[A])
    gamma = np.zeros(M)
    gamma[A] = 1.0 - st.alpha[A] * np.diag(Sig)
    extra = {}
    if F is not None and F.shape[1]:
        # c given w: least squares of y − Φw on F (the pivoted QR of _project; a column F's others span gets 0);
        # its covariance adds the penalised part's through F⁺Φ
        Fp = pre.F_pinv()
        free = Fp @ (y - Pn[:, A] @ mu)
        P = Fp @ Pn[:, A]
        free_cov = pre.F_gram() / st.beta + P @ Sig @ P.T
        # what a prediction's covariance at other rows needs (prediction_cov: F⁺ and the training Φ)
        extra = {"F_pinv": Fp, "Phi": Pn, "Phi_scale": nrm_s}
    else:
        free, free_cov = np.zeros(0), np.zeros((0, 0))
    return SparseFit(alpha, mean, cov, free, free_cov, 1.0 / st.beta, st.log_evidence(A, Sig, mu), gamma, it,
                     converged, int(st.n), extra)


def log_evidence_ard(Phi, y, alpha, noise_var, F=None) -> float:
    """log p(y | α, σ²) computed directly in the data space, ``−½ [n log 2π + log|C| + ỹᵀ C⁻¹ ỹ]`` with
    ``C = σ² I + Σ_j φ̃_j φ̃_jᵀ / α_j`` on the rows projected off ``F`` (an orthonormal basis of the complement:
    ``n = N − rank F`` coordinates). The O(N³) reference for :func:`sparse_bayes`'s evidence (tests)."""
    Phi = np.asarray(Phi, float)
    y = np.asarray(y, float)
    N = len(y)
    if F is not None and np.size(F):
        (_,), r, fac = _project(np.asarray(F, float).reshape(N, -1), y)
        U, _, _ = np.linalg.svd(np.eye(N) - fac[0] @ fac[0].T)
        B = U[:, : N - r]  # orthonormal basis of the complement
    else:
        B = np.eye(N)
    Pb, yb = B.T @ Phi, B.T @ y
    a = np.asarray(alpha, float)
    keep = np.isfinite(a)
    C = noise_var * np.eye(len(yb)) + (Pb[:, keep] / a[keep]) @ Pb[:, keep].T
    _, logdet = np.linalg.slogdet(C)
    return float(-0.5 * (len(yb) * _LOG2PI + logdet + yb @ np.linalg.solve(C, yb)))
