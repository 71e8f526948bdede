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
from estcal.base.errors import InputError

from ._common import noise_known, resolve_free
from .result import CalibrationResult, accuracy

__all__ = ["calibrate_lsq", "UnidentifiableError", "check_identifiable", "LSQ_METHODS"]

LSQ_METHODS = ("lm", "gauss-newton", "iterated-lls", "scipy-lm")


class UnidentifiableError(InputError):
    """The free parameters are not all identifiable from these data."""


def _weighted(rows, free):
    w = 1.0 / rows.sigma
    A = rows.H[:, free] * w[:, None]
    b = rows.e * w
    return A, b


def check_identifiable(A, names, tol_factor: float = None):
    """Raise :class:`UnidentifiableError` naming dependent / no-effect columns of ``A``.

    Uses QR with column pivoting of the unit-norm-scaled matrix and GECARO's
    numerical zero τ = c·ε·max|R_jj| (App. III, eq. [34]).
    """
    norms = np.linalg.norm(A, axis=0)
    zero = norms <= np.finfo(float).eps * max(norms.max(), 1e-300) * A.shape[0]
    if zero.any():
        bad = [n for n, z in zip(names, zero) if z]
        raise UnidentifiableError(
            f"parameters without effect on these measurements: {bad}. Fix them (remove from --free) — "
            f"run `estcal identifiable` to see the identifiable set")
    As = A / norms
    _, R, piv = sla.qr(As, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    c = A.shape[1]
    tau = (tol_factor or c) * np.finfo(float).eps * d.max() * max(A.shape) / c
    tau = max(tau, 1e-10 * d.max())
    rank = int(np.sum(d > tau))
    if rank < c:
        dep = [names[i] for i in piv[rank:]]
        raise UnidentifiableError(
            f"{c - rank} of the {c} free parameters are not identifiable from these data "
            f"(linearly dependent columns; e.g. {dep}). Fix or regroup them — "
            f"`estcal identifiable` lists an identifiable set")
    return float(d[0] / d[rank - 1])


def _solve(A, b, mu=0.0):
    """Column-scaled (damped) least-squares step.

    Solves ``min ‖As x − b‖² + μ‖x‖²`` with ``As = A diag(1/s)``, ``s`` the column
    norms, through a QR factorisation of the (augmented) scaled matrix — the same
    solution as an SVD-based ``lstsq`` for a full-rank system (identifiability is
    checked before the loop), at a fraction of the cost.
    """
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    As = A / s
    if mu > 0:
        As = np.vstack([As, np.sqrt(mu) * np.eye(A.shape[1])])
        b = np.concatenate([b, np.zeros(A.shape[1])])
    Q, R = np.linalg.qr(As)
    d = np.abs(np.diag(R))
    if d.min() <= 1e-13 * d.max():  # (numerically) rank deficient: fall back to the minimum-norm step
        x, *_ = np.linalg.lstsq(As, b, rcond=None)
    else:
        x = sla.solve_triangular(R, Q.T @ b, check_finite=False)
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
    chunk : poses per chunk of the bounded-memory path (:mod:`estcal.estimate.reduced`; default:
        automatic above ``CHUNK_POSES`` poses for lm / gauss-newton / iterated-lls, with or without prior)

    Returns
    -------
    CalibrationResult
    """
    from .robust import calibrate_irls, check_kernel

    if check_kernel(robust) is not None:
        return calibrate_irls(problem, method, free, robust=robust, robust_k=robust_k, max_iter=max_iter, tol=tol,
                              theta0=theta0, validation=validation, check=check, single_thread=single_thread,
                              prior_std=prior_std, prior_mean=prior_mean)
    from .reduced import use_chunks

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


class _DenseSystem:
    """The weighted data rows of the whole problem: ``A = H_free/σ``, ``b = e/σ`` (M × p)."""

    def __init__(self, problem, fidx):
        self.problem, self.fidx = problem, fidx
        self.m = 0
        self._trial = None  # (θ, rows) of the last trial evaluated with its Jacobian

    def linear(self, theta):
        """``(A, b, bᵀb)`` at θ (reusing the trial's rows when the trial was accepted)."""
        if self._trial is not None and np.array_equal(self._trial[0], theta):
            rows = self._trial[1]
        else:
            rows = self.problem.evaluate(theta)
        self._trial = None
        A, b = _weighted(rows, self.fidx)
        self.m = rows.e.size
        return A, b, float(b @ b)

    def cost(self, theta, jacobian: bool) -> float:
        """``Σ (e/σ)²`` at a trial θ; with ``jacobian`` the rows are kept, so that an accepted
        step (the common case) needs no second forward-kinematics pass."""
        rows = self.problem.evaluate(theta, jacobian=jacobian)
        if jacobian:
            self._trial = (theta.copy(), rows)
        return float(np.sum((rows.e / rows.sigma) ** 2))


class _ReducedSystem:
    """The same least-squares problem as its triangular factor ``(R, Qᵀb)``, built ``chunk`` poses
    at a time (:mod:`estcal.estimate.reduced`): every quantity below is unchanged, the memory is
    O(chunk · p) instead of O(M · p)."""

    def __init__(self, problem, fidx, chunk: int):
        self.problem, self.fidx, self.chunk = problem, fidx, int(chunk)
        self.m = 0

    def linear(self, theta):
        from .reduced import reduce_system

        R, c, rss, self.m = reduce_system(self.problem, theta, self.fidx, self.chunk)
        return R, c, rss

    def cost(self, theta, jacobian: bool) -> float:
        from .reduced import chunked_cost

        return chunked_cost(self.problem, theta, self.chunk)


def _covariance(A) -> np.ndarray:
    """Σ = (AᵀA)⁻¹ via the QR factor of the column-scaled A (stable for poorly scaled columns)."""
    s = np.linalg.norm(A, axis=0)
    s[s == 0] = 1.0
    _, R = np.linalg.qr(A / s)
    Rinv = sla.solve_triangular(R, np.eye(R.shape[0]))
    return (Rinv @ Rinv.T) / np.outer(s, s)


def _calibrate_lsq(problem, method, free, max_iter, tol, theta0, validation, check, verbose,
                   prior_std=None, prior_mean=None, chunk=None):
    """Gauss–Newton / Levenberg–Marquardt / iterated linear least squares on the weighted system
    of :class:`_DenseSystem`, or of :class:`_ReducedSystem` when ``chunk`` is given (the same
    iterations, steps and covariance in bounded memory); scipy's LM on the dense system."""
    if method not in LSQ_METHODS:
        raise ValueError(f"unknown least-squares method {method!r}; choose one of {LSQ_METHODS}")
    problem, fidx, names = resolve_free(problem, free)
    pv = problem.params
    theta = pv.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    t0 = time.perf_counter()
    if prior_std is not None:
        winv, mu_p = prior_arrays(names, prior_std, prior_mean, nominal)
        pk = np.flatnonzero(winv > 0)
        P = np.zeros((pk.size, fidx.size))
        P[np.arange(pk.size), pk] = winv[pk]
    else:
        pk = np.zeros(0, int)
    system = _DenseSystem(problem, fidx) if chunk is None else _ReducedSystem(problem, fidx, chunk)

    def prior_cost(th):
        return float(np.sum(((th[fidx][pk] - mu_p[pk]) * winv[pk]) ** 2)) if pk.size else 0.0

    def linear(th):
        """``(A, b, cost, data rows of A, data χ²)``: the data system, then the prior rows
        ``(μ − θ)/τ`` of the penalised parameters."""
        A_, b_, rss = system.linear(th)
        n_data = A_.shape[0]
        if pk.size:
            A_ = np.vstack([A_, P])
            b_ = np.concatenate([b_, (mu_p[pk] - th[fidx][pk]) * winv[pk]])
        return A_, b_, rss + prior_cost(th), n_data, rss

    A, b, cost, n_data, rss = linear(theta)
    if system.m + pk.size < fidx.size:  # fewer equations than unknowns: singular whatever the data
        raise UnidentifiableError(f"{system.m + pk.size} equations for {fidx.size} free parameters — measure more poses "
                                  f"or estimate fewer parameters")
    if check:
        check_identifiable(A, names)
    converged = False
    it = 0
    if method == "scipy-lm":
        from scipy.optimize import least_squares

        def fun(x):
            th = theta.copy()
            th[fidx] = x
            r = problem.evaluate(th, jacobian=False)
            out = -r.e / r.sigma
            return np.concatenate([out, (x[pk] - mu_p[pk]) * winv[pk]]) if pk.size else out

        def jac(x):
            th = theta.copy()
            th[fidx] = x
            r = problem.evaluate(th)
            out = r.H[:, fidx] / r.sigma[:, None]
            return np.vstack([out, P]) if pk.size else out

        sol = least_squares(fun, theta[fidx], jac=jac, method="lm", x_scale="jac", xtol=tol, ftol=tol,
                            gtol=tol, max_nfev=max_iter * 10)
        theta[fidx] = sol.x
        it, converged = int(sol.njev or sol.nfev), bool(sol.success)
        A, b, cost, n_data, rss = linear(theta)
    else:
        mu, nu = 1e-2, 10.0
        from estcal.base.progress import progress

        with progress(total=max_iter, desc=f"calibrate ({method}, {fidx.size} parameters)", unit="iter") as bar:
            for it in range(1, max_iter + 1):
                if method == "lm":
                    while True:
                        dx = _solve(A, b, mu)
                        trial = theta.copy()
                        trial[fidx] += dx
                        c_t = system.cost(trial, jacobian=True) + prior_cost(trial)
                        if c_t <= cost or mu > 1e12:
                            break
                        mu *= nu
                    mu = max(mu / nu, 1e-12)
                else:
                    dx = _solve(A, b)
                    step = 1.0
                    trial = theta.copy()
                    trial[fidx] += dx
                    if method == "gauss-newton":
                        while True:
                            c_t = system.cost(trial, jacobian=step == 1.0) + prior_cost(trial)
                            if c_t <= cost or step < 1e-6:
                                break
                            step *= 0.5
                            trial = theta.copy()
                            trial[fidx] += step * dx
                        dx = step * dx
                theta = trial
                A, b, new_cost, n_data, rss = linear(theta)
                scale = np.maximum(np.abs(theta[fidx]), 1e-3)
                small_step = np.max(np.abs(dx) / scale) < np.sqrt(tol)
                small_cost = abs(cost - new_cost) <= tol * max(cost, 1e-300)
                cost = new_cost
                bar.update(1)
                bar.set_postfix(cost=f"{cost:.4g}")
                if verbose:
                    print(f"iter {it}: cost {cost:.6g}, max|step| {np.max(np.abs(dx)):.3g}")
                if small_step or small_cost:
                    converged = True
                    break
    chi2 = float(rss)  # the data part (the prior rows are not measurements)
    dof = int(system.m - fidx.size)
    cov = _covariance(A)
    p_eff = float(fidx.size)
    if pk.size:  # effective number of parameters tr(Σ HᵀWH) of the regularised fit
        Ad = A[:n_data]
        p_eff = float(np.einsum("ij,ji->", cov, Ad.T @ Ad))
        dof_eff = system.m - p_eff
    else:
        dof_eff = dof
    known = noise_known(problem)
    if not known and dof_eff > 0:
        cov = cov * (chi2 / dof_eff)
    res = CalibrationResult(method=method, names=names, estimate=theta[fidx].copy(),
                            std=np.sqrt(np.diag(cov)), covariance=cov, nominal=nominal, theta=theta,
                            all_names=list(pv.names), n_iterations=it, converged=converged, chi2=chi2, dof=dof,
                            covariance_source="model" if known else "scaled by sigma0^2",
                            problem=problem, validation_data=list(validation))
    res.extra["time_s"] = time.perf_counter() - t0
    if chunk is not None:
        res.extra["chunk_poses"] = int(chunk)
    if pk.size:
        res.extra["prior"] = {"std": {names[k]: float(1.0 / winv[k]) for k in pk},
                              "mean": {names[k]: float(mu_p[k]) for k in pk},
                              "effective_parameters": p_eff, "dof_effective": dof_eff}
    res.accuracy = score(problem, pv.values if theta0 is None else np.asarray(theta0, float), theta, validation)
    return res


def score(problem, theta_before, theta_after, validation=()) -> dict:
    """Accuracy before/after on the training terms and on each validation dataset."""
    robot = problem.robot
    out = {}
    t = problem.terms[0]
    if t.data.kind != "none":
        out["train"] = {"before": accuracy(robot, theta_before, t.data),
                        "after": accuracy(robot, theta_after, t.data), "path": t.data.where}
    vals = []
    for d in validation:
        vals.append({"path": d.where, "before": accuracy(robot, theta_before, d),
                     "after": accuracy(robot, theta_after, d)})
    if vals:
        out["validation"] = vals
    return out
