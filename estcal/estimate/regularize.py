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

A prior per parameter group
---------------------------
One τ mixes metres and radians. :func:`fit_group_prior` gives every *group* of like parameters
(:func:`prior_groups`: lengths, angles, joint offsets, each kind of effect) its own nominal-centred
width ``τ_g`` and chooses the widths by the evidence of the linearised model (type-II maximum
likelihood; MacKay 1992, *Neural Comput.* 4:415; Bishop 2006 §3.5), alternating with the MAP fit.
With several groups a CV grid is out of reach (one dimension per group, tens of postures to rank
it), while the evidence is smooth, closed-form and recovers the true deviation scale when the model
holds (``tests/test_group_prior.py``); ``criterion="evidence+cv"`` adds one common multiplier by the
leave-one-posture-out PRESS above, the guard against a residual made of model error. Measured at new
postures on real robots in docs/real-data.md ("A prior instead of a level").
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estcal.base.units import display_unit  # the one rule for a parameter's unit (mm / mrad)

from ._common import resolve_free
from estcal.methods.reduced import weighted

__all__ = ["loo_curve", "choose_prior_std", "RegularizationChoice", "DEFAULT_GRID", "prior_groups", "GroupPrior",
           "fit_group_prior", "log_evidence", "evidence_widths"]

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


# ---------------------------------------------------------------------------------------------------
# A prior per parameter group (MAP with group widths chosen by the evidence)
# ---------------------------------------------------------------------------------------------------

def prior_groups(robot, names) -> dict:
    """The prior group of every parameter of ``names`` (``{name: group}``), by unit and meaning.

    ``length`` (m) and ``angle`` (rad) for the geometric and tool parameters (translations and rotations
    of the links' placements; Khalil–Kleinfinger d, r vs α, θ, β), ``offset`` for revolute joint offsets
    (rad) and ``offset_length`` for prismatic ones (m), ``gain`` for encoder gains, and one group per
    kind of effect parameter (``compliance``, ``backlash``, ``harmonic1`` … — the prefix of its name),
    so that a width never mixes metres with radians or one physical cause with another: the scaling of
    the calibration literature, where each parameter is judged against its own manufacturing tolerance
    (Mooring, Roth & Driels 1991, §4.6 on parameter scaling; GECARO's scaled columns). Base, marker and
    registration parameters get a group too (``base``, ``marker``); the caller leaves them free.
    """
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    out = {}
    for n in names:
        k = kinds[n]
        if k in ("geometric", "tool"):
            out[n] = "angle" if display_unit(n, robot)[0] == "mrad" else "length"
        elif k == "offset":
            out[n] = "offset_length" if display_unit(n, robot)[0] == "mm" else "offset"
        elif k == "effect":
            out[n] = n.split("_")[0]
        else:
            out[n] = k
    return out


@dataclass
class GroupPrior:
    """Result of :func:`fit_group_prior`: the MAP estimate under a Gaussian prior ``θ_j ~ N(μ_j, τ_g²)``
    centred on the nominal values, one width ``τ_g`` per parameter group.

    widths : ``{group: τ_g}`` (SI: m, rad, rad/N·m … — the unit of the group's parameters)
    groups : ``{parameter: group}`` of the penalised parameters; the other free ones are not penalised
    sigma0 : the fitted scale of the weighted residual (1 = the noise model's σ)
    log_evidence : log marginal likelihood of the linearised model at the chosen widths
    result : the :class:`~estcal.estimate.result.CalibrationResult` of the MAP fit (posterior covariance)
    criterion : ``"evidence"`` or ``"evidence+cv"`` (a common multiplier ``scale`` of the evidence widths by
        leave-one-posture-out CV; ``cv_curve``: the multipliers and their RMSE, mm)
    """

    widths: dict
    groups: dict
    sigma0: float
    log_evidence: float
    result: object
    criterion: str = "evidence"
    scale: float = 1.0
    cv_curve: dict = field(default_factory=dict)
    rounds: int = 0

    @property
    def prior_std(self) -> dict:
        """``prior_std`` argument of :func:`estcal.estimate.calibrate_lsq` for the problem's noise model (one
        entry per penalised parameter): ``scale·τ_g/σ0``, because the weighted rows are in units of the noise
        model's σ and the fitted noise is σ0 times it (the MAP of ``‖b − Ax‖²/σ0² + Σ (x_j/τ_j)²``)."""
        return {n: self.scale * self.widths[g] / self.sigma0 for n, g in self.groups.items()}

    def to_dict(self) -> dict:
        return {"widths": {g: float(self.scale * t) for g, t in self.widths.items()},
                "evidence_widths": {g: float(t) for g, t in self.widths.items()}, "scale": float(self.scale),
                "sigma0": float(self.sigma0), "log_evidence": float(self.log_evidence), "criterion": self.criterion,
                "n_penalised": len(self.groups), "cv_curve": self.cv_curve, "rounds": self.rounds}

    def __str__(self) -> str:
        w = ", ".join(f"{g} {self.scale * t:.3g}" for g, t in self.widths.items())
        return f"group prior ({self.criterion}): widths {w} (SI); σ0 = {self.sigma0:.3g}"


def _gram(A, y):
    """``(AᵀA, Aᵀy, yᵀy, M, column norms)``: what the evidence needs of the system, computed once per width
    search (an evaluation then costs O(n³) in the n columns instead of O(M n²) in the M rows)."""
    AtA = A.T @ A
    return AtA, A.T @ y, float(y @ y), A.shape[0], np.sqrt(np.maximum(np.diag(AtA), 0.0))


def _evidence_system(gram, group_of, log_tau, log_s2):
    """The scaled system of :func:`log_evidence`: ``(Cholesky factor L of G or None, c, log|G| of the unscaled
    system, s², the penalised mask)`` with ``G = D AᵀA D / s² + diag(pen)``, ``c = D Aᵀy / s²`` and ``D`` the
    column scales (τ_j penalised, 1/‖a_j‖ free)."""
    AtA, Aty, _, _, nrm = gram
    s2 = np.exp(log_s2)
    pen = group_of >= 0
    d = np.where(pen, np.exp(np.asarray(log_tau)[np.maximum(group_of, 0)]), 0.0)
    d[~pen] = 1.0 / np.where(nrm[~pen] > 0, nrm[~pen], 1.0)
    G = AtA * np.outer(d, d) / s2 + np.diag(pen.astype(float))
    try:
        L = np.linalg.cholesky(G)
    except np.linalg.LinAlgError:
        return None, None, None, s2, pen
    # log|G| of the unscaled system = log|G_s| − 2 Σ log d; the Σ_pen log τ_j² term cancels the penalised part
    logdet = 2.0 * np.sum(np.log(np.diag(L))) - 2.0 * np.sum(np.log(d[~pen]))
    return L, d * Aty / s2, logdet, s2, pen


def _log_p(gram, logdet, s2, z) -> float:
    _, _, yty, M, _ = gram
    return float(-0.5 * (M * np.log(2 * np.pi * s2) + logdet + yty / s2 - z @ z))


def log_evidence(A, y, group_of, log_tau, log_s2) -> float:
    """Log marginal likelihood of ``y = A x + ε``, ``ε ~ N(0, s² I)``, ``x_j ~ N(0, τ_g(j)²)`` for the
    penalised columns (``group_of[j] ≥ 0``) and a flat prior on the others (``group_of[j] = -1``; the
    restricted likelihood of those, up to a constant). Bishop 2006 eq. 3.86 in the parameter space with
    the determinant lemma::

        −2 log p(y) = M log 2πs² + Σ_pen log τ_j² + log|G| + (yᵀy − cᵀG⁻¹c)/s²,
        G = AᵀA/s² + diag(1/τ_j², 0 for free),   c = Aᵀy

    evaluated on the columns scaled by τ_j (penalised) or their norm (free), so that widths from
    micro-radians to metres stay well conditioned.
    """
    from scipy.linalg import solve_triangular

    gram = _gram(A, y)
    L, c, logdet, s2, _ = _evidence_system(gram, group_of, log_tau, log_s2)
    if L is None:
        return -np.inf
    return _log_p(gram, logdet, s2, solve_triangular(L, c, lower=True))


def log_evidence_grad(A, y, group_of, log_tau, log_s2):
    """``(log p(y), ∂ log p / ∂ log τ (n_groups,), ∂ log p / ∂ log s²)`` of :func:`log_evidence`, the
    gradient in closed form. In the scaled coordinates ``u_j = x_j / τ_j`` with posterior mean ``m = G⁻¹c``
    and covariance ``G⁻¹``::

        ∂ log p / ∂ log τ_g = Σ_{j ∈ g} (m_j² + (G⁻¹)_jj − 1)
        ∂ log p / ∂ log s²  = ½ (|y − A_s m|²/s² − M + n − Σ_pen (G⁻¹)_jj)

    (MacKay 1992 eq. 4.14 in log coordinates: a width grows while its parameters' posterior second moment
    exceeds the prior's; n columns, M rows), with ``|y − A_s m|²/s² = yᵀy/s² − cᵀm − Σ_pen m_j²`` (as
    ``G m = c``). One Cholesky factor and its triangular inverse per evaluation, where finite differences
    took one factor per group and per side. ``-inf`` and a zero gradient where ``G`` is not positive
    definite."""
    return _log_evidence_grad(_gram(A, y), group_of, log_tau, log_s2)


def _log_evidence_grad(gram, group_of, log_tau, log_s2):
    from scipy.linalg.lapack import dtrtri

    n_groups = len(log_tau)
    L, c, logdet, s2, pen = _evidence_system(gram, group_of, log_tau, log_s2)
    if L is None:
        return -np.inf, np.zeros(n_groups), 0.0
    Li, info = dtrtri(L, lower=1)  # L⁻¹: diag(G⁻¹) = column sums of its squares
    if info != 0:
        return -np.inf, np.zeros(n_groups), 0.0
    z = Li @ c
    lp = _log_p(gram, logdet, s2, z)
    Gii = np.einsum("ij,ij->j", Li, Li)
    m = Li.T @ z
    per = np.where(pen, m ** 2 + Gii - 1.0, 0.0)
    g_tau = np.bincount(group_of[pen], weights=per[pen], minlength=n_groups)
    _, _, yty, M, _ = gram
    r2 = yty / s2 - float(z @ z) - float(np.sum(m[pen] ** 2))
    g_s2 = 0.5 * (r2 - M + len(c) - float(Gii[pen].sum()))
    return lp, g_tau, g_s2


def evidence_widths(A, y, group_of, n_groups, start=None, bounds=(1e-8, 10.0)):
    """``(log τ (n_groups,), log s², log evidence)`` maximising :func:`log_evidence` (type-II maximum
    likelihood, MacKay 1992; L-BFGS-B over the logs with the gradient of :func:`log_evidence_grad`, bounded to
    ``bounds`` in SI)."""
    from scipy.optimize import minimize

    from estcal.base.blas import single_thread_blas

    r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
    s2_0 = max(float(r @ r) / max(len(y) - A.shape[1], 1), 1e-12 * max(float(y @ y), 1e-300))
    x0 = np.concatenate([np.log(np.full(n_groups, 1e-3) if start is None else np.asarray(start, float)),
                         [np.log(s2_0)]])
    lo, hi = np.log(bounds[0]), np.log(bounds[1])

    gram = _gram(A, y)

    def f(x):
        lp, g_tau, g_s2 = _log_evidence_grad(gram, group_of, x[:-1], x[-1])
        return -lp, -np.append(g_tau, g_s2)

    box = [(lo, hi)] * n_groups + [(np.log(s2_0) - 12.0, np.log(s2_0) + 12.0)]
    # where the system is not positive definite the evidence is −∞ (a step the line search rejects): not worth
    # a RuntimeWarning to the user. The gradient in closed form (log_evidence_grad). One BLAS thread:
    # the evidence's small factorisations, a few hundred per search, only spin threads (a TIAGo prior fit
    # 30–50 s multi-threaded on 2 busy cores, ~1 s on one; the CLI is single-threaded already, the API was not)
    with np.errstate(invalid="ignore", over="ignore"), single_thread_blas():
        best = minimize(f, x0, method="L-BFGS-B", jac=True, bounds=box)
        # a second start from the narrow side of the box: the evidence of a group can be flat (a group the data
        # cannot see) or bimodal; keep the better optimum. Both starts sit at the tolerance scale of calibration
        # (1 mm / 1 mrad and below), a statement of where the deviations are believed to lie: a width the
        # evidence is flat in stays there. Measured with the exact gradient (docs/real-data.md, "A prior instead
        # of a level"): on TIAGo 11-30 a wide start (0.1 m / rad) reaches the same optimum with group widths,
        # and with one width per parameter a slightly higher evidence (−1720.6 against −1723.9 nats) that
        # predicts held-out postures neither better nor worse (CV 2.73 against 2.68 mm)
        x1 = x0.copy()
        x1[:-1] = np.log(1e-5)
        other = minimize(f, x1, method="L-BFGS-B", jac=True, bounds=box)
    if other.fun < best.fun:
        best = other
    return best.x[:-1], float(best.x[-1]), float(-best.fun)


def fit_group_prior(problem, free, penalised, groups=None, *, criterion: str = "evidence", rounds: int = 3,
                    cv_grid=None, posture_tol=(1e-3, 1e-3), max_iter: int = 60) -> GroupPrior:
    """MAP calibration with a nominal-centred Gaussian prior per parameter group, the widths chosen on
    the problem's own rows.

    The widths maximise the evidence of the model linearised at the current estimate (type-II maximum
    likelihood, :func:`evidence_widths`); the MAP fit (:func:`estcal.estimate.calibrate_lsq` with
    ``prior_std``) moves the estimate, and the two alternate ``rounds`` times (the linearised evidence is
    re-evaluated at the new estimate, as in MacKay's iterative re-estimation). With ``criterion =
    "evidence+cv"`` a common multiplier of the evidence widths is then chosen by leave-one-posture-out CV
    (block PRESS, linearised at the MAP estimate; ``cv_grid`` of multipliers, default ¼ … 8 — 1 is on the
    grid): the evidence sets the ratios between groups, CV the overall strength — the guard against a
    residual made of model error, which the evidence reads as noise.

    Parameters
    ----------
    problem : :class:`estcal.methods.Problem`; free : every parameter to estimate
    penalised : the subset under the prior (the others — base, markers, unknown tool — stay free)
    groups : ``{parameter: group}`` (default :func:`prior_groups` of the problem's robot)
    """
    from .lsq import calibrate_lsq

    problem, fidx, names = resolve_free(problem, free)
    pen_names = [n for n in names if n in set(penalised)]
    if not pen_names:
        raise ValueError("no parameter to penalise: give the geometric / offset / effect parameters in `penalised`")
    groups = prior_groups(problem.robot, pen_names) if groups is None else {n: groups[n] for n in pen_names}
    glist = list(dict.fromkeys(groups.values()))
    group_of = np.array([glist.index(groups[n]) if n in groups else -1 for n in names])
    mu = problem.params.values[fidx].copy()
    theta = problem.params.values.copy()
    log_tau, res, lev, log_s2 = None, None, -np.inf, 0.0
    for it in range(max(rounds, 1)):
        rows = problem.evaluate(theta)
        A, b = weighted(rows, fidx)
        # the prior mean in the coordinates of the step from θ: μ − θ (0 for the free columns)
        m = np.where(group_of >= 0, mu - theta[fidx], 0.0)
        log_tau, log_s2, lev = evidence_widths(A, b - A @ m, group_of, len(glist), None if log_tau is None
                                               else np.exp(log_tau))
        std = {n: float(np.exp(log_tau[glist.index(g)] - 0.5 * log_s2)) for n, g in groups.items()}  # τ/σ0
        res = calibrate_lsq(problem, "lm", free=names, check=False, prior_std=std, prior_mean=dict(zip(names, mu)),
                            theta0=theta, max_iter=max_iter)
        moved = np.max(np.abs(res.theta[fidx] - theta[fidx]) / np.maximum(res.std, 1e-300))
        theta = res.theta
        if moved < 0.1:  # the linearisation point moved by less than a tenth of a standard deviation
            break
    gp = GroupPrior(dict(zip(glist, np.exp(log_tau).tolist())), groups, float(np.exp(0.5 * log_s2)), lev, res,
                    rounds=it + 1)
    if criterion == "evidence+cv":
        _cv_scale(problem, gp, names, fidx, group_of, mu, theta, cv_grid, posture_tol, max_iter)
    elif criterion != "evidence":
        raise ValueError(f"criterion must be 'evidence' or 'evidence+cv', got {criterion!r}")
    return gp


def _cv_scale(problem, gp, names, fidx, group_of, mu, theta, grid, posture_tol, max_iter) -> None:
    """The common multiplier of the evidence widths with the lowest leave-one-posture-out RMSE (in place)."""
    from .lsq import calibrate_lsq

    grid = np.geomspace(0.25, 8.0, 6) if grid is None else np.asarray(grid, float)
    rows = problem.evaluate(theta)
    A, b = weighted(rows, fidx)
    m = np.where(group_of >= 0, mu - theta[fidx], 0.0)
    press = _press_of(problem, rows, A, b - A @ m, posture_tol)
    tau = np.array([gp.widths[gp.groups[n]] / gp.sigma0 if n in gp.groups else np.inf for n in names])
    curve = []
    for k in grid:
        try:
            curve.append(press.rmse(np.where(np.isfinite(tau), (k * tau) ** -2.0, 0.0)))
        except np.linalg.LinAlgError:
            curve.append(np.inf)
    gp.scale = float(grid[int(np.argmin(curve))])
    gp.criterion = "evidence+cv"
    gp.cv_curve = {"scale": grid.tolist(), "loo_rmse_mm": (np.asarray(curve) * 1e3).tolist()}
    if gp.scale != 1.0:
        gp.result = calibrate_lsq(problem, "lm", free=names, check=False, prior_std=gp.prior_std,
                                  prior_mean=dict(zip(names, mu)), theta0=theta, max_iter=max_iter)
