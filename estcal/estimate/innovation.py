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

__all__ = ["InnovationMonitor", "InnovationTests", "GrowingArray", "ljung_box"]


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

    @property
    def cause(self) -> str | None:
        """What a failed NIS test says about the noise (None when it passed): NIS/row ≪ 1 — the innovations
        are smaller than the assumed noise predicts, the noise is overstated (a clean file read with the
        default 0.1 mm); ≫ 1 — larger: the noise is understated or the model misses an effect."""
        if "NIS" not in self.failed or not self.nis_mean_per_row > 0:
            return None
        f = float(np.sqrt(self.nis_mean_per_row))
        if self.nis_mean_per_row < 1:
            return (f"the innovations are {f:.2g}× the size the assumed measurement noise predicts (NIS/row "
                    f"{self.nis_mean_per_row:.3g} < 1): the noise is overstated — the data are consistent with a "
                    f"noise about {f:.2g}× the assumed one; give that noise to test the model")
        return (f"the innovations are {f:.2g}× the size the assumed noise and the estimate's uncertainty predict "
                f"(NIS/row {self.nis_mean_per_row:.3g} > 1): the noise is understated, or the model misses an "
                f"effect (estcal diagnose names it)")

    def __str__(self) -> str:
        verdict = "MODEL REJECTED (" + ", ".join(self.failed) + ")" if self.fires else "consistent"
        if self.cause:
            verdict += " — " + self.cause
        return (f"innovations: {self.n_steps} steps after burn-in {self.burn_in}; "
                f"NIS/row {self.nis_mean_per_row:.3f} (p={self.nis_p_value:.3g}), "
                f"mean χ²={self.mean_chi2:.1f}/{self.mean_dof} (p={self.mean_p_value:.3g}), "
                f"Ljung-Box={self.ljung_box:.1f}/{self.ljung_box_dof} (p={self.ljung_box_p_value:.3g}): {verdict}")


class GrowingArray:
    """An append-only numpy array with amortised O(1) appends (capacity doubles).

    The per-row records of a long stream (10⁶ rows) kept as Python lists cost ~100–200 bytes
    per number; here they cost the ``itemsize``."""

    def __init__(self, dtype=float, width: int | None = None, capacity: int = 1024):
        shape = (capacity,) if width is None else (capacity, width)
        self._a = np.empty(shape, dtype)
        self.n = 0

    def __len__(self) -> int:
        return self.n

    @property
    def values(self) -> np.ndarray:
        """The filled part (a view: copy it to keep it beyond the next append)."""
        return self._a[:self.n]

    def extend(self, v) -> None:
        v = np.asarray(v, self._a.dtype)
        k = 1 if v.ndim == self._a.ndim - 1 else len(v)
        if self.n + k > len(self._a):
            grown = np.empty((max(2 * len(self._a), self.n + k),) + self._a.shape[1:], self._a.dtype)
            grown[:self.n] = self._a[:self.n]
            self._a = grown
        self._a[self.n:self.n + k] = v
        self.n += k

    append = extend


class InnovationMonitor:
    """Accumulates innovations ν_k and their covariances S_k; runs the tests on demand.

    Storage per step: the NIS, the dimension m_k and the m_k whitened components, in flat
    numpy buffers (8 + 4 + 8 m_k bytes; 10⁶ pose rows: 68 MB), plus prefix sums of NIS and
    dimensions so that :meth:`running` costs O(1) at any stream length."""

    def __init__(self):
        self._nis = GrowingArray(float)
        self._dims = GrowingArray(np.int32)
        self._white = GrowingArray(float)  # whitened components of every step, concatenated
        self._cum_nis = GrowingArray(float)  # Σ NIS of the first k steps (k = 0 … n), sequential sums
        self._cum_dims = GrowingArray(np.int64)
        self._cum_nis.append(0.0)
        self._cum_dims.append(0)

    def __len__(self) -> int:
        return len(self._nis)

    @property
    def nis(self) -> np.ndarray:
        """(n,) NIS of every step."""
        return self._nis.values

    @property
    def dims(self) -> np.ndarray:
        """(n,) dimension m_k of every step's innovation."""
        return self._dims.values

    @property
    def white_flat(self) -> np.ndarray:
        """(Σ m_k,) whitened innovations ``L_k⁻¹ ν_k`` of every step, concatenated."""
        return self._white.values

    @property
    def white(self) -> list[np.ndarray]:
        """The whitened innovation of every step (a list of (m_k,) arrays)."""
        return np.split(self.white_flat, np.cumsum(self.dims)[:-1]) if len(self) else []

    def add(self, y, S) -> float:
        """Record one innovation; returns its NIS."""
        y = np.asarray(y, float).reshape(-1)
        S = np.asarray(S, float)
        L = np.linalg.cholesky(0.5 * (S + S.T))
        w = np.linalg.solve(L, y)
        nis = float(w @ w)
        self.record(nis, w)
        return nis

    def record(self, nis: float, w) -> None:
        """Append a step already whitened (``w`` of size m_k, ``nis = wᵀw``)."""
        w = np.asarray(w, float).reshape(-1)
        self._nis.append(nis)
        self._dims.append(w.size)
        self._white.extend(w)
        self._cum_nis.append(self._cum_nis.values[-1] + nis)
        self._cum_dims.append(self._cum_dims.values[-1] + w.size)

    def record_many(self, nis, dims, white_flat) -> None:
        """Append several steps at once (``nis`` (B,), ``dims`` (B,), ``white_flat`` (Σ dims,)); the
        running sums are extended in the order :meth:`record` would add them one by one."""
        nis = np.asarray(nis, float).reshape(-1)
        dims = np.asarray(dims, np.int64).reshape(-1)
        self._nis.extend(nis)
        self._dims.extend(dims)
        self._white.extend(np.asarray(white_flat, float).reshape(-1))
        cn = np.cumsum(np.r_[self._cum_nis.values[-1], nis])[1:]  # sequential sums, as record() adds
        self._cum_nis.extend(cn)
        self._cum_dims.extend(self._cum_dims.values[-1] + np.cumsum(dims))

    def running_at(self, k, burn_in=0) -> np.ndarray:
        """Mean NIS per row over steps ``burn_in … k − 1`` for every ``k`` of an array (``burn_in`` a
        number or one per k; NaN where no step after the burn-in is included): the value
        :meth:`running` gave after step k."""
        k = np.asarray(k, np.int64)
        b = np.minimum(np.maximum(np.asarray(burn_in, np.int64), 0), k)
        cn, cd = self._cum_nis.values, self._cum_dims.values
        num, den = cn[k] - cn[b], cd[k] - cd[b]
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1), np.nan)

    @classmethod
    def from_record(cls, nis, dims, white_flat) -> "InnovationMonitor":
        """A monitor holding a saved record (``nis``, ``dims`` and the concatenated ``white``); its
        running sums are rebuilt in the same order as :meth:`record` adds them."""
        mon = cls()
        nis, dims = np.asarray(nis, float), np.asarray(dims, np.int64)
        white_flat = np.asarray(white_flat, float)
        if dims.size != nis.size or int(dims.sum()) != white_flat.size:
            raise ValueError(f"innovation record: {nis.size} NIS, {dims.size} dimensions and "
                             f"{white_flat.size} whitened components do not match")
        mon._nis.extend(nis)
        mon._dims.extend(dims)
        mon._white.extend(white_flat)
        mon._cum_nis.extend(np.cumsum(nis))  # numpy's cumsum adds sequentially, as record() does
        mon._cum_dims.extend(np.cumsum(dims))
        return mon

    def running(self, burn_in: int = 0) -> dict:
        """Cheap running summary for live displays: steps, mean NIS per row, last NIS (O(1))."""
        n = len(self)
        b = min(max(int(burn_in), 0), n)
        if n - b == 0:
            return {"steps": n, "nis_per_row": float("nan"), "last_nis": float("nan")}
        cn, cd = self._cum_nis.values, self._cum_dims.values
        return {"steps": n, "nis_per_row": float((cn[n] - cn[b]) / (cd[n] - cd[b])),
                "last_nis": float(self.nis[-1]), "last_dim": int(self.dims[-1])}

    def components(self, burn_in: int = 0) -> list[np.ndarray]:
        """Whitened component j (j = 0 … max m_k − 1) of every step after ``burn_in`` that has it;
        under the model each is an i.i.d. N(0, 1) series."""
        dims = self.dims.astype(np.int64)
        starts = np.concatenate([[0], np.cumsum(dims)[:-1]])[burn_in:]
        dims = dims[burn_in:]
        m = int(dims.max()) if dims.size else 0
        return [self.white_flat[starts[dims > j] + j] for j in range(m)]

    def tests(self, burn_in: int = 0, lags: int = 10, alpha: float = 0.05) -> InnovationTests:
        """Run the three tests on the innovations after ``burn_in`` steps."""
        nis = np.asarray(self.nis[burn_in:])
        dims = np.asarray(self.dims[burn_in:], int)
        n = nis.size
        if n < 3:
            raise ValueError(f"only {n} innovations after a burn-in of {burn_in}: too few to test")
        from scipy import stats  # imported where used: scipy.stats costs ~1 s of start-up
        tot, dof = float(nis.sum()), int(dims.sum())
        cdf = stats.chi2.cdf(tot, dof)
        p_nis = float(2 * min(cdf, 1 - cdf))
        du, inv = np.unique(dims, return_inverse=True)  # χ² quantiles once per distinct dimension
        lo, hi = stats.chi2.ppf(0.025, du)[inv], stats.chi2.ppf(0.975, du)[inv]
        outside = float(np.mean((nis < lo) | (nis > hi)))
        comp = self.components(burn_in)
        m = len(comp)
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
