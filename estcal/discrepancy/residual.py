"""Structure no library effect explains: a Gaussian-process model of the residual.

Not a layer of the diagnosis any more: fitted on the training sessions' residuals, it learned those sessions
and did not carry to another day (docs/discrepancy.md, "What stays unexplained"). It is kept so that a saved
model carrying such a layer (``calibration.residual_model``) still predicts in ``fk``, ``compensate`` and
``export``; the description below is of that layer.

After the geometric model and the named effects, what is left of the measured point
errors is either noise (unstructured) or a smooth function of where the robot is that
no effect of the library describes — a bearing wobble whose axis tilt follows its own
joint angle, a ripple of the tracker along one of its axes. A Gaussian process with
*automatic relevance determination* (ARD: one length scale per input) over

* the joint readings (``space="joints"``), or
* the predicted Cartesian position of the measured point in the measuring frame
  (``space="cartesian"``; the model's prediction, known at a new posture, not the
  measurement),

learns such a function from the residuals; its posture-grouped cross-validated gain
is the part of the error that has structure (``structured_unnamed_mm`` of the error
budget), and its inverse length scales tell which joint or axis carries it.

Model (Rasmussen & Williams, *Gaussian Processes for Machine Learning*, 2006, eq. 2.25–2.26
and §5.1 for ARD)::

    r(x) ~ GP(0, a² exp(−½ Σ_j (x_j − x'_j)²/ℓ_j²)) + white noise s²       (inputs standardised)
    mean  μ(x*) = k*ᵀ α,           α = (K + s² I)⁻¹ Y        (one α column per coordinate)
    var   v(x*) = a² − k*ᵀ (K + s² I)⁻¹ k*   (+ s² for a new measurement)

All coordinates of all points share one kernel (one set of hyperparameters fitted on
the summed log marginal likelihood), which is scikit-learn's multi-output treatment.

**Why scikit-learn's GaussianProcessRegressor** (its model, its fit) and not GPyTorch: the data are
small (tens to a few thousand measured rows), where an exact GP with a Cholesky factor is fast and
deterministic on a CPU; GPyTorch's strengths (GPU, scalable approximations for 10⁵+ points) buy
nothing here and would bring torch. The fit is scikit-learn's operation for operation
(:func:`_fit_ard_gp`, the same bits, tested against it) without importing it — its import, with the
scipy.stats and pandas it pulls in, cost more CPU than the fit (docs/benchmarks.md, "Everyday commands").

The fitted model is kept as plain data (:class:`ResidualGP`: training inputs, the
weights α, the Cholesky factor, the hyperparameters), and :meth:`ResidualGP.predict`
evaluates mean and variance with numpy alone — a saved model carries it and ``fk`` /
``compensate`` use it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ResidualGP", "JointGP", "fit_residual_gp", "fit_joint_gp", "joint_gp_design", "gp_inputs", "SPACES",
           "residual_model_from_dict", "fit_residual_model", "residual_correction", "compensate_with_residual"]

SPACES = ("joints", "cartesian")
#: the residual models of a recommended model (``--residual-model``): the GP in the space whose GP lowers the
#: held-out error most, or in the one space named
RESIDUAL_MODELS = ("gp", "gp-joints", "gp-cartesian")


def residual_choice(residual_model) -> tuple[str, tuple]:
    """``(GP rule of the procedure, spaces)`` of a ``residual_model`` (None: ``("never", SPACES)`` — the budget
    still measures the structure both GPs find; ``"gp"``: ``("always", SPACES)``, the better space;
    ``"gp-joints"`` / ``"gp-cartesian"``: ``("always", (space,))``)."""
    if residual_model is None:
        return "never", SPACES
    if residual_model not in RESIDUAL_MODELS:
        raise ValueError(f"unknown residual model {residual_model!r}; choose one of {', '.join(RESIDUAL_MODELS)}")
    space = residual_model.partition("-")[2]
    return "always", (space,) if space else SPACES
#: bounds of the standardised length scales: below 0.05 a GP memorises single postures
LENGTH_BOUNDS = (0.05, 100.0)


@dataclass
class ResidualGP:
    """A fitted residual GP as plain arrays (evaluated with numpy; see the module docstring).

    space : ``"joints"`` or ``"cartesian"``; input_names : the input columns (joint names or x, y, z)
    x_mean, x_scale : (d,) standardisation of the inputs; X : (n, d) standardised training inputs
    alpha : (n, m) weights; L : (n, n) lower Cholesky factor of K + s² I (standardised units)
    amplitude2, noise2 : a², s² (standardised); length_scales : (d,) standardised ℓ_j
    y_scale : output scale (m); n_points : points per row (m = 3 · n_points coordinates)
    """

    space: str
    input_names: list
    x_mean: np.ndarray
    x_scale: np.ndarray
    X: np.ndarray
    alpha: np.ndarray
    L: np.ndarray
    amplitude2: float
    noise2: float
    length_scales: np.ndarray
    y_scale: float
    n_points: int
    extra: dict = field(default_factory=dict)

    def _k(self, Xs):
        d = (Xs[:, None, :] - self.X[None, :, :]) / self.length_scales
        return self.amplitude2 * np.exp(-0.5 * np.sum(d * d, axis=-1))

    def standardise(self, X):
        return (np.asarray(X, float) - self.x_mean) / self.x_scale

    def predict(self, X, return_std: bool = False, include_noise: bool = False):
        """Residual mean (M, n_points, 3) in m at raw inputs ``X`` (M, d); with ``return_std``
        also the predictive std per coordinate (M,) in m (the latent function's, plus the white
        noise when ``include_noise`` — the spread of a new measurement about the mean)."""
        Xs = self.standardise(X)
        Ks = self._k(Xs)
        mean = (Ks @ self.alpha) * self.y_scale
        mean = mean.reshape(len(Xs), self.n_points, 3)
        if not return_std:
            return mean
        from scipy.linalg import solve_triangular

        v = solve_triangular(self.L, Ks.T, lower=True)
        var = np.maximum(self.amplitude2 - np.sum(v * v, axis=0), 0.0)
        if include_noise:
            var = var + self.noise2
        return mean, np.sqrt(var) * self.y_scale

    @property
    def relevance(self) -> dict:
        """ARD relevance of each input, largest first: (1/ℓ_j) / Σ_i (1/ℓ_i) on standardised inputs."""
        inv = 1.0 / np.asarray(self.length_scales, float)
        sc = inv / inv.sum()
        order = np.argsort(-sc, kind="stable")
        return {str(self.input_names[j]): float(sc[j]) for j in order}

    def to_dict(self) -> dict:
        """Plain data (lists) for JSON / a saved model; :meth:`from_dict` inverts it."""
        return {"kind": "gaussian_process", "space": self.space, "input_names": list(self.input_names),
                "x_mean": self.x_mean.tolist(), "x_scale": self.x_scale.tolist(), "X": self.X.tolist(),
                "alpha": self.alpha.tolist(), "L": self.L.tolist(), "amplitude2": float(self.amplitude2),
                "noise2": float(self.noise2), "length_scales": np.asarray(self.length_scales).tolist(),
                "y_scale": float(self.y_scale), "n_points": int(self.n_points), "extra": dict(self.extra)}

    @classmethod
    def from_dict(cls, d: dict) -> "ResidualGP":
        a = lambda k: np.asarray(d[k], float)  # noqa: E731
        return cls(d["space"], list(d["input_names"]), a("x_mean"), a("x_scale"), np.atleast_2d(a("X")),
                   np.atleast_2d(a("alpha")), np.atleast_2d(a("L")), float(d["amplitude2"]), float(d["noise2"]),
                   a("length_scales"), float(d["y_scale"]), int(d["n_points"]), dict(d.get("extra", {})))


def gp_inputs(space: str, readings, predicted_points, joint_names):
    """Inputs of the residual GP: the joint readings, or the mean predicted point (x, y, z) of each row."""
    if space == "joints":
        return np.asarray(readings, float), list(joint_names)
    if space == "cartesian":
        P = np.asarray(predicted_points, float)
        return P.reshape(len(P), -1, 3).mean(axis=1), ["x", "y", "z"]
    raise ValueError(f"unknown residual space {space!r}; choose one of {SPACES}")


def fit_residual_gp(X, residuals, input_names, space: str, restarts: int = 2, rng=0, start=None) -> ResidualGP:
    """Fit the ARD GP of the module docstring to residuals, return it as plain data.

    Parameters
    ----------
    X : (n, d) inputs (raw units: rad / m); residuals : (n, k, 3) measured − predicted points (m).
    input_names : d names; space : ``"joints"`` / ``"cartesian"``.
    restarts : extra L-BFGS-B starts of the marginal-likelihood fit (scikit-learn's
        ``n_restarts_optimizer``); rng : seed.
    start : a fitted :class:`ResidualGP` whose hyperparameters start the fit (cross-validation folds
        start from the fit on all rows; each fold still optimises on its own rows).

    The fit is scikit-learn's ``GaussianProcessRegressor(ConstantKernel · RBF + WhiteKernel,
    n_restarts_optimizer=restarts)`` computed by :func:`_fit_ard_gp` (see there for why it is not
    called) — the same hyperparameters, weights and factor to the bit (``tests/test_residual_budget.py``).
    """
    X = np.asarray(X, float)
    R = np.asarray(residuals, float)
    n = len(X)
    R = R.reshape(n, -1, 3)
    k = R.shape[1]
    Y = R.reshape(n, -1)
    x_mean = X.mean(0)
    x_scale = X.std(0)
    x_scale[x_scale < 1e-12] = 1.0
    Xs = (X - x_mean) / x_scale
    y_scale = float(np.sqrt(np.mean(Y ** 2))) or 1.0
    d = X.shape[1]
    a2, ls0, s2 = (0.5, np.ones(d), 0.5) if start is None else (
        float(np.clip(start.amplitude2, 1e-4, 10)), np.clip(start.length_scales, *LENGTH_BOUNDS),
        float(np.clip(start.noise2, 1e-4, 10)))
    seed = int(np.random.default_rng(rng).integers(2**31))
    a2, ls, s2, L, alpha, lml = _fit_ard_gp(Xs, Y / y_scale, a2, ls0, s2, restarts, np.random.RandomState(seed))
    return ResidualGP(space, list(input_names), x_mean, x_scale, Xs, alpha.reshape(n, -1), L, a2, s2, ls,
                      y_scale, k, {"log_marginal_likelihood": lml})


# _ard_kernel, _ard_lml and _fit_ard_gp below are adapted from scikit-learn
# (sklearn/gaussian_process/kernels.py: RBF, ConstantKernel, WhiteKernel __call__;
# sklearn/gaussian_process/_gpr.py: GaussianProcessRegressor.fit, log_marginal_likelihood),
# used under its license:
#
#   BSD 3-Clause License
#   Copyright (c) 2007-2026 The scikit-learn developers. All rights reserved.
#
#   Redistribution and use in source and binary forms, with or without modification, are
#   permitted provided that the following conditions are met:
#   * Redistributions of source code must retain the above copyright notice, this list of
#     conditions and the following disclaimer.
#   * Redistributions in binary form must reproduce the above copyright notice, this list of
#     conditions and the following disclaimer in the documentation and/or other materials
#     provided with the distribution.
#   * Neither the name of the copyright holder nor the names of its contributors may be used
#     to endorse or promote products derived from this software without specific prior
#     written permission.
#
#   THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS" AND ANY EXPRESS
#   OR IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE IMPLIED WARRANTIES OF
#   MERCHANTABILITY AND FITNESS FOR A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE
#   COPYRIGHT HOLDER OR CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL,
#   EXEMPLARY, OR CONSEQUENTIAL DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF
#   SUBSTITUTE GOODS OR SERVICES; LOSS OF USE, DATA, OR PROFITS; OR BUSINESS INTERRUPTION)
#   HOWEVER CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY, OR
#   TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE OF THIS
#   SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.

#: bounds of the amplitude a² and the white noise s² of :func:`fit_residual_gp` (standardised units)
AMPLITUDE_BOUNDS = NOISE_BOUNDS = (1e-4, 10.0)
#: jitter added to the kernel's diagonal before factorising (scikit-learn's ``alpha`` default)
_JITTER = 1e-10


def _ard_kernel(X, theta, gradient: bool):
    """``a² exp(−½ Σ_j (x_j − x'_j)²/ℓ_j²) + s² I`` at ``theta = [log a², log ℓ (d), log s²]`` and, with
    ``gradient``, its derivatives with respect to theta, (n, n, d + 2) — scikit-learn's
    ``ConstantKernel * RBF + WhiteKernel`` evaluated with the same operations in the same order."""
    from scipy.spatial.distance import pdist, squareform

    n, d = X.shape
    c = np.exp(theta[0])
    ls = np.squeeze(np.exp(theta[1:1 + d]) if d > 1 else np.exp(theta[1])).astype(float)
    noise = np.exp(theta[1 + d])
    dists = pdist(X / ls, metric="sqeuclidean")
    Kr = squareform(np.exp(-0.5 * dists))
    np.fill_diagonal(Kr, 1)
    Kc = np.full((n, n), c, dtype=np.array(c).dtype)
    if not gradient:
        return Kc * Kr + noise * np.eye(n)
    if d > 1:  # one length scale per input (ARD)
        Gr = (X[:, np.newaxis, :] - X[np.newaxis, :, :]) ** 2 / (ls ** 2)
        Gr *= Kr[..., np.newaxis]
    else:
        Gr = (Kr * squareform(dists))[:, :, np.newaxis]
    G = np.dstack((np.full((n, n, 1), c, dtype=np.array(c).dtype) * Kr[:, :, np.newaxis], Gr * Kc[:, :, np.newaxis]))
    return Kc * Kr + noise * np.eye(n), np.dstack((G, noise * np.eye(n)[:, :, np.newaxis]))


def _ard_lml(X, Y, theta):
    """Log marginal likelihood of :func:`_ard_kernel` summed over the columns of ``Y`` and its gradient
    (Rasmussen & Williams 2006, eq. 2.30 and 5.9), in scikit-learn's operations and order."""
    from scipy.linalg import cho_solve, cholesky

    K, dK = _ard_kernel(X, theta, True)
    K[np.diag_indices_from(K)] += _JITTER
    try:
        L = cholesky(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return -np.inf, np.zeros_like(theta)
    alpha = cho_solve((L, True), Y, check_finite=False)
    lml = -0.5 * np.einsum("ik,ik->k", Y, alpha)
    lml -= np.log(np.diag(L)).sum()
    lml -= K.shape[0] / 2 * np.log(2 * np.pi)
    inner = np.einsum("ik,jk->ijk", alpha, alpha)
    inner -= cho_solve((L, True), np.eye(K.shape[0]), check_finite=False)[..., np.newaxis]
    return lml.sum(axis=-1), (0.5 * np.einsum("ijl,jik->kl", inner, dK)).sum(axis=-1)


def _fit_ard_gp(X, Y, a2, ls0, s2, restarts, rs):
    """``(a², ℓ, s², L, α, log marginal likelihood)`` of the ARD GP on standardised ``X`` (n, d), ``Y`` (n, m):
    L-BFGS-B on the log hyperparameters from ``(a2, ls0, s2)``, then ``restarts`` runs from uniform draws of
    ``rs`` (a ``RandomState``) in the log box; the best run's factor ``L`` of K + jitter·I and weights α.

    This is what ``GaussianProcessRegressor(ConstantKernel(a2, AMPLITUDE_BOUNDS) * RBF(ls0, LENGTH_BOUNDS) +
    WhiteKernel(s2, NOISE_BOUNDS), n_restarts_optimizer=restarts, random_state=rs).fit(X, Y)`` computes,
    operation for operation (its kernel, likelihood, optimiser call, draws and choice of the best run), so
    the results are the same bits; ``tests/test_residual_budget.py`` fits both and compares them. It is not
    called because importing scikit-learn costs ~0.35 s of CPU and brings scipy.stats and pandas (another
    ~0.3 s) — a fifth of ``estcal diagnose`` on a TIAGo session (docs/benchmarks.md, "Everyday commands")
    — for an exact GP of a few dozen rows whose joint-space sibling (:class:`JointGP`) is numpy already.
    """
    from scipy.linalg import cho_solve, cholesky
    from scipy.optimize import minimize

    d = X.shape[1]
    theta0 = np.log(np.hstack([a2, np.asarray(ls0, float), s2]))
    bounds = np.log(np.vstack([np.atleast_2d(AMPLITUDE_BOUNDS), np.repeat(np.atleast_2d(LENGTH_BOUNDS), d, 0)
                               if d > 1 else np.atleast_2d(LENGTH_BOUNDS), np.atleast_2d(NOISE_BOUNDS)]))

    def obj(theta):
        lml, grad = _ard_lml(X, Y, theta)
        return -lml, -grad

    optima = []
    for r in range(1 + max(int(restarts), 0)):
        x0 = theta0 if r == 0 else rs.uniform(bounds[:, 0], bounds[:, 1])
        res = minimize(obj, x0, method="L-BFGS-B", jac=True, bounds=bounds)
        optima.append((res.x, res.fun))
    values = [f for _, f in optima]
    theta = optima[int(np.argmin(values))][0]
    K = _ard_kernel(X, theta, False)
    K[np.diag_indices_from(K)] += _JITTER
    L = cholesky(K, lower=True, check_finite=False)
    alpha = cho_solve((L, True), Y, check_finite=False)
    ls = np.atleast_1d(np.exp(theta[1:1 + d]) if d > 1 else np.full(1, np.exp(theta[1])))
    return float(np.exp(theta[0])), ls, float(np.exp(theta[-1])), L, alpha, float(-np.min(values))


# ---------------------------------------------------------------------------------------------
# joint space: each joint's placement varies smoothly with its own angle
# ---------------------------------------------------------------------------------------------
def joint_parameter_columns(robot) -> dict:
    """``{joint name: [geometric parameter names of that joint's placement]}``.

    URDF chains name them ``tx_<joint>`` … ``rz_<joint>``; Khalil–Kleinfinger robots
    ``theta_<i>``, ``d_<i>``, ``a_<i>``, ``alpha_<i>``, ``beta_<i>`` (i = 1…n).
    """
    out = {}
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    geo = [n for n in robot.params.names if kinds[n] == "geometric"]
    for i, j in enumerate(robot.joint_names):
        cols = [n for n in geo if n.endswith("_" + j) or n.endswith(f"_{i + 1}") and not any(
            n.endswith("_" + o) for o in robot.joint_names)]
        if cols:
            out[j] = cols
    return out


def joint_gp_design(robot, theta, readings, context=None, n_points: int = 1):
    """Inputs of the joint-space GP: the readings and each row's Jacobian of the measured points
    with respect to every joint's placement parameters, ``(Q (N, n), H (N, 3k, p), names (p,),
    joint_of (p,))`` (analytic, :meth:`SerialRobot.kinematics`)."""
    cols = joint_parameter_columns(robot)
    names = [n for j in robot.joint_names for n in cols.get(j, [])]
    joint_of = np.array([robot.joint_names.index(j) for j in robot.joint_names for _ in cols.get(j, [])], int)
    kin = robot.kinematics(readings, theta, context or {}, jacobian=True)
    idx = robot.params.indices(names)
    if n_points and robot.n_markers >= n_points:
        Jp = kin.J_points[:, :n_points][..., idx]          # (N, k, 3, p)
    else:
        Jp = np.repeat(kin.J[:, None, :3][..., idx], max(n_points, 1), axis=1)
    N = len(Jp)
    return np.asarray(readings, float), Jp.reshape(N, -1, len(idx)), names, joint_of


@dataclass
class JointGP:
    """Joint-space residual GP: every joint's placement parameters vary smoothly with its own angle.

    The residual of row i (3k coordinates) is ``r_i = Σ_j H̃_ij g_j(q_ij) + ε``, with H̃_ij the
    Jacobian of the points with respect to joint j's placement parameters (columns scaled to unit
    RMS) and g_j ~ GP(0, a_j² exp(−(q − q')²/(2ℓ_j²)) I) — a linear operator applied to independent
    GPs (Rasmussen & Williams 2006, §9.4), so ``K = Σ_j a_j² (k_j ⊗ 1) ⊙ (H̃_j H̃_jᵀ) + s² I``.
    One amplitude a_j and one length scale ℓ_j (ARD over the joint angles) per joint, fitted on
    the log marginal likelihood with its analytic gradient (L-BFGS-B). A constant g_j is a
    geometric parameter error (already fitted), a g_j varying with q_j is an axis that wobbles,
    a placement that changes along the joint's travel — structure the geometric model cannot hold.

    ``relevance``: each joint's share of the squared norm of the fitted mean, Σ‖K_j α‖² normalised.
    Stored as plain data: training readings, scaled Jacobians, residuals and hyperparameters;
    the factorisation is recomputed with numpy on first use.
    """

    joint_names: list
    param_names: list
    joint_of: np.ndarray
    col_scale: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    Y: np.ndarray
    amplitude: np.ndarray
    length_scales: np.ndarray
    noise: float
    n_points: int
    space: str = "joints"
    extra: dict = field(default_factory=dict)

    # --- kernel ------------------------------------------------------------------------------
    def _blocks(self, Qa, Ha, Qb, Hb, amp=None, ls=None):
        amp = self.amplitude if amp is None else amp
        ls = self.length_scales if ls is None else ls
        m = Ha.shape[1]
        K = np.zeros((len(Qa) * m, len(Qb) * m))
        for j in range(len(self.joint_names)):
            c = self.joint_of == j
            if not c.any():
                continue
            G = Ha[:, :, c].reshape(-1, c.sum()) @ Hb[:, :, c].reshape(-1, c.sum()).T
            d = Qa[:, [j]] - Qb[:, j][None, :]
            k = np.exp(-0.5 * d * d / ls[j] ** 2)
            K += amp[j] ** 2 * np.kron(k, np.ones((m, m))) * G
        return K

    def _factor(self):
        if "_L" not in self.__dict__:
            from scipy.linalg import cho_solve

            K = self._blocks(self.Q, self.H, self.Q, self.H) + self.noise ** 2 * np.eye(self.Y.size)
            cf = (np.linalg.cholesky(K), True)
            self.__dict__["_L"] = cf
            self.__dict__["_alpha"] = cho_solve(cf, self.Y.reshape(-1), check_finite=False)
        return self.__dict__["_L"], self.__dict__["_alpha"]

    def _scaled(self, H):
        return np.asarray(H, float) / self.col_scale

    def predict(self, readings, H, return_std: bool = False, include_noise: bool = False):
        """Residual mean (M, k, 3) in m at new rows (readings (M, n), Jacobians H (M, 3k, p) of
        :func:`joint_gp_design`); with ``return_std`` the predictive std (M, 3k) too."""
        Qs, Hs = np.asarray(readings, float), self._scaled(H)
        cf, alpha = self._factor()
        Ks = self._blocks(Qs, Hs, self.Q, self.H)
        mean = (Ks @ alpha).reshape(len(Qs), -1, 3)
        if not return_std:
            return mean
        from scipy.linalg import solve_triangular

        v = solve_triangular(cf[0], Ks.T, lower=True)
        prior = np.zeros(Ks.shape[0])
        for j in range(len(self.joint_names)):
            c = self.joint_of == j
            if c.any():
                prior += self.amplitude[j] ** 2 * np.sum(Hs[:, :, c] ** 2, axis=2).reshape(-1)
        var = np.maximum(prior - np.sum(v * v, axis=0), 0.0) + (self.noise ** 2 if include_noise else 0.0)
        return mean, np.sqrt(var).reshape(len(Qs), -1)

    @property
    def relevance(self) -> dict:
        _, alpha = self._factor()
        share = {}
        for j, name in enumerate(self.joint_names):
            c = self.joint_of == j
            if not c.any():
                continue
            amp = np.zeros_like(self.amplitude)
            amp[j] = self.amplitude[j]
            share[name] = float(np.sum((self._blocks(self.Q, self.H, self.Q, self.H, amp=amp) @ alpha) ** 2))
        tot = sum(share.values()) or 1.0
        return {k: v / tot for k, v in sorted(share.items(), key=lambda kv: -kv[1])}

    def to_dict(self) -> dict:
        return {"kind": "gaussian_process", "space": "joints", "joint_names": list(self.joint_names),
                "param_names": list(self.param_names), "joint_of": self.joint_of.tolist(),
                "col_scale": self.col_scale.tolist(), "Q": self.Q.tolist(), "H": self.H.tolist(), "Y": self.Y.tolist(),
                "amplitude": self.amplitude.tolist(), "length_scales": self.length_scales.tolist(),
                "noise": float(self.noise), "n_points": int(self.n_points), "extra": dict(self.extra)}

    @classmethod
    def from_dict(cls, d: dict) -> "JointGP":
        a = lambda k: np.asarray(d[k], float)  # noqa: E731
        return cls(list(d["joint_names"]), list(d["param_names"]), np.asarray(d["joint_of"], int), a("col_scale"),
                   a("Q"), a("H"), a("Y"), a("amplitude"), a("length_scales"), float(d["noise"]),
                   int(d["n_points"]), "joints", dict(d.get("extra", {})))


def fit_joint_gp(readings, H, residuals, param_names, joint_of, joint_names, restarts: int = 1, rng=0,
                 maxiter: int = 200, start=None) -> JointGP:
    """Fit :class:`JointGP` (log marginal likelihood, analytic gradient, L-BFGS-B in log space).

    readings (N, n), H (N, 3k, p) from :func:`joint_gp_design`, residuals (N, k, 3) in m.
    start : a fitted :class:`JointGP` whose hyperparameters start the optimisation (instead of the default
        start; cross-validation folds start from the fit on all rows and optimise on their own rows).
    restarts : random restarts, run only when the first optimisation is suspect (:func:`_restarts`).
    """
    from estcal.base.blas import single_thread_blas

    fit = joint_gp_fit_problem(readings, H, residuals, joint_of, joint_names, start)
    with single_thread_blas():
        best = _restarts(fit.nll, fit.bounds, restarts, np.random.default_rng(rng), maxiter, fit.x0)
    na, nj = len(fit.active), len(joint_names)
    amp = np.zeros(nj)
    ls = fit.qsd.copy()
    amp[fit.active] = np.exp(best.x[:na])
    ls[fit.active] = np.exp(best.x[na:2 * na])
    N, m, _ = fit.Hs.shape
    return JointGP(list(joint_names), list(param_names), fit.joint_of, fit.scale, fit.Q, fit.Hs, fit.Y.reshape(N, m),
                   amp, ls, float(np.exp(best.x[-1])), m // 3, "joints",
                   {"neg_log_marginal_likelihood": float(best.fun)})


def joint_gp_fit_problem(readings, H, residuals, joint_of, joint_names, start=None):
    """What :func:`fit_joint_gp` optimises, as plain data: the scaled design (``Q``, ``Hs``, ``scale``, ``Y``),
    the joints with an amplitude (``active``: a placement and some travel), the objective ``nll``
    (:func:`joint_gp_objective`), the box ``bounds`` of ``x = [log a_j, log ℓ_j, log s]`` (amplitudes
    10⁻³–30 × the residual RMS, length scales 0.05–50 × each joint's spread, noise 10⁻³–3 × the RMS) and the
    start ``x0`` (``start``'s hyperparameters clipped to the box, else a_j = 0.3 RMS, ℓ_j = the joint's
    spread, s = 0.7 RMS)."""
    from types import SimpleNamespace

    Q = np.asarray(readings, float)
    H = np.asarray(H, float)
    Y = np.asarray(residuals, float).reshape(-1)
    N, m, p = H.shape
    scale = np.sqrt(np.mean(H.reshape(-1, p) ** 2, axis=0))
    scale[scale < 1e-15] = 1.0
    Hs = H / scale
    joint_of = np.asarray(joint_of, int)
    nj = len(joint_names)
    active = [j for j in range(nj) if np.any(joint_of == j) and np.ptp(Q[:, j]) > 1e-9]
    rms = float(np.sqrt(np.mean(Y ** 2))) or 1.0
    qsd = np.array([max(Q[:, j].std(), 1e-6) for j in range(nj)])
    na = len(active)
    bounds = ([(np.log(1e-3 * rms), np.log(30 * rms))] * na
              + [(np.log(0.05 * qsd[j]), np.log(50 * qsd[j])) for j in active]
              + [(np.log(1e-3 * rms), np.log(3 * rms))])
    if start is not None:
        x0 = np.clip(np.r_[np.log(np.maximum(start.amplitude[active], 1e-300)),
                           np.log(start.length_scales[active]), np.log(start.noise)],
                     [b[0] for b in bounds], [b[1] for b in bounds])
    else:
        x0 = np.r_[np.full(na, np.log(0.3 * rms)), np.log(qsd[active]), np.log(0.7 * rms)]
    return SimpleNamespace(Q=Q, Hs=Hs, scale=scale, Y=Y, joint_of=joint_of, active=active, qsd=qsd,
                           nll=joint_gp_objective(Q, Hs, Y, joint_of, active, m), bounds=bounds, x0=x0)


def joint_gp_objective(Q, Hs, Y, joint_of, active, m: int):
    """Negative log marginal likelihood of :class:`JointGP` and its analytic gradient, as a function of
    ``x = [log a_j (active joints), log ℓ_j, log s]`` (up to the constant M/2 log 2π; R & W eq. 5.8–5.9).

    The signal of posture a lies in the range of its design block ``H̃_a`` (m × p): the joints' placement
    parameters move the measured body rigidly, so the m = 3k coordinates of k points span at most 6
    directions (a twist). With an orthonormal basis ``[V_a V⊥_a]`` of each posture's coordinates, V_a
    spanning that range (r = max_a rank H̃_a columns), the covariance ``K = Σ_j … + s² I`` becomes
    block-diagonal: ``K̃ + s² I`` on the rotated coordinates ``z_a = V_aᵀ y_a`` (K̃ built from ``V_aᵀ H̃_a``
    as K from H̃) and ``s² I`` on the N(m − r) others, ``w_a = V⊥_aᵀ y_a``. An orthogonal change of basis
    keeps the likelihood, so

        nll = nll_K̃(z) + ‖w‖² / (2 s²) + N (m − r) log s

    exactly, and its factorisations are of (N r)², not (N m)² — on a TIAGo session with four markers
    222 instead of 444 rows, an eighth of the Cholesky and inverse flops. r = m (one point per posture,
    or a design of full rank) leaves the problem as it is. Below, :func:`_joint_gp_blocks_objective`."""
    Hs = np.asarray(Hs, float)
    Y = np.asarray(Y, float)
    M = Y.size
    N = M // m
    Hb = Hs.reshape(N, m, -1)
    U, sv, _ = np.linalg.svd(Hb[:, :, np.isin(joint_of, list(active))], full_matrices=True)
    r = int(np.max(np.sum(sv > 1e-10 * np.maximum(sv[:, :1], 1e-300), axis=1))) if sv.size else 0
    if r >= m or r == 0:
        return _joint_gp_blocks_objective(Q, Hs, Y, joint_of, active, m)
    V = U[:, :, :r]  # (N, m, r): an orthonormal basis of each posture's signal directions
    Yb = Y.reshape(N, m)
    z = np.einsum("nir,ni->nr", V, Yb)
    w2 = float(np.sum((Yb - np.einsum("nir,nr->ni", V, z)) ** 2))  # ‖w‖², the residual off the signal range
    n_off = N * (m - r)
    inner = _joint_gp_blocks_objective(Q, np.einsum("nir,nip->nrp", V, Hb), z.reshape(-1), joint_of, active, r)

    def nll(x):
        val, g = inner(x)
        if val >= 1e25:
            return val, g
        s2 = float(np.exp(2 * x[-1]))
        g = g.copy()
        g[-1] += n_off - w2 / s2
        return val + 0.5 * w2 / s2 + n_off * x[-1], g

    return nll


def _joint_gp_blocks_objective(Q, Hs, Y, joint_of, active, m: int):
    """:func:`joint_gp_objective` on the rows as given (blocks of ``m`` per posture).

    Rows come in blocks of ``m`` per posture and the kernel of joint j is ``a_j² (k_j ⊗ 1) ⊙ G_j``:
    its squared-exponential part ``k_j`` is an N × N matrix of postures, ``G_j = H̃_j H̃_jᵀ`` does not
    depend on x. So ``K`` is assembled posture block by posture block as one batched product
    ``Σ_j a_j² k_j[a, b] G_j[a, b]`` and each gradient term ``tr(W ∂K/∂θ)`` is an N × N sum of the
    block sums ``S_j[a, b] = Σ (W ⊙ G_j)[a, b]`` (one batched product as well): the exponentials are
    taken on N², not M² entries, and the M² work is two batched matrix products per evaluation. Both factors
    are symmetric, so only the blocks with a ≥ b are formed and summed (the Cholesky factorisation reads
    K's lower triangle, LAPACK's ``dpotri`` returns K⁻¹ in the same triangle): half the block work."""
    from scipy.linalg.lapack import dpotrf, dpotri, dpotrs

    M = Y.size
    N = M // m
    na = len(active)
    Hb = Hs.reshape(N, m, -1)
    Hj = [Hb[:, :, joint_of == j] for j in active]  # G_j = H̃_j H̃_jᵀ
    ia, ib = np.tril_indices(N)  # the T = N(N+1)/2 blocks (a, b) with a ≥ b
    G = np.stack([np.einsum("tic,tkc->tik", h[ia], h[ib]).reshape(len(ia), m * m) for h in Hj],
                 axis=1)  # (T, na, m·m): G[t, j] = block (ia[t], ib[t]) of G_j, flattened
    # the same blocks transposed, (k, i) order: LAPACK's K⁻¹ is column-major, its transpose a C-ordered view
    GT = np.ascontiguousarray(G.reshape(-1, na, m, m).transpose(0, 1, 3, 2)).reshape(G.shape)
    d2 = np.stack([(Q[ia, j] - Q[ib, j]) ** 2 for j in active])  # (na, T)
    diag_G = np.stack([np.einsum("aic,aic->ai", h, h).reshape(M) for h in Hj])  # (na, M)
    off = ia != ib
    w = np.where(off, 2.0, 1.0)  # an off-diagonal pair stands for (a, b) and (b, a) in the full N × N sums

    def unpack(x):
        return np.exp(x[:na]), np.exp(x[na:2 * na]), float(np.exp(x[-1]))

    def nll(x):
        amp, ls, s = unpack(x)
        C = amp[:, None] ** 2 * np.exp(-0.5 * d2 / ls[:, None] ** 2)  # (na, T)
        # K's lower triangle laid out in Fortran order (the transpose of a C-ordered array whose upper
        # triangle holds the transposed blocks): LAPACK reads it in place — a C-ordered K would be copied
        # to Fortran order first, as long as the factorisation itself at this size
        K4 = np.zeros((N, m, N, m))
        K4[ib, :, ia, :] = (C.T[:, None, :] @ GT).reshape(-1, m, m)
        K = K4.reshape(M, M).T
        K[np.diag_indices(M)] += s * s
        L, info = dpotrf(K, lower=1, clean=1, overwrite_a=1)
        if info != 0:
            return 1e25, np.zeros_like(x)
        alpha = dpotrs(L, Y, lower=1)[0]
        val = 0.5 * Y @ alpha + np.sum(np.log(np.diag(L)))
        Ki = dpotri(L, lower=1, overwrite_c=1)[0]  # K⁻¹ in the lower triangle (over L); the upper one stays zero
        dK = np.diag(Ki).copy()
        Kb = Ki.T.reshape(N, m, N, m)[ib, :, ia, :].reshape(-1, m * m, 1)  # block (a, b) of K⁻¹, transposed
        Sl = (GT @ Kb)[..., 0].T  # (na, T): Σ over block (a, b) of K⁻¹'s lower triangle ⊙ G_j
        # a diagonal block holds its lower half (diagonal included) only: its sum over the whole block is
        # twice that minus the diagonal
        Sl[:, ~off] = 2 * Sl[:, ~off] - (diag_G * dK).reshape(na, N, m).sum(-1)
        ab = alpha.reshape(N, m)
        U = [np.einsum("aic,ai->ac", h, ab) for h in Hj]
        S = np.stack([np.sum(u[ia] * u[ib], axis=1) for u in U]) - Sl  # (na, T)
        CS = C * S * w
        g = np.zeros_like(x)
        g[:na] = -np.sum(CS, axis=1)
        g[na:2 * na] = -0.5 * np.sum(CS * d2, axis=1) / ls ** 2
        g[-1] = -(alpha @ alpha - np.sum(dK)) * s * s
        return val, g

    return nll


#: L-BFGS-B stops when the negative log marginal likelihood changes by less than this fraction of its
#: value (~2·10⁻³ nats on a TIAGo session, |nll| ≈ 2000): far below the half-nat that separates
#: hyperparameters statistically, and half the evaluations of scipy's default (2.2·10⁻⁹)
NLL_FTOL = 1e-6

#: correction pairs L-BFGS-B keeps (scipy's default 10): at least the 2·(active joints) + 1 dimensions of a
#: 7–8-joint arm. Measured when this GP was the error budget's last layer (that experiment went with the layer): every joint GP fit of the budget on the published data
#: and the simulated two-optima cases (50 fits): 7.7 % fewer likelihood evaluations (10.7 % of their cost),
#: none ending more than half a nat worse than with 10 pairs, from the same start
LBFGS_MEMORY = 20


def _suspect(res, bounds) -> bool:
    """Whether an L-BFGS-B result calls for the random restarts: it did not report convergence, or some
    hyperparameter stopped on a bound of the box (the box, not the likelihood, decided it there)."""
    lo, hi = np.array(bounds, float).T
    tol = 1e-8 * np.maximum(hi - lo, 1.0)
    return (not res.success) or bool(np.any((res.x <= lo + tol) | (res.x >= hi - tol)))


def _restarts(nll, bounds, restarts, gen, maxiter, x0):
    """The best of one L-BFGS-B run from ``x0`` and, only when that run is suspect (:func:`_suspect`),
    ``restarts`` runs from uniform random points of the box.

    Random restarts guard against local optima of the marginal likelihood (Rasmussen & Williams 2006,
    §5.4.1: "multiple local optima … restarts"). They are spent where a local optimum is plausible: the
    first run did not converge, or it ended on the box (a flat direction — an amplitude switched off
    leaves its length scale without gradient — or the box truncating the optimum). The random draws are
    taken only when a restart runs, so a suspect fit sees the same draws as before.

    Evidence for the gate (measured when this GP was ``estcal diagnose``'s last layer, the experiment removed with it: every joint GP fit of the
    error budget on the published data — TIAGo 11-26, 11-30 and both, the three TALOS sessions, UR10; the
    fit on all rows and its five posture-grouped folds — and 36 fits of a simulated likelihood with two
    optima, a short-scale wobble of one wrist joint against "all noise"; each first run repeated, then five
    random restarts; L-BFGS-B with scipy's 10 correction pairs then, :data:`LBFGS_MEMORY` since): of the 32
    real fits that ended converged with a length scale on its lower bound, the restart this function would
    run (the first draw) ended > 0.5 nats lower in 2 (TIAGo 11-26 fold 3:
    23.7 nats; TALOS 02-10 fold 5: 0.53) and one of five restarts in 16 (up to 33 nats, TIAGo 11-26 folds;
    TALOS 02-10 all rows: 1.3); of the 10 other real fits, 0 and 1. Simulated: 2 and 3 of 10 on the lower
    bound (15.5 nats once), 1 and 5 of 26 otherwise. A length scale on its lower bound is a symptom of a
    local optimum, on real data too, so the gate is kept as it is; on the TIAGo 11-30 session the all-rows
    fit ends with two wrist length scales on the bound, and its restart (~80 evaluations, ~0.5 s) runs and
    ends 26 nats worse there. The folds (started from the all-rows fit, ``restarts=0`` in the budget) are
    where better optima were found most often.
    """
    from scipy.optimize import minimize

    best = None
    for r in range(1 + max(int(restarts), 0)):
        if r == 1 and not _suspect(best, bounds):
            break
        xr = x0 if r == 0 else np.array([gen.uniform(lo, hi) for lo, hi in bounds])
        res = minimize(nll, xr, jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": maxiter, "ftol": NLL_FTOL, "maxcor": LBFGS_MEMORY})
        if best is None or res.fun < best.fun:
            best = res
    return best


def residual_model_from_dict(d: dict):
    """A residual GP (:class:`JointGP` or :class:`ResidualGP`) from its :meth:`to_dict` form."""
    return JointGP.from_dict(d) if d.get("space") == "joints" and "joint_of" in d else ResidualGP.from_dict(d)


def _predicted(robot, theta, readings, context, k):
    kin = robot.kinematics(readings, theta, context or {}, jacobian=False)
    if k and robot.n_markers >= k:
        return kin.points[:, :k]
    return np.repeat(kin.p[:, None, :], max(k, 1), axis=1)


def fit_residual_model(space: str, robot, theta, readings, residuals, context=None, restarts: int = 1, rng=0,
                       start=None):
    """The residual GP of ``space`` fitted to ``residuals`` (N, k, 3) of ``robot`` at ``theta``:
    :class:`JointGP` for ``"joints"``, :class:`ResidualGP` over the predicted point for ``"cartesian"``."""
    R = np.asarray(residuals, float)
    k = R.shape[1]
    if space == "joints":
        Q, H, names, jo = joint_gp_design(robot, theta, readings, context, k)
        return fit_joint_gp(Q, H, R, names, jo, robot.joint_names, restarts=restarts, rng=rng, start=start)
    X, names = gp_inputs(space, readings, _predicted(robot, theta, readings, context, k), robot.joint_names)
    return fit_residual_gp(X, R, names, space, restarts=restarts, rng=rng, start=start)


def residual_correction(model, robot, theta, readings, context=None, return_std: bool = False):
    """The residual model's mean correction (N, k, 3) in m at ``readings`` (add it to the robot's
    prediction); with ``return_std`` also the predictive std per coordinate (N, 3k)."""
    k = model.n_points
    if isinstance(model, JointGP):
        Q, H, _, _ = joint_gp_design(robot, theta, readings, context, k)
        return model.predict(Q, H, return_std=return_std)
    X, _ = gp_inputs(model.space, readings, _predicted(robot, theta, readings, context, k), robot.joint_names)
    out = model.predict(X, return_std=return_std)
    if not return_std:
        return out
    mean, sd = out
    return mean, np.repeat(sd[:, None], 3 * k, axis=1)


def compensate_with_residual(robot, model, targets, q_start, context=None, iterations: int = 5, **kw):
    """Compensated readings with a residual layer: the calibrated model plus the GP mean reach ``targets``.

    :func:`estcal.compensation.compensate` solves FK(q) = x; with the residual layer the
    point reached is FK(q) + μ(q), so the solve is repeated for the shifted targets
    ``x − μ(q_k)`` (fixed point; μ varies slowly with q, two or three passes suffice).
    Returns ``(CompensationResult, residual_std_mm (N,))``: the result of the last solve and
    the GP's predictive std (RMS over the three coordinates, mm) at the compensated readings.
    """
    from estcal.compensation import compensate

    x = np.asarray(targets, float)
    q = np.asarray(q_start, float)
    res = None
    for _ in range(max(int(iterations), 1)):
        mu = residual_correction(model, robot, robot.params.values, q, context)[:, 0]
        shifted = x.copy()
        shifted[:, :3] = x[:, :3] - mu  # positions (a pose target's quaternion is kept)
        res = compensate(robot, shifted, q, context=context, **kw)
        q = res.readings
    _, sd = residual_correction(model, robot, robot.params.values, q, context, return_std=True)
    return res, np.sqrt(np.mean(sd[:, :3] ** 2, axis=1)) * 1e3

