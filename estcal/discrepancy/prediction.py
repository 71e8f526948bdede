"""A prediction at new postures, and its 95 % region, from the nested cross-validation's held-out errors.

The error budget (:mod:`estcal.discrepancy.budget`) holds every outer fold's postures out of the whole
procedure of the diagnosis — its choices included (Varma & Simon 2006; Cawley & Talbot 2010: a CV that
chooses and then scores its own choice is optimistic) — and keeps each held-out point's error with the
fold model's prediction covariance there. This module turns them into a prediction and a region.

The prediction region
---------------------
A 95 % region for the measured point at a new posture is ``eᵀ Σ⁻¹ e ≤ q̂`` with
``Σ = b·N·J C_θ Jᵀ + τ² I₃``: the parameter covariance propagated by the analytic Jacobian (scaled
as below), plus τ², the part of the nested held-out residual variance that the parameter
covariance does not explain (the unstructured residual, the between-session part, what a residual
GP leaves). The
threshold q̂ is not χ²₃(0.95) = 7.81 but the conformal quantile of the same score over the
nested held-out points — the ⌈0.95 (n + 1)⌉-th smallest (split-conformal / CV+, Barber, Candès,
Ramdas & Tibshirani 2021, *Ann. Statist.* 49(1)) — so heavy tails (a few postures far off)
widen the region instead of breaking its coverage. The scores come from models that never saw
the scored postures, so the coverage holds at new postures like the training ones.

At the postures where the robot will be used
--------------------------------------------
Postures *unlike* the training ones — beyond the training joint ranges, where the fit is an
extrapolation — have larger errors than the CV's held-out postures, and a CV average does not
see them. Their distance from the training postures, in the metric of the identification
Jacobian, is the leverage of the posture (Cook & Weisberg 1982): ``v = N · tr(J C_θ Jᵀ)`` with
C_θ the fit's parameter covariance and N its number of training rows — the prediction variance in
units of one training row's share, so that a fold's fit (fewer rows) and the final fit measure
distance alike. Inside the nested CV every held-out point has its ``v`` from the fold's own fit,
and its error is modelled as ``e ~ N(0, b·S + (a/3) I₃)``, so that ``E|e|² = a + b·v``
(:func:`variance_model`: maximum likelihood with ``a, b ≥ 0``): ``a`` the error a model makes anywhere (unstructured residual, session
offsets, what a GP leaves), ``b`` how fast it grows as the posture leaves the span of the
training postures — on real robots mostly model error amplified by extrapolation, which more
rows of the same postures do not remove (hence the scaling by N). Given target postures (their
joint readings only, never their measurements) the expected RMSE there is ``√mean(a + b·v_t)``
with ``v_t`` from the final fit (:func:`predicted_rmse_at`); at targets like the CV's held-out
postures it is the nested CV figure. The region becomes ``Σ = b·N·J C_θ Jᵀ + (a/3) I₃`` (a GP's
variance is in ``a``: far from its data it is its prior amplitude wherever the posture is), so it
widens with the distance, and its conformal threshold is taken over the same nested scores — a
normalised conformal region (Lei, G'Sell, Rinaldo, Tibshirani & Wasserman 2018, *JASA* 113, §5.2).

The held-out points vouch for ``b`` only up to the farthest of them: the nested CV never holds out a
posture as far from its training postures as a target beyond every training range can be. Beyond that
leverage the region takes the one-sided 95 % profile-likelihood upper bound of ``b``
(:func:`slope_upper`; Venzon & Moolgavkar 1988, *Appl. Statist.* 37) — wide where the held-out points
say little about the growth, close to ``b`` where they say much — and :func:`beyond_leverage` reports
the share of such targets. The expected RMSE there stays the estimate ``√mean(a + b·v_t)``: a bound is
not an expectation.
"""
from __future__ import annotations

import numpy as np

from estcal.estimate.robust import chi2_ppf  # scipy.stats.chi2.ppf's value without importing scipy.stats (~0.3 s)

__all__ = ["region_scores", "conformal_threshold", "region_coverage", "variance_model", "slope_upper",
           "predicted_rmse_at", "region_sigma", "beyond_leverage"]


def region_scores(e, S, tau2: float) -> np.ndarray:
    """``eᵀ (S + τ² I)⁻¹ e`` of every point: e (..., 3) errors, S (..., 3, 3) covariances (m², m)."""
    e = np.asarray(e, float)
    Sig = np.asarray(S, float) + tau2 * np.eye(3)
    return np.einsum("...i,...i->...", e, np.linalg.solve(Sig, e[..., None])[..., 0])


def conformal_threshold(scores, level: float = 0.95) -> float:
    """The ⌈level·(n + 1)⌉-th smallest score (∞ when there are too few): the split-conformal /
    CV+ threshold of a ``level`` region (Barber et al. 2021)."""
    s = np.sort(np.asarray(scores, float).reshape(-1))
    n = len(s)
    r = int(np.ceil(level * (n + 1)))
    return float(s[r - 1]) if 1 <= r <= n else float("inf")


def region_coverage(region: dict, e, S) -> float:
    """Share of the points (errors ``e`` (…, 3), covariances ``S`` (…, 3, 3) of the model that predicts
    them) inside the region ``{"tau_mm", "threshold_d2"[, "scale"]}`` of a budget (:func:`region_sigma`)."""
    d2 = region_scores(e, region_sigma(region, S), 0.0)
    return float(np.mean(d2 <= region["threshold_d2"]))


def region_sigma(region: dict, S) -> np.ndarray:
    """Σ = scale · S + τ² I₃ of a region (``scale`` = b of :func:`variance_model`, 1 when absent); at points
    whose leverage tr S exceeds the region's ``leverage_max`` (the farthest held-out point that fitted b)
    the scale is ``scale_far`` (:func:`slope_upper`) when the region has one."""
    S = np.asarray(S, float)
    scale = region.get("scale", 1.0)
    if region.get("scale_far") is not None and region.get("leverage_max_m2") is not None:
        far = np.trace(S, axis1=-2, axis2=-1) > region["leverage_max_m2"]
        scale = np.where(far, region["scale_far"], scale)[..., None, None]
    return scale * S + (region["tau_mm"] * 1e-3) ** 2 * np.eye(3)


def beyond_leverage(region: dict, S) -> float:
    """Share of the points (covariances ``S`` (…, 3, 3)) beyond the farthest held-out leverage of the region:
    where its slope is the bound of :func:`slope_upper`, not an estimate."""
    lm = region.get("leverage_max_m2")
    v = np.trace(np.asarray(S, float), axis1=-2, axis2=-1)
    return float(np.mean(v > lm)) if lm is not None and v.size else 0.0


def _eigen_scores(e, S):
    """(z, λ, scale) of errors ``e`` (…, 3) in the eigenbasis of their covariances ``S`` (…, 3, 3): z = (Uᵀe)²
    and λ per component, both divided by the mean squared error per coordinate (the scale)."""
    e = np.asarray(e, float).reshape(-1, 3)
    S = np.asarray(S, float).reshape(-1, 3, 3)
    lam, U = np.linalg.eigh(0.5 * (S + S.transpose(0, 2, 1)))
    z = np.einsum("nji,nj->ni", U, e) ** 2
    s = max(float(z.mean()), 1e-300) if z.size else 1.0
    return z / s, np.clip(lam, 0.0, None) / s, s


def _nll(b, t, z, lam) -> float:
    """½ Σ z/(bλ + t) + log(bλ + t): the Gaussian negative log-likelihood (constants dropped)."""
    var = b * lam + t
    return 0.5 * float(np.sum(z / var + np.log(var)))


def _fit_ml(z, lam, b_lo, t_lo) -> tuple[float, float, float]:
    """(b, t, negative log-likelihood) at the maximum over b ≥ b_lo, t ≥ t_lo: the profile in log b (τ² profiled
    out, :func:`_profile_t`) on a coarse grid, then bounded Brent around its best point (two parameters: nested
    one-dimensional searches are deterministic and cheap)."""
    from scipy.optimize import minimize_scalar

    lmax = float(lam.max())
    lo = np.log(max(b_lo, 1e-8 / lmax))
    hi = max(np.log(1e4 / lmax), lo + 1.0)
    grid = np.linspace(lo, hi, 33)
    f = [_profile_t(np.exp(x), z, lam, t_lo)[0] for x in grid]
    k = int(np.argmin(f))
    r = minimize_scalar(lambda x: _profile_t(np.exp(x), z, lam, t_lo)[0], method="bounded",
                        bounds=(grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]), options={"xatol": 1e-8})
    cands = [(float(r.fun), float(np.exp(r.x))), (f[k], float(np.exp(grid[k])))]
    if b_lo <= np.exp(lo):  # the bound itself (b = 0 when b_lo is 0)
        cands.append((_profile_t(b_lo, z, lam, t_lo)[0], b_lo))
    fun, b = min(cands)
    return b, _profile_t(b, z, lam, t_lo)[1], fun


def variance_model(e, S, b_min: float = 0.0, tau2_floor: float = 0.0) -> tuple[float, float]:
    """``(a, b)``, a ≥ 3·``tau2_floor`` (m²) and b ≥ ``b_min``, of the region's own error model
    ``e ~ N(0, b·S + (a/3) I₃)`` fitted by maximum likelihood over the points: ``e`` (…, 3) held-out errors,
    ``S`` (…, 3, 3) the (scaled) covariance the model that predicted them gives them (module docstring).
    Then ``E|e|² = a + b·tr S``.

    Maximum likelihood and not least squares of ``|e|²`` on ``tr S``: a squared norm's spread grows with its
    mean, so a line fitted to them is ruled by the few largest errors wherever they fall, and the trace
    forgets the direction — a point whose error lies along its large-variance direction is evidence for
    ``b``, one across it for ``a``. With ``S = U diag(λ) Uᵀ`` and ``z = (Uᵀe)²`` the negative log-likelihood
    is ``½ Σ z/(bλ + τ²) + log(bλ + τ²)`` (τ² = a/3), minimised over the box (:func:`_fit_ml`)."""
    z, lam, s = _eigen_scores(e, S)
    if z.size == 0:
        return 3.0 * tau2_floor, b_min
    t_lo = max(tau2_floor / s, 1e-9)
    if not np.any(lam > 0):
        return 3.0 * max(s * float(z.mean()), tau2_floor), b_min
    b, t, _ = _fit_ml(z, lam, b_min, t_lo)
    return float(3.0 * t * s), float(b)


def slope_upper(e, S, b: float, tau2_floor: float = 0.0, level: float = 0.95) -> float:
    """One-sided ``level`` upper confidence bound of ``b`` in :func:`variance_model` by the profile likelihood
    (Venzon & Moolgavkar 1988): the b > b̂ where twice the rise of the negative log-likelihood, τ² profiled out,
    reaches the χ²₁ quantile of ``2·level − 1`` (2.71 for 95 %). The held-out points say how fast the error
    grows with the leverage only up to the farthest of them; beyond it the region takes the largest slope
    they do not rule out (∞ when nothing bounds it)."""
    from scipy.optimize import brentq

    z, lam, s = _eigen_scores(e, S)
    if z.size == 0 or not np.any(lam > 0):
        return float("inf")
    t_lo = max(tau2_floor / s, 1e-9)

    def profile(bb):
        return _profile_t(bb, z, lam, t_lo)[0]

    q = float(chi2_ppf(2 * level - 1, 1)) / 2
    l0 = profile(b)
    lo = np.log(max(b, 1e-9 / float(lam.max())))
    for step in range(1, 60):
        if profile(np.exp(lo + step)) - l0 > q:
            return float(np.exp(brentq(lambda lb: profile(np.exp(lb)) - l0 - q, lo + step - 1, lo + step,
                                       xtol=1e-6)))
    return float("inf")


def _profile_t(b, z, lam, t_lo) -> tuple[float, float]:
    """(min over t ≥ t_lo of the negative log-likelihood at slope b, the minimising t): bounded Brent over
    log t (z and λ are in units of the mean squared error, so t ≤ 10³ bounds it), and the bound t_lo."""
    from scipy.optimize import minimize_scalar

    r = minimize_scalar(lambda lt: _nll(b, np.exp(lt), z, lam), bounds=(np.log(t_lo), np.log(1e3)),
                        method="bounded", options={"xatol": 1e-9})
    at_lo = _nll(b, t_lo, z, lam)
    return (at_lo, t_lo) if at_lo <= r.fun else (float(r.fun), float(np.exp(r.x)))


def _nnls_line(y, v) -> tuple[float, float]:
    """min Σ (y − a − b v)² subject to a, b ≥ 0 (two columns: the interior or an edge solution)."""
    vc = v - v.mean()
    den = float(vc @ vc)
    if den > 0:
        b = float(vc @ (y - y.mean())) / den
        a = float(y.mean() - b * v.mean())
        if a >= 0 and b >= 0:
            return a, b
    only_a = (max(float(y.mean()), 0.0), 0.0)
    vv = float(v @ v)
    if vv <= 0:
        return only_a
    only_b = (0.0, max(float(v @ y) / vv, 0.0))
    sse = lambda ab: float(np.sum((y - ab[0] - ab[1] * v) ** 2))  # noqa: E731
    return min((only_a, only_b), key=sse)


def predicted_rmse_at(a: float, b: float, S, leverage_max: float | None = None) -> float:
    """Expected RMSE (m) of the point-error norms at points whose model covariance is ``S`` (…, 3, 3):
    √mean(a + b·min(tr S, leverage_max)) (:func:`variance_model`).

    ``leverage_max``: the largest leverage the variance model was fitted on (the nested CV's held-out points);
    beyond it the line a + b·v is not calibrated, and extrapolated it multiplies a wide posterior direction
    (a joint's offset and its load-side backlash nearly collinear on the training postures) into a prediction
    several times the error measured there (TIAGo: 12.9 mm for 2.4). A point beyond is held at the largest
    tested leverage; the output says how many points are beyond (``beyond_cv_leverage``)."""
    v = np.trace(np.asarray(S, float), axis1=-2, axis2=-1)
    if leverage_max is not None:
        v = np.minimum(v, leverage_max)
    return float(np.sqrt(np.mean(a + b * v))) if v.size else float("nan")
