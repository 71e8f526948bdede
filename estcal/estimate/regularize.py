"""Choosing the prior width of a regularised (MAP / ridge) calibration by cross-validation.

When the geometric model is only part of the truth (real robots: backlash,
compliance, thermal drift), the full identifiable parameter set is larger than
the data support: weakly excited parameters absorb the unmodelled errors of the
calibration file and generalise badly. Instead of dropping parameters
(subset selection: AIC/BIC, whose choice is unstable on small files), keep the
whole identifiable set and shrink the poorly determined combinations toward the
nominal model with a Gaussian prior ``θ_j ~ N(μ_j, τ²)`` on the *penalised*
parameters (geometric placements, joint offsets; the base frame and the
unknown points stay free)::

    minimise  ‖W^{1/2}(e − HΔθ)‖² + Σ_j ((θ_j − μ_j)/τ)²          (Tikhonov; ridge)

The single width ``τ`` (SI: m for lengths, rad for angles — one number, because
for arm-sized links a millimetre and a milliradian move the end point by similar
amounts) is chosen by **leave-one-posture-out cross-validation on the calibration
data**, never on validation data: every pose whose joint readings agree within 1e-3 rad /
1e-3 m with pose *i* (the same posture in another session or file) leaves with it, so a
twin never predicts its own posture (docs/real-data.md). For the model linearised at ``θ``, the
leave-one-posture-out residual of posture *i* (rows *i*) is exact without refitting (block PRESS,
e.g. Hastie, Tibshirani & Friedman, *Elements of Statistical Learning* §7.10;
the ridge rows are not deleted with the pose)::

    r_(−i) = (I − A_i G⁻¹ A_iᵀ)⁻¹ r_i,    G = AᵀA + T⁻¹,   r = b − A G⁻¹ Aᵀ b

with ``A = W^{1/2}H`` and ``A_i`` the rows of pose *i*. Cross-validation rather
than the marginal likelihood (empirical Bayes) picks τ because the residual is
dominated by model error, and CV is the robust choice under misspecification
(Wahba 1985, *Ann. Statist.* 13:1378).

Shapes and units: the CV error is the RMS of the held-out point-error norms (m),
the same "norm RMSE" as every accuracy table.

One width per parameter, chosen by the evidence
-----------------------------------------------
The diagnosis's model gives every parameter its own width and chooses them by the evidence of the linearised
model with automatic relevance determination (:mod:`estcal.estimate.sparse`): a τ per parameter, which a CV
grid cannot reach, and the evidence prunes what the data do not support.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


from ._common import resolve_free
from estcal.methods.reduced import weighted

__all__ = ["loo_curve", "choose_prior_std", "RegularizationChoice", "DEFAULT_GRID"]

#: candidate prior widths τ (SI), 0.1 mm / 0.1 mrad … 100 mm / 100 mrad, 31 log-spaced values
DEFAULT_GRID = np.geomspace(1e-4, 1e-1, 31)


@dataclass
class RegularizationChoice:
    """Result of :func:`choose_prior_std`.

    tau : chosen prior std (SI); ``inf`` when no finite width beats the unregularised fit
    penalised : names of the penalised parameters (the others are free)
    grid, loo_rmse_mm : the CV curve (τ values and their leave-one-posture-out RMSE, mm)
    loo_rmse_unregularised_mm : the same for τ = ∞ (plain least squares)
    """

    tau: float
    penalised: list[str]
    grid: np.ndarray
    loo_rmse_mm: np.ndarray
    loo_rmse_unregularised_mm: float
    linearised_at: str = "registration fit"
    extra: dict = field(default_factory=dict)

    @property
    def prior_std(self) -> dict:
        """``prior_std`` argument for :func:`estcal.estimate.calibrate_lsq`."""
        return {n: self.tau for n in self.penalised} if np.isfinite(self.tau) else None

    def to_dict(self) -> dict:
        i = int(np.argmin(self.loo_rmse_mm))
        return {"tau": float(self.tau), "tau_mm_or_mrad": float(self.tau * 1e3), "penalised": list(self.penalised),
                "loo_rmse_mm": float(self.loo_rmse_mm[i]),
                "loo_rmse_unregularised_mm": float(self.loo_rmse_unregularised_mm),
                "curve": {"tau": [float(t) for t in self.grid], "loo_rmse_mm": [float(v) for v in self.loo_rmse_mm]},
                "criterion": "leave-one-posture-out CV on the calibration data (block PRESS, linearised)",
                "linearised_at": self.linearised_at}

    def __str__(self) -> str:
        d = self.to_dict()
        return (f"prior width τ = {d['tau_mm_or_mrad']:.3g} mm / mrad on {len(self.penalised)} parameters "
                f"(leave-one-posture-out RMSE {d['loo_rmse_mm']:.3f} mm; unregularised "
                f"{d['loo_rmse_unregularised_mm']:.3f} mm)")


def _posture_blocks(problem, rows, tol=(1e-3, 1e-3)):
    """Row indices grouped by posture, padded: ``(idx (G, m), mask (G, m))``.

    Rows of every pose whose readings agree within ``tol`` (rad, m) — the same posture in another
    term (file, session) or twice in one file — form one block, so the held-out posture's twin is
    never in the fit (:func:`estcal.validation.posture_groups`; docs/real-data.md).
    """
    from estcal.validation import posture_groups

    term = np.zeros(len(rows.e), int) if rows.term is None else np.asarray(rows.term, int)
    datas = [t.data for t in problem.terms]
    offset = np.cumsum([0] + [d.n for d in datas])
    Q = np.vstack([d.readings for d in datas])
    g = posture_groups(Q, problem.robot.joint_types, *tol)[offset[term] + np.asarray(rows.pose, int)]
    order = np.argsort(g, kind="stable")
    labels, start, counts = np.unique(g[order], return_index=True, return_counts=True)
    m = int(counts.max())
    idx = np.zeros((len(labels), m), int)
    mask = np.arange(m)[None, :] < counts[:, None]
    idx[mask] = order
    return idx, mask


def loo_curve(problem, free, penalised, taus, theta=None, posture_tol=(1e-3, 1e-3)) -> np.ndarray:
    """Leave-one-posture-out RMSE (m) of the ridge estimate for each τ in ``taus`` (``inf`` allowed).

    A *posture* is every pose whose readings agree within ``posture_tol`` (rad, m): with one
    row per posture this is leave-one-pose-out; repeated postures are held out together.

    Parameters
    ----------
    problem : :class:`estcal.methods.Problem` (direct measures: position, points, pose rows)
    free : free parameter names; penalised : the subset with the prior ``N(θ_j, τ²)``
    taus : (K,) prior stds (SI)
    theta : linearisation point (default: the problem's values)

    Returns
    -------
    (K,) RMS over the held-out poses of the position-error norm of every measured point (m).
    Orientation rows (pose data) take part in the fit but not in the score.
    """
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values if theta is None else np.asarray(theta, float)
    rows = problem.evaluate(theta)
    A, b = weighted(rows, fidx)
    pen = np.isin(names, list(penalised))
    press = _press_of(problem, rows, A, b, posture_tol)
    return np.asarray([press.rmse(np.where(pen, 0.0 if not np.isfinite(tau) else tau ** -2.0, 0.0))
                       for tau in np.atleast_1d(np.asarray(taus, float))])


def _press_of(problem, rows, A, b, posture_tol) -> "_Press":
    """:class:`_Press` of the weighted system ``(A, b)`` of ``rows``, blocks by posture, scored on position rows."""
    blocks, mask = _posture_blocks(problem, rows, posture_tol)
    pos = mask & (rows.kind[blocks] == 0)  # position rows
    return _Press(A, b, blocks, mask, pos, rows.sigma[blocks], pos.sum() / 3.0)


class _Press:
    """Block PRESS of the linearised ridge system ``A x ≈ b`` (module docstring): the held-out residual of
    every posture block without refitting, for any diagonal prior precision ``λ`` (one Cholesky factor of
    ``AᵀA + diag(λ)`` each)."""

    def __init__(self, A, b, blocks, mask, pos, sig, n_points):
        self.Ab = np.where(mask[..., None], A[blocks], 0.0)  # (G, m, p); padding rows are zero
        self.bb = np.where(mask, b[blocks], 0.0)
        self.pos, self.sig, self.n_points = pos, sig, n_points
        self.AtA, self.Atb = A.T @ A, A.T @ b

    def residuals(self, lam):
        """(G, m) held-out weighted residuals of every posture block; raises LinAlgError when singular."""
        Ab = self.Ab
        L = np.linalg.cholesky(self.AtA + np.diag(lam))
        x = np.linalg.solve(L.T, np.linalg.solve(L, self.Atb))
        r = self.bb - Ab @ x
        Y = np.linalg.solve(L, Ab.reshape(-1, Ab.shape[2]).T).T.reshape(Ab.shape)  # A_i L⁻ᵀ
        Hii = np.einsum("nrp,nsp->nrs", Y, Y)
        return np.linalg.solve(np.eye(Hii.shape[1]) - Hii, r[..., None])[..., 0]

    def rmse(self, lam) -> float:
        """RMS over the held-out postures of the measured points' error norms (m)."""
        e_m = np.where(self.pos, self.residuals(lam) * self.sig, 0.0)
        return float(np.sqrt(np.sum(e_m ** 2) / self.n_points))


def choose_prior_std(problem, free, penalised, theta=None, grid=None, posture_tol=(1e-3, 1e-3)
                     ) -> RegularizationChoice:
    """The prior width τ with the lowest leave-one-posture-out RMSE on the problem's data.

    See the module docstring. ``grid`` defaults to :data:`DEFAULT_GRID`; the unregularised
    fit (τ = ∞) is a candidate too, so regularisation is only used when CV supports it.
    """
    grid = DEFAULT_GRID if grid is None else np.asarray(grid, float)
    penalised = [n for n in free if n in set(penalised)]
    if not penalised:
        raise ValueError("no parameter to penalise: give the geometric / offset parameters in `penalised`")
    curve = loo_curve(problem, free, penalised, grid, theta, posture_tol)
    plain = float(loo_curve(problem, free, penalised, [np.inf], theta, posture_tol)[0])
    i = int(np.argmin(curve))
    tau = float(grid[i]) if curve[i] < plain else float("inf")
    return RegularizationChoice(tau, penalised, grid, curve * 1e3, plain * 1e3)
