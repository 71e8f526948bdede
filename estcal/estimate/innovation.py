"""Innovation tests: does the filter's model explain the data?

With a correct model (A, H, Q, R, P0, μx) the innovations ν_k = z_k − H_k x̂_k(−)
of a Kalman filter are zero-mean, white, and have covariance
S_k = H_k P_k(−) H_kᵀ + R_k (textbook §4.5, "model-error test"). Whitening each
innovation with the Cholesky factor of its own S_k, ``w_k = L_k⁻¹ ν_k`` with
``L_k L_kᵀ = S_k``, gives under the model i.i.d. N(0, 1) components, so:

* **normalised innovation squared** NIS_k = ν_kᵀ S_k⁻¹ ν_k ~ χ²(m_k) and
  Σ_k NIS_k ~ χ²(Σ m_k) (two-sided test: too large means a missing effect or
  optimistic R, too small a pessimistic R);
* **zero mean**: for each component j of the group (row j of every
  measurement), ``n_j w̄_j² `` ~ χ²(1), summed over j ~ χ²(m);
* **whiteness**: the Ljung–Box statistic of each component's series,
  Q_j = n(n+2) Σ_{l=1}^{L} ρ_j(l)²/(n − l) ~ χ²(L), summed over j ~ χ²(L·m).

The tests fire when any p-value falls below α/3 (Bonferroni over the three).
Innovations before ``burn_in`` steps are left out: until the data determine
every parameter, S is dominated by the (deliberately wide, not "true") prior.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import stats

__all__ = ["InnovationMonitor", "InnovationTests", "ljung_box"]


def ljung_box(x, lags: int) -> float:
    """Ljung–Box statistic ``n(n+2) Σ_{l=1}^{L} ρ(l)²/(n−l)`` of a series (mean not removed:
    under the model its mean is 0, and removing it would hide a bias from this test)."""
    x = np.asarray(x, float)
    n = x.size
    L = min(lags, n - 1)
    if L < 1:
        return 0.0
    c0 = float(x @ x)
    if c0 <= 0:
        return 0.0
    rho = np.array([x[:-l] @ x[l:] for l in range(1, L + 1)]) / c0
    return float(n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, L + 1))))


@dataclass
class InnovationTests:
    """Results of the innovation tests (see module docstring). p-values are two-sided for NIS."""

    n_steps: int
    n_components: int
    burn_in: int
    nis_total: float
    nis_dof: int
    nis_mean_per_row: float
    nis_p_value: float
    nis_outside_95: float
    mean_chi2: float
    mean_dof: int
    mean_p_value: float
    ljung_box: float
    ljung_box_dof: int
    ljung_box_p_value: float
    lags: int
    alpha: float
    fires: bool
    failed: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, (np.floating,)) else v) for k, v in asdict(self).items()}

    def __str__(self) -> str:
        verdict = "MODEL REJECTED (" + ", ".join(self.failed) + ")" if self.fires else "consistent"
        return (f"innovations: {self.n_steps} steps after burn-in {self.burn_in}; "
                f"NIS/row {self.nis_mean_per_row:.3f} (p={self.nis_p_value:.3g}), "
                f"mean χ²={self.mean_chi2:.1f}/{self.mean_dof} (p={self.mean_p_value:.3g}), "
                f"Ljung-Box={self.ljung_box:.1f}/{self.ljung_box_dof} (p={self.ljung_box_p_value:.3g}): {verdict}")


class InnovationMonitor:
    """Accumulates innovations ν_k and their covariances S_k; runs the tests on demand."""

    def __init__(self):
        self.nis: list[float] = []
        self.dims: list[int] = []
        self.white: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self.nis)

    def add(self, y, S) -> float:
        """Record one innovation; returns its NIS."""
        y = np.asarray(y, float).reshape(-1)
        S = np.asarray(S, float)
        L = np.linalg.cholesky(0.5 * (S + S.T))
        w = np.linalg.solve(L, y)
        nis = float(w @ w)
        self.nis.append(nis)
        self.dims.append(y.size)
        self.white.append(w)
        return nis

    def running(self, burn_in: int = 0) -> dict:
        """Cheap running summary for live displays: steps, mean NIS per row, last NIS."""
        nis = np.asarray(self.nis[burn_in:])
        dims = np.asarray(self.dims[burn_in:])
        if nis.size == 0:
            return {"steps": len(self.nis), "nis_per_row": float("nan"), "last_nis": float("nan")}
        return {"steps": len(self.nis), "nis_per_row": float(nis.sum() / dims.sum()),
                "last_nis": float(nis[-1]), "last_dim": int(dims[-1])}

    def tests(self, burn_in: int = 0, lags: int = 10, alpha: float = 0.05) -> InnovationTests:
        """Run the three tests on the innovations after ``burn_in`` steps."""
        nis = np.asarray(self.nis[burn_in:])
        dims = np.asarray(self.dims[burn_in:], int)
        white = self.white[burn_in:]
        n = nis.size
        if n < 3:
            raise ValueError(f"only {n} innovations after a burn-in of {burn_in}: too few to test")
        tot, dof = float(nis.sum()), int(dims.sum())
        cdf = stats.chi2.cdf(tot, dof)
        p_nis = float(2 * min(cdf, 1 - cdf))
        lo, hi = stats.chi2.ppf(0.025, dims), stats.chi2.ppf(0.975, dims)
        outside = float(np.mean((nis < lo) | (nis > hi)))
        m = int(dims.max())
        # component j of every step that has it; whitened components are i.i.d. N(0, 1) under the model
        comp = [np.array([w[j] for w in white if w.size > j]) for j in range(m)]
        mean_chi2 = float(sum(c.size * c.mean() ** 2 for c in comp if c.size))
        p_mean = float(stats.chi2.sf(mean_chi2, m))
        L = int(min(lags, max(1, n // 4)))
        lb = float(sum(ljung_box(c, L) for c in comp if c.size > L + 1))
        lb_dof = int(L * sum(1 for c in comp if c.size > L + 1))
        p_lb = float(stats.chi2.sf(lb, lb_dof)) if lb_dof else 1.0
        a = alpha / 3
        failed = [name for name, p in (("NIS", p_nis), ("mean", p_mean), ("whiteness", p_lb)) if p < a]
        return InnovationTests(n, dof, burn_in, tot, dof, tot / dof, p_nis, outside, mean_chi2, m, p_mean, lb,
                               lb_dof, p_lb, L, alpha, bool(failed), failed)
