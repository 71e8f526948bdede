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
def test_variance_model_is_the_maximum_likelihood_of_the_region_model(a_true, b_true):
    # held-out errors drawn from the region's own model N(0, b S + a/3 I): the fit is the maximum of the
    # Gaussian likelihood (checked against scipy's multivariate normal density maximised by Nelder-Mead over
    # log-parameters) and recovers the truth on 400 points
    from scipy.optimize import minimize
    from scipy.stats import multivariate_normal

    rng = np.random.default_rng(1)
    S = _cov(rng, 400, rng.uniform(0.2e-3, 2e-3, 400))
    Sig = b_true * S + a_true / 3 * np.eye(3) + 1e-14 * np.eye(3)
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(Sig), rng.standard_normal((400, 3)))
    floor = 0.01 * float(np.mean(e ** 2))
    a, b = variance_model(e, S, tau2_floor=floor)

    def nll(x, e=e, S=S):  # x = log(b), log(τ² − floor), in mm²: the Gaussian density by determinant and solve
        bb, tt = np.exp(x[0]), floor * 1e6 + np.exp(x[1])
        C = bb * S * 1e6 + tt * np.eye(3)
        em = e * 1e3
        return 0.5 * float(np.sum(np.linalg.slogdet(C)[1]) + np.einsum("ni,ni->", em, np.linalg.solve(C, em[..., None])[..., 0]))

    x1 = [np.log(b_true + 0.1), np.log(1e-3)]  # the density itself, against scipy's, at one point
    C1 = np.exp(x1[0]) * S[:5] * 1e6 + (floor * 1e6 + np.exp(x1[1])) * np.eye(3)
    scipy_nll = -sum(multivariate_normal.logpdf(e[i] * 1e3, cov=C1[i]) for i in range(5)) - 7.5 * np.log(2 * np.pi)
    assert nll(x1, e[:5], S[:5]) == pytest.approx(scipy_nll, rel=1e-10)

    ref = min((minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 3000})
               for x0 in ([np.log(b_true + 0.5), np.log(a_true / 3 * 1e6 + 1e-3)], [0.0, -3.0])), key=lambda r: r.fun)
    assert nll([np.log(b), np.log(max(a / 3 * 1e6 - floor * 1e6, 1e-300))]) <= ref.fun + 1e-6
    assert b == pytest.approx(np.exp(ref.x[0]), rel=1e-3, abs=1e-4)
    assert a / 3 * 1e6 == pytest.approx(floor * 1e6 + np.exp(ref.x[1]), rel=1e-3, abs=1e-6)
    assert b == pytest.approx(b_true, rel=0.2)
    assert a == pytest.approx(max(a_true, 3 * floor), rel=0.3, abs=0.3e-6)
    # b_min: a bound the fit respects, active when the truth lies below it
    a1, b1 = variance_model(e, S, b_min=b_true + 1.0)
    assert b1 == pytest.approx(b_true + 1.0) and a1 >= 0


def test_variance_model_weighs_the_direction_of_the_error():
    # the same squared norms, errors along the large-variance direction of S or across it: the likelihood
    # gives the first to b and the second to a (a line of |e|² on tr S sees no difference)
    rng = np.random.default_rng(5)
    n = 300
    U = np.linalg.qr(rng.standard_normal((n, 3, 3)))[0]
    lam = np.array([1e-6, 1e-8, 1e-8]) * rng.uniform(0.5, 2.0, (n, 1))
    S = np.einsum("nij,nj,nkj->nik", U, lam, U)
    size = np.sqrt(2e-6 + lam[:, 0]) * rng.standard_normal(n)
    along = U[:, :, 0] * size[:, None]
    across = U[:, :, 1] * size[:, None]
    a_al, b_al = variance_model(along, S)
    a_ac, b_ac = variance_model(across, S)
    assert b_al > 5 * b_ac
    assert a_ac > 5 * a_al


def test_predicted_rmse_at_is_the_root_mean_of_the_line():
    rng = np.random.default_rng(2)
    S = _cov(rng, 50, np.full(50, 1e-3))
    a, b = 3e-6, 2.0
    by_hand = np.sqrt(np.mean([a + b * (S[i, 0, 0] + S[i, 1, 1] + S[i, 2, 2]) for i in range(50)]))
    assert predicted_rmse_at(a, b, S) == pytest.approx(by_hand, rel=1e-12)
    # beyond the largest leverage the line was fitted on, a point is held at it
    tr = np.array([np.trace(S[i]) for i in range(50)])
    cap = float(np.median(tr))
    held = np.sqrt(np.mean([a + b * min(t, cap) for t in tr]))
    assert predicted_rmse_at(a, b, S, leverage_max=cap) == pytest.approx(held, rel=1e-12)
    assert predicted_rmse_at(a, b, S, leverage_max=cap) < predicted_rmse_at(a, b, S)
    assert predicted_rmse_at(a, b, S, leverage_max=tr.max()) == pytest.approx(by_hand, rel=1e-12)
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
    from estcal.discrepancy import diagnose
    from estcal.kinematics.robots import puma560
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
        res = diagnose(sim.nominal_robot, data, validate=[targets], noise=sigma, effects=(), geometric="full",
                       time_blocks=False)
        v = res.accuracy["validation"][0]
        assert v["n_new"] == targets.n and not v["registered"]
        truth.append((v["rmse_mm"] * 1e-3) ** 2 + 3 * sigma ** 2)
        at.append(v["predicted_mm"])
        cv.append(res.answer["expected_mm"])
    truth_mm = np.sqrt(np.mean(truth)) * 1e3
    assert np.mean(at) == pytest.approx(truth_mm, rel=0.3), (np.mean(at), truth_mm)
    assert np.mean(cv) < 0.75 * truth_mm, (np.mean(cv), truth_mm)


def test_region_and_prediction_cover_a_misspecified_model_used_beyond_its_joint_range():
    # the model extrapolates: joint 2 trained on one half of its range [0, π/2] and used on the other half,
    # and the truth has an error outside the model (joint 3's axis tilts by 3 mrad · sin q₃), so the fit's
    # parameter covariance alone says nothing of the error there. Monte Carlo over 8 draws (postures,
    # geometric errors, noise): the 95 % region covers 85–100 % of the target points and the prediction at
    # the targets (their readings only) is within 30 % of the RMSE measured there.
    import sys
    from pathlib import Path

    from estcal.discrepancy import diagnose
    from estcal.kinematics.robots import puma560
    from estcal.simulate import simulate

    sys.path.insert(0, str(Path(__file__).parent))
    from test_residual_budget import _noisy, _tilted

    cover, pred_sq, meas_sq, beyond = [], [], [], []
    for draw in range(8):
        rng = np.random.default_rng(draw)
        Q, Qt = rng.uniform(-0.5, 0.5, (20, 6)) * np.pi, rng.uniform(-0.5, 0.5, (40, 6)) * np.pi
        Q[:, 1], Qt[:, 1] = rng.uniform(0, 0.5, 20) * np.pi, rng.uniform(-0.5, 0, 40) * np.pi
        sim = simulate(puma560(), readings=np.r_[Q, Qt], measure="points", errors="random", n_points=2, seed=draw)
        data = _noisy(sim, _tilted(sim, 3, 3e-3), 100 + draw)
        train, targets = data.subset(np.arange(20)), data.subset(np.arange(20, 60))
        res = diagnose(sim.nominal_robot, train, validate=[targets], effects=(), geometric="full", time_blocks=False)
        r = res.accuracy["validation"][0]
        cover.append(r["coverage"])
        pred_sq.append(r["predicted_mm"] ** 2)
        meas_sq.append(r["rmse_mm"] ** 2)
        beyond.append(r["beyond_cv_leverage"])
    assert 0.85 <= np.mean(cover) <= 1.0, cover
    assert np.sqrt(np.mean(pred_sq) / np.mean(meas_sq)) == pytest.approx(1.0, abs=0.3)
    assert np.mean(beyond) > 0.2  # the targets lie beyond what the nested CV held out


def test_slope_upper_is_the_profile_likelihood_bound_and_covers():
    from estcal.discrepancy.prediction import slope_upper

    rng = np.random.default_rng(7)

    def draw(n, b_true=2.0, a_true=3e-6):
        S = _cov(rng, n, rng.uniform(0.2e-3, 1.5e-3, n))
        Sig = b_true * S + a_true / 3 * np.eye(3)
        return np.einsum("nij,nj->ni", np.linalg.cholesky(Sig), rng.standard_normal((n, 3))), S

    e, S = draw(80)
    a, b = variance_model(e, S)
    bu = slope_upper(e, S, b)

    def nll_profile(bb):  # τ² profiled out on a fine grid, the density by determinant and solve
        def nll(t2):
            C = bb * S + t2 * np.eye(3)
            return 0.5 * float(np.sum(np.linalg.slogdet(C)[1]) + np.einsum("ni,ni->", e, np.linalg.solve(C, e[..., None])[..., 0]))
        return min(nll(t2) for t2 in np.geomspace(1e-8, 1e-4, 800))

    assert bu > b
    assert nll_profile(bu) - nll_profile(b) == pytest.approx(2.705543 / 2, abs=0.02)
    # one-sided 95 %: the true slope lies below the bound in about 95 % of the draws
    hits = []
    for _ in range(60):
        e, S = draw(40)
        hits.append(2.0 <= slope_upper(e, S, variance_model(e, S)[1]))
    assert np.mean(hits) >= 0.85


def test_validation_rows_extrapolating_farther_than_the_nested_cv_are_flagged():
    """``reach_at``: joint 2 of a PUMA trained on [0, 0.3π]; targets at −0.6π (twice the range beyond it, farther
    than any held-out posture of the nested CV went beyond its fold's range) are flagged, with the joint named —
    the distance recomputed here from the readings — and the text says the prediction is untested there."""
    from estcal.discrepancy import diagnose
    from estcal.kinematics.robots import puma560
    from estcal.simulate import simulate

    rng = np.random.default_rng(3)
    Q = rng.uniform(-0.4, 0.4, (24, 6)) * np.pi
    Q[:, 1] = rng.uniform(0.0, 0.3, 24) * np.pi
    far = Q[:6].copy()
    far[:, 1] = -0.6 * np.pi
    sim = simulate(puma560(), readings=np.r_[Q, far], measure="position", errors="random", seed=3,
                   noise={"position": 1e-4})
    train, targets = sim.dataset.subset(np.arange(24)), sim.dataset.subset(np.arange(24, 30))
    res = diagnose(sim.nominal_robot, train, validate=[targets], effects=(), geometric="full", k_folds=4,
                   time_blocks=False)
    cv = res.budget["extrapolation"]["cv_reach_max"]
    assert 0.0 < cv < 2.0  # the folds' held-out postures do extrapolate, but not that far
    r = res.accuracy["validation"][0]
    lo, hi = Q[:, 1].min(), Q[:, 1].max()
    assert r["reach_joint"] == sim.nominal_robot.joint_names[1]
    assert r["reach_max"] == pytest.approx((lo + 0.6 * np.pi) / (hi - lo), rel=1e-12)
    assert r["beyond_cv_reach"] == 1.0
    text = str(res)
    assert "extrapolate farther than the cross-validation tried" in text and "untested" in text
    # readings inside the training ranges are not flagged
    from estcal.discrepancy.budget import reach_at

    inside = reach_at(res.budget, Q, Q[:5], sim.nominal_robot.joint_names)
    assert inside["reach_max"] == 0.0 and inside["beyond_cv_reach"] == 0.0


def test_budget_says_when_the_geometry_alone_predicts_better():
    """The budget's hint: the geometry alone scoring lower than the model at new postures (the nested CV's figures,
    known before any validation file is read) points at `--effects none`; otherwise nothing."""
    from estcal.discrepancy.budget import budget_lines

    b = {"folds": "posture", "k_folds": 5, "n_postures": 16, "n_rows": 16, "nominal_mm": 9.0,
         "geometry_mm": 3.77, "model_mm": 4.09, "model_se_mm": 0.2, "repeatability_mm": None, "time": {}}
    assert any("--effects none" in line for line in budget_lines(b))
    assert any("(3.770 against 4.090 ± 0.200 mm)" in line for line in budget_lines(b))
    assert not any("--effects none" in line for line in budget_lines(dict(b, geometry_mm=5.0)))
