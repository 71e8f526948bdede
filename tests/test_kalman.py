"""Kalman filtering (filterpy EKF/UKF), offline Riccati analysis and innovation tests."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from estcal.estimate.kalman import ParameterFilter, calibrate_kalman, process_noise
from estcal.estimate.lsq import calibrate_lsq
from estcal.estimate.riccati import (covariance_sequence, information_matrix, periodic_steady_state,
                                     planned_jacobians, repetition_covariance, riccati_residual, steady_state,
                                     stopping_index, stopping_index_sequence)
from estcal.estimate.testproblems import drifting_problem, simulated_problem

D = np.pi / 180


@pytest.fixture(scope="module")
def puma():
    sim = simulated_problem("puma560", n_poses=100, seed=3)
    return sim, calibrate_lsq(sim.problem)


# --------------------------------------------------------------- linear algebra of the recursion
def _two_link_H(r1, r2, t1, t2):
    """Digest §5.3, corrected (4.217–4.218): rows of ∂(x, y)/∂(θ1, θ2, r1, r2), derived by hand."""
    t1, t2 = t1 * D, t2 * D
    s1, c1, s12, c12 = np.sin(t1), np.cos(t1), np.sin(t1 + t2), np.cos(t1 + t2)
    return np.array([[-r1 * s1 - r2 * s12, -r2 * s12, c1, c12], [r1 * c1 + r2 * c12, r2 * c12, s1, s12]])


def test_two_link_jacobian_matches_planar2_robot():
    from estcal.kinematics.robots import planar2

    rob = planar2(1.0, 0.8)
    q = np.array([[0.3, -1.1]])
    J = rob.kinematics(q).J[0, :2]
    names = rob.params.names
    cols = [names.index("offset_1"), names.index("offset_2"), names.index("a_1"), names.index("a_2")]
    np.testing.assert_allclose(J[:, cols], _two_link_H(1.0, 0.8, 0.3 / D, -1.1 / D), atol=1e-12)


P0_BOOK = np.diag([0.05, 0.05, 0.1, 0.1])
S_BOOK = np.array([[0.2, 0.1], [0.1, 0.2]])


def _F(r1, r2, poses, c=1.0):
    return information_matrix([_two_link_H(r1, r2, *q) for q in poses], [c * S_BOOK] * len(poses))


def test_stopping_index_reproduces_digest_notes():
    # digest §5.3 reproduction notes: correct Jacobian + symmetric P(j) give Ex.1 = 537, Ex.2 = 91,
    # Ex.3 = 10 / 11 / 11 (2 / 1 / ∞ norms), case 4 M = 2.
    assert stopping_index(_F(1, 1, [(45, 33), (57, -5)]), P0_BOOK, 0.1)["M"] == 537
    assert stopping_index(_F(10, 9, [(45, 33), (57, -5)]), P0_BOOK, 0.1)["M"] == 91
    F3 = _F(10, 9, [(45, 33), (57, -5)], 0.1)
    assert [stopping_index(F3, P0_BOOK, 0.1, norm=n)["M"] for n in (2, 1, np.inf)] == [10, 11, 11]
    assert stopping_index(_F(10, 9, [(0, 90), (45, -90)], 0.1), P0_BOOK, 0.1)["M"] == 2
    # scaling Σ_Ψ by c moves the crossing to c·t*
    r = stopping_index(_F(1, 1, [(45, 33), (57, -5)]), P0_BOOK, 0.1)
    r2 = stopping_index(_F(1, 1, [(45, 33), (57, -5)], 0.3), P0_BOOK, 0.1)
    assert r2["M"] == int(np.ceil(0.3 * r["t_star"]))
    assert r["M1"] >= r["M"] * 0 and r["M1"] >= 1


def test_repetition_covariance_equals_recursion_and_is_symmetric():
    poses = [(45, 33), (57, -5)]
    Hs = [_two_link_H(1, 1, *q) for q in poses] * 7
    Ps = covariance_sequence(Hs, [S_BOOK] * len(Hs), P0_BOOK)
    Pj = repetition_covariance(_F(1, 1, poses), P0_BOOK, 7)
    np.testing.assert_allclose(Ps[-1], Pj, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(Pj, Pj.T, atol=1e-15)
    # closed form (P0⁻¹ + jF)⁻¹
    np.testing.assert_allclose(Pj, np.linalg.inv(np.linalg.inv(P0_BOOK) + 7 * _F(1, 1, poses)), rtol=1e-9)


def test_dare_floor_satisfies_eq_4_113_and_is_the_recursion_limit():
    rng = np.random.default_rng(0)
    H = rng.standard_normal((8, 4))
    R = np.diag(rng.uniform(0.5, 2, 8))
    A = rng.standard_normal((4, 4))
    Q = 1e-2 * (A @ A.T + np.eye(4))
    P_inf = steady_state(H, R, Q)
    assert np.abs(riccati_residual(P_inf, H, R, Q)).max() < 1e-12
    Ps = covariance_sequence([H] * 400, R, np.eye(4), Q)
    np.testing.assert_allclose(Ps[-1], P_inf, rtol=1e-8, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(P_inf) > 0)
    # periodic solution of the same pass fed row block by row block ends at the same floor
    # when the pass is measured all at once (one step) — consistency of the two routes
    Pp, _ = periodic_steady_state([H], [R], Q)
    np.testing.assert_allclose(Pp, P_inf, rtol=1e-8)
    M = stopping_index_sequence(Ps, P_inf, 1e-3 * np.linalg.norm(P_inf, 2))
    assert 1 < M < 400
    with pytest.raises(ValueError, match="rank"):
        steady_state(H[:2], R[:2, :2], Q)


def test_q_zero_covariance_goes_to_zero_like_one_over_k():
    rob_H, s, _ = planned_jacobians(__import__("estcal.kinematics.robots", fromlist=["planar2"]).planar2(),
                                    np.random.default_rng(1).uniform(-3, 3, (400, 2)), "position",
                                    free=["a_1", "a_2", "offset_1", "offset_2"])
    Hs = rob_H[:, :2]  # planar arm: x, y rows only (z row is zero)
    tr = covariance_sequence(list(Hs), [np.diag(si[:2] ** 2) for si in s], np.eye(4) * 0.01, out="trace")
    ratio = tr[99] / tr[399]
    assert 3.2 < ratio < 4.8  # ≈ 4 for a 4× longer sequence


# --------------------------------------------------------------- filter on a simulated PUMA
def test_ekf_after_all_rows_equals_batch_lm(puma):
    sim, lm = puma
    kf = calibrate_kalman(sim.problem)  # Q = 0, wide prior, one pass
    z = (kf.estimate - lm.estimate) / lm.std
    assert np.abs(z).max() < 0.1
    np.testing.assert_allclose(kf.std, lm.std, rtol=1e-3)
    assert kf.names == lm.names
    # iterated passes converge to the MAP (= LM up to the negligible wide prior)
    kf3 = calibrate_kalman(sim.problem, passes=3)
    assert np.abs((kf3.estimate - lm.estimate) / lm.std).max() < 1e-3
    # batch-by-batch gives the same final answer as row by row (linear-Gaussian algebra)
    kfb = calibrate_kalman(sim.problem, batch_size=10, passes=3)
    assert np.abs((kfb.estimate - lm.estimate) / lm.std).max() < 1e-3
    d = kf.to_dict()
    assert d["method"] == "kalman" and "innovation" in d and set(d["parameters"]) == set(lm.names)


def test_ukf_close_to_lm(puma):
    sim, lm = puma
    uk = calibrate_kalman(sim.problem, filter="ukf")
    # single pass with statistical linearisation of the early, wide-prior steps: looser than the EKF
    assert np.abs((uk.estimate - lm.estimate) / lm.std).max() < 1.0
    np.testing.assert_allclose(uk.std, lm.std, rtol=0.1)
    # with a prior of the size of the corrections the second-order mean term is negligible: ≈ MAP
    uk2 = calibrate_kalman(sim.problem, filter="ukf", prior_std=3e-3)
    map2 = calibrate_kalman(sim.problem, prior_std=3e-3, passes=3)
    assert np.abs((uk2.estimate - map2.estimate) / map2.std).max() < 0.1
    np.testing.assert_allclose(uk2.std, map2.std, rtol=5e-3)


def test_filter_covariance_is_data_independent(puma):
    sim, _ = puma
    pv = sim.problem.params
    H, s, names = planned_jacobians(sim.problem.robot, sim.problem.terms[0].data.readings, "location",
                                    free=sim.free, sigma_p=1e-4, sigma_r=1e-4)
    P0 = np.eye(len(names)) * 0.01
    Ps = covariance_sequence(list(H), list(s), P0)
    kf = calibrate_kalman(sim.problem, P0=P0, passes=1)
    # filter P (not rescaled: noise known) vs the recursion at nominal H; equal to first order
    np.testing.assert_allclose(kf.std, np.sqrt(np.diag(Ps[-1])), rtol=2e-2)
    assert pv.free_names == names


def test_process_noise_forms():
    names = ["a_1", "a_2", "theta_2"]
    np.testing.assert_allclose(process_noise(names, 2.0), 4 * np.eye(3))
    np.testing.assert_allclose(np.diag(process_noise(names, {"a_*": 1e-3})), [1e-6, 1e-6, 0])
    with pytest.raises(ValueError, match="matches no"):
        process_noise(names, {"gain_*": 1.0})


# --------------------------------------------------------------- innovation tests
def test_innovation_tests_calibrated_under_the_model():
    """Correct linear-Gaussian model: the test's false-alarm rate ≈ α (binomial tolerance)."""
    rng = np.random.default_rng(5)
    p, m, K, runs = 3, 2, 60, 200
    fires = 0
    for _ in range(runs):
        x = rng.standard_normal(p)
        flt = ParameterFilter(np.zeros(p), np.arange(p), np.eye(p), kind="ekf")

        class Lin:
            def __init__(self, H, z):
                self.H, self.z = H, z

            def evaluate(self, theta, jacobian=True):
                from estcal.methods.base import Rows

                e = self.z - self.H @ theta
                return Rows(e, self.H, np.ones(m), np.zeros(m, int), np.zeros(m, int))

        for _k in range(K):
            H = rng.standard_normal((m, p))
            flt.step(Lin(H, H @ x + rng.standard_normal(m)))
        fires += flt.monitor.tests(burn_in=0, lags=5).fires
    lo, hi = stats.binom.ppf([0.0005, 0.9995], runs, 0.05)
    assert fires <= hi  # Bonferroni over three tests: rate ≤ α


def test_unmodelled_effect_fires_innovation_test():
    # truth has a gear-ratio error on joint 2 that the estimated model does not have (gain fixed)
    sim0 = simulated_problem("puma560", n_poses=100, seed=7)
    truth = sim0.truth.copy()
    truth[sim0.problem.params.index("gain_2")] *= 1.002
    sim = simulated_problem("puma560", n_poses=100, seed=7, truth=truth, free=sim0.free)
    bad = calibrate_kalman(sim.problem)
    good = calibrate_kalman(sim0.problem)
    assert bad.extra["innovation"]["fires"]
    assert not good.extra["innovation"]["fires"]


def test_drift_tracked_with_q_not_with_q0():
    sim = drifting_problem("puma560", n_poses=200, seed=2, drift={"theta_2": 3e-3})
    i = sim.free.index("theta_2")
    k0 = calibrate_kalman(sim.problem, q=0.0)
    kq = calibrate_kalman(sim.problem, q={"theta_2": 3e-3 / 200 * 2})
    err0 = (k0.estimate[i] - sim.truth_free[i]) / k0.std[i]
    errq = (kq.estimate[i] - sim.truth_free[i]) / kq.std[i]
    assert abs(errq) < 3.5
    assert abs(err0) > 6
    assert k0.extra["innovation"]["fires"]


def test_recursion_equals_information_form_property():
    """Q = 0: the recursion's P_K equals (P0⁻¹ + Σ Hᵀ R⁻¹ H)⁻¹ (4.70) for random problems."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=25, deadline=None)
    @given(st.integers(1, 6), st.integers(1, 4), st.integers(1, 12), st.integers(0, 10_000))
    def check(p, m, K, seed):
        rng = np.random.default_rng(seed)
        Hs = [rng.standard_normal((m, p)) for _ in range(K)]
        Rs = [np.diag(rng.uniform(0.1, 2.0, m)) for _ in range(K)]
        A = rng.standard_normal((p, p))
        P0 = A @ A.T + 0.5 * np.eye(p)
        P = covariance_sequence(Hs, Rs, P0)[-1]
        info = np.linalg.inv(P0) + information_matrix(Hs, Rs)
        np.testing.assert_allclose(P, np.linalg.inv(info), rtol=1e-8, atol=1e-10)
        # and the repetition formula for K copies of the first measurement
        Pj = repetition_covariance(information_matrix(Hs[:1], Rs[:1]), P0, K)
        np.testing.assert_allclose(Pj, covariance_sequence(Hs[:1] * K, Rs[:1] * K, P0)[-1], rtol=1e-7, atol=1e-10)

    check()


def test_plan_calibration_predicts_the_filter(puma):
    from estcal.estimate.riccati import plan_calibration

    sim, _ = puma
    readings = sim.problem.terms[0].data.readings
    plan = plan_calibration(sim.problem.robot, readings, "location", free=sim.free, sigma_p=1e-4, sigma_r=1e-4,
                            prior_std=0.1, eps=1e-6)
    kf = calibrate_kalman(sim.problem, prior_std=0.1)
    np.testing.assert_allclose(plan.std[-1], kf.std, rtol=2e-2)
    assert 1 <= plan.stop <= len(readings) and "4.220" in plan.rule
    cyc = np.tile(readings[:25], (8, 1))  # a 25-pose cycle measured 8 times
    planq = plan_calibration(sim.problem.robot, cyc, "location", free=sim.free, sigma_p=1e-4, sigma_r=1e-4,
                             q=1e-5, cycle=25)
    assert np.all(planq.floor_std > 0) and planq.stop % 25 == 0
    assert "stop after" in str(planq) and planq.to_dict()["stop"] == planq.stop
