"""Low-rank covariance updates (Sherman–Morrison–Woodbury) for adding measurements.

Adding one pose with whitened Jacobian rows ``B = W^{1/2} H`` (r × p, r = 3 for
a position, 6 for a pose) to information ``M = C⁻¹`` gives

.. math::

    C^+ = (M + B^T B)^{-1} = C - C B^T S^{-1} B C,\\qquad S = I_r + B C B^T

(Woodbury; for r = 1 Sherman–Morrison). This is exactly the Kalman / MAP
covariance update of a constant parameter vector, Mooring (4.106) with
``R = W⁻¹``: ``P⁺ = P − P Hᵀ (H P Hᵀ + R)⁻¹ H P``. Scalar criteria of ``C⁺``
follow without forming it:

* ``det C⁺ = det C / det S``  (matrix determinant lemma),
* ``trace(G C⁺) = trace(G C) − trace(S⁻¹ B C G C Bᵀ)`` for any weight ``G``
  (``G = I``: A-criterion; ``G = J0ᵀJ0``: test-pose ρ0²).

Every function is vectorised over K candidate poses (``B`` of shape (K, r, p));
cost O(K r p²) instead of K inversions of p × p matrices.
"""
from __future__ import annotations

import numpy as np

from .criteria import normalise_criterion

__all__ = ["woodbury_covariance", "added_logdet_cov", "added_trace", "added_test_pose_variance",
           "added_criterion_value", "FAST_CRITERIA", "whiten"]

#: criteria with a closed-form low-rank update
FAST_CRITERIA = ("D", "A", "test-pose", "test-pose-max", "G")


def whiten(H, sigma) -> np.ndarray:
    """``B = W^{1/2} H``: rows divided by their standard deviations (σ broadcast to (..., r))."""
    H = np.asarray(H, float)
    return H / np.broadcast_to(np.asarray(sigma, float), H.shape[:-1])[..., None]


def _S_solve(C, B):
    """CBᵀ (K, p, r), S = I + B C Bᵀ (K, r, r) and S⁻¹ B C (K, r, p)."""
    CBt = np.einsum("pq,krq->kpr", C, B)
    S = np.eye(B.shape[-2]) + np.einsum("krp,kps->krs", B, CBt)
    X = np.linalg.solve(S, np.swapaxes(CBt, -1, -2))  # S⁻¹ B C
    return CBt, S, X


def woodbury_covariance(C, B) -> np.ndarray:
    """``C⁺ = C − C Bᵀ (I + B C Bᵀ)⁻¹ B C`` for each of K candidates (K, r, p) → (K, p, p)."""
    C = np.asarray(C, float)
    B = np.asarray(B, float)
    if B.ndim == 2:
        B = B[None]
    CBt, S, X = _S_solve(C, B)
    return C[None] - np.einsum("kpr,krq->kpq", CBt, X)


def added_logdet_cov(C, B, logdet_C=None) -> np.ndarray:
    """``log det C⁺ = log det C − log det S`` for each candidate (K,)."""
    C = np.asarray(C, float)
    B = np.asarray(B, float)
    if logdet_C is None:
        logdet_C = np.linalg.slogdet(C)[1]
    _, S, _ = _S_solve(C, B)
    return logdet_C - np.linalg.slogdet(S)[1]


def added_trace(C, B, G=None) -> np.ndarray:
    """``trace(G C⁺)`` for each candidate (K,); ``G`` defaults to the identity."""
    C = np.asarray(C, float)
    B = np.asarray(B, float)
    CBt, S, X = _S_solve(C, B)
    if G is None:
        return np.trace(C) - np.einsum("krp,kpr->k", X, CBt)
    G = np.asarray(G, float)
    return np.einsum("pq,qp->", G, C) - np.einsum("krp,pq,kqr->k", X, G, CBt)


def added_test_pose_variance(C, B, J0) -> np.ndarray:
    """``trace(J0_t C⁺ J0_tᵀ)`` for K candidates and T test poses → (K, T)."""
    C = np.asarray(C, float)
    B = np.asarray(B, float)
    J0 = np.asarray(J0, float)
    if J0.ndim == 2:
        J0 = J0[None]
    CBt, S, X = _S_solve(C, B)
    base = np.einsum("tap,pq,taq->t", J0, C, J0)
    U = np.einsum("tap,kpr->ktar", J0, CBt)  # J0 C Bᵀ
    V = np.einsum("krp,tap->ktra", X, J0)  # S⁻¹ B C J0ᵀ
    return base[None] - np.einsum("ktar,ktra->kt", U, V)


def added_criterion_value(criterion: str, C, B, J_test=None, logdet_C=None) -> np.ndarray:
    """Criterion value of ``C⁺`` for each candidate, for the criteria in :data:`FAST_CRITERIA`."""
    name = normalise_criterion(criterion)
    C = np.asarray(C, float)
    p = C.shape[0]
    if name == "D":
        return np.exp(added_logdet_cov(C, B, logdet_C) / p)
    if name == "A":
        return added_trace(C, B)
    if name == "test-pose":  # mean_t trace(J0_t C⁺ J0_tᵀ) = trace(Ḡ C⁺), Ḡ = mean_t J0_tᵀ J0_t
        J0 = np.asarray(J_test, float).reshape(-1, *np.shape(J_test)[-2:])
        return added_trace(C, B, np.einsum("tap,taq->pq", J0, J0) / len(J0))
    if name in ("test-pose-max", "G"):
        return added_test_pose_variance(C, B, J_test).max(-1)
    raise ValueError(f"criterion {name!r} has no low-rank update; use one of {FAST_CRITERIA}")
