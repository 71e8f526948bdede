"""Statistical efficiency of the batch least-squares estimators (docs/calibration.md, "Statistical efficiency").

With Gaussian measurement noise of known covariance, well-excited poses and an
identifiable parameter set, the weighted least-squares estimate is (to first
order) unbiased with covariance ``(JᵀWJ)⁻¹`` — the Cramér–Rao bound
(textbook 4.71–4.73). Monte Carlo check over K noise realisations:

* NEES ``ε_k = (θ̂_k − θ)ᵀ Σ̂_k⁻¹ (θ̂_k − θ)``; ``Σ_k ε_k ~ χ²(K·p)``;
* per parameter ``Σ_k z_ki² ~ χ²(K)`` with ``z = (θ̂ − θ)/σ̂`` (Bonferroni over p);
* the posterior variance factor: ``Σ_k χ²_k ~ χ²(K·(M − p))``.

Tolerances are the two-sided 99.9 % quantiles of those distributions (seeds fixed).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from estcal.estimate import calibrate_lsq
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics import puma560
from estcal.kinematics.transforms import so3_exp
from estcal.methods import NoiseModel, Problem

FREE = ["offset_2", "offset_3", "offset_5", "a_2", "a_3", "d_3", "d_4", "alpha_2", "alpha_3", "alpha_4",
        "base_tx", "base_ty", "base_rz", "tool_tz"]
ALPHA = 1e-3


def _interval(dof, alpha=ALPHA):
    return stats.chi2.ppf(alpha / 2, dof), stats.chi2.ppf(1 - alpha / 2, dof)


@pytest.fixture(scope="module")
def monte_carlo():
    robot = puma560()
    rng = np.random.default_rng(20240611)
    n_poses, K = 25, 100
    sp, sr = 2e-4, 1e-3  # m, rad (CMM-like)
    truth = robot.params.values.copy()
    idx = robot.params.indices(FREE)
    truth[idx] += rng.normal(0, 2e-3, len(FREE))
    q = robot.random_readings(n_poses, rng)
    kin = robot.kinematics(q, truth, jacobian=False)
    out = {m: [] for m in ("lm", "iterated-lls")}
    for k in range(K):
        R = so3_exp(rng.normal(0, sr, (n_poses, 3))) @ kin.R
        p = kin.p + rng.normal(0, sp, (n_poses, 3))
        ds = dataset_from_arrays(robot.joint_names, q, R=R, p=p)
        prob = Problem(robot, [(None, ds, NoiseModel(sp, sr, known=True))])
        for m in out:
            res = calibrate_lsq(prob, m, free=FREE)
            assert res.converged
            e = res.estimate - truth[robot.params.indices(res.names)]  # result order = vector order
            out[m].append((e, res.covariance, res.std, res.chi2, res.dof))
    return out, len(FREE), K


@pytest.mark.parametrize("method", ["lm", "iterated-lls"])
def test_nees_is_chi2_consistent(monte_carlo, method):
    out, p, K = monte_carlo
    nees = sum(float(e @ np.linalg.solve(C, e)) for e, C, *_ in out[method])
    lo, hi = _interval(K * p)
    assert lo < nees < hi, f"sum NEES {nees:.1f} outside [{lo:.1f}, {hi:.1f}] (K·p = {K * p})"


@pytest.mark.parametrize("method", ["lm", "iterated-lls"])
def test_per_parameter_variances_match_prediction(monte_carlo, method):
    out, p, K = monte_carlo
    z2 = np.sum([(e / s) ** 2 for e, _, s, *_ in out[method]], axis=0)
    lo, hi = _interval(K, ALPHA / p)  # Bonferroni over the p parameters
    bad = [(i, round(float(v), 1)) for i, v in enumerate(z2) if not lo < v < hi]
    assert not bad, f"Σz² outside [{lo:.1f}, {hi:.1f}] for {bad}"


def test_monte_carlo_covariance_matches_cramer_rao(monte_carlo):
    """Whitened errors L⁻¹e have identity covariance: every sample correlation of two
    whitened components is ~N(0, 1/K); 4.4/√K bounds all p(p−1)/2 of them at ~1e-3 overall."""
    out, p, K = monte_carlo
    C = np.mean([c for _, c, *_ in out["lm"]], axis=0)
    L = np.linalg.cholesky(C)
    W = np.array([np.linalg.solve(L, e) for e, *_ in out["lm"]])
    corr = (W.T @ W) / K
    d = np.sqrt(np.diag(corr))
    r = corr / np.outer(d, d)
    off = np.abs(r[np.triu_indices(p, 1)])
    bound = stats.norm.ppf(1 - ALPHA / 2 / (p * (p - 1) / 2)) / np.sqrt(K)
    assert off.max() < bound, f"max |corr| {off.max():.3f} > {bound:.3f}"


def test_posterior_variance_factor_is_chi2(monte_carlo):
    out, p, K = monte_carlo
    chi2 = sum(c for *_, c, _ in out["lm"])
    dof = sum(d for *_, d in out["lm"])
    lo, hi = _interval(dof)
    assert lo < chi2 < hi


def test_nees_detects_a_wrong_covariance(monte_carlo):
    """Power check: a covariance 30 % too small (noise under-stated by 14 %) is rejected."""
    out, p, K = monte_carlo
    nees = sum(float(e @ np.linalg.solve(0.7 * C, e)) for e, C, *_ in out["lm"])
    lo, hi = _interval(K * p)
    assert nees > hi
