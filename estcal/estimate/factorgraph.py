"""Calibration as a factor graph in gtsam (batch LM / Dogleg, incremental iSAM2, smoothing).

Variables
---------
* ``x0`` — the free calibration parameters as one ``gtsam`` Vector variable
  (or, for time-varying calibration, a constant block ``c0`` plus one varying
  block ``v{b}`` per time batch b);
* optionally ``q{i}`` — the latent joint readings of pose i (errors in
  variables): the encoder reading enters as a prior factor with the encoder
  noise, instead of being taken as exact.

By default a batch solve needs no Python callback inside gtsam: each
Levenberg–Marquardt step evaluates the whole problem once (vectorised FK and
analytic Jacobian) and hands gtsam a *Gaussian* factor graph of linear factors
(:func:`_levenberg_marquardt_linear`). The nonlinear graph below is built for
robust kernels, latent joints, Pose3 frames, Dogleg and iSAM2.

Factors
-------
* one :class:`gtsam.CustomFactor` per measurement group (the rows of one pose
  of one term of the :class:`~estcal.methods.problem.Problem`, so every
  measurement method of the problem is supported). Its error is the whitened
  residual ``(predicted − measured)/σ = −e/σ`` and its Jacobian ``H/σ`` (rows
  of the identification Jacobian), with a unit noise model — optionally wrapped
  in ``noiseModel.Robust`` with a Huber or Cauchy kernel (threshold in σ units);
* Gaussian priors on the parameters (``PriorFactorVector``), optional for the
  batch solvers (none by default: the solution is then the least-squares one)
  and required by iSAM2 and the smoother;
* between factors ``(v_{b+1} − v_b)/σ_q`` whose noise is the process noise —
  the batch (smoother) counterpart of the random-walk Kalman filter.

The factor callbacks share a cache: gtsam linearises every factor at the same
values, so the first factor of a block evaluates all the block's poses in one
vectorised ``Problem.evaluate`` and the others read their rows from it.
``extra["python_factor_time_s"]`` reports the time spent inside the Python
callbacks (kinematics included) against the total solve time, which says
whether the Python ``CustomFactor`` is the bottleneck.
"""
from __future__ import annotations

import time

import numpy as np

from estcal.base.blas import single_thread_blas
from estcal.identify.select import check_identifiable
from estcal.kinematics.transforms import matrix_to_rpy, rot_y, rot_z, rpy_to_matrix
from estcal.methods.reduced import DenseSystem, ReducedSystem, chi2_and_rows, reduce_system, use_chunks, weighted

from ._common import GroupedProblem, finish_result, noise_known, prior_std_vector, resolve_free
from .kalman import process_noise
from .robust import kernel_threshold

__all__ = ["calibrate_gtsam", "calibrate_isam2", "calibrate_timevarying", "robust_noise", "rpy_rate_matrix"]


def _gtsam():
    try:
        import gtsam
    except ImportError as exc:  # pragma: no cover - gtsam is a declared dependency
        raise ImportError("the factor-graph estimators need gtsam (pip install gtsam)") from exc
    return gtsam


def robust_noise(dim: int, kernel: str | None = None, k: float | None = None):
    """Unit noise model of dimension ``dim``, optionally robust (``huber`` k=1.345, ``cauchy`` k=2.385).

    The residuals are already whitened, so the kernel threshold ``k`` is in units of σ; the kernel
    weighs the norm of the factor's ``dim`` rows, so the scalar threshold is carried to ``dim``
    dimensions at the same inlier probability (:func:`estcal.estimate.robust.kernel_threshold`).
    """
    gtsam = _gtsam()
    base = gtsam.noiseModel.Unit.Create(dim)
    if kernel is None or kernel in ("none", "l2", "gaussian"):
        return base
    kernel = kernel.lower()
    if kernel == "huber":
        m = gtsam.noiseModel.mEstimator.Huber.Create(kernel_threshold("huber", dim, k))
    elif kernel == "cauchy":
        m = gtsam.noiseModel.mEstimator.Cauchy.Create(kernel_threshold("cauchy", dim, k))
    else:
        raise ValueError(f"unknown robust kernel {kernel!r}; choose 'huber', 'cauchy' or none")
    return gtsam.noiseModel.Robust.Create(m, base)


class _Timer:
    def __init__(self):
        self.t = 0.0
        self.calls = 0
        self.evals = 0


class _Block:
    """Rows of a set of groups at a given free-parameter vector, cached on the vector's bytes."""

    def __init__(self, gp: GroupedProblem, ids, theta, fidx, timer: _Timer):
        self.sub, self.row_group = _sub_with_rows(gp, ids)
        self.theta = theta
        self.fidx = fidx
        self.timer = timer
        self._key = None
        self._rows = None
        self.slices = {g: np.flatnonzero(self.row_group == g) for g in ids}

    def rows(self, x):
        k = x.tobytes()
        if k != self._key:
            th = self.theta.copy()
            th[self.fidx] = x
            r = self.sub.evaluate(th)
            self._rows = (-r.e / r.sigma, r.H[:, self.fidx] / r.sigma[:, None])
            self._key = k
            self.timer.evals += 1
        return self._rows


def _sub_with_rows(gp: GroupedProblem, ids):
    """Sub-problem of groups ``ids`` and the group id of each of its rows."""
    return gp.subproblem_rows(list(ids))


def _measurement_factor(block: _Block, g: int, keys, parts, x_template, noise):
    """CustomFactor on ``keys``; ``parts[i]`` = positions in the free vector of key i's entries."""
    gtsam = _gtsam()
    sl = block.slices[g] if np.isscalar(g) else np.concatenate([block.slices[i] for i in g])
    timer = block.timer

    def error(this, values, jac):
        t = time.perf_counter()
        x = x_template.copy()
        for key, part in zip(keys, parts):
            x[part] = values.atVector(key)
        r, A = block.rows(x)
        if jac is not None:
            for i, part in enumerate(parts):
                jac[i] = A[sl][:, part]
        timer.t += time.perf_counter() - t
        timer.calls += 1
        return r[sl]

    return gtsam.CustomFactor(noise, list(keys), error)


_SIX = ("tx", "ty", "tz", "rx", "ry", "rz")


def rpy_rate_matrix(rpy) -> np.ndarray:
    """N(rpy): angular velocity in the parent frame = N · d(rpy)/dt for R = Rz(y) Ry(p) Rx(r).

    Columns: roll axis Rz Ry x̂, pitch axis Rz ŷ, yaw axis ẑ. Singular at pitch = ±90°.
    """
    r, p, y = rpy
    Rz = rot_z(y)
    return np.column_stack([Rz @ rot_y(p) @ np.array([1.0, 0, 0]), Rz @ np.array([0, 1.0, 0]), np.array([0, 0, 1.0])])


def _pose3_param_map(R, rpy):
    """G = ∂(t, rpy)/∂ξ for the retraction T·Exp(ξ), ξ = (ω, v) in gtsam's order: dt = R v, d(rpy) = N⁻¹ R ω."""
    N = rpy_rate_matrix(rpy)
    if abs(np.linalg.det(N)) < 1e-9:
        raise ValueError("frame at pitch ±90° (gimbal lock of the rpy parameters): use the vector form "
                         "(base_pose3/tool_pose3 = False)")
    G = np.zeros((6, 6))
    G[:3, 3:] = R
    G[3:, :3] = np.linalg.solve(N, R)
    return G


class _PoseLayout:
    """Free-vector positions of the 6 parameters of the frames held as Pose3 variables."""

    def __init__(self, names, frames):
        self.frames = list(frames)
        self.pos6 = {}
        for f in self.frames:
            want = [f"{f}_{c}" for c in _SIX]
            miss = [w for w in want if w not in names]
            if miss:
                raise ValueError(f"{f}_pose3 needs all six {f} parameters free; missing {miss}")
            self.pos6[f] = np.array([names.index(w) for w in want])
        used = np.concatenate([self.pos6[f] for f in self.frames]) if self.frames else np.zeros(0, int)
        self.vec = np.setdiff1d(np.arange(len(names)), used)

    def pose_of(self, x, f):
        gtsam = _gtsam()
        p6 = x[self.pos6[f]]
        return gtsam.Pose3(gtsam.Rot3(rpy_to_matrix(p6[3:])), gtsam.Point3(*p6[:3]))

    def write(self, x, f, pose):
        x[self.pos6[f][:3]] = np.asarray(pose.translation())
        x[self.pos6[f][3:]] = matrix_to_rpy(pose.rotation().matrix())


def _pose_factor(block, g, xkey, vec, layout, pkeys, x_template, noise):
    """Measurement factor on the vector variable and the Pose3 frame variables."""
    gtsam = _gtsam()
    sl = block.slices[g]
    timer = block.timer

    def error(this, values, jac):
        t = time.perf_counter()
        x = x_template.copy()
        if vec.size:
            x[vec] = values.atVector(xkey)
        poses = {}
        for f, k in zip(layout.frames, pkeys):
            poses[f] = values.atPose3(k)
            layout.write(x, f, poses[f])
        r, A = block.rows(x)
        if jac is not None:
            Ag = A[sl]
            i = 0
            if vec.size:
                jac[0] = Ag[:, vec]
                i = 1
            for j, f in enumerate(layout.frames):
                G = _pose3_param_map(poses[f].rotation().matrix(), x[layout.pos6[f][3:]])
                jac[i + j] = Ag[:, layout.pos6[f]] @ G
        timer.t += time.perf_counter() - t
        timer.calls += 1
        return r[sl]

    keys = ([xkey] if vec.size else []) + list(pkeys)
    return gtsam.CustomFactor(noise, keys, error)


#: The convergence test of the factor-graph estimators: the Gauss–Newton step at the returned
#: estimate, in units of the estimate's own marginal standard deviations, is at most this. A
#: converged estimate is then within this many σ of the (local) minimum of its graph.
CONVERGED_STEP_SIGMA = 1e-3


def _step_sigma(linear_graph) -> float:
    """``max_j |δ_j| / σ_j`` of the Gauss–Newton step δ of a Gaussian factor graph, σ its marginal
    standard deviations (tangent coordinates for Pose3 variables), over all its variables;
    ``inf`` for an indeterminate system (not a converged minimum)."""
    gtsam = _gtsam()
    try:
        delta = linear_graph.optimize()
        marg = gtsam.Marginals(linear_graph, delta)
        worst = 0.0
        for key in linear_graph.keyVector():
            sd = np.sqrt(np.maximum(np.diag(np.asarray(marg.marginalCovariance(key))), 1e-300))
            worst = max(worst, float(np.max(np.abs(np.asarray(delta.at(key))) / sd)))
    except RuntimeError:
        return float("inf")
    return worst


def _stationary_step(graph, values) -> float:
    """The Gauss–Newton step (:func:`_step_sigma`) of the nonlinear ``graph`` linearised at ``values``
    (robust kernels included, as their iteratively reweighted linearisation) — the convergence
    test behind ``converged`` (``≤`` :data:`CONVERGED_STEP_SIGMA`), taken after the optimiser
    stopped (an optimiser can also stop on its iteration limit, its damping bound, or — iSAM2 —
    simply because the stream ended)."""
    try:
        linear = graph.linearize(values)
    except RuntimeError:
        return float("inf")
    return _step_sigma(linear)


def _fit_statistics(problem, theta, fidx, x):
    """The full parameter vector with the free values ``x``, its χ² and dof = M − p."""
    theta_full = theta.copy()
    theta_full[fidx] = x
    chi2, m = chi2_and_rows(problem, theta_full)  # chunk by chunk on large data
    return theta_full, chi2, m - len(fidx)


def _prior_std(problem, names, prior_std):
    if isinstance(prior_std, str) and prior_std == "default":
        prior_std = None
    return prior_std_vector(problem, names, prior_std)


def _check(problem, fidx, names, theta):

    ck = use_chunks(problem)  # large data: R has A's rank and conditioning
    A = reduce_system(problem, theta, fidx, ck)[0] if ck is not None else weighted(problem.evaluate(theta), fidx)[0]
    check_identifiable(A, names)


def _latent_factor(sub, theta, fidx, robot, xkey, qkey, noise, timer):
    """Errors-in-variables factor: measurement of one pose as a function of (θ, joint readings)."""
    gtsam = _gtsam()
    term = sub.terms[0]
    data0 = term.data
    off = robot.offset_idx
    gi = robot.gain_idx

    def error(this, values, jac):
        t = time.perf_counter()
        x = values.atVector(xkey)
        r = np.asarray(values.atVector(qkey), float)
        th = theta.copy()
        th[fidx] = x
        d = data0.subset(slice(None))
        d.readings = r[None, :]
        rows = term.method.rows(robot, th, d, term.noise, jacobian=jac is not None)
        err = -rows.e / rows.sigma
        if jac is not None:
            Hs = rows.H / rows.sigma[:, None]
            K = th[gi]
            if robot.coupling is None:
                D = np.diag(K)
            else:
                Cj, Cm = (np.asarray(c, float) for c in robot.coupling)
                D = Cj @ np.diag(K) @ Cm
            jac[0] = Hs[:, fidx]
            jac[1] = Hs[:, off] @ D  # ∂pred/∂reading = ∂pred/∂q · ∂q/∂reading (offset column = ∂/∂q)
        timer.t += time.perf_counter() - t
        timer.calls += 1
        timer.evals += 1
        return err

    return gtsam.CustomFactor(noise, [xkey, qkey], error)


def calibrate_gtsam(problem, free=None, validation=(), *, optimizer: str = "lm", robust: str | None = None,
                    robust_k: float | None = None, prior_std=None, use_prior: bool = False, theta0=None,
                    max_iter: int = 100, latent_joints: bool = False, encoder_std=None, check: bool = True,
                    marginals: bool = True, base_pose3: bool = False, tool_pose3: bool = False,
                    base_prior=None, poses_per_factor: int = 1, linear: bool | None = None, **_ignored):
    """Batch factor-graph calibration (gtsam LM or Dogleg) with marginal covariances.

    Parameters
    ----------
    problem : :class:`~estcal.methods.problem.Problem`
    free : free parameter names/patterns (default: the problem's free mask)
    optimizer : ``"lm"`` (LevenbergMarquardtOptimizer) or ``"dogleg"`` (DoglegOptimizer)
    robust : ``None``, ``"huber"`` or ``"cauchy"`` (threshold ``robust_k`` in σ units)
    prior_std / use_prior : Gaussian prior on the free parameters around their initial
        values (added when ``use_prior`` or ``prior_std`` is given)
    latent_joints : errors-in-variables — one latent reading vector per pose with an
        encoder prior of std ``encoder_std`` (rad or m per joint; default 1e-4)
    marginals : covariance from :class:`gtsam.Marginals` (of the free-parameter variable)
    base_pose3 / tool_pose3 : hold the base (world → frame 0) / tool frame as a ``gtsam.Pose3``
        variable instead of its six ``tx…rz`` entries of the vector (all six must be free); the
        factor Jacobian w.r.t. the Pose3 tangent ξ = (ω, v) is ``H_(t,rpy) · ∂(t, rpy)/∂ξ``
        (:func:`_pose3_param_map`), and the reported covariance is mapped back to the parameters
    poses_per_factor : measurement groups per CustomFactor (1 = one factor per pose, what robust
        kernels need; larger values cut the Python-callback overhead, see the module docstring)
    base_prior : ``(T_world_base (4, 4), sigmas (6,) in gtsam order ω then v)`` — a
        ``PriorFactorPose3`` on the base (e.g. from a registration); needs ``base_pose3``
    linear : solve each Levenberg–Marquardt step as a gtsam *Gaussian* factor graph built
        from one vectorised evaluation of the analytic Jacobian (no Python callback inside
        gtsam: :func:`_levenberg_marquardt_linear`). Default: on whenever the graph is the
        plain one (no robust kernel, latent joints or Pose3 frames, optimizer ``lm``); the
        nonlinear ``CustomFactor`` graph stays for those and for iSAM2.

    Returns
    -------
    CalibrationResult (``method="gtsam"``); ``extra`` holds the optimiser, kernel,
    final graph error, and Python-callback timing; with latent joints the estimated
    readings' corrections in ``extra["latent_readings_correction"]``.
    """
    gtsam = _gtsam()
    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    if check:
        with single_thread_blas():  # a QR of a tall thin matrix: BLAS threads only spin
            _check(problem, fidx, names, theta)
    plain = robust is None and not latent_joints and not base_pose3 and not tool_pose3 and optimizer == "lm"
    if linear is None:  # asking for grouped CustomFactors means asking for the nonlinear graph
        linear = plain and poses_per_factor == 1
    prior = (nominal.copy(), _prior_std(problem, names, prior_std)) if (use_prior or prior_std is not None) else None
    if linear:
        if not plain:
            raise ValueError("linear=True needs the plain graph: no robust kernel, latent joints or Pose3 frames, "
                             "optimizer 'lm'")
        return _gtsam_linear(problem, fidx, names, theta, nominal, max_iter, prior, marginals, validation, t0)
    g = _Graph(gtsam, GroupedProblem(problem), _Timer(), nominal, theta, fidx, names)
    if latent_joints:
        g.add_latent_joints(encoder_std, robust, robust_k)
    elif base_pose3 or tool_pose3:
        g.add_pose3_frames(base_pose3, tool_pose3, base_prior, robust, robust_k)
    else:
        g.add_measurements(poses_per_factor, robust, robust_k)
    if prior is not None:
        g.graph.add(gtsam.PriorFactorVector(g.X, prior[0], gtsam.noiseModel.Diagonal.Sigmas(prior[1])))
    result, n_iter, solve_s = _optimise(gtsam, g.graph, g.init, optimizer, max_iter)
    x = g.solution(result)
    t_m = time.perf_counter()
    cov = g.marginal_covariance(result, x) if marginals else np.full((len(fidx), len(fidx)), np.nan)
    marg_s = time.perf_counter() - t_m if marginals else 0.0
    theta_full, chi2, dof = _fit_statistics(problem, theta, fidx, x)
    src = "gtsam marginals"
    if not noise_known(problem) and dof > 0 and robust is None:
        cov = cov * (chi2 / dof)
        src = "gtsam marginals scaled by sigma0^2"
    step = _stationary_step(g.graph, result)
    extra = {"optimizer": optimizer, "robust": robust or "none", "graph_error": float(g.graph.error(result)),
             "final_step_sigma": step,
             "pose3_frames": [f for f, on in (("base", base_pose3), ("tool", tool_pose3)) if on],
             "n_factors": int(g.graph.size()), "solve_time_s": solve_s, "marginals_time_s": marg_s,
             "python_factor_time_s": g.timer.t, "python_factor_calls": g.timer.calls,
             "kinematics_evaluations": g.timer.evals,
             "python_factor_fraction": g.timer.t / max(solve_s + marg_s, 1e-12)}
    if latent_joints:
        extra["latent_readings_correction"] = np.array([np.asarray(result.atVector(k)) - r0 for k, r0 in g.qkeys])
        extra["encoder_std"] = g.encoder_std
    return finish_result(problem, "gtsam", names, fidx, x, cov, theta_full, nominal, n_iterations=n_iter,
                         converged=n_iter < max_iter and step <= CONVERGED_STEP_SIGMA, covariance_source=src,
                         theta_before=theta, validation=validation, t0=t0, extra=extra)


def _gtsam_linear(problem, fidx, names, theta, nominal, max_iter, prior, marginals, validation, t0):
    """The plain graph solved step by step as gtsam Gaussian factor graphs (:func:`_levenberg_marquardt_linear`)."""
    with single_thread_blas():  # tall thin matrices: BLAS threads only spin (see single_thread_blas)
        x, cov, n_iter, info = _levenberg_marquardt_linear(problem, fidx, theta, nominal, max_iter, prior, marginals)
    theta_full, chi2, dof = _fit_statistics(problem, theta, fidx, x)
    src = "gtsam marginals (Gaussian factor graph)"
    if not noise_known(problem) and dof > 0:
        cov = cov * (chi2 / dof)
        src += " scaled by sigma0^2"
    extra = {"optimizer": "lm (Gaussian factor graph per step)", "robust": "none", **info,
             "python_factor_time_s": 0.0, "python_factor_fraction": 0.0}
    return finish_result(problem, "gtsam", names, fidx, x, cov, theta_full, nominal, n_iterations=n_iter,
                         converged=info["converged"], covariance_source=src, theta_before=theta,
                         validation=validation, t0=t0, extra=extra)


class _Graph:
    """The nonlinear factor graph of :func:`calibrate_gtsam`: the free-parameter vector ``X`` and,
    depending on the options, latent joint readings or Pose3 base / tool frames."""

    def __init__(self, gtsam, gp, timer, nominal, theta, fidx, names):
        self.gtsam, self.gp, self.timer = gtsam, gp, timer
        self.nominal, self.theta, self.fidx, self.names = nominal, theta, fidx, names
        self.X = gtsam.symbol("x", 0)
        self.graph = gtsam.NonlinearFactorGraph()
        self.init = gtsam.Values()
        self.init.insert(self.X, nominal.copy())
        self.layout, self.pkeys, self.qkeys, self.encoder_std = None, [], [], None

    def add_latent_joints(self, encoder_std, robust, robust_k):
        """Errors-in-variables: one latent reading vector per pose with an encoder prior."""
        gtsam, gp = self.gtsam, self.gp
        if not gp.splittable:
            raise ValueError("latent joints need a Problem whose terms have datasets")
        if any(g.poses.size > 1 for g in gp.groups):
            raise ValueError("latent joints are implemented for per-pose methods (position, location, points, "
                             "planes); link and distance methods compare several rows per factor")
        robot = gp.problem.robot
        es = np.broadcast_to(np.asarray(1e-4 if encoder_std is None else encoder_std, float), (robot.n_joints,))
        self.encoder_std = es
        enc_noise = gtsam.noiseModel.Diagonal.Sigmas(es.copy())
        for gi in range(len(gp.groups)):
            sub = gp.subproblem([gi])
            r0 = sub.terms[0].data.readings[0].astype(float)
            qk = gtsam.symbol("q", gi)
            self.qkeys.append((qk, r0))
            self.init.insert(qk, r0.copy())
            self.graph.add(gtsam.PriorFactorVector(qk, r0.copy(), enc_noise))
            m = len(sub.evaluate(self.theta, jacobian=False).e)
            self.graph.add(_latent_factor(sub, self.theta, self.fidx, robot, self.X, qk,
                                          robust_noise(m, robust, robust_k), self.timer))

    def add_pose3_frames(self, base_pose3, tool_pose3, base_prior, robust, robust_k):
        """The base and/or tool frame as Pose3 variables (their six entries leave ``X``)."""
        gtsam, gp, nominal = self.gtsam, self.gp, self.nominal
        layout = _PoseLayout(self.names, [f for f, on in (("base", base_pose3), ("tool", tool_pose3)) if on])
        self.layout = layout
        self.init.erase(self.X)
        if layout.vec.size:
            self.init.insert(self.X, nominal[layout.vec].copy())
        self.pkeys = [gtsam.symbol(f[0], 0) for f in layout.frames]
        for f, k in zip(layout.frames, self.pkeys):
            self.init.insert(k, layout.pose_of(nominal, f))
        block = _Block(gp, range(len(gp)), self.theta, self.fidx, self.timer)
        for g in range(len(gp)):
            m = block.slices[g].size
            self.graph.add(_pose_factor(block, g, self.X, layout.vec, layout, self.pkeys, nominal,
                                        robust_noise(m, robust, robust_k)))
        if base_prior is not None:
            if not base_pose3:
                raise ValueError("base_prior needs base_pose3=True")
            Tb, sb = base_prior
            Tb = np.asarray(Tb, float)
            self.graph.add(gtsam.PriorFactorPose3(self.pkeys[0],
                                                  gtsam.Pose3(gtsam.Rot3(Tb[:3, :3]), gtsam.Point3(*Tb[:3, 3])),
                                                  gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sb, float))))

    def add_measurements(self, poses_per_factor, robust, robust_k):
        """One CustomFactor per ``poses_per_factor`` measurement groups on ``X``."""
        gp = self.gp
        block = _Block(gp, range(len(gp)), self.theta, self.fidx, self.timer)
        allpos = np.arange(len(self.fidx))
        for start in range(0, len(gp), poses_per_factor):
            gs = list(range(start, min(start + poses_per_factor, len(gp))))
            m = sum(block.slices[g].size for g in gs)
            self.graph.add(_measurement_factor(block, gs, [self.X], [allpos], self.nominal,
                                               robust_noise(m, robust, robust_k)))

    def solution(self, result) -> np.ndarray:
        """The free parameters at the optimum (Pose3 frames written back as their six entries)."""
        if self.layout is None:
            return np.asarray(result.atVector(self.X), float)
        x = self.nominal.copy()
        if self.layout.vec.size:
            x[self.layout.vec] = np.asarray(result.atVector(self.X), float)
        for f, k in zip(self.layout.frames, self.pkeys):
            self.layout.write(x, f, result.atPose3(k))
        return x

    def marginal_covariance(self, result, x) -> np.ndarray:
        """Covariance of the free parameters from :class:`gtsam.Marginals`; with Pose3 frames the joint
        marginal of (X, pose keys) in tangent coordinates, mapped to the parameters."""
        mg = self.gtsam.Marginals(self.graph, result)
        layout = self.layout
        if layout is None:
            return np.asarray(mg.marginalCovariance(self.X))
        keys = ([self.X] if layout.vec.size else []) + self.pkeys
        jm = mg.jointMarginalCovariance(self.gtsam.KeyVector(keys))
        blocks = ([layout.vec] if layout.vec.size else []) + [layout.pos6[f] for f in layout.frames]
        maps = ([np.eye(layout.vec.size)] if layout.vec.size else []) + [
            _pose3_param_map(result.atPose3(k).rotation().matrix(), x[layout.pos6[f][3:]])
            for f, k in zip(layout.frames, self.pkeys)]
        p = len(self.fidx)
        cov = np.zeros((p, p))
        for ka, ia, Ga in zip(keys, blocks, maps):
            for kb, ib, Gb in zip(keys, blocks, maps):
                cov[np.ix_(ia, ib)] = Ga @ np.asarray(jm.at(ka, kb)) @ Gb.T
        return cov


def _optimise(gtsam, graph, init, optimizer: str, max_iter: int):
    """``(values, iterations, seconds)`` of gtsam's Levenberg–Marquardt or Dogleg on ``graph``."""
    if optimizer == "lm":
        params = gtsam.LevenbergMarquardtParams()
        params.setDiagonalDamping(True)
        params.setlambdaInitial(1e-3)
    elif optimizer == "dogleg":
        params = gtsam.DoglegParams()
    else:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose 'lm' or 'dogleg'")
    params.setMaxIterations(max_iter)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-14)
    t_opt = time.perf_counter()
    opt = (gtsam.LevenbergMarquardtOptimizer if optimizer == "lm" else gtsam.DoglegOptimizer)(graph, init, params)
    result = opt.optimize()
    return result, int(opt.iterations()), time.perf_counter() - t_opt


def _levenberg_marquardt_linear(problem, fidx, theta, x0, max_iter, prior=None, marginals=True,
                                rtol: float = 1e-15):
    """Levenberg–Marquardt where every step is a gtsam Gaussian factor graph.

    At each iterate the whole problem is evaluated once (vectorised FK and analytic
    Jacobian over all poses) and handed to gtsam as linear factors on the free-parameter
    variable: the whitened measurement block with
    ``A = H/σ``, ``b = e/σ`` (e = measured − predicted) — handed over as one
    ``HessianFactor(x, AᵀA, Aᵀb, bᵀb)`` —, the optional prior
    ``JacobianFactor(x, diag(1/s), (x_prior − x)/s)`` and the damping
    ``JacobianFactor(x, √λ · diag(‖A_j‖), 0)`` (Marquardt's diagonal scaling). gtsam
    eliminates the graph (multifrontal QR/Cholesky) and returns the step; the step is
    accepted when the cost decreases (λ ÷ 10), else λ × 10 (Madsen, Nielsen & Tingleff,
    *Methods for non-linear least squares problems*, 2004, §3.2). The covariance is
    ``gtsam.Marginals`` of the undamped graph at the solution. Returns
    ``(x, cov, iterations, info)``.

    On large per-pose data (:func:`estcal.methods.reduced.use_chunks`) the block is built from
    the triangular factor ``[R c]`` of ``[A b]`` instead (``RᵀR = AᵀA``, ``Rᵀc = Aᵀb``; the
    constant is the true ``bᵀb``), chunk by chunk: the same graph in O(chunk · p) memory.
    """

    gtsam = _gtsam()
    ck = use_chunks(problem)
    system = DenseSystem(problem, fidx) if ck is None else ReducedSystem(problem, fidx, ck)
    X = gtsam.symbol("x", 0)
    th = theta.copy()
    p = len(fidx)
    t_lin = [0.0]

    def linearise(x, jacobian=True):
        """``(A, b, bᵀb)`` at x (``(R, c, bᵀb)`` on large data; ``A``, ``b`` None without Jacobian)."""
        t = time.perf_counter()
        th[fidx] = x
        out = system.linear(th) if jacobian else (None, None, system.cost(th, jacobian=False))
        t_lin[0] += time.perf_counter() - t
        return out

    def cost(x, f):
        c = float(f)
        if prior is not None:
            c += float(np.sum(((x - prior[0]) / prior[1]) ** 2))
        return c

    def graph(x, G, g, f, damping=None):
        # the measurement block as one HessianFactor (AᵀA, Aᵀb, bᵀb): the p × p information
        # of every pose at once — gtsam's linear algebra then costs O(p³) per step, not O(M p²)
        fg = gtsam.GaussianFactorGraph()
        fg.add(gtsam.HessianFactor(X, G, g, f))
        if prior is not None:
            fg.add(gtsam.JacobianFactor(X, np.diag(1.0 / prior[1]), (prior[0] - x) / prior[1],
                                        gtsam.noiseModel.Unit.Create(p)))
        if damping is not None:
            fg.add(gtsam.JacobianFactor(X, np.diag(damping), np.zeros(p), gtsam.noiseModel.Unit.Create(p)))
        return fg

    t_solve = 0.0
    x = np.asarray(x0, float).copy()
    A, b, f = linearise(x)
    c = cost(x, f)
    lam = 1e-3
    it, converged = 0, False
    for it in range(1, max_iter + 1):
        G, gv = A.T @ A, A.T @ b
        scale = np.sqrt(np.maximum(np.diag(G), 1e-300))
        # the parameters' standard deviations at this linearisation (data only), to measure steps in σ
        try:
            sd = np.sqrt(np.maximum(np.diag(np.linalg.inv(G)), 1e-300))
        except np.linalg.LinAlgError:
            sd = 1.0 / scale
        accepted = False
        while True:
            t = time.perf_counter()
            dx = np.asarray(graph(x, G, gv, f, np.sqrt(lam) * scale).optimize().at(X))
            t_solve += time.perf_counter() - t
            step = float(np.max(np.abs(dx) / sd))
            if step < 1e-9:  # the minimum to well below the estimate's uncertainty
                converged = True
                break
            xn = x + dx
            cn = cost(xn, linearise(xn, jacobian=False)[2])  # trial: residuals only
            if cn <= c:
                accepted = True
                break
            if step < 1e-6 or lam > 1e12:  # no decrease possible: at the minimum to working precision
                converged = True
                break
            lam *= 10.0
        if not accepted:
            break
        small = step < 1e-8 or c - cn <= rtol * max(c, 1e-300)
        x, c = xn, cn
        A, b, f = linearise(x)
        lam = max(lam / 10.0, 1e-12)
        if small:
            converged = True
            break
    # one undamped Gauss–Newton step to finish: the damped steps stop short of the minimum by
    # about λ times their length; near the minimum Gauss–Newton converges quadratically
    G, gv = A.T @ A, A.T @ b
    dx = np.asarray(graph(x, G, gv, f).optimize().at(X))
    cn = cost(x + dx, linearise(x + dx, jacobian=False)[2])
    if cn <= c * (1.0 + 1e-12):
        x, c = x + dx, cn
        A, b, f = linearise(x)
    cov = np.full((p, p), np.nan)
    t_m = time.perf_counter()
    if marginals:
        fg = graph(x, A.T @ A, A.T @ b, f)
        cov = np.asarray(gtsam.Marginals(fg, fg.optimize()).marginalCovariance(X))
    info = {"converged": converged, "linearise_time_s": t_lin[0], "solve_time_s": t_solve,
            "marginals_time_s": time.perf_counter() - t_m, "final_lambda": lam, "n_factors": 1 + (prior is not None)}
    return x, cov, it, info


def calibrate_isam2(problem, free=None, validation=(), *, prior_std=None, theta0=None, batch_size: int = 1,
                    relinearize_threshold: float = 1e-9, robust: str | None = None, robust_k: float | None = None,
                    history: bool = False, linear: bool | None = None, relinearize_sigma: float = 1.0,
                    final_sigma: float = 1e-6, final_updates: int = 50, **_ignored):
    """Incremental calibration with gtsam's iSAM2: measurement groups added as they arrive.

    A Gaussian prior (default :func:`default_prior_std`, wide) makes the problem
    well posed before enough poses have arrived. After each update the current
    estimate and marginal covariance are available (``history=True`` keeps their
    trajectory and the per-update time in ``extra``).

    linear : (default: on without a robust kernel) the measurements enter iSAM2 as *linear*
        factors, no Python callback inside gtsam (:func:`_isam2_linear`): each new group is
        linearised once, with the vectorised analytic Jacobian, at the current reference
        point, and the information of all groups so far is one
        ``gtsam.LinearContainerFactor(HessianFactor)`` that each update replaces — the cost of
        an update does not grow with the number of poses. When the estimate has moved more
        than ``relinearize_sigma`` marginal standard deviations from the reference point, the
        groups so far are re-linearised in one vectorised evaluation (Levenberg–Marquardt from
        the reference point when that step did not lower the cost); at the end of the stream
        this is repeated until the move is below ``final_sigma`` σ, so the result is the batch
        minimum of prior + least squares. With the default 1 σ the intermediate estimates of a
        PUMA 560 full-pose stream stay within 1e-4 σ of the batch minimum of the poses so far
        (0.1 σ: 2e-8 σ, at about ten times the relinearisation work). ``linear=False`` (and any robust kernel) adds one
        nonlinear ``CustomFactor`` per group, relinearised by iSAM2 itself
        (``relinearize_threshold``, gtsam's per-variable delta threshold) with Powell's dogleg
        step (``gtsam.ISAM2DoglegParams``).
    final_sigma : end of the stream (linear containers): relinearise until the reference point
        moves less than this many σ.
    final_updates : at most this many end-of-stream relinearisations (containers) or empty
        ``ISAM2.update`` calls with forced relinearisation (CustomFactor graph).

    ``converged`` is the test at the returned estimate (:func:`_step_sigma`): the prior and every
    measurement linearised there, the Gauss–Newton step is at most :data:`CONVERGED_STEP_SIGMA`
    of its marginal σ; ``extra["final_step_sigma"]`` is that step. The end of the stream is not
    convergence: a stream that could not finish (e.g. ``relinearize_threshold`` too high, or
    ``final_sigma`` too loose) reports ``converged=False``.
    """
    gtsam = _gtsam()
    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    gp = GroupedProblem(problem)
    if linear is None:
        linear = robust is None
    if linear:
        if robust is not None:
            raise ValueError("linear=True cannot take a robust kernel: use linear=False (CustomFactor graph)")
        s = _prior_std(problem, names, prior_std)
        x, cov, times, hist, info = _isam2_linear(gp, theta, fidx, nominal, s, batch_size, relinearize_sigma,
                                                  final_sigma, history, final_updates)
        theta_full, chi2, dof = _fit_statistics(problem, theta, fidx, x)
        src = "iSAM2 marginal (linear containers)"
        if not noise_known(problem) and dof > 0:
            cov = cov * (chi2 / dof)
            src += " scaled by sigma0^2"
        extra = {"n_updates": len(times), "update_time_s": np.array(times),
                 "mean_update_time_s": float(np.mean(times)), "python_factor_time_s": 0.0, "prior_std": s, **info}
        if history:
            extra["history"] = {"estimate": np.array(hist[0]), "std": np.array(hist[1])}
        return finish_result(problem, "isam2", names, fidx, x, cov, theta_full, nominal, n_iterations=len(times),
                             converged=info["converged"], covariance_source=src, theta_before=theta,
                             validation=validation, t0=t0, extra=extra)
    timer = _Timer()
    X = gtsam.symbol("x", 0)
    p = len(fidx)
    block = _Block(gp, range(len(gp)), theta, fidx, timer)
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = 1
    # Powell's dogleg instead of a plain Gauss–Newton step per update (gtsam's ISAM2DoglegParams:
    # the incremental trust region of Rosen, Kaess & Leonard, RISE, IEEE T-RO 2014): while few
    # poses have arrived the linearisation is poor far from it, and undamped steps wander by
    # whole turns of the angles (TALOS: to 2π-equivalent minima hundreds of σ from LM's)
    params.setOptimizationParams(gtsam.ISAM2DoglegParams())
    isam = gtsam.ISAM2(params)
    s = _prior_std(problem, names, prior_std)
    first = gtsam.NonlinearFactorGraph()
    first.add(gtsam.PriorFactorVector(X, nominal.copy(), gtsam.noiseModel.Diagonal.Sigmas(s)))
    init = gtsam.Values()
    init.insert(X, nominal.copy())
    pending = first
    times, cpu, hist_x, hist_s = [], [], [], []
    allpos = np.arange(p)
    for start in range(0, len(gp), batch_size):
        g = pending if start == 0 else gtsam.NonlinearFactorGraph()
        for gi in range(start, min(start + batch_size, len(gp))):
            m = block.slices[gi].size
            g.add(_measurement_factor(block, gi, [X], [allpos], nominal, robust_noise(m, robust, robust_k)))
        tu, cu = time.perf_counter(), time.process_time()
        isam.update(g, init if start == 0 else gtsam.Values())
        times.append(time.perf_counter() - tu)
        cpu.append(time.process_time() - cu)
        if history:
            est = isam.calculateEstimate()
            hist_x.append(np.asarray(est.atVector(X)))
            hist_s.append(np.sqrt(np.diag(isam.marginalCovariance(X))))
    est, step, n_final = _finish_isam2(isam, final_updates)
    converged = step <= CONVERGED_STEP_SIGMA
    x = np.asarray(est.atVector(X), float)
    cov = np.asarray(isam.marginalCovariance(X))
    theta_full, chi2, dof = _fit_statistics(problem, theta, fidx, x)
    src = "iSAM2 marginal"
    if not noise_known(problem) and dof > 0:
        cov = cov * (chi2 / dof)
        src = "iSAM2 marginal scaled by sigma0^2"
    extra = {"n_updates": len(times), "update_time_s": np.array(times), "mean_update_time_s": float(np.mean(times)),
             "python_factor_time_s": timer.t, "kinematics_evaluations": timer.evals, "prior_std": s,
             "update_cpu_s": np.array(cpu), "final_step_sigma": step, "final_updates": n_final}
    if history:
        extra["history"] = {"estimate": np.array(hist_x), "std": np.array(hist_s)}
    return finish_result(problem, "isam2", names, fidx, x, cov, theta_full, nominal, n_iterations=len(times),
                         converged=converged, covariance_source=src, theta_before=theta, validation=validation, t0=t0,
                         extra=extra)


def _finish_isam2(isam, max_updates: int):
    """End of the stream: iSAM2 takes one step per update, so the last estimate is not yet the
    minimum of the whole graph; empty updates with forced relinearisation (Kaess et al., iSAM2,
    IJRR 31(2), 2012, Alg. 6: relinearise the variables whose δ exceeds the threshold,
    re-eliminate, solve) continue, at most ``max_updates``, until the convergence test passes at
    the estimate. Returns ``(estimate, Gauss–Newton step in σ, updates taken)``."""
    gtsam = _gtsam()
    est = isam.calculateEstimate()
    step = _stationary_step(isam.getFactorsUnsafe(), est)
    n = 0
    while step > CONVERGED_STEP_SIGMA and n < max_updates:
        isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), force_relinearize=True)
        est = isam.calculateEstimate()
        step = _stationary_step(isam.getFactorsUnsafe(), est)
        n += 1
    return est, step, n


def _isam2_linear(gp: GroupedProblem, theta, fidx, nominal, prior_s, batch_size, relin_sigma, final_sigma, history,
                  final_updates=50):
    """iSAM2 over linear factors: the streaming counterpart of :func:`_levenberg_marquardt_linear`.

    The free parameters are one variable ``x`` that every measurement touches, so the Bayes
    tree is a single clique and iSAM2 re-eliminates, at every update, all factors on ``x``:
    with one factor per pose an update costs O(k) (and O(k) Python callbacks when the factors
    are ``CustomFactor``). Information adds: the Gauss–Newton model of groups 1…k at a
    reference point ``x_r`` is the one quadratic ``‖A δ − b‖² = δᵀGδ − 2δᵀg + f`` with
    ``G = Σ AᵢᵀAᵢ``, ``g = Σ Aᵢᵀbᵢ``, ``f = Σ bᵢᵀbᵢ`` (Dellaert & Kaess, *Factor graphs for
    robot perception*, 2017, §3), so the graph holds the prior and one
    ``LinearContainerFactor(HessianFactor(x, G, g, f), {x: x_r})``, replaced (factor removal
    in ``ISAM2.update``) when a group arrives: O(m p²) to linearise the new group and O(p³)
    to eliminate, whatever k. The model is exact only at ``x_r``; as in iSAM2's fluid
    relinearisation (Kaess et al., *iSAM2*, IJRR 31(2), 2012, §5) the reference point moves
    to the estimate when ``max_j |x_j − x_r,j| / σ_j > relin_sigma`` and the groups so far are
    re-linearised there in one vectorised evaluation — amortised O(1): the move per pose
    shrinks like 1/k while σ shrinks like 1/√k. Returns ``(x, cov, update times, history, info)``.
    """
    gtsam = _gtsam()
    X = gtsam.symbol("x", 0)
    p = len(fidx)
    starts = list(range(0, len(gp), batch_size))
    # the data of each arriving batch (bookkeeping, outside the timed update, as in calibrate_kalman)
    subs = [gp.subproblem(list(range(a, min(a + batch_size, len(gp))))) for a in starts]
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.0)  # prior and containers are linear: relinearising them is C++ only
    params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    first = gtsam.NonlinearFactorGraph()
    first.add(gtsam.PriorFactorVector(X, nominal.copy(), gtsam.noiseModel.Diagonal.Sigmas(prior_s)))
    init = gtsam.Values()
    init.insert(X, nominal.copy())
    isam.update(first, init)
    th = theta.copy()
    st = {"x_ref": nominal.copy(), "G": np.zeros((p, p)), "g": np.zeros(p), "f": 0.0, "idx": None,
          "n_relin": 0, "relin_groups": 0, "relin_s": 0.0, "n_damped": 0}

    def information(sub, x):
        th[fidx] = x
        r = sub.evaluate(th)
        w = 1.0 / r.sigma
        A = r.H[:, fidx] * w[:, None]
        b = r.e * w
        return A.T @ A, A.T @ b, float(b @ b)

    def replace():
        lp = gtsam.Values()
        lp.insert(X, st["x_ref"])
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.LinearContainerFactor(gtsam.HessianFactor(X, st["G"], st["g"], st["f"]), lp))
        res = isam.update(graph, gtsam.Values(), [] if st["idx"] is None else [st["idx"]])
        st["idx"] = int(res.getNewFactorsIndices()[0])
        x = np.asarray(isam.calculateEstimate().atVector(X), float)
        return x, np.asarray(isam.marginalCovariance(X))

    def prior_cost(x):
        return float(np.sum(((x - nominal) / prior_s) ** 2))

    def relinearise(k, x):
        t = time.perf_counter()
        sub = gp.subproblem(list(range(k)))
        G, g, f = information(sub, x)
        # step acceptance (the trust-region safeguard of iSAM2 in Kaess et al. 2012, §5, and of
        # gtsam's ISAM2DoglegParams): the step from the reference point to x was predicted by the
        # model linearised at the reference point; when the true cost (prior + groups so far) did
        # not decrease, that model was not to be trusted so far out — Levenberg–Marquardt from the
        # reference point (gtsam Gaussian factor graphs, damped, monotone) takes its place
        if st["idx"] is not None and f + prior_cost(x) > st["f"] + prior_cost(st["x_ref"]):
            x = _levenberg_marquardt_linear(sub, fidx, theta, st["x_ref"], 100, (nominal, prior_s), False)[0]
            G, g, f = information(sub, x)
            st["n_damped"] += 1
        st["x_ref"] = x.copy()
        st["G"], st["g"], st["f"] = G, g, f
        st["n_relin"] += 1
        st["relin_groups"] += k
        out = replace()
        st["relin_s"] += time.perf_counter() - t
        return out

    def moved(x, cov):
        return float(np.max(np.abs(x - st["x_ref"]) / np.sqrt(np.maximum(np.diag(cov), 1e-300))))

    times, cpu, hx, hs = [], [], [], []
    x, cov = nominal.copy(), None
    for a, sub in zip(starts, subs):
        tu, cu = time.perf_counter(), time.process_time()
        Gi, gi, fi = information(sub, st["x_ref"])
        st["G"], st["g"], st["f"] = st["G"] + Gi, st["g"] + gi, st["f"] + fi
        x, cov = replace()
        if moved(x, cov) > relin_sigma:
            x, cov = relinearise(min(a + batch_size, len(gp)), x)
        times.append(time.perf_counter() - tu)
        cpu.append(time.process_time() - cu)
        if history:
            hx.append(x)
            hs.append(np.sqrt(np.diag(cov)))
    # end of the stream: Gauss–Newton on the whole model (steps accepted as above) until the
    # reference point is the minimum
    for _ in range(final_updates):
        if cov is not None and moved(x, cov) <= final_sigma:
            break
        x, cov = relinearise(len(gp), x)
    # the convergence test, at the returned estimate itself: every group and the prior linearised
    # at x, the Gauss–Newton step of that graph in its marginal σ (the loop above tests the move of
    # the reference point, which the step acceptance and the iteration limit can cut short)
    Gx, gx, fx = information(gp.problem, x)
    fg = gtsam.GaussianFactorGraph()
    fg.add(gtsam.HessianFactor(X, Gx, gx, fx))
    fg.add(gtsam.JacobianFactor(X, np.diag(1.0 / prior_s), (nominal - x) / prior_s, gtsam.noiseModel.Unit.Create(p)))
    step = _step_sigma(fg)
    info = {"converged": step <= CONVERGED_STEP_SIGMA, "final_step_sigma": step, "n_damped_relinearisations": st["n_damped"],
            "n_relinearisations": st["n_relin"],
            "relinearised_groups": st["relin_groups"], "relinearise_time_s": st["relin_s"],
            "relinearize_sigma": relin_sigma, "update_cpu_s": np.array(cpu)}
    return x, cov, times, (hx, hs), info


def calibrate_timevarying(problem, free=None, validation=(), *, q=0.0, batch_size: int = 10, prior_std=None,
                          theta0=None, max_iter: int = 100, robust: str | None = None,
                          robust_k: float | None = None, **_ignored):
    """Time-varying calibration: one parameter state per batch of poses, linked by process noise.

    Parameters whose process-noise std ``q`` (per batch transition, same forms as
    :func:`estcal.estimate.kalman.process_noise` except full matrices) is zero
    share one constant variable; the others get a variable ``v_b`` per batch b,
    linked by between factors ``(v_{b+1} − v_b)/q``. A prior (default wide) sits on
    the first state. The smoothed trajectory and its marginal stds are in
    ``extra["trajectory"]``; the returned estimate is the last batch's state (the
    quantity the Kalman filter reports after the last update).
    """
    gtsam = _gtsam()
    t0 = time.perf_counter()
    problem, fidx, names = resolve_free(problem, free)
    theta = problem.params.values.copy() if theta0 is None else np.asarray(theta0, float).copy()
    nominal = theta[fidx].copy()
    qs = np.sqrt(np.diag(process_noise(names, q)))
    var = np.flatnonzero(qs > 0)
    const = np.flatnonzero(qs == 0)
    if var.size == 0:
        raise ValueError("time-varying calibration needs q > 0 for at least one parameter")
    gp = GroupedProblem(problem)
    timer = _Timer()
    batches = [list(range(i, min(i + batch_size, len(gp)))) for i in range(0, len(gp), batch_size)]
    s = _prior_std(problem, names, prior_std)
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    C = gtsam.symbol("c", 0)
    if const.size:
        init.insert(C, nominal[const].copy())
        graph.add(gtsam.PriorFactorVector(C, nominal[const].copy(), gtsam.noiseModel.Diagonal.Sigmas(s[const])))
    V = [gtsam.symbol("v", b) for b in range(len(batches))]
    graph.add(gtsam.PriorFactorVector(V[0], nominal[var].copy(), gtsam.noiseModel.Diagonal.Sigmas(s[var])))
    between = gtsam.noiseModel.Diagonal.Sigmas(qs[var])
    for b, ids in enumerate(batches):
        init.insert(V[b], nominal[var].copy())
        if b:
            graph.add(gtsam.BetweenFactorVector(V[b - 1], V[b], np.zeros(var.size), between))
        block = _Block(gp, ids, theta, fidx, timer)
        keys, parts = ([C, V[b]], [const, var]) if const.size else ([V[b]], [var])
        for g in ids:
            m = block.slices[g].size
            graph.add(_measurement_factor(block, g, keys, parts, nominal, robust_noise(m, robust, robust_k)))
    params = gtsam.LevenbergMarquardtParams()
    params.setDiagonalDamping(True)
    params.setMaxIterations(max_iter)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-14)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, init, params)
    result = opt.optimize()
    marg = gtsam.Marginals(graph, result)
    traj = np.empty((len(batches), len(fidx)))
    tstd = np.empty_like(traj)
    for b in range(len(batches)):
        traj[b, var] = np.asarray(result.atVector(V[b]))
        if const.size:
            traj[b, const] = np.asarray(result.atVector(C))
    # covariance of the last state: joint marginal of (c, v_last)
    keys = gtsam.KeyVector([C, V[-1]]) if const.size else gtsam.KeyVector([V[-1]])
    J = np.asarray(marg.jointMarginalCovariance(keys).fullMatrix())
    order = np.concatenate([const, var]) if const.size else var
    cov = np.empty((len(fidx), len(fidx)))
    cov[np.ix_(order, order)] = J
    for b in range(len(batches)):
        vs = np.sqrt(np.diag(np.asarray(marg.marginalCovariance(V[b]))))
        tstd[b, var] = vs
        if const.size:
            tstd[b, const] = np.sqrt(np.clip(np.diag(cov)[const], 0, None))
    x = traj[-1]
    step = _stationary_step(graph, result)
    theta_full = theta.copy()
    theta_full[fidx] = x
    extra = {"trajectory": {"estimate": traj, "std": tstd, "batch_size": batch_size,
                            "batch_first_group": [b[0] for b in batches]},
             "q": qs, "varying": [names[i] for i in var], "python_factor_time_s": timer.t, "final_step_sigma": step}
    return finish_result(problem, "gtsam-timevarying", names, fidx, x, cov, theta_full, nominal,
                         n_iterations=int(opt.iterations()),
                         converged=int(opt.iterations()) < max_iter and step <= CONVERGED_STEP_SIGMA,
                         covariance_source="gtsam marginals (last state)", theta_before=theta,
                         validation=validation, t0=t0, extra=extra)
