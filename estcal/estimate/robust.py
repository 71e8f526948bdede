"""Robust kernels for every estimator, and the report of the rows they down-weighted.

Kernel on a measurement group
-----------------------------
A robust kernel weighs one *measurement group* — the rows of one dataset row (pose): 3
position rows, 6 pose rows, 3k point rows — by the norm of its whitened residual
``r = ‖e/σ‖`` (what gtsam's ``noiseModel.Robust`` does with one factor per pose). The
textbook thresholds are for scalars (Huber k = 1.345, Cauchy k = 2.385, in σ); applied to
the norm of an m-vector they would down-weight most clean poses (a clean 6-row pose has
E r ≈ 2.3). The threshold is therefore carried to m dimensions at the same inlier
probability: ``k_m = √(χ²_m quantile of P(|z| ≤ k))`` (k_1 = k; Huber: k_3 = 2.36, k_6 = 3.00;
Cauchy: k_3 = 3.34, k_6 = 4.04). Weights: Huber ``w = min(1, k_m/r)``, Cauchy
``w = 1/(1 + (r/k_m)²)``.

Estimators
----------
* ``gtsam``, ``isam2``, ``gtsam-timevarying``: ``gtsam.noiseModel.Robust`` with the kernel at
  ``k_m`` on each pose factor (:func:`estcal.estimate.factorgraph.robust_noise`);
* ``lm``, ``gauss-newton``, ``iterated-lls``, ``scipy-lm``: iteratively reweighted least squares
  (:func:`estcal.estimate.lsq.calibrate_irls`: the M-estimate is the fixed point of a weighted LS fit whose σ are
  divided by √w — the same normal equations gtsam's robust LM solves);
* ``kalman`` (EKF): each innovation is weighed by the kernel of its normalised norm
  ``√(νᵀS⁻¹ν)`` and R is divided by the weight before the update (a Huber/Cauchy-robust
  Kalman filter);
* ``ukf`` and ``mcmc`` refuse ``--robust`` with a message (no robust update / likelihood).

Report (:func:`outlier_report`)
-------------------------------
Every pose's residual norm in σ units is standardised by a *robust* σ0
(``σ̂0² = median(r²)/median(χ²_m)``, insensitive to the outliers themselves). A pose is
**named** as down-weighted when its standardised residual exceeds the χ²_m quantile
``1 − α`` (α = :data:`OUTLIER_ALPHA` = 10⁻⁴: about one false alarm per 10⁴ clean poses) — the
kernel's weight is then well below that of any clean pose. The report gives its CSV line,
its weight, and its residual in σ; χ², dof and σ0 with all poses and without the named ones.
"""
from __future__ import annotations

import numpy as np

from estcal.methods.reduced import evaluate_chunks, use_chunks

from ._common import GroupedProblem

__all__ = ["KERNELS", "OUTLIER_ALPHA", "kernel_threshold", "kernel_weight", "group_norms", "outlier_report",
           "WeightedProblem", "check_kernel"]

KERNELS = {"huber": 1.345, "cauchy": 2.385}
OUTLIER_ALPHA = 1e-4


def check_kernel(kernel) -> str | None:
    if kernel is None or str(kernel).lower() in ("none", "l2", "gaussian"):
        return None
    k = str(kernel).lower()
    if k not in KERNELS:
        raise ValueError(f"unknown robust kernel {kernel!r}; choose 'huber', 'cauchy' or none")
    return k


def chi2_ppf(p, d):
    """Quantile ``p`` of χ²_d: ``2·gammaincinv(d/2, p)``, what ``scipy.stats.chi2.ppf`` computes, from
    ``scipy.special`` — importing ``scipy.stats`` costs 0.4 s of CPU, half of a small command."""
    from scipy.special import gammaincinv

    return 2.0 * gammaincinv(np.asarray(d, float) / 2.0, p)


def chi2_cdf(x, d):
    """``P(χ²_d ≤ x)`` (``scipy.special.chdtr``, as ``scipy.stats.chi2.cdf``)."""
    from scipy.special import chdtr

    return chdtr(d, x)


def chi2_median(d):
    """Median of χ²_d."""
    return chi2_ppf(0.5, d)


def kernel_threshold(kernel: str, dim: int, k: float | None = None) -> float:
    """Threshold in σ of the norm of a ``dim``-row group (module docstring); ``k`` = scalar threshold."""
    k1 = KERNELS[kernel] if k is None else float(k)
    if dim <= 1:
        return k1
    p = chi2_cdf(k1 ** 2, 1)  # P(|z| ≤ k)
    return float(np.sqrt(chi2_ppf(p, dim)))


def kernel_weight(kernel: str, r, km) -> np.ndarray:
    r = np.asarray(r, float)
    if kernel == "huber":
        return np.minimum(1.0, km / np.maximum(r, 1e-300))
    return 1.0 / (1.0 + (r / km) ** 2)


def group_norms(problem, theta):
    """``(r, dims, lines, row_group)``: whitened residual norm and row count of every measurement
    group at ``theta``, the CSV line of its first dataset row, and the group of every row."""
    ck = use_chunks(problem)
    if ck is not None:
        return _pose_norms_chunked(problem, theta, ck)
    gp = GroupedProblem(problem)
    rows = problem.evaluate(theta, jacobian=False)
    w = rows.e / rows.sigma
    ng = len(gp)
    r2 = np.bincount(gp.row_group, weights=w * w, minlength=ng)
    dims = np.bincount(gp.row_group, minlength=ng)
    lines = []
    for g in gp.groups:
        data = problem.terms[g.term].data if getattr(problem, "terms", None) else None
        ln = getattr(data, "lines", None)
        lines.append(int(ln[g.pose]) if ln is not None else g.pose + 2)
    return np.sqrt(r2), dims, np.asarray(lines), gp.row_group


def _pose_norms_chunked(problem, theta, chunk):
    """:func:`group_norms` of a large per-pose problem (one group per pose, in file order),
    evaluated ``chunk`` poses at a time: memory O(rows), not O(rows × kinematics)."""
    (t,) = problem.terms
    n = t.data.n
    r2 = np.zeros(n)
    dims = np.zeros(n, int)
    row_group = []
    for a, rows in evaluate_chunks(problem, theta, chunk, jacobian=False):
        w = rows.e / rows.sigma
        pose = np.asarray(rows.pose, int) + a
        r2 += np.bincount(pose, weights=w * w, minlength=n)
        dims += np.bincount(pose, minlength=n)
        row_group.append(pose)
    ln = getattr(t.data, "lines", None)
    lines = np.asarray(ln, int)[:n] if ln is not None else np.arange(n) + 2
    return np.sqrt(r2), dims, lines, np.concatenate(row_group) if row_group else np.zeros(0, int)


def outlier_report(problem, theta, kernel: str, k: float | None = None, n_params: int = 0,
                   alpha: float = OUTLIER_ALPHA, norms=None) -> dict:
    """Rows down-weighted by ``kernel`` at ``theta`` and the fit statistics with and without them.

    ``norms``: precomputed ``(r, dims, lines)`` (e.g. per-batch states of a smoother).
    """
    r, dims, lines = norms if norms is not None else group_norms(problem, theta)[:3]
    km = np.array([kernel_threshold(kernel, int(m), k) for m in dims])
    w = kernel_weight(kernel, r, km)
    med = np.median(r ** 2 / chi2_median(np.maximum(dims, 1)))
    s0 = float(np.sqrt(med)) if med > 0 else 1.0
    limit = np.sqrt(chi2_ppf(1 - alpha, np.maximum(dims, 1)))
    named = np.flatnonzero(r / s0 > limit)
    named = named[np.argsort(-r[named])]
    keep = np.ones(r.size, bool)
    keep[named] = False
    chi2_all = float(np.sum(r ** 2))
    dof_all = int(dims.sum() - n_params)
    chi2_in = float(np.sum(r[keep] ** 2))
    dof_in = int(dims[keep].sum() - n_params)
    return {
        "kernel": kernel, "threshold_sigma_scalar": KERNELS[kernel] if k is None else float(k),
        "alpha": alpha, "robust_sigma0": s0,
        "rows": [{"line": int(lines[i]), "weight": float(w[i]), "residual_sigma": float(r[i]),
                  "residual_robust_sigma": float(r[i] / s0)} for i in named],
        "n_groups": int(r.size), "n_weight_below_1": int(np.sum(w < 1 - 1e-12)),
        "chi2_all": chi2_all, "dof_all": dof_all,
        "sigma0_all": float(np.sqrt(chi2_all / dof_all)) if dof_all > 0 else float("nan"),
        "chi2_without_named": chi2_in, "dof_without_named": dof_in,
        "sigma0_without_named": float(np.sqrt(chi2_in / dof_in)) if dof_in > 0 else float("nan"),
    }


def format_report(rep: dict, most: int = 20) -> str:
    """Text block for the CLI."""
    rows = rep["rows"]
    head = (f"robust kernel {rep['kernel']}: {len(rows)} of {rep['n_groups']} poses named as down-weighted "
            f"(residual beyond the χ² {1 - rep['alpha']:.4g} quantile at the robust σ0 = "
            f"{rep['robust_sigma0']:.3g}); σ0 = {rep['sigma0_all']:.3g} with all poses (χ² {rep['chi2_all']:.4g}, "
            f"dof {rep['dof_all']}), {rep['sigma0_without_named']:.3g} without them (χ² "
            f"{rep['chi2_without_named']:.4g}, dof {rep['dof_without_named']})")
    lines = [head]
    for d in rows[:most]:
        lines.append(f"  line {d['line']}: weight {d['weight']:.3g}, residual {d['residual_sigma']:.3g} σ")
    if len(rows) > most:
        lines.append(f"  … {len(rows) - most} more in the JSON (robust_report.rows)")
    return "\n".join(lines)


class WeightedProblem:
    """A Problem whose row σ are multiplied by ``row_scale`` (IRLS weights: scale = 1/√w)."""

    def __init__(self, base, row_scale):
        self.base = base
        self.row_scale = np.asarray(row_scale, float)

    @property
    def robot(self):
        return self.base.robot

    @property
    def terms(self):
        return self.base.terms

    @property
    def params(self):
        return self.base.params

    def evaluate(self, theta=None, jacobian: bool = True):
        r = self.base.evaluate(theta, jacobian)
        r.sigma = r.sigma * self.row_scale
        return r

    def with_free(self, names):
        return WeightedProblem(self.base.with_free(names), self.row_scale)

    def with_values(self, theta):
        return WeightedProblem(self.base.with_values(theta), self.row_scale)
