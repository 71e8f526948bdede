"""The linear-Gaussian core of the repeatability model (pure numerical functions).

Session ``s`` sees the parameters ``θ_s = θ + E u_s``, ``u_s ~ N(0, Q)``, where
``E`` selects the subset S of the free parameters that varies between sessions
(joint offsets after re-homing, the base after the tracker moved, …) and
``Q = diag(q)``. Linearised about ``θ_lin + E û_s`` and whitened by the
measurement noise, session s gives

    r̃_s = A_s δθ + B_s u_s + ε_s,      ε_s ~ N(0, s² I),   B_s = A_s E,

with the pseudo-data ``r̃_s = r_s + B_s û_s`` (r_s the whitened residual at the
session's linearisation point). Integrating ``u_s`` out gives the marginal
covariance ``V_s = s² I + B_s Q B_sᵀ``; the generalised least-squares estimate
``δθ = N⁻¹ g`` with ``N = Σ A_sᵀ V_s⁻¹ A_s``, ``g = Σ A_sᵀ V_s⁻¹ r̃_s`` is the
best linear unbiased estimate and ``N⁻¹`` its covariance; ``û_s`` are the best
linear unbiased predictions (Henderson's mixed-model equations; Searle, Casella
& McCulloch, *Variance Components*, 1992, ch. 7). Every product with ``V_s⁻¹``
goes through Woodbury's identity with ``C = B_s Q^{1/2}``,
``K = s² I + CᵀC`` (k × k), so only the normal-equation blocks ``AᵀA``, ``Aᵀr̃``
and ``r̃ᵀr̃`` of each session are needed — and ``q_j = 0`` (a parameter that
does not vary) is allowed.

The variance components ``q`` (and ``s²`` when the noise level is not trusted)
are estimated by restricted maximum likelihood (REML, Patterson & Thompson 1971;
Harville 1977, eq. 4.4)::

    −2 ℓ_R = Σ_s log|V_s| + log|N| + Σ_s r̃_sᵀ V_s⁻¹ r̃_s − gᵀ N⁻¹ g   (+ const),

with ``log|V_s| = (m_s − k) log s² + log|K_s|``. Its uncertainty comes from the
observed information (numerical Hessian of −ℓ_R in q).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg as sla
from scipy import optimize

__all__ = ["SessionBlocks", "blocks_from_rows", "gls", "reml", "reml_objective"]


@dataclass
class SessionBlocks:
    """Normal-equation blocks of one session (whitened, free parameters only).

    AtA : (p, p); Atr : (p,); rtr : float; m : number of rows. ``S`` (indices into
    the free parameters) selects the varying subset, so ``B = A[:, S]``.
    """

    AtA: np.ndarray
    Atr: np.ndarray
    rtr: float
    m: int


def blocks_from_rows(A: np.ndarray, r: np.ndarray) -> SessionBlocks:
    """Blocks of one session from its whitened Jacobian ``A`` (m, p) and pseudo-data ``r`` (m,)."""
    return SessionBlocks(A.T @ A, A.T @ r, float(r @ r), int(A.shape[0]))


def _session_terms(b: SessionBlocks, S, q, s2):
    """(AᵀV⁻¹A, AᵀV⁻¹r, rᵀV⁻¹r, log|V|, K⁻¹-pieces) for one session via Woodbury."""
    d = np.sqrt(np.maximum(q, 0.0))
    k = len(S)
    AtB = b.AtA[:, S]
    CtC = d[:, None] * b.AtA[np.ix_(S, S)] * d[None, :]
    K = s2 * np.eye(k) + CtC
    cf = sla.cho_factor(K)
    AtC = AtB * d[None, :]
    Ctr = d * b.Atr[S]
    X = sla.cho_solve(cf, AtC.T)  # K⁻¹ CᵀA (k, p)
    y = sla.cho_solve(cf, Ctr)  # K⁻¹ Cᵀr
    AVA = (b.AtA - AtC @ X) / s2
    AVr = (b.Atr - AtC @ y) / s2
    rVr = (b.rtr - Ctr @ y) / s2
    logdetV = (b.m - k) * np.log(s2) + 2.0 * np.sum(np.log(np.diag(cf[0])))
    return AVA, AVr, rVr, logdetV, cf, d


def gls(blocks: list[SessionBlocks], S, q, s2: float = 1.0):
    """GLS estimate of ``δθ``, its covariance ``N⁻¹`` and the BLUPs ``û_s`` with their error covariances.

    Returns ``(delta (p,), cov (p, p), u (n_s, k), u_cov (n_s, k, k))``. ``u_cov`` is the
    prediction-error covariance ``s² D K⁻¹ D + L N⁻¹ Lᵀ`` (L = ∂û/∂δθ), D = Q^{1/2}.
    """
    S = np.asarray(S, int)
    q = np.asarray(q, float)
    p = blocks[0].AtA.shape[0]
    N = np.zeros((p, p))
    g = np.zeros(p)
    parts = []
    for b in blocks:
        AVA, AVr, _, _, cf, d = _session_terms(b, S, q, s2)
        N += AVA
        g += AVr
        parts.append((cf, d))
    cov = np.linalg.inv(N)
    cov = 0.5 * (cov + cov.T)
    delta = cov @ g
    u = np.zeros((len(blocks), len(S)))
    ucov = np.zeros((len(blocks), len(S), len(S)))
    for i, (b, (cf, d)) in enumerate(zip(blocks, parts)):
        # û = D K⁻¹ D (Bᵀr̃ − BᵀA δθ)
        rhs = b.Atr[S] - b.AtA[S] @ delta
        u[i] = d * sla.cho_solve(cf, d * rhs)
        Kinv = sla.cho_solve(cf, np.eye(len(S)))
        L = -(d[:, None] * (Kinv @ (d[:, None] * b.AtA[S])))
        ucov[i] = s2 * (d[:, None] * Kinv * d[None, :]) + L @ cov @ L.T
    return delta, cov, u, ucov


def reml_objective(blocks: list[SessionBlocks], S, q, s2: float = 1.0) -> float:
    """−2 ℓ_R(q, s²) up to a constant (module docstring)."""
    S = np.asarray(S, int)
    p = blocks[0].AtA.shape[0]
    N = np.zeros((p, p))
    g = np.zeros(p)
    tot = 0.0
    for b in blocks:
        AVA, AVr, rVr, logdetV, _, _ = _session_terms(b, S, q, s2)
        N += AVA
        g += AVr
        tot += logdetV + rVr
    try:
        cf = sla.cho_factor(N)
    except np.linalg.LinAlgError:
        return np.inf
    return float(tot + 2.0 * np.sum(np.log(np.diag(cf[0]))) - g @ sla.cho_solve(cf, g))


def reml(blocks: list[SessionBlocks], S, q0=None, estimate_scale: bool = False, scale0: float = 1.0,
         q_max: float = 1.0):
    """REML estimate of the variance components ``q`` (and of ``s²`` with ``estimate_scale``).

    Optimises over ``η = log q`` (and ``log s²``) with L-BFGS-B; a component at its lower
    bound (1e-14 of ``q_max``, effectively zero) means "does not vary". Returns
    ``(q, s2, q_std, info)`` with ``q_std`` from the numerical Hessian of −ℓ_R in ``q``
    (NaN for components at the bound, whose likelihood is flat or increasing there).
    """
    S = np.asarray(S, int)
    k = len(S)
    if k == 0:
        return np.zeros(0), float(scale0), np.zeros(0), {"objective": reml_objective(blocks, S, [], scale0)}
    q0 = np.full(k, 1e-6 * q_max) if q0 is None else np.maximum(np.asarray(q0, float), 1e-12 * q_max)
    lo = np.log(1e-14 * q_max)
    hi = np.log(q_max)

    def unpack(x):
        q = np.exp(x[:k])
        s2 = float(np.exp(x[k])) if estimate_scale else float(scale0)
        return q, s2

    def f(x):
        q, s2 = unpack(x)
        return reml_objective(blocks, S, q, s2)

    x0 = np.log(np.clip(q0, np.exp(lo), np.exp(hi)))
    bounds = [(lo, hi)] * k
    if estimate_scale:
        x0 = np.append(x0, np.log(scale0))
        bounds.append((np.log(1e-6), np.log(1e6)))
    best = None
    # a few starts: the REML surface in log q is flat near zero, so start low and high
    for start in (x0, np.full_like(x0, np.log(1e-4 * q_max))):
        if estimate_scale:
            start = start.copy()
            start[k] = np.log(scale0)
        res = optimize.minimize(f, start, method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    q, s2 = unpack(best.x)
    at_bound = best.x[:k] <= lo + 1e-3
    q = np.where(at_bound, 0.0, q)
    q_std = _q_std(blocks, S, q, s2, at_bound)
    return q, s2, q_std, {"objective": float(best.fun), "converged": bool(best.success),
                          "at_zero": at_bound.tolist()}


def _q_std(blocks, S, q, s2, at_bound):
    """Std of q from the observed information ½ ∂²(−2ℓ_R)/∂q² (central differences)."""
    k = len(q)
    free = np.flatnonzero(~at_bound)
    out = np.full(k, np.nan)
    if not free.size:
        return out
    h = np.maximum(1e-3 * q[free], 1e-16)
    H = np.empty((free.size, free.size))
    base = reml_objective(blocks, S, q, s2)
    for a, i in enumerate(free):
        for b_, j in enumerate(free):
            if b_ < a:
                H[a, b_] = H[b_, a]
                continue
            def ev(si, sj):
                qq = q.copy()
                qq[i] += si * h[a]
                qq[j] += sj * h[b_]
                return reml_objective(blocks, S, qq, s2)
            if i == j:
                H[a, a] = (ev(1, 0) - 2 * base + ev(-1, 0)) / h[a] ** 2
            else:
                H[a, b_] = (ev(1, 1) - ev(1, -1) - ev(-1, 1) + ev(-1, -1)) / (4 * h[a] * h[b_])
    info = 0.5 * H
    try:
        cov = np.linalg.inv(info)
        out[free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        pass
    return out
