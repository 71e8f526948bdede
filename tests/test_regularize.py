"""MAP / ridge calibration (Gaussian prior rows in calibrate_lsq) and the choice of its width by
leave-one-pose-out CV (estcal.estimate.regularize), each against an independent computation."""
import numpy as np
import pytest

from estcal.estimate import calibrate_lsq
from estcal.estimate.factorgraph import calibrate_gtsam
from estcal.workflows.calibrate import run_calibration
from estcal.estimate.regularize import choose_prior_std, loo_curve
from estcal.estimate.testproblems import simulated_problem


def test_map_lm_matches_gtsam_prior_factors():
    """Another estimator: gtsam with PriorFactorVector on every free parameter (same σ, same mean)."""
    sim = simulated_problem("puma560", n_poses=30, seed=21)
    g = calibrate_gtsam(sim.problem, prior_std=1e-3)
    for method in ("lm", "gauss-newton", "scipy-lm"):
        r = calibrate_lsq(sim.problem, method, prior_std=1e-3)
        assert np.abs((r.estimate - g.estimate) / g.std).max() < 1e-4, method
        np.testing.assert_allclose(r.std, g.std, rtol=1e-4)


def test_prior_moves_estimate_toward_mean_and_vanishes_when_wide():
    sim = simulated_problem("puma560", n_poses=30, seed=22)
    plain = calibrate_lsq(sim.problem)
    wide = calibrate_lsq(sim.problem, prior_std=1e3)
    assert np.abs((wide.estimate - plain.estimate) / plain.std).max() < 1e-6
    tight = calibrate_lsq(sim.problem, prior_std=1e-7)  # far below the data's precision
    assert np.abs(tight.estimate - plain.nominal).max() < 1e-6
    assert tight.extra["prior"]["effective_parameters"] < 0.1


def test_partial_prior_covariance_is_the_linear_posterior():
    """Σ = (HᵀWH + T⁻¹)⁻¹ recomputed at the solution, prior on the 'd_*' and 'a_*' parameters only."""
    sim = simulated_problem("puma560", n_poses=25, seed=23, method="position", sigma_p=2e-4)
    r = calibrate_lsq(sim.problem, prior_std={"d_*": 5e-4, "a_*": 5e-4})
    pen = [n for n in r.names if n.startswith(("d_", "a_"))]
    assert sorted(r.extra["prior"]["std"]) == sorted(pen) and pen
    rows = sim.problem.evaluate(r.theta)
    idx = sim.problem.params.indices(r.names)
    A = rows.H[:, idx] / rows.sigma[:, None]
    T = np.diag([5e-4 ** -2 if n in pen else 0.0 for n in r.names])
    cov = np.linalg.inv(A.T @ A + T)
    np.testing.assert_allclose(r.covariance, cov, rtol=1e-6, atol=1e-18)
    p_eff = np.trace(cov @ A.T @ A)
    assert r.extra["prior"]["effective_parameters"] == pytest.approx(p_eff, rel=1e-8)
    assert len(r.names) - len(pen) < p_eff < len(r.names)
    with pytest.raises(ValueError, match="matches no free parameter"):
        calibrate_lsq(sim.problem, prior_std={"nothing_*": 1e-3})


def _brute_force_loo(problem, free, penalised, tau, theta):
    """Refit the linearised ridge problem without each pose and predict it (independent of PRESS)."""
    prob = problem.with_free(free)
    idx = prob.params.indices(free)
    rows = prob.evaluate(theta)
    A = rows.H[:, idx] / rows.sigma[:, None]
    b = rows.e / rows.sigma
    prior = np.diag([1.0 / tau if n in penalised else 0.0 for n in free])
    keep = np.any(prior != 0, axis=1)
    sq, npts = 0.0, 0
    for i in np.unique(rows.pose):
        out = rows.pose == i
        Aa = np.vstack([A[~out], prior[keep]])
        ba = np.concatenate([b[~out], np.zeros(keep.sum())])
        x = np.linalg.lstsq(Aa, ba, rcond=None)[0]
        pos = out & (rows.kind == 0)  # the score is the position error (orientation rows only fit)
        e = (b[pos] - A[pos] @ x) * rows.sigma[pos]
        sq += float(e @ e)
        npts += pos.sum() // 3
    return np.sqrt(sq / npts)


@pytest.mark.parametrize("method", ["position", "location"])
def test_block_press_equals_refitting_without_each_pose(method):
    sim = simulated_problem("puma560", n_poses=15, seed=24, method=method, deviation=(2e-3, 2e-3))
    free = sim.free
    penalised = [n for n in free if not n.startswith("base_")]
    theta = sim.problem.params.values  # nominal: far from the truth, residuals are large
    taus = [3e-4, 3e-3, np.inf]
    ours = loo_curve(sim.problem, free, penalised, taus, theta)
    ref = [_brute_force_loo(sim.problem, free, penalised, t, theta) for t in taus]
    np.testing.assert_allclose(ours, ref, rtol=1e-8)


def test_cv_chosen_prior_improves_prediction_when_the_data_are_weak():
    """Few, noisy position measurements of small true deviations: the CV-chosen prior must predict
    new poses better than plain least squares (the situation the regulariser is for)."""
    sim = simulated_problem("puma560", n_poses=14, seed=25, method="position", sigma_p=1e-3,
                            deviation=(2e-4, 2e-4))
    free = sim.free
    penalised = [n for n in free if not n.startswith("base_")]
    choice = choose_prior_std(sim.problem, free, penalised)
    assert np.isfinite(choice.tau)
    assert choice.to_dict()["loo_rmse_mm"] < choice.loo_rmse_unregularised_mm
    plain = calibrate_lsq(sim.problem)
    ridge = calibrate_lsq(sim.problem, prior_std=choice.prior_std)
    # noise-free prediction error on 500 fresh poses
    rob = sim.problem.robot
    q = rob.random_readings(500, np.random.default_rng(5), margin=0.05)
    truth_p = rob.kinematics(q, sim.truth, jacobian=False).p

    def err(r):
        return np.sqrt(np.mean(np.sum((rob.kinematics(q, r.theta, jacobian=False).p - truth_p) ** 2, axis=1)))

    assert err(ridge) < 0.8 * err(plain)


def test_run_calibration_regularize_errors_and_record():
    sim = simulated_problem("puma560", n_poses=20, seed=26, method="location")
    robot, data = sim.problem.robot, sim.problem.terms[0].data
    with pytest.raises(ValueError, match="least-squares estimator"):
        run_calibration(robot, data, estimator="kalman", level="full", regularize="loo")
    with pytest.raises(ValueError, match="unknown regularize"):
        run_calibration(robot, data, level="full", regularize="gcv")
    res, _, _ = run_calibration(robot, data, level="full", regularize=1e-3)
    assert "prior" in res.extra and all(not n.startswith("base_") for n in res.extra["prior"]["std"])
    res, _, _ = run_calibration(robot, data, level="full", regularize="loo")
    reg = res.extra["regularization"]
    assert len(reg["curve"]["tau"]) == len(reg["curve"]["loo_rmse_mm"]) and reg["loo_rmse_mm"] > 0


def test_repeated_postures_leave_together():
    """The same 12 postures in two terms (two sessions): the block PRESS holds out both copies of a
    posture, equal to refitting without them; a leave-one-row-out would score memory."""
    from estcal.methods import Problem

    sim = simulated_problem("puma560", n_poses=12, seed=26, method="position", deviation=(2e-3, 2e-3))
    t = sim.problem.terms[0]
    d2 = t.data.subset(slice(None))
    d2.points = d2.points + 1e-4 * np.random.default_rng(0).standard_normal(d2.points.shape)
    prob = Problem(sim.problem.robot, [(t.method, t.data, t.noise), (t.method, d2, t.noise)])
    free = sim.free
    penalised = [n for n in free if not n.startswith("base_")]
    theta = prob.params.values
    p2 = prob.with_free(free)
    idx = p2.params.indices(free)
    rows = p2.evaluate(theta)
    A = rows.H[:, idx] / rows.sigma[:, None]
    b = rows.e / rows.sigma
    for tau in (3e-4, np.inf):
        prior = np.diag([1.0 / tau if n in penalised else 0.0 for n in free])
        keep = np.any(prior != 0, axis=1)
        sq, npts = 0.0, 0
        for i in range(12):
            out = rows.pose == i  # pose i of both terms: one posture
            x = np.linalg.lstsq(np.vstack([A[~out], prior[keep]]), np.r_[b[~out], np.zeros(keep.sum())],
                                rcond=None)[0]
            e = (b[out] - A[out] @ x) * rows.sigma[out]
            sq += float(e @ e)
            npts += out.sum() // 3
        ours = loo_curve(prob, free, penalised, [tau], theta)[0]
        assert ours == pytest.approx(np.sqrt(sq / npts), rel=1e-8)
