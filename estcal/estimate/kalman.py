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

    def update_block(self, H, e, sigma, dims, x_lin, tau: float | None = None) -> BlockStep:
        """Predict and update with B groups linearised at ``x_lin`` (free parameters): the filter
        of B :meth:`step` calls with that ``x_lin``, computed as one block (:func:`block_update`:
        the same innovations, NIS, estimate and covariance, to rounding). EKF only.

        ``H`` (M, p) Jacobian rows in the free parameters, ``e`` (M,) residuals (measured −
        predicted) and ``sigma`` (M,) noise stds at ``x_lin``, stacked group by group; ``dims``
        (B,) rows per group. ``tau``: stop before the first group whose predecessor's estimate is
        more than ``tau`` of its σ from ``x_lin`` (it must be relinearised); returns the steps made."""
        if self.kind != "ekf":
            raise ValueError("block updates are an EKF computation (the UKF steps row by row)")
        if self.robust is not None:
            raise ValueError("block updates have no robust kernel (its weight depends on each innovation)")
        f = self.f
        nu = e - H @ (f.x - np.asarray(x_lin, float))
        blk = block_update(f.x, f.P, self.Q, H, nu, sigma, dims, q_zero=self._q_zero)
        k = len(dims) if tau is None else blk.kept(x_lin, tau)
        f.x, f.P, w = blk.state(k)
        st = blk.step if k == len(dims) else blk.step.head(k)
        self.monitor.record_many(st.nis, st.dims, w)
        self.n_steps += k
        self.n_rows += int(np.sum(st.dims))
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

    def head(self, k: int) -> "BlockStep":
        """The first k groups."""
        return BlockStep(self.nis[:k], self.dims[:k], self.estimate[:k], self.var[:k], self.trace[:k])


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
    A :class:`Block`: every group's NIS, estimate, variances and trace of P (``.step``), and the
    state after any number k of its groups (``.state(k)``: a block can be cut short).
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
    return Block(P, Q, A, w, np.r_[starts, A.shape[0]], BlockStep(nis, dims, X, V, T))


@dataclass
class Block:
    """The result of :func:`block_update`, with the state after its first k groups."""

    P: np.ndarray
    Q: np.ndarray
    A: np.ndarray  # (M, p) L⁻¹ Cov(z, x)
    w: np.ndarray  # (M,) whitened innovations
    bounds: np.ndarray  # (B + 1,) first row of each group, then M
    step: BlockStep

    def state(self, k: int):
        """``(x_k, P_k, w of the first k groups)``: the filter after k groups of the block."""
        r = self.bounds[k]
        A = self.A[:r]
        P = self.P + k * self.Q - A.T @ A
        return self.step.estimate[k - 1].copy(), 0.5 * (P + P.T), self.w[:r]

    def kept(self, x_lin, tau: float) -> int:
        """Groups processed before one whose predecessor's estimate is more than ``tau`` of its σ
        from the linearisation point ``x_lin`` (all: B) — there the filter relinearises."""
        st = self.step
        moved = np.max(np.abs(st.estimate[:-1] - x_lin) / np.sqrt(np.maximum(st.var[:-1], 1e-300)), axis=1)
        far = np.flatnonzero(moved > tau)
        return int(far[0]) + 1 if far.size else len(st.nis)


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


#: the default move (in standard deviations of the estimate) after which the segmented filter
#: relinearises within a segment (:func:`run_steps`)
RELINEARIZE_SIGMA = 0.5


def _moved(x, x_lin, var) -> float:
    return float(np.max(np.abs(x - x_lin) / np.sqrt(np.maximum(var, 1e-300))))


def run_steps(flt, a: int, b: int, evaluate, relinearize="auto", lin=None, x_lin=None, rowwise: int = 32,
              tau: float | None = None):
    """Steps ``a … b−1`` of an EKF :class:`ParameterFilter`, linearised in segments, in blocks.

    ``evaluate(i, j, theta)`` returns ``(H, e, sigma, dims)`` of steps i … j−1 at the full
    parameter vector ``theta`` (rows stacked step by step; H in the free parameters).

    Linearisation: step k is linearised at the point of its segment (:func:`segment_of`), which is
    the estimate before the segment's first step — or, as soon as the estimate before step k has
    moved more than ``tau`` (default :data:`RELINEARIZE_SIGMA`) of its σ from that point, the
    estimate before step k (the segment goes on from there). The rule looks at the estimates up
    to step k − 1 only, so it linearises a stream the same way however it is cut into calls.
    ``x_lin``: linearise every step there instead (an iterated pass).

    Steps are evaluated in windows aligned to multiples of a power of two (the whole
    :data:`EVAL_GROUPS` while no relinearisation happens; about twice the steps between the last
    relinearisations after one) and updated in blocks cut at multiples of :data:`BLOCK_GROUPS`,
    window ends and relinearisations. A call that ends at a multiple of :data:`BLOCK_GROUPS` or at
    a segment start therefore leaves every floating-point operation as it would be without the
    cut, once the carried state ``lin`` = ``(segment start, point, step it was set at, window)``
    is passed on to the next call (it is in the checkpoints).

    Returns ``(steps, lin)``: the :class:`BlockStep` of each block and the state to carry over."""
    out = []
    tau = RELINEARIZE_SIGMA if tau is None else tau
    n = a
    s, xl, at, h = lin if lin is not None else (None, None, None, EVAL_GROUPS)
    while n < b:
        if x_lin is not None:
            end, xl, at, s = b, np.asarray(x_lin, float), a, a
        else:
            seg, end = segment_of(n, relinearize, rowwise)
            if seg != s or _moved(flt.f.x, xl, np.diag(flt.f.P)) > tau:
                s, xl, at = seg, flt.x, n  # a segment starts, or the estimate moved away from its point
        stop = min(b, end, (n // h + 1) * h)
        H, e, sigma, dims = evaluate(n, stop, flt.full(xl))
        off = np.r_[0, np.cumsum(dims)]
        i = n
        while i < stop:
            j = min(stop, (i // BLOCK_GROUPS + 1) * BLOCK_GROUPS)
            r0, r1 = off[i - n], off[j - n]
            st = flt.update_block(H[r0:r1], e[r0:r1], sigma[r0:r1], dims[i - n:j - n], xl,
                                  None if x_lin is not None else tau)
            out.append(st)
            i += len(st.nis)
            if i < j:  # the next step is relinearised: evaluate about twice the last run ahead
                h = min(EVAL_GROUPS, 1 << max(2 * (i - at) - 1, 0).bit_length())
                break
        else:
            h = min(EVAL_GROUPS, 2 * h)
        n = i
    return out, (None if x_lin is not None else (s, xl, at, h))


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


def _steps_evaluator(gp, fidx, batch_size: int, sigma_scale=None, slr=None):
    """``evaluate(i, j, theta)`` for :func:`run_steps` over a :class:`GroupedProblem`: step k is the
    groups ``k·batch_size … (k+1)·batch_size − 1``, its rows stacked together.

    ``sigma_scale`` (n_steps,): divide each step's noise std by it (robust weights √w).
    ``slr`` = (x, P, points): statistical linearisation instead of the Jacobian (the UKF's
    iterated passes): the sigma points of N(x, P) are evaluated (one batched kinematics call per
    set of groups) and each row's residual is regressed on them — mean residual and slope."""
    ng = len(gp)

    def evaluate(i, j, theta):
        ids = np.arange(i * batch_size, min(j * batch_size, ng))
        sub, rg = gp.subproblem_rows(ids)
        step = rg // batch_size
        o = np.argsort(step, kind="stable")
        if slr is None:
            r = sub.evaluate(theta)
            H, e = r.H[o][:, fidx], r.e[o]
        else:
            x, P, pts = slr
            sig = pts.sigma_points(x, P)
            TH = np.broadcast_to(theta, (sig.shape[0], theta.size)).copy()
            TH[:, fidx] = sig
            E = evaluate_many(sub, TH)[:, o]  # (W, M) residuals at the sigma points
            e = pts.Wm @ E
            cross = (sig - x).T @ (pts.Wc[:, None] * (E - e))  # (p, M): Cov(x, e)
            H = -np.linalg.solve(P, cross).T  # the slope of the prediction −e
            r = sub.evaluate(theta, jacobian=False)
        sigma = r.sigma[o]
        if sigma_scale is not None:
            sigma = sigma / sigma_scale[step[o]]
        return H, e, sigma, np.bincount(step[o] - i, minlength=j - i)

    return evaluate


def _one_pass(gp, theta, fidx, names, P0m, Q, opts, x_lin=None, weights=None, slr=None):
    """One filter pass over every group from the prior: ``(filter, [BlockStep])``.

    The first pass (``x_lin`` and ``slr`` None) linearises by the schedule ``opts["relinearize"]``
    (the online filter); later passes linearise every group at ``x_lin`` (Gauss–Newton) or, for
    the UKF, by the statistical linearisation ``slr``, applied as exact block updates. Robust
    first passes, the UKF's first pass and ``relinearize=1`` step group by group through filterpy."""
    bs, ng = opts["batch_size"], len(gp)
    n_steps = -(-ng // bs)
    first = x_lin is None and slr is None
    rowwise = first and (opts["filter"] == "ukf" or opts["robust"] is not None or opts["relinearize"] == 1)
    flt = ParameterFilter(theta, fidx, P0m, Q, kind=opts["filter"] if rowwise else "ekf", names=names,
                          ukf_alpha=opts["ukf_alpha"], robust=opts["robust"] if rowwise else None,
                          robust_k=opts["robust_k"])
    if rowwise:
        steps = []
        for k in range(n_steps):
            flt.step(gp.subproblem(list(range(k * bs, min((k + 1) * bs, ng)))), x_lin,
                     None if weights is None else weights[k])
            steps.append(BlockStep(np.array([flt.monitor.nis[-1]]), np.array([flt.monitor.dims[-1]]), flt.x[None],
                                   np.diag(flt.f.P)[None], np.array([np.trace(flt.f.P)])))
        return flt, steps
    scale = None if weights is None else np.sqrt(np.maximum(np.asarray(weights, float), 1e-12))
    evaluate = _steps_evaluator(gp, fidx, bs, scale, slr)
    from estcal.base.blas import single_thread_blas

    with single_thread_blas():  # small matrices: BLAS threads only spin
        steps, _ = run_steps(flt, 0, n_steps, evaluate, opts["relinearize"],
                             x_lin=slr[0] if slr is not None else x_lin, rowwise=max(32, 4 * len(names)))
    return flt, steps


def _robust_weights(gp, flt, x_lin, batch_size: int, robust, robust_k) -> list:
    """IRLS weights of every step from its residual at ``x_lin`` (kernel of the normalised norm)."""
    from .robust import kernel_threshold, kernel_weight

    out, ng = [], len(gp)
    for k in range(-(-ng // batch_size)):
        r = gp.subproblem(list(range(k * batch_size, min((k + 1) * batch_size, ng)))).evaluate(
            flt.full(x_lin), jacobian=False)
        rn = float(np.linalg.norm(r.e / r.sigma))
        out.append(float(kernel_weight(robust, rn, kernel_threshold(robust, r.e.size, robust_k))))
    return out


def _iterate_passes(gp, theta, fidx, names, P0m, Q, opts, passes, max_iter, tol):
    """Filter passes until an iterated pass moves the estimate by less than ``tol`` of its σ
    (``passes`` None, at most ``max_iter`` passes) or exactly ``passes`` passes.

    Returns ``(filter, steps, n_passes, converged, change)``; ``converged`` is the convergence
    test itself: the last pass was an iterated one and moved the estimate by < tol σ."""
    from estcal.base.progress import progress

    limit = max_iter if passes is None else passes
    x_prev, weights, slr, change = None, None, None, float("inf")
    converged = False
    n = 0
    pts = None
    if opts["filter"] == "ukf":
        from filterpy.kalman import MerweScaledSigmaPoints

        pts = MerweScaledSigmaPoints(len(names), alpha=opts["ukf_alpha"], beta=2.0, kappa=0.0)
    with progress(total=limit, desc=f"kalman ({opts['filter']}, passes)", unit="pass") as bar:
        for n in range(1, limit + 1):
            flt, steps = _one_pass(gp, theta, fidx, names, P0m, Q, opts, x_lin=None if pts else x_prev,
                                   weights=weights, slr=slr)
            bar.update(1)
            if x_prev is not None:
                change = float(np.max(np.abs(flt.x - x_prev) / np.maximum(flt.std, 1e-300)))
                converged = change < tol
                if converged and passes is None:
                    break
            x_prev = flt.x
            if pts is not None:
                slr = (flt.x, flt.P, pts)
            if opts["robust"] is not None:  # IRLS: weights from the residuals at this pass's estimate
                weights = _robust_weights(gp, flt, x_prev, opts["batch_size"], opts["robust"], opts["robust_k"])
    return flt, steps, n, converged, change


def calibrate_kalman(problem, free=None, validation=(), *, filter: str = "ekf", prior_std=None, P0=None,
                     q=0.0, batch_size: int = 1, passes: int | None = None, max_iter: int = 50, tol: float = 1e-3,
                     relinearize="auto", theta0=None, burn_in: int | None = None, lags: int = 10,
                     history: bool = False, ukf_alpha: float = 1e-2, scale_covariance: bool | None = None,
                     robust: str | None = None, robust_k: float | None = None, **_ignored):
    """Kalman-filter calibration: the poses one group at a time, in passes until converged.

    The first pass is the online filter (:class:`estcal.workflows.online.OnlineCalibrator`'s
    engine: groups linearised by the schedule :func:`segment_of`, applied as exact block
    updates). Each further pass re-runs the filter from the same prior with every group
    linearised at the previous pass's estimate — a Gauss–Newton step on the MAP problem, whose
    fixed point (Q = 0) is the MAP estimate; for the UKF, at the statistical linearisation of the
    previous pass's posterior (sigma points: an iterated posterior linearisation). The passes go
    on until one moves the estimate by less than ``tol`` standard deviations: that is the
    convergence test ``converged`` reports (a single pass has none, so ``passes=1`` reports
    ``converged=False``).

    Parameters
    ----------
    problem : :class:`~estcal.methods.problem.Problem`
    free : free parameter names/patterns (default: the problem's free mask)
    filter : ``"ekf"`` (filterpy ExtendedKalmanFilter) or ``"ukf"`` (UnscentedKalmanFilter)
    prior_std / P0 : prior std (scalar, per-parameter array or ``{name: std}``) or full P0;
        default :func:`~estcal.estimate._common.default_prior_std` (0.1, wide)
    q : process-noise std per step (see :func:`process_noise`); 0 = constant parameters
    batch_size : poses per update (1 = measurement by measurement)
    passes : exactly this many passes (default: until converged, at most ``max_iter``)
    max_iter, tol : the pass limit and the convergence test (largest change of an iterated pass,
        in standard deviations of the estimate)
    relinearize : linearisation of the first pass: ``"auto"`` (:func:`segment_of`) or G groups per
        linearisation (1 = every group at the current estimate, filterpy's EKF step by step)
    robust, robust_k : ``"huber"`` / ``"cauchy"`` kernel and scalar threshold (σ); EKF only: the
        first pass weighs each update by the kernel of its innovation, the next ones by the kernel
        of its residual at the previous pass's estimate — iteratively reweighted, whose fixed point
        is the robust M-estimate (:mod:`estcal.estimate.robust`)
    theta0 : full initial parameter vector (prior mean of the free ones); default the problem's values
    burn_in : steps left out of the innovation tests (default: until 2 p rows were seen)
    history : keep per-step estimates and standard deviations (of the last pass) in ``extra``
    scale_covariance : multiply P by σ0² = χ²/dof (default: when the noise is not known,
        as :func:`~estcal.estimate.lsq.calibrate_lsq` does)

    Returns
    -------
    CalibrationResult with ``extra["innovation"]`` (tests, of the last pass), ``extra["filter"]``,
    ``extra["q"]``, ``extra["passes"]`` and ``extra["last_change_sigma"]``.
    """
    t0 = time.perf_counter()
    if relinearize != "auto" and not (isinstance(relinearize, (int, np.integer, float)) and relinearize >= 1
                                      and float(relinearize).is_integer()):
        raise ValueError(f"relinearize must be 'auto' or an integer ≥ 1, got {relinearize!r}")
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    P0m = _prior(problem, names, fidx, prior_std, P0)
    Q = process_noise(names, q)
    gp = GroupedProblem(problem)
    opts = {"filter": filter, "batch_size": int(batch_size), "relinearize": relinearize if relinearize == "auto"
            else int(relinearize), "ukf_alpha": ukf_alpha, "robust": robust if robust not in (None, "none") else None,
            "robust_k": robust_k}
    if filter not in ("ekf", "ukf"):
        raise ValueError(f"unknown filter {filter!r}; choose 'ekf' or 'ukf'")
    flt, steps, n_pass, converged, change = _iterate_passes(gp, theta, fidx, names, P0m, Q, opts, passes,
                                                            int(max_iter), float(tol))
    x, P = flt.x, flt.P
    theta_full = flt.full(x)
    from estcal.methods.reduced import chi2_and_rows

    chi2, m_rows = chi2_and_rows(problem, theta_full)
    dof = m_rows - len(fidx)
    if scale_covariance is None:
        scale_covariance = not noise_known(problem)
    src = "model (filter P)"
    if scale_covariance and dof > 0 and opts["robust"] is None:  # σ0² would count the outliers (as gtsam)
        P = P * (chi2 / dof)
        src = "filter P scaled by sigma0^2"
    bi = default_burn_in(flt.monitor.dims, len(fidx)) if burn_in is None else burn_in
    extra = {"filter": filter, "q": np.sqrt(np.diag(Q)), "n_updates": flt.n_steps, "batch_size": batch_size,
             "passes": n_pass, "last_change_sigma": change, "tol": tol, "prior_std": np.sqrt(np.diag(P0m)),
             "relinearize": opts["relinearize"]}
    try:
        extra["innovation"] = flt.monitor.tests(burn_in=bi, lags=lags).to_dict()
    except ValueError as exc:
        extra["innovation"] = {"error": str(exc)}
    if history:
        st = concat_steps(steps)
        extra["history"] = {"estimate": st.estimate, "std": st.std, "nis": np.array(flt.monitor.nis)}
    return finish_result(problem, "kalman" if filter == "ekf" else "ukf", names, fidx, x, P, theta_full, nominal,
                         n_iterations=n_pass, converged=converged, covariance_source=src, theta_before=theta,
                         validation=validation, t0=t0, extra=extra)


def calibrate_ukf(problem, free=None, validation=(), **options):
    """:func:`calibrate_kalman` with filterpy's UnscentedKalmanFilter (single pass)."""
    options.pop("filter", None)
    return calibrate_kalman(problem, free=free, validation=validation, filter="ukf", **options)
