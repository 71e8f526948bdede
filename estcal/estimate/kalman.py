"""Recursive calibration: extended and unscented Kalman filtering of the parameter vector.

State: the free parameters x (absolute values, SI). Random-walk model of the
textbook (§4.5, eqs 4.104–4.112)::

    x_k = x_{k−1} + w_{k−1},  Cov(w) = Q        (Q = 0: constant parameters, 4.104–4.106)
    z_k = h_k(x_k) + v_k,      Cov(v) = R_k      (one measurement group: the rows of one pose)

Predict ``P_k(−) = P_{k−1} + Q``; gain ``K_k = P_k(−) H_kᵀ (H_k P_k(−) H_kᵀ + R_k)⁻¹``
(4.111); update ``x̂_k = x̂_{k−1} + K_k ν_k`` (4.110) and
``P_k = P_k(−) − K_k H_k P_k(−)`` (4.112; filterpy uses the Joseph form).
With Q = 0 and a prior (μx, P0) the last estimate equals the batch MAP of
eqs 4.69–4.70 for a linear model; with Q > 0 the covariance does not fall
below the Riccati floor P∞ (:mod:`estcal.estimate.riccati`).

The measurement of one group is written for filterpy as ``z = 0`` and
``h(x) = −e(x) = predicted − measured`` so that the innovation ``z − h(x)`` is
the residual ``e`` of :class:`~estcal.methods.problem.Problem` and
``∂h/∂x = H`` (the identification Jacobian) — the filters are filterpy's
:class:`~filterpy.kalman.ExtendedKalmanFilter` and
:class:`~filterpy.kalman.UnscentedKalmanFilter`, not hand-written ones.
The UKF's sigma points are evaluated in one vectorised call
(:meth:`estcal.methods.problem.Problem.evaluate_many`).

The UKF predicts each measurement as the mean of h over the current Gaussian
(second-order term ½ tr(∇²h P) included): with a very wide prior that term
biases the first updates and the final estimate can sit a fraction of a
standard deviation from the MAP (docs/probabilistic.md gives numbers); give it
a prior of the size of the expected corrections.

``passes > 1`` re-runs the filter from the same prior with every group
linearised at the previous pass's estimate (an iterated — Gauss–Newton — EKF):
for Q = 0 its fixed point is the MAP / least-squares solution.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ._common import GroupedProblem, evaluate_many, finish_result, noise_known, prior_std_vector, resolve_free
from .innovation import InnovationMonitor

__all__ = ["ParameterFilter", "BlockStep", "block_update", "segment_of", "run_steps", "concat_steps",
           "calibrate_kalman", "calibrate_ukf", "process_noise", "default_burn_in"]


def process_noise(names, q=0.0) -> np.ndarray:
    """Process-noise covariance Q (per update step) from std ``q``.

    ``q`` is a scalar (same std for every free parameter, SI units per step), an
    array (one std per free parameter), a dict ``{name or pattern: std}`` (others
    0), or a full (p, p) covariance matrix.
    """
    import fnmatch

    p = len(names)
    if isinstance(q, dict):
        s = np.zeros(p)
        for pat, v in q.items():
            hit = [i for i, n in enumerate(names) if fnmatch.fnmatchcase(n, pat)]
            if not hit:
                raise ValueError(f"process noise: {pat!r} matches no free parameter (free: {names})")
            s[hit] = float(v)
        return np.diag(s ** 2)
    q = np.asarray(q, float)
    if q.ndim == 2:
        if q.shape != (p, p):
            raise ValueError(f"Q must be ({p}, {p}), got {q.shape}")
        return q
    s = np.broadcast_to(q, (p,)).astype(float)
    return np.diag(s ** 2)


def default_burn_in(dims, n_free: int) -> int:
    """Steps until the rows seen reach twice the number of free parameters."""
    c = np.cumsum(dims)
    k = int(np.searchsorted(c, 2 * n_free))
    return min(k + 1, len(dims))


@dataclass
class Step:
    """One filter step: innovation, its covariance and NIS."""

    y: np.ndarray
    S: np.ndarray
    nis: float


class ParameterFilter:
    """A filterpy EKF or UKF over the free parameters of a problem.

    Parameters
    ----------
    theta : (P,) full parameter vector (fixed parameters keep these values).
    fidx : indices of the free parameters.
    P0 : (p, p) prior covariance; Q : (p, p) process noise per step.
    kind : ``"ekf"`` or ``"ukf"``.
    ukf_alpha, ukf_beta, ukf_kappa : Van der Merwe sigma-point parameters.
    """

    def __init__(self, theta, fidx, P0, Q=None, kind: str = "ekf", names=None, ukf_alpha: float = 1e-2,
                 ukf_beta: float = 2.0, ukf_kappa: float = 0.0, robust: str | None = None,
                 robust_k: float | None = None):
        self.theta0 = np.asarray(theta, float).copy()
        self.fidx = np.asarray(fidx, int)
        self.names = list(names) if names is not None else [str(i) for i in self.fidx]
        p = self.fidx.size
        self.Q = np.zeros((p, p)) if Q is None else np.asarray(Q, float)
        self.kind = kind
        from .robust import check_kernel

        self.robust, self.robust_k = check_kernel(robust), robust_k
        if self.robust is not None and kind != "ekf":
            raise ValueError(f"robust kernels are implemented for the EKF (--filter ekf / estimator kalman), "
                             f"not the {kind.upper()}")
        self.weights: list[float] = []  # robust weight of every update (1 without a kernel)
        x0 = self.theta0[self.fidx].copy()
        if kind == "ekf":
            from filterpy.kalman import ExtendedKalmanFilter

            f = ExtendedKalmanFilter(dim_x=p, dim_z=1)
        elif kind == "ukf":
            from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

            pts = MerweScaledSigmaPoints(p, alpha=ukf_alpha, beta=ukf_beta, kappa=ukf_kappa)
            f = UnscentedKalmanFilter(dim_x=p, dim_z=1, dt=1.0, hx=None, fx=lambda x, dt: x, points=pts)
        else:
            raise ValueError(f"unknown filter {kind!r}; choose 'ekf' or 'ukf'")
        f.x = x0  # 1-D state: filterpy's algebra works unchanged and avoids (p, 1) reshapes
        f.P = np.array(P0, float)
        f.Q = self.Q
        self._q_zero = not np.any(self.Q)
        self.f = f
        self.monitor = InnovationMonitor()
        self.n_steps = 0
        self.n_rows = 0

    # ---------------------------------------------------------------- state
    @property
    def x(self) -> np.ndarray:
        return np.asarray(self.f.x, float).copy()

    @property
    def P(self) -> np.ndarray:
        return np.asarray(self.f.P, float).copy()

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.f.P), 0, None))

    def full(self, x=None) -> np.ndarray:
        th = self.theta0.copy()
        th[self.fidx] = self.f.x if x is None else x
        return th

    # ---------------------------------------------------------------- step
    def step(self, sub, x_lin=None, weight=None) -> Step:
        """Predict (P += Q) and update with the rows of ``sub`` (an object with ``evaluate``).

        ``x_lin`` : linearise at this free-parameter vector instead of the current
        estimate (EKF only; used by iterated passes).
        ``weight`` : robust weight of this update (default: the kernel of the innovation's
        normalised norm when the filter has a kernel).
        """
        f = self.f
        if self.kind == "ekf":
            f.predict()
            lin = f.x if x_lin is None else np.asarray(x_lin, float)
            rows = sub.evaluate(self.full(lin))
            H = rows.H[:, self.fidx]
            e = rows.e
            R = np.diag(rows.sigma ** 2)
            if x_lin is None:
                hx = -e
            else:  # affine model about x_lin: h(x) = −e_lin + H (x − x_lin)
                hx = -e + H @ (f.x - lin)
            z = np.zeros(e.size)
            w = 1.0 if weight is None else float(weight)
            if self.robust is not None and weight is None:
                # weigh the innovation by the kernel of its normalised norm √(νᵀS⁻¹ν)
                # (docs: estcal.estimate.robust); R / w is the reweighted measurement noise
                from .robust import kernel_threshold, kernel_weight

                nu = z - hx
                S = H @ f.P @ H.T + R
                r = float(np.sqrt(nu @ np.linalg.solve(S, nu)))
                w = float(kernel_weight(self.robust, r, kernel_threshold(self.robust, e.size, self.robust_k)))
            if w != 1.0:
                R = R / max(w, 1e-12)
            self.weights.append(w)
            f.update(z, lambda x: H, lambda x: hx, R=R)
            y, S = np.asarray(f.y, float), np.asarray(f.S, float)
        else:
            f.predict()
            sig = f.sigmas_f
            TH = np.broadcast_to(self.theta0, (sig.shape[0], self.theta0.size)).copy()
            TH[:, self.fidx] = sig
            E = evaluate_many(sub, TH)
            lookup = {s.tobytes(): -E[i] for i, s in enumerate(sig)}
            rows = sub.evaluate(self.full(f.x), jacobian=False)
            R = np.diag(rows.sigma ** 2)
            f.update(np.zeros(E.shape[1]), R=R, hx=lambda s: lookup[np.asarray(s).tobytes()])
            f.P = 0.5 * (f.P + f.P.T)
            y, S = np.asarray(f.y, float), np.asarray(f.S, float)
        nis = self.monitor.add(y, S)
        self.n_steps += 1
        self.n_rows += y.size
        return Step(y, S, nis)

    def update_block(self, H, e, sigma, dims, x_lin) -> BlockStep:
        """Predict and update with B groups linearised at ``x_lin`` (free parameters): the filter
        of B :meth:`step` calls with that ``x_lin``, computed as one block (:func:`block_update`:
        the same innovations, NIS, estimate and covariance, to rounding). EKF only.

        ``H`` (M, p) Jacobian rows in the free parameters, ``e`` (M,) residuals (measured −
        predicted) and ``sigma`` (M,) noise stds at ``x_lin``, stacked group by group; ``dims``
        (B,) rows per group."""
        if self.kind != "ekf":
            raise ValueError("block updates are an EKF computation (the UKF steps row by row)")
        if self.robust is not None:
            raise ValueError("block updates have no robust kernel (its weight depends on each innovation)")
        f = self.f
        nu = e - H @ (f.x - np.asarray(x_lin, float))
        x, P, w, st = block_update(f.x, f.P, self.Q, H, nu, sigma, dims, q_zero=self._q_zero)
        f.x, f.P = x, P
        self.monitor.record_many(st.nis, dims, w)
        self.n_steps += len(dims)
        self.n_rows += int(np.sum(dims))
        return st


@dataclass
class BlockStep:
    """The groups of one :meth:`ParameterFilter.update_block`: NIS and dimension of each group's
    innovation, and the estimate, variances and trace of P after each group (exact, not interpolated)."""

    nis: np.ndarray  # (B,)
    dims: np.ndarray  # (B,)
    estimate: np.ndarray  # (B, p)
    var: np.ndarray  # (B, p) diagonal of P after each group
    trace: np.ndarray  # (B,) trace of P after each group

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(self.var, 0, None))


def block_update(x, P, Q, H, nu, sigma, dims, q_zero: bool | None = None):
    """B sequential Kalman steps (predict ``P += Q``, update with one group) as one exact block.

    The B groups are linearised at one point (affine measurement models); the innovations of
    the sequential filter are then those of the joint Gaussian of the stacked measurements
    z = (z_1 … z_B). With x_k = x_0 + w_1 + … + w_k (random walk, Cov w = Q)::

        Cov(z_i, z_j) = H_i (P + min(i, j) Q) H_jᵀ + δ_ij R_i,   Cov(x_k, z_j) = (P + j Q) H_jᵀ  (j ≤ k)

    With the lower Cholesky factor L Lᵀ = Cov(z), the whitened stacked innovation
    ``w = L⁻¹ ν⁰`` (ν⁰ = z − E z under the pre-block estimate) is, block by block, exactly
    ``L_k⁻¹ ν_k`` of the sequential filter (L_k L_kᵀ = S_k: the block pivots of the block LDLᵀ
    factorisation of Cov(z) are the innovation covariances S_k), so each group's NIS is
    ``|w_k|²``. With ``A = L⁻¹ C`` (C the stacked Cov(z_j, x)), the estimate and covariance
    after group k are the prefix sums ``x_k = x_0 + Σ_{j≤k} A_jᵀ w_j`` and
    ``P_k = P + k Q − Σ_{j≤k} A_jᵀ A_j`` (the leading blocks of L are the Cholesky factors of
    the leading blocks of Cov(z)). Textbook §4.5 (eqs 4.104–4.112) in sequential form; the
    block form is the same conditioning done at once.

    Parameters
    ----------
    x, P, Q : (p,), (p, p), (p, p) — estimate and covariance before the block, process noise per step.
    H : (M, p) stacked Jacobian rows ∂h/∂x of the B groups; ``nu`` (M,) their innovations at x
        (``e(x_lin) − H (x − x_lin)`` for residuals e at the linearisation point);
        ``sigma`` (M,) noise std of each row; ``dims`` (B,) rows per group (Σ dims = M).

    Returns
    -------
    (x_B, P_B, w, step): the state after the block, the (M,) whitened innovations and a
    :class:`BlockStep` with every group's NIS, estimate, variances and trace of P.
    """
    from scipy.linalg import cholesky, solve_triangular

    dims = np.asarray(dims, np.int64)
    B = dims.size
    k = np.repeat(np.arange(1, B + 1), dims)  # step index of each stacked row
    HP = H @ P
    S = HP @ H.T
    C = HP
    if q_zero is None:
        q_zero = not np.any(Q)
    if not q_zero:
        HQ = H @ Q
        S = S + (HQ @ H.T) * np.minimum.outer(k, k)
        C = HP + HQ * k[:, None]
    S[np.diag_indices_from(S)] += np.asarray(sigma, float) ** 2
    L = cholesky(S, lower=True, check_finite=False)
    w = solve_triangular(L, nu, lower=True, check_finite=False)
    A = solve_triangular(L, C, lower=True, check_finite=False)
    starts = np.r_[0, np.cumsum(dims)[:-1]]
    nis = np.add.reduceat(w * w, starts)
    X = x + np.cumsum(np.add.reduceat(A * w[:, None], starts, axis=0), axis=0)
    A2 = np.add.reduceat(A * A, starts, axis=0)
    steps = np.arange(1, B + 1)[:, None]
    V = np.diag(P) + steps * np.diag(Q) - np.cumsum(A2, axis=0)
    T = np.trace(P) + steps[:, 0] * np.trace(Q) - np.cumsum(A2.sum(axis=1))
    P_new = P + B * Q - A.T @ A
    P_new = 0.5 * (P_new + P_new.T)
    return X[-1].copy(), P_new, w, BlockStep(nis, dims, X, V, T)


#: groups per Cholesky block of :func:`block_update` (its cost per group grows like the block's
#: rows squared; with ~3 rows per group the minimum is near 32 groups: 6 µs per group, 30 parameters)
BLOCK_GROUPS = 32
#: largest linearisation segment of the ``"auto"`` schedule, and groups evaluated per kinematics call
MAX_SEGMENT = 256
EVAL_GROUPS = 1024


def segment_of(n: int, relinearize="auto", rowwise: int = 32) -> tuple[int, int]:
    """``(start, end)`` of the linearisation segment holding step ``n`` (0-based, absolute).

    Every step of a segment is linearised at the estimate before the segment's first step.
    ``relinearize``: an integer G (segments of G steps; 1 = every step at the current estimate,
    the classical EKF) or ``"auto"``: one step per segment for the first ``rowwise`` steps (while
    the estimate still moves by many of its σ), then G = the largest power of two ≤ n/16, at
    most :data:`MAX_SEGMENT`. A segment then starts at step ≥ 16 G, so the estimate moves
    within it by about σ·√(G/n) ≤ σ/4 and the linearisation error it leaves is second order in
    that move (docs/probabilistic.md, "Online at sensor rate"). The segments are a function of
    the step index alone, so a stream cut anywhere, or resumed, is linearised the same way."""
    if relinearize != "auto":
        G = int(relinearize)
        return n - n % G, n - n % G + G
    if n < rowwise:
        return n, n + 1
    G = min(MAX_SEGMENT, 1 << max((n // 16).bit_length() - 1, 0))
    start = n - n % G
    return max(start, rowwise), start + G


def run_steps(flt, a: int, b: int, evaluate, relinearize="auto", lin=None, x_lin=None, rowwise: int = 32):
    """Steps ``a … b−1`` of an EKF :class:`ParameterFilter` in linearisation segments and blocks.

    ``evaluate(i, j, theta)`` returns ``(H, e, sigma, dims)`` of steps i … j−1 at the full
    parameter vector ``theta`` (rows stacked step by step; H in the free parameters).
    ``x_lin``: linearise every step there (an iterated pass) instead of by the schedule
    :func:`segment_of`; ``lin``: ``(segment start, x_lin)`` carried over from a call that ended
    inside a segment. Blocks are cut at multiples of :data:`BLOCK_GROUPS` and evaluations at
    multiples of :data:`EVAL_GROUPS` (absolute step indices), so the floating-point operations
    depend only on where the calls start and end.

    Returns ``(steps, lin)``: the :class:`BlockStep` of each block and the linearisation to carry
    over (None at a segment end)."""
    out = []
    n = a
    while n < b:
        if x_lin is not None:
            s, end, xl = a, b, x_lin
        else:
            s, end = segment_of(n, relinearize, rowwise)
            if lin is not None and lin[0] == s:
                xl = np.asarray(lin[1], float)
            elif n == s:
                xl = flt.x
            else:
                raise ValueError(f"step {n} is inside the linearisation segment starting at step {s}, whose "
                                 f"linearisation point is not known (resume from a checkpoint of this run)")
        stop = min(b, end, (n // EVAL_GROUPS + 1) * EVAL_GROUPS)
        H, e, sigma, dims = evaluate(n, stop, flt.full(xl))
        off = np.r_[0, np.cumsum(dims)]
        i = n
        while i < stop:
            j = min(stop, (i // BLOCK_GROUPS + 1) * BLOCK_GROUPS)
            r0, r1 = off[i - n], off[j - n]
            out.append(flt.update_block(H[r0:r1], e[r0:r1], sigma[r0:r1], dims[i - n:j - n], xl))
            i = j
        n = stop
        lin = (s, xl) if (x_lin is None and n < end) else None
    return out, lin


def concat_steps(steps) -> BlockStep:
    """One :class:`BlockStep` of several consecutive ones."""
    if len(steps) == 1:
        return steps[0]
    return BlockStep(*(np.concatenate([getattr(s, k) for s in steps]) for k in
                       ("nis", "dims", "estimate", "var", "trace")))


def _prior(problem, names, fidx, prior_std, P0):
    if P0 is not None:
        P0 = np.asarray(P0, float)
        if P0.ndim == 1:
            P0 = np.diag(P0 ** 2)
        return P0
    return np.diag(prior_std_vector(problem, names, prior_std) ** 2)


def calibrate_kalman(problem, free=None, validation=(), *, filter: str = "ekf", prior_std=None, P0=None,
                     q=0.0, batch_size: int = 1, passes: int | None = None, theta0=None,
                     burn_in: int | None = None,
                     lags: int = 10, history: bool = False, ukf_alpha: float = 1e-2,
                     scale_covariance: bool | None = None, robust: str | None = None, robust_k: float | None = None,
                     **_ignored):
    """Kalman-filter calibration: process the problem's poses one group at a time.

    Parameters
    ----------
    problem : :class:`~estcal.methods.problem.Problem`
    free : free parameter names/patterns (default: the problem's free mask)
    filter : ``"ekf"`` (filterpy ExtendedKalmanFilter) or ``"ukf"`` (UnscentedKalmanFilter)
    prior_std / P0 : prior std (scalar, per-parameter array or ``{name: std}``) or full P0;
        default :func:`~estcal.estimate._common.default_prior_std` (0.1, wide)
    q : process-noise std per step (see :func:`process_noise`); 0 = constant parameters
    batch_size : poses per update (1 = measurement by measurement)
    passes : iterated-EKF passes (each re-linearises at the previous pass's estimates); default 1,
        3 with a robust kernel: the first pass weighs each update by the kernel of its innovation
        (early outliers, seen while P is still wide, pass almost unweighted), the next ones by the
        kernel of its residual at the previous pass's estimate — iteratively reweighted, whose
        fixed point is the robust M-estimate (:mod:`estcal.estimate.robust`)
    robust, robust_k : ``"huber"`` / ``"cauchy"`` kernel and scalar threshold (σ); EKF only
    theta0 : full initial parameter vector (prior mean of the free ones); default the problem's values
    burn_in : steps left out of the innovation tests (default: until 2 p rows were seen)
    history : keep per-step estimates and standard deviations in ``extra``
    scale_covariance : multiply P by σ0² = χ²/dof (default: when the noise is not known,
        as :func:`~estcal.estimate.lsq.calibrate_lsq` does)

    Returns
    -------
    CalibrationResult with ``extra["innovation"]`` (tests), ``extra["filter"]``, ``extra["q"]``.
    """
    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    P0m = _prior(problem, names, fidx, prior_std, P0)
    Q = process_noise(names, q)
    gp = GroupedProblem(problem)
    ng = len(gp)
    starts = range(0, ng, batch_size)

    def subs():  # built as they are used: 10⁶ sub-problems held at once would cost GBs
        for i in starts:
            yield gp.subproblem(list(range(i, min(i + batch_size, ng))))

    x_lin = None
    hist_x, hist_s = [], []
    if passes is None:
        passes = 3 if robust not in (None, "none") and filter == "ekf" else 1
    weights = None
    from estcal.base.progress import progress

    n_pass = 1 if filter == "ukf" else passes
    with progress(total=n_pass * len(starts), desc=f"kalman ({filter}, {n_pass} pass(es))", unit="update") as bar:
        for it in range(passes):
            flt = ParameterFilter(theta, fidx, P0m, Q, kind=filter, names=names, ukf_alpha=ukf_alpha, robust=robust,
                                  robust_k=robust_k)
            for k, sub in enumerate(subs()):
                flt.step(sub, x_lin, None if weights is None else weights[k])
                bar.update(1)
                if history and it == passes - 1:
                    hist_x.append(flt.x)
                    hist_s.append(flt.std)
            if filter == "ukf":
                break
            # next pass: every group linearised at this pass's final estimate (a Gauss–Newton step)
            x_lin = flt.x
            if flt.robust is not None:  # IRLS: weights from the residuals at this pass's estimate
                from .robust import kernel_threshold, kernel_weight

                weights = []
                for sub in subs():
                    r = sub.evaluate(flt.full(x_lin), jacobian=False)
                    rn = float(np.linalg.norm(r.e / r.sigma))
                    weights.append(float(kernel_weight(flt.robust, rn,
                                                       kernel_threshold(flt.robust, r.e.size, robust_k))))
    x, P = flt.x, flt.P
    theta_full = flt.full(x)
    known = noise_known(problem)
    from .reduced import chi2_and_rows

    chi2, m_rows = chi2_and_rows(problem, theta_full)
    dof = m_rows - len(fidx)
    if scale_covariance is None:
        scale_covariance = not known
    src = "model (filter P)"
    if scale_covariance and dof > 0 and robust is None:  # σ0² would count the outliers (as gtsam: unscaled)
        P = P * (chi2 / dof)
        src = "filter P scaled by sigma0^2"
    bi = default_burn_in(flt.monitor.dims, len(fidx)) if burn_in is None else burn_in
    extra = {"filter": filter, "q": np.sqrt(np.diag(Q)), "n_updates": flt.n_steps, "batch_size": batch_size,
             "passes": passes, "prior_std": np.sqrt(np.diag(P0m))}
    try:
        extra["innovation"] = flt.monitor.tests(burn_in=bi, lags=lags).to_dict()
    except ValueError as exc:
        extra["innovation"] = {"error": str(exc)}
    if history:
        extra["history"] = {"estimate": np.array(hist_x), "std": np.array(hist_s), "nis": np.array(flt.monitor.nis)}
    return finish_result(problem, "kalman" if filter == "ekf" else "ukf", names, fidx, x, P, theta_full, nominal,
                         n_iterations=passes, converged=True, covariance_source=src, theta_before=theta,
                         validation=validation, t0=t0, extra=extra)


def calibrate_ukf(problem, free=None, validation=(), **options):
    """:func:`calibrate_kalman` with filterpy's UnscentedKalmanFilter (single pass)."""
    options.pop("filter", None)
    return calibrate_kalman(problem, free=free, validation=validation, filter="ukf", **options)
