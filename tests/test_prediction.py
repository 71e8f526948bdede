"""The prediction at new postures (estcal.discrepancy.prediction): the variance model of the nested
held-out errors, the expected RMSE at target postures and the normalised conformal region.

Each formula is checked against an independent computation: bounded least squares (scipy's
``lsq_linear``), the order statistic of the split-conformal rule, Monte Carlo refits of a correctly
specified model whose targets lie beyond the training postures.
"""
import numpy as np
import pytest

from estcal.discrepancy.prediction import (conformal_threshold, predicted_rmse_at, region_coverage, region_scores,
                                           region_sigma, variance_model)


def _cov(rng, n, scale):
    A = rng.standard_normal((n, 3, 3)) * scale[:, None, None]
    return A @ A.transpose(0, 2, 1)


@pytest.mark.parametrize("a_true,b_true", [(2e-6, 3.0), (0.0, 1.5), (4e-6, 1.0), (5e-6, 0.2)])
def test_variance_model_is_the_bounded_least_squares_line(a_true, b_true):
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(1)
    S = _cov(rng, 400, rng.uniform(0.2e-3, 2e-3, 400))
    v = np.trace(S, axis1=1, axis2=2)
    # errors whose squared norm has mean a + b tr S (isotropic Gaussian with that variance)
    e = rng.standard_normal((400, 3)) * np.sqrt((a_true + b_true * v) / 3)[:, None]
    a, b = variance_model(e, S, b_min=1.0)
    y = np.sum(e ** 2, -1)

    def bounded(y):  # in units of the data's scale, so that the solver's tolerances mean something
        ys, vs = np.abs(y).mean(), v.mean()
        x = lsq_linear(np.c_[np.ones_like(v), v / vs], y / ys, bounds=([0, 0], [np.inf, np.inf]), tol=1e-14).x
        return x[0] * ys, x[1] * ys / vs

    ref = bounded(y - v)  # b_min = 1: the excess over the parameter covariance
    assert a == pytest.approx(ref[0], rel=1e-6, abs=1e-9 * y.mean())
    assert b == pytest.approx(1 + ref[1], rel=1e-6, abs=1e-9)
    assert b >= 1 and a >= 0
    # b_min = 0: the plain non-negative line, close to the truth on 400 points
    a0, b0 = variance_model(e, S, b_min=0.0)
    ref0 = bounded(y)
    assert a0 == pytest.approx(ref0[0], rel=1e-6, abs=1e-9 * y.mean())
    assert b0 == pytest.approx(ref0[1], rel=1e-6, abs=1e-9)
    assert b0 == pytest.approx(b_true, abs=0.35 * b_true + 0.3)


def test_predicted_rmse_at_is_the_root_mean_of_the_line():
    rng = np.random.default_rng(2)
    S = _cov(rng, 50, np.full(50, 1e-3))
    a, b = 3e-6, 2.0
    by_hand = np.sqrt(np.mean([a + b * (S[i, 0, 0] + S[i, 1, 1] + S[i, 2, 2]) for i in range(50)]))
    assert predicted_rmse_at(a, b, S) == pytest.approx(by_hand, rel=1e-12)
    # Monte Carlo: errors drawn with covariance b S + a/3 I have that RMSE
    region = {"tau_mm": np.sqrt(a / 3) * 1e3, "scale": b}
    Sig = region_sigma(region, S)
    L = np.linalg.cholesky(Sig)
    e = np.einsum("nij,mnj->mni", L, rng.standard_normal((4000, 50, 3)))
    assert np.sqrt(np.mean(np.sum(e ** 2, -1))) == pytest.approx(by_hand, rel=0.02)


def test_conformal_threshold_is_the_order_statistic_and_covers():
    rng = np.random.default_rng(3)
    s = rng.exponential(size=99)
    assert conformal_threshold(s, 0.95) == np.sort(s)[94]  # ⌈0.95 · 100⌉ = 95th smallest
    assert conformal_threshold(s[:10], 0.95) == np.inf  # too few scores for a 95 % region
    # exchangeable scores: the next point falls inside with probability ≥ 95 % (Barber et al. 2021)
    hits = []
    for _ in range(2000):
        x = rng.standard_t(3, size=41)
        hits.append(x[-1] ** 2 <= conformal_threshold(x[:-1] ** 2, 0.95))
    assert 0.94 <= np.mean(hits) <= 0.99


def test_scaled_region_covers_errors_that_grow_with_the_parameter_variance():
    # held-out errors with E|e|² = a + 3 tr S: the scaled region covers 95 % of new points whatever their
    # variance; the unscaled one (b = 1) misses the high-variance points
    rng = np.random.default_rng(4)

    def draw(n, hi):
        S = _cov(rng, n, rng.uniform(0.1e-3, hi, n))
        Sig = 3.0 * S + 1e-6 * np.eye(3)
        return np.einsum("nij,nj->ni", np.linalg.cholesky(Sig), rng.standard_normal((n, 3))), S

    e, S = draw(600, 1e-3)
    a, b = variance_model(e, S)
    assert b == pytest.approx(3.0, rel=0.25)
    region = {"tau_mm": np.sqrt(a / 3) * 1e3, "scale": b}
    region["threshold_d2"] = conformal_threshold(region_scores(e, region_sigma(region, S), 0.0))
    e_far, S_far = draw(600, 3e-3)  # targets farther from the training postures
    assert 0.92 <= region_coverage(region, e_far, S_far) <= 0.98
    unscaled = dict(region, scale=1.0, tau_mm=np.sqrt(np.mean(e ** 2)) * 1e3)
    unscaled["threshold_d2"] = conformal_threshold(region_scores(e, region_sigma(unscaled, S), 0.0))
    assert region_coverage(unscaled, e_far, S_far) < 0.9


def test_prediction_at_target_postures_beyond_the_training_ones_matches_monte_carlo_refits():
    # a correct model (full geometry of a PUMA 560, Gaussian noise) fitted on 14 postures within ±0.3π of
    # zero and used at 100 postures within ±0.7π: the nested CV's average error is that of postures like
    # the training ones and is optimistic there; the prediction from the targets' readings is not. The
    # truth: the mean squared error at the targets over refits on 8 noise draws (+ the targets' own noise).
    from estcal.discrepancy.budget import error_budget, measured_points, predicted_at
    from estcal.kinematics.robots import puma560
    from estcal.methods import NoiseModel
    from estcal.simulate import simulate

    sigma = 2e-4
    rng = np.random.default_rng(1)
    Q, Qt = rng.uniform(-0.3, 0.3, (14, 6)) * np.pi, rng.uniform(-0.7, 0.7, (100, 6)) * np.pi
    sim = simulate(puma560(), readings=Q, measure="points", errors="random", n_points=2, seed=3)
    targets = simulate(puma560(), readings=Qt, measure="points", errors="random", n_points=2, seed=3).dataset
    truth, at, cv = [], [], []
    for draw in range(8):
        data = sim.dataset.subset(slice(None))
        data.points = sim.dataset.points + sigma * np.random.default_rng(100 + draw).standard_normal(data.points.shape)
        b = error_budget(sim.nominal_robot, data, NoiseModel(position=sigma, known=True), level="full", k_folds=5,
                         spaces=())
        e = measured_points(targets) - b.extra["fitted"].predict(targets)
        truth.append(np.mean(np.sum(e ** 2, -1)) + 3 * sigma ** 2)
        no_measurement = targets.subset(slice(None))
        no_measurement.points = np.full_like(targets.points, np.nan)  # readings only
        at.append(predicted_at(b, no_measurement))
        cv.append(b.predicted_validation_mm)
    truth_mm = np.sqrt(np.mean(truth)) * 1e3
    assert np.mean(at) == pytest.approx(truth_mm, rel=0.3), (np.mean(at), truth_mm)
    assert np.mean(cv) < 0.75 * truth_mm, (np.mean(cv), truth_mm)
