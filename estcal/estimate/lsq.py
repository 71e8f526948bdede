"""Batch least-squares calibration: iterated linear LS, Gauss–Newton, Levenberg–Marquardt.

Each iteration solves the weighted, column-scaled linearised system (GECARO
eq. [6]-[10]; textbook eqs. 4.47, 4.154, 4.156)::

    minimise ‖ W^{1/2} (e − H Δθ) ‖²,   W = diag(1/σ²)

* ``iterated-lls`` — GECARO's iterated linear least squares: the full step
  ``Δθ = (W^{1/2} H)⁺ W^{1/2} e``, observation matrix rebuilt every iteration
  (identical to Gauss–Newton; kept under its published name).
* ``gauss-newton`` — the same step with a backtracking line search on the cost.
* ``lm`` — Levenberg–Marquardt with Marquardt's rule (μ divided by ν = 10 after a
  successful step, multiplied by ν until the cost falls; textbook §4.6),
  damping ``μ·I`` on the column-scaled system (i.e. ``μ·diag(HᵀWH)``).
* ``scipy-lm`` — :func:`scipy.optimize.least_squares` (``method="lm"``,
  MINPACK) with the analytic Jacobian, for comparison.

Columns are scaled to unit norm before every solve (equilibration), so metres
and radians, large and small parameters are treated alike. The covariance at
the solution is ``Σ = (HᵀWH)⁻¹`` (textbook 4.54/4.71), multiplied by the
posterior variance factor ``σ0² = χ²/(M − p)`` when the noise is not known
(``NoiseModel.known = False``).
"""
from __future__ import annotations

import time

import numpy as np
import scipy.linalg as sla

from estcal.base.blas import single_thread_blas
from estcal.base.progress import progress
from estcal.identify.core import STRUCTURAL_TOL
from estcal.identify.select import UnidentifiableError, check_identifiable
from estcal.methods.reduced import DenseSystem, ReducedSystem, chi2_and_rows, use_chunks

from ._common import noise_known, resolve_free
from .result import CalibrationResult, score
from .robust import WeightedProblem, check_kernel, group_norms, kernel_threshold, kernel_weight

__all__ = ["calibrate_lsq", "LSQ_METHODS", "calibrate_irls"]

LSQ_METHODS = ("lm", "gauss-newton", "iterated-lls", "scipy-lm")


def _factor(A, b):
    """``(s, R, c)``: the column norms ``s`` of ``A`` and the QR factorisation ``A/s = QR``, ``c = Qᵀb``.

    One factorisation per iteration serves the Gauss–Newton step, every damped step Marquardt's
    rule tries (:func:`_solve`), the stopping test (``‖c‖²`` is the cost decrease the Gauss–Newton
    step predicts) and the covariance at the solution. LAPACK's ``geqrf`` and ``ormqr`` directly
    (``c`` from the Householder reflectors, Q never formed): the R of ``numpy.linalg.qr`` bit for
    bit, at half its cost on a fit's small systems."""
    from scipy.linalg import lapack

    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    m, p = A.shape
    if m < p:  # fewer equations than unknowns (the caller refuses): numpy's reduced QR
        Q, R = np.linalg.qr(A / s)
        return s, R, Q.T @ b
    qr, tau, _, info = lapack.dgeqrf(A / s)
    c, _, info2 = lapack.dormqr("L", "T", qr, tau, np.asarray(b, float)[:, None], max(1, 64))
    if info or info2:  # pragma: no cover - LAPACK argument errors
        raise np.linalg.LinAlgError(f"QR failed (geqrf info {info}, ormqr info {info2})")
    return s, np.triu(qr[:p]), c[:p, 0]


def _solve(A, b, mu=0.0, fac=None):
    """Column-scaled (damped) least-squares step.

    Solves ``min ‖As x − b‖² + μ‖x‖²`` with ``As = A diag(1/s)``, ``s`` the column
    norms, through the QR factorisation ``As = QR`` (``fac`` from :func:`_factor`, computed when not
    given): ``‖As x − b‖² = ‖R x − Qᵀb‖² + const``, so the damped step is the least-squares solution
    of the small system ``[R; √μ I] x = [Qᵀb; 0]`` — the same solution as an SVD-based ``lstsq`` of
    the (augmented) full system for a full-rank system (identifiability is checked before the loop),
    at a fraction of the cost.
    """
    s, R, c = _factor(A, b) if fac is None else fac
    p = R.shape[1]
    if mu > 0:
        Qm, R = np.linalg.qr(np.vstack([R, np.sqrt(mu) * np.eye(p)]))
        c = Qm.T @ np.concatenate([c, np.zeros(p)])
    d = np.abs(np.diag(R))
    if d.min() <= 1e-13 * d.max():  # (numerically) rank deficient: fall back to the minimum-norm step
        x, *_ = np.linalg.lstsq(R, c, rcond=None)
    else:
        x = sla.solve_triangular(R, c, check_finite=False)
    return x / s


def calibrate_lsq(problem, method: str = "lm", free=None, max_iter: int = 100, tol: float = 1e-10,
                  theta0=None, validation=(), check: bool = True, verbose: bool = False,
                  single_thread: bool = True, prior_std=None, prior_mean=None, robust=None,
                  robust_k=None, chunk: int | None = None) -> CalibrationResult:
    """Estimate the free parameters of ``problem`` by nonlinear least squares.

    Parameters
    ----------
    problem : :class:`estcal.methods.problem.Problem`
    method : one of ``lm``, ``gauss-newton``, ``iterated-lls``, ``scipy-lm``
    free : parameter names/patterns to estimate (default: the problem's free mask)
    max_iter, tol : stop when the relative step ‖Δθ/scale‖ and relative cost change are below ``tol``
    theta0 : full initial parameter vector (default: the problem's current values)
    validation : datasets scored with the estimate (accuracy before/after)
    single_thread : run BLAS single-threaded (see :func:`single_thread_blas`)
    prior_std : optional Gaussian prior (MAP / Tikhonov-regularised estimate): ``{name or
        pattern: std}`` (SI units; parameters not matched are not penalised) or an array aligned
        with the free names (``inf`` = not penalised). Adds the rows ``(μ_j − θ_j)/τ_j`` to the
        weighted system, so the estimate minimises ``‖W^{1/2}(e − HΔθ)‖² + Σ_j ((θ_j − μ_j)/τ_j)²``
        and ``Σ = (HᵀWH + T⁻¹)⁻¹`` (the Gaussian posterior of the linearised model). ``chi2`` is the
        data part; ``dof = M − p_eff`` with ``p_eff = tr((HᵀWH + T⁻¹)⁻¹ HᵀWH)`` the effective
        number of parameters. See :mod:`estcal.estimate.regularize` for choosing τ.
    prior_mean : ``{name: value}`` or array aligned with the free names (default: the initial values)
    robust, robust_k : ``"huber"`` / ``"cauchy"`` kernel (scalar threshold in σ): iteratively
        reweighted least squares, :func:`estcal.estimate.robust.calibrate_irls`
    chunk : poses per chunk of the bounded-memory path (:mod:`estcal.methods.reduced`; default:
        automatic above ``CHUNK_POSES`` poses for lm / gauss-newton / iterated-lls, with or without prior)

    Returns
    -------
    CalibrationResult
    """
    if check_kernel(robust) is not None:
        return calibrate_irls(problem, method, free, robust=robust, robust_k=robust_k, max_iter=max_iter, tol=tol,
                              theta0=theta0, validation=validation, check=check, single_thread=single_thread,
                              prior_std=prior_std, prior_mean=prior_mean)
    ck = use_chunks(problem, chunk) if method != "scipy-lm" else None
    with single_thread_blas(single_thread):
        return _calibrate_lsq(problem, method, free, max_iter, tol, theta0, validation, check, verbose,
                              prior_std, prior_mean, ck)


def prior_arrays(names, prior_std, prior_mean, start) -> tuple[np.ndarray, np.ndarray]:
    """``(1/τ, μ)`` aligned with ``names`` from the ``prior_std`` / ``prior_mean`` forms of
    :func:`calibrate_lsq` (``1/τ = 0``: not penalised)."""
    import fnmatch

    names = list(names)
    if isinstance(prior_std, dict):
        tau = np.full(len(names), np.inf)
        for k, v in prior_std.items():
            hit = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, k)]
            if not hit:
                raise ValueError(f"prior_std: {k!r} matches no free parameter (free: {names})")
            tau[hit] = float(v)
    else:
        tau = np.broadcast_to(np.asarray(prior_std, float), (len(names),)).copy()
    if np.any(~(tau > 0)):
        raise ValueError("prior standard deviations must be positive (use inf for 'not penalised')")
    mu = np.asarray(start, float).copy()
    if isinstance(prior_mean, dict):
        for k, v in prior_mean.items():
            if k not in names:
                raise ValueError(f"prior_mean: {k!r} is not a free parameter (free: {names})")
            mu[names.index(k)] = float(v)
    elif prior_mean is not None:
        mu = np.broadcast_to(np.asarray(prior_mean, float), (len(names),)).copy()
    return 1.0 / tau, mu


def _clearly_identifiable(fac, margin: float = 1e3) -> bool:
    """True when the factorisation ``fac`` of :func:`_factor` already shows the columns independent with
    room to spare: every column norm above ``margin`` × the structural zero tolerance (relative to the
    largest) and every ``|R_jj|`` of the unit-norm columns above ``margin`` × :data:`STRUCTURAL_TOL`.
    ``|R_jj|`` of an unpivoted QR is the distance of unit column j from the span of the columns before
    it — the quantity the priority-ordered scan :func:`estcal.identify.core.sequential_rank` compares
    with the tolerance, in the same (given) order — so the full check could only refuse when this
    returns False; then it runs and names the parameters."""
    s, R, _ = fac
    d = np.abs(np.diag(R))
    return bool(s.min() > margin * STRUCTURAL_TOL * s.max() and d.size and d.min() > margin * STRUCTURAL_TOL)


def _covariance(A, fac=None) -> np.ndarray:
    """Σ = (AᵀA)⁻¹ via the QR factor of the column-scaled A (stable for poorly scaled columns);
    ``fac``: the factorisation of A by :func:`_factor` when the last iteration made it."""
    s, R, _ = _factor(A, np.zeros(A.shape[0])) if fac is None else fac
    Rinv = sla.solve_triangular(R, np.eye(R.shape[0]))
    return (Rinv @ Rinv.T) / np.outer(s, s)


class _Penalised:
    """The weighted data system of the free parameters (:class:`~estcal.methods.reduced.DenseSystem`,
    or :class:`~estcal.methods.reduced.ReducedSystem` in bounded memory) with the prior rows
    ``(μ − θ)/τ`` of the penalised parameters appended (MAP; none without ``prior_std``)."""

    def __init__(self, problem, fidx, names, nominal, prior_std, prior_mean, chunk):
        self.fidx = fidx
        self.system = DenseSystem(problem, fidx) if chunk is None else ReducedSystem(problem, fidx, chunk)
        self.pk = np.zeros(0, int)
        if prior_std is not None:
            self.winv, self.mu = prior_arrays(names, prior_std, prior_mean, nominal)
            self.pk = np.flatnonzero(self.winv > 0)
            self.P = np.zeros((self.pk.size, fidx.size))
            self.P[np.arange(self.pk.size), self.pk] = self.winv[self.pk]

    def prior_cost(self, th) -> float:
        pk = self.pk
        return float(np.sum(((th[self.fidx][pk] - self.mu[pk]) * self.winv[pk]) ** 2)) if pk.size else 0.0

    def prior_rows(self, x):
        """Residuals ``(x − μ)/τ`` of the penalised free values ``x`` (scipy's sign)."""
        return (x[self.pk] - self.mu[self.pk]) * self.winv[self.pk]

    def linear(self, th):
        """``(A, b, cost, data rows of A, data χ²)`` at ``th``."""
        A, b, rss = self.system.linear(th)
        n_data = A.shape[0]
        if self.pk.size:
            A = np.vstack([A, self.P])
            b = np.concatenate([b, -self.prior_rows(th[self.fidx])])
        return A, b, rss + self.prior_cost(th), n_data, rss

    def cost(self, th, jacobian: bool) -> float:
        return self.system.cost(th, jacobian=jacobian) + self.prior_cost(th)

    @property
    def m(self) -> int:
        return self.system.m


def _calibrate_lsq(problem, method, free, max_iter, tol, theta0, validation, check, verbose,
                   prior_std=None, prior_mean=None, chunk=None):
    """Gauss–Newton / Levenberg–Marquardt / iterated linear least squares on the weighted system of
    :class:`_Penalised` (dense, or reduced when ``chunk`` is given: the same iterations, steps and
    covariance in bounded memory); scipy's LM on the dense system."""
    if method not in LSQ_METHODS:
        raise ValueError(f"unknown least-squares method {method!r}; choose one of {LSQ_METHODS}")
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    t0 = time.perf_counter()
    sysp = _Penalised(problem, fidx, names, nominal, prior_std, prior_mean, chunk)
    A, b, cost, n_data, rss = sysp.linear(theta)
    if sysp.m + sysp.pk.size < fidx.size:  # fewer equations than unknowns: singular whatever the data
        raise UnidentifiableError(f"{sysp.m + sysp.pk.size} equations for {fidx.size} free parameters — measure "
                                  f"more poses or estimate fewer parameters")
    fac0 = _factor(A, b) if method != "scipy-lm" else None
    if check and not (fac0 is not None and _clearly_identifiable(fac0)):
        check_identifiable(A, names)
    if method == "scipy-lm":
        theta, it, converged = _scipy_lm(problem, sysp, theta, max_iter, tol)
        A, b, cost, n_data, rss = sysp.linear(theta)
        fac = None
    else:
        theta, it, converged, (A, b, n_data, rss), fac = _iterate(sysp, theta, (A, b, cost, n_data, rss), method,
                                                                  max_iter, tol, verbose, noise_known(problem), fac0)
    res = _lsq_result(problem, sysp, method, names, nominal, theta, A, n_data, rss, it, converged, validation, fac)
    res.extra["time_s"] = time.perf_counter() - t0
    if chunk is not None:
        res.extra["chunk_poses"] = int(chunk)
    before = problem.params.values if theta0 is None else np.asarray(theta0, float)
    res.accuracy = score(problem, before, theta, validation, _train_errors(sysp.system, before, theta))
    return res


def _train_errors(system, before, after):
    """The training point-error norms before and after from the first and last linearisations' residuals
    (:func:`estcal.estimate.result.point_errors_from_rows`), or None (then :func:`score` runs the
    kinematics at both θ: another pass, a seventh of a TIAGo fit)."""
    from estcal.estimate.result import point_errors_from_rows

    first, last = getattr(system, "first", None), getattr(system, "last", None)
    if first is None or not (np.array_equal(first[0], before) and np.array_equal(last[0], after)):
        return None
    eb, ea = point_errors_from_rows(system.problem, first[1]), point_errors_from_rows(system.problem, last[1])
    return None if eb is None or ea is None else (eb, ea)


def _scipy_lm(problem, sysp: _Penalised, theta, max_iter, tol):
    """``(θ, iterations, converged)`` of :func:`scipy.optimize.least_squares` (MINPACK LM) with the
    analytic Jacobian."""
    from scipy.optimize import least_squares

    fidx, pk = sysp.fidx, sysp.pk

    def fun(x):
        th = theta.copy()
        th[fidx] = x
        r = problem.evaluate(th, jacobian=False)
        out = -r.e / r.sigma
        return np.concatenate([out, sysp.prior_rows(x)]) if pk.size else out

    def jac(x):
        th = theta.copy()
        th[fidx] = x
        r = problem.evaluate(th)
        out = r.H[:, fidx] / r.sigma[:, None]
        return np.vstack([out, sysp.P]) if pk.size else out

    sol = least_squares(fun, theta[fidx], jac=jac, method="lm", x_scale="jac", xtol=tol, ftol=tol,
                        gtol=tol, max_nfev=max_iter * 10)
    theta = theta.copy()
    theta[fidx] = sol.x
    return theta, int(sol.njev or sol.nfev), bool(sol.success)


#: stop when the Gauss–Newton step left at the current estimate is shorter than this fraction of a
#: standard deviation (its Mahalanobis length under the covariance the fit reports): no figure the
#: fit reports would change, and the test needs no further pass over the data
STEP_LEFT_SIGMA = 1e-6


def _iterate(sysp: _Penalised, theta, linear, method, max_iter, tol, verbose, known=True, fac=None):
    """``(θ, iterations, converged, (A, b, data rows, data χ²), factorisation of A or None)`` of LM,
    Gauss–Newton with a backtracking line search, or iterated linear least squares (module docstring).

    Stops when the step left at the current point, ``‖Qᵀb‖`` in standard deviations (σ0-scaled when
    the noise is estimated), is below :data:`STEP_LEFT_SIGMA` — checked before a step, so the last
    iteration is not spent confirming a negligible one. The older tests, the relative step or the
    relative change of the cost below ``tol``, stop the loop only when, in addition, the step left no
    longer shrinks (by half from one linearisation to the next): the rounding floor, or a crawl. On
    their own they stopped Gauss–Newton's linear convergence on large residuals (TIAGo: ×0.1 per
    iteration) several 10⁻⁶ σ short of the minimum."""
    fidx = sysp.fidx
    A, b, cost, n_data, rss = linear
    converged, it, mu, gn = False, 0, 1e-2, True
    small, left_before = False, np.inf
    with progress(total=max_iter, desc=f"calibrate ({method}, {fidx.size} parameters)", unit="iter") as bar:
        for it in range(1, max_iter + 1):
            fac = _factor(A, b) if fac is None else fac  # the caller's at the start point
            s0 = 1.0 if known else rss / max(sysp.m - fidx.size, 1)
            left = float(fac[2] @ fac[2]) / s0  # squared step left, in standard deviations
            if left <= STEP_LEFT_SIGMA ** 2 or (small and left > 0.25 * left_before):
                converged, it = True, it - 1
                break
            left_before = left
            if method == "lm":
                # the Gauss–Newton step is tried again only after an iteration where it was accepted
                # or not tried: a failed one costs a pass over the data and is likely to fail again
                trial, dx, mu, took_gn = _lm_step(sysp, theta, A, b, cost, mu, fac, gauss_newton=gn)
                gn = took_gn or not gn
            else:
                trial, dx = _gauss_newton_step(sysp, theta, A, b, cost, method == "gauss-newton", fac)
            theta = trial
            A, b, new_cost, n_data, rss = sysp.linear(theta)
            fac = None
            scale = np.maximum(np.abs(theta[fidx]), 1e-3)
            small = (np.max(np.abs(dx) / scale) < np.sqrt(tol)) or abs(cost - new_cost) <= tol * max(cost, 1e-300)
            cost = new_cost
            bar.update(1)
            bar.set_postfix(cost=f"{cost:.4g}")
            if verbose:
                print(f"iter {it}: cost {cost:.6g}, max|step| {np.max(np.abs(dx)):.3g}, step left {np.sqrt(left):.3g} σ")
    return theta, it, converged, (A, b, n_data, rss), fac


def _lm_step(sysp: _Penalised, theta, A, b, cost, mu, fac=None, nu: float = 10.0, gauss_newton: bool = True):
    """``(θ, Δθ, μ, Gauss–Newton step taken)``: the undamped Gauss–Newton step first (when
    ``gauss_newton``), kept if the cost falls — near the minimum it is the step Marquardt's damping
    only shortens, so LM converges at Gauss–Newton's rate (the hybrid of Madsen, Nielsen & Tingleff,
    *Methods for non-linear least squares problems*, 2004, §3.4) — then Marquardt's rule: damping μ
    multiplied by ν until the cost falls, then divided by ν (every step from the one factorisation
    ``fac`` of the iteration)."""
    fac = _factor(A, b) if fac is None else fac
    if gauss_newton:
        dx = _solve(A, b, 0.0, fac)
        trial = theta.copy()
        trial[sysp.fidx] += dx
        if sysp.cost(trial, jacobian=True) <= cost:
            return trial, dx, max(mu / nu, 1e-12), True
    while True:
        dx = _solve(A, b, mu, fac)
        trial = theta.copy()
        trial[sysp.fidx] += dx
        if sysp.cost(trial, jacobian=True) <= cost or mu > 1e12:
            break
        mu *= nu
    return trial, dx, max(mu / nu, 1e-12), False


def _gauss_newton_step(sysp: _Penalised, theta, A, b, cost, line_search: bool, fac=None):
    """The full Gauss–Newton step; with ``line_search`` halved until the cost falls (down to 1e-6)."""
    dx = _solve(A, b, 0.0, fac)
    step = 1.0
    trial = theta.copy()
    trial[sysp.fidx] += dx
    if line_search:
        while not (sysp.cost(trial, jacobian=step == 1.0) <= cost or step < 1e-6):
            step *= 0.5
            trial = theta.copy()
            trial[sysp.fidx] += step * dx
        dx = step * dx
    return trial, dx


def _lsq_result(problem, sysp: _Penalised, method, names, nominal, theta, A, n_data, rss, it, converged,
                validation, fac=None) -> CalibrationResult:
    """The result at the solution: ``Σ = (AᵀA)⁻¹``, scaled by σ0² when the noise is not known (with a
    prior, over the effective number of parameters ``tr(Σ HᵀWH)``)."""
    fidx, pk = sysp.fidx, sysp.pk
    chi2 = float(rss)  # the data part (the prior rows are not measurements)
    dof = int(sysp.m - fidx.size)
    cov = _covariance(A, fac)
    p_eff, dof_eff = float(fidx.size), dof
    if pk.size:  # effective number of parameters tr(Σ HᵀWH) of the regularised fit
        Ad = A[:n_data]
        p_eff = float(np.einsum("ij,ji->", cov, Ad.T @ Ad))
        dof_eff = sysp.m - p_eff
    known = noise_known(problem)
    if not known and dof_eff > 0:
        cov = cov * (chi2 / dof_eff)
    res = CalibrationResult(method=method, names=names, estimate=theta[fidx].copy(),
                            std=np.sqrt(np.diag(cov)), covariance=cov, nominal=nominal, theta=theta,
                            all_names=list(problem.params.names), n_iterations=it, converged=converged, chi2=chi2,
                            dof=dof, covariance_source="model" if known else "scaled by sigma0^2",
                            problem=problem, validation_data=list(validation))
    if pk.size:
        res.extra["prior"] = {"std": {names[k]: float(1.0 / sysp.winv[k]) for k in pk},
                              "mean": {names[k]: float(sysp.mu[k]) for k in pk},
                              "effective_parameters": p_eff, "dof_effective": dof_eff}
    return res


def calibrate_irls(problem, method: str = "lm", free=None, robust: str = "huber", robust_k=None,
                   max_outer: int = 200, tol: float = 1e-6, validation=(), inner_iter: int = 1, **options):
    """Robust least squares by iteratively reweighted LS (module docstring).

    Each outer iteration fits with the σ of every group divided by √w (weights fixed), then
    recomputes the weights at the new estimate; stops when no weight changes by more than
    ``tol`` or the estimate moved by less than ``tol`` standard deviations. The covariance is that of the last weighted fit (the approximation gtsam's robust
    marginals also give; scaled by that fit's σ0² when the noise is not known).
    """
    kernel = check_kernel(robust)
    options.pop("max_iter", None)
    problem, fidx, names = resolve_free(problem, free)
    theta0 = options.pop("theta0", None)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    theta_before = theta.copy()
    r, dims, _, row_group = group_norms(problem, theta)
    km = np.array([kernel_threshold(kernel, int(m), robust_k) for m in dims])
    w = np.ones(r.size)
    res = None
    # the fixed point does not depend on the inner solver; Gauss–Newton with its line search
    # takes full steps where LM's damping, restarted at every reweighting, would crawl
    inner = "scipy-lm" if method == "scipy-lm" else "gauss-newton"
    for it in range(1, max_outer + 1):
        wp = WeightedProblem(problem, 1.0 / np.sqrt(w[row_group]))
        # one Gauss–Newton / LM step per reweighting (as gtsam's robust LM re-weighs at every
        # linearisation): far fewer fits than iterating each weighted fit to convergence
        res = calibrate_lsq(wp, inner, theta0=theta, max_iter=inner_iter, **options)
        step = np.max(np.abs(res.theta[fidx] - theta[fidx]) / np.maximum(res.std, 1e-300))
        theta = res.theta
        r = group_norms(problem, theta)[0]
        w_new = kernel_weight(kernel, r, km)
        # converged when the weights are stable or the estimate moves by < tol standard deviations
        done = np.max(np.abs(w_new - w)) <= tol or step <= tol
        w = w_new
        if done:
            break
    res.n_iterations = it
    res.converged = bool(done)
    res.method = method
    # χ² and accuracy of the unweighted data (the report adds the split with / without outliers)
    res.chi2 = chi2_and_rows(problem, theta)[0]
    res.covariance_source = f"weighted LS at the robust ({kernel}) weights"
    res.accuracy = score(problem, theta_before, theta, validation)
    res.extra["robust_outer_iterations"] = it
    return res
