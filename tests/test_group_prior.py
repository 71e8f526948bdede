"""A prior per parameter group (estcal.estimate.regularize: prior_groups, log_evidence, evidence_widths,
fit_group_prior), each against an independent computation: the dense Gaussian marginal likelihood, MacKay's
fixed-point equations at the evidence optimum, and simulated robots whose true deviation scale is known."""
import numpy as np
import pytest

from estcal.estimate import calibrate_lsq
from estcal.estimate.regularize import evidence_widths, fit_group_prior, log_evidence, prior_groups
from estcal.estimate.testproblems import simulated_problem
from estcal.identify.select import UnidentifiableError
from estcal.kinematics import puma560, tiago
from estcal.methods import Problem


def _linear_model(seed=0, M=60, p_pen=(4, 3), p_free=2, taus=(0.5, 2.0), s=0.3):
    rng = np.random.default_rng(seed)
    group_of = np.concatenate([np.full(n, g) for g, n in enumerate(p_pen)] + [np.full(p_free, -1)])
    A = rng.standard_normal((M, group_of.size))
    x = np.where(group_of >= 0, np.asarray(taus)[np.maximum(group_of, 0)], 3.0) * rng.standard_normal(group_of.size)
    return A, A @ x + s * rng.standard_normal(M), group_of


def test_log_evidence_is_the_dense_gaussian_marginal():
    """N(0, s²I + A T Aᵀ) by scipy; the flat-prior columns as the limit of wide ones (+ log τ each)."""
    from scipy.stats import multivariate_normal

    A, y, group_of = _linear_model()
    log_tau, s2 = np.log([0.7, 1.9]), 0.2
    tau_free = 1e3
    t = np.where(group_of >= 0, np.exp(log_tau)[np.maximum(group_of, 0)], tau_free)
    dense = multivariate_normal(np.zeros(len(y)), s2 * np.eye(len(y)) + (A * t ** 2) @ A.T).logpdf(y)
    ours = log_evidence(A, y, group_of, log_tau, np.log(s2))
    assert ours == pytest.approx(dense + np.sum(group_of < 0) * np.log(tau_free), abs=1e-4)
    # all columns penalised: exactly the dense marginal
    g2 = np.maximum(group_of, 0)
    dense2 = multivariate_normal(np.zeros(len(y)), s2 * np.eye(len(y)) + (A * np.exp(log_tau)[g2] ** 2) @ A.T).logpdf(y)
    assert log_evidence(A, y, g2, log_tau, np.log(s2)) == pytest.approx(dense2, rel=1e-10)


def test_evidence_optimum_satisfies_mackays_fixed_point():
    """At the type-II maximum: τ_g² = ‖m_g‖²/γ_g and s² = ‖y − Am‖²/(M − γ) with γ_g = Σ_g (1 − Σ_jj/τ_g²),
    γ = Σ_g γ_g + number of free columns (MacKay 1992, Neural Comput. 4:415, eqs. 4.9–4.10)."""
    A, y, group_of = _linear_model(seed=3, M=200, p_pen=(8, 6))
    log_tau, log_s2, _ = evidence_widths(A, y, group_of, 2)
    tau2, s2 = np.exp(2 * log_tau), np.exp(log_s2)
    prec = np.where(group_of >= 0, 1.0 / tau2[np.maximum(group_of, 0)], 0.0)
    Sig = np.linalg.inv(A.T @ A / s2 + np.diag(prec))
    m = Sig @ A.T @ y / s2
    gam = 1.0 - np.diag(Sig) * prec
    for g in range(2):
        sel = group_of == g
        assert tau2[g] == pytest.approx(np.sum(m[sel] ** 2) / np.sum(gam[sel]), rel=2e-3)
    r = y - A @ m
    assert s2 == pytest.approx(r @ r / (len(y) - gam.sum()), rel=2e-3)


def test_prior_groups_by_unit_and_meaning(tiago_dir):
    r = tiago(n_markers=1)
    g = prior_groups(r, ["tx_arm_1_joint", "rz_arm_1_joint", "offset_arm_2_joint", "offset_torso_lift_joint",
                         "tool_tz", "tool_rx", "base_tx"])
    assert g == {"tx_arm_1_joint": "length", "rz_arm_1_joint": "angle", "offset_arm_2_joint": "offset",
                 "offset_torso_lift_joint": "offset_length", "tool_tz": "length", "tool_rx": "angle", "base_tx": "base"}
    p = puma560()
    g = prior_groups(p, ["d_2", "a_3", "alpha_3", "theta_2", "beta_3"])
    assert g == {"d_2": "length", "a_3": "length", "alpha_3": "angle", "theta_2": "angle", "beta_3": "angle"}


def _narrow_then_wide(seed, n_train, deviation):
    """PUMA 560 measured (points, 0.05 mm) at ``n_train`` postures within ±0.3π, scored at 200 postures within
    ±0.8π: data that determine the parameters poorly, used far beyond their span."""
    rng = np.random.default_rng(seed)
    q = np.vstack([rng.uniform(-0.3 * np.pi, 0.3 * np.pi, (n_train, 6)), rng.uniform(-0.8 * np.pi, 0.8 * np.pi, (200, 6))])
    sim = simulated_problem("puma560", seed=seed, method="position", sigma_p=5e-5, deviation=deviation, known=False,
                            readings=q)
    t = sim.problem.terms[0]
    train = Problem(sim.problem.robot, [("position", t.data.subset(np.arange(n_train)), t.noise)]).with_free(sim.free)
    new = Problem(sim.problem.robot, [("position", t.data.subset(np.arange(n_train, n_train + 200)), t.noise)])

    def rmse(theta):
        e = new.evaluate(theta, jacobian=False).e.reshape(-1, 3)
        return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))

    return sim, train, rmse


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_evidence_recovers_the_deviation_scale_and_map_beats_free_and_nominal(seed):
    """True deviations 1 mm (lengths) and 2 mrad (angles): the chosen widths are within a factor 2 of the
    drawn deviations' RMS per group, and at new postures the MAP fit beats both the free fit and the
    nominal model (registration only)."""
    sim, train, rmse = _narrow_then_wide(seed, 15, (1e-3, 2e-3))
    pen = [n for n in sim.free if not n.startswith("base_")]
    gp = fit_group_prior(train, sim.free, pen)
    pv = sim.problem.params
    for group, tau in gp.widths.items():
        idx = pv.indices([n for n in pen if gp.groups[n] == group])
        true = np.sqrt(np.mean((sim.truth[idx] - pv.values[idx]) ** 2))
        assert 0.5 < tau / true < 2.0, (group, tau, true)
    assert 0.7 < gp.sigma0 < 1.5  # the noise model's σ is the simulated one
    free = calibrate_lsq(train, free=sim.free)
    nominal = calibrate_lsq(train, free=[n for n in sim.free if n.startswith("base_")])
    e_map, e_free, e_nom = rmse(gp.result.theta), rmse(free.theta), rmse(nominal.theta)
    assert e_map < e_free and e_map < 0.2 * e_nom, (e_map, e_free, e_nom)


def test_map_works_where_the_free_fit_is_unidentifiable():
    """8 postures (24 coordinates) for 31 parameters: least squares refuses, the MAP fit predicts new postures
    several times better than the nominal model."""
    sim, train, rmse = _narrow_then_wide(4, 8, (1e-3, 2e-3))
    pen = [n for n in sim.free if not n.startswith("base_")]
    with pytest.raises(UnidentifiableError):
        calibrate_lsq(train, free=sim.free)
    gp = fit_group_prior(train, sim.free, pen)
    nominal = calibrate_lsq(train, free=[n for n in sim.free if n.startswith("base_")])
    assert rmse(gp.result.theta) < 0.5 * rmse(nominal.theta)
    assert gp.result.extra["prior"]["effective_parameters"] < 24


def test_cv_multiplier_and_bad_arguments():
    sim, train, _ = _narrow_then_wide(5, 15, (1e-3, 2e-3))
    pen = [n for n in sim.free if not n.startswith("base_")]
    gp = fit_group_prior(train, sim.free, pen, criterion="evidence+cv")
    assert gp.criterion == "evidence+cv" and gp.scale in gp.cv_curve["scale"]
    assert np.argmin(gp.cv_curve["loo_rmse_mm"]) == gp.cv_curve["scale"].index(gp.scale)
    d = gp.to_dict()
    assert set(d["widths"]) == {"length", "angle"} and d["n_penalised"] == len(pen)
    with pytest.raises(ValueError, match="criterion"):
        fit_group_prior(train, sim.free, pen, criterion="aic")
    with pytest.raises(ValueError, match="no parameter to penalise"):
        fit_group_prior(train, sim.free, [])


def test_log_evidence_gradient_matches_central_differences():
    """The closed-form gradient of the log evidence (MacKay's second-moment condition, and the noise term)
    against central differences of ``log_evidence`` itself: penalised groups from micro to metre scale, two free
    columns, a group the data barely see."""
    from estcal.estimate.regularize import log_evidence, log_evidence_grad

    rng = np.random.default_rng(0)
    M, n = 60, 9
    A = rng.normal(size=(M, n)) * np.geomspace(1e-3, 10, n)
    y = A @ rng.normal(0, 0.1, n) + rng.normal(0, 0.05, M)
    group_of = np.array([0, 0, 1, 1, 1, -1, 2, -1, 3])
    for lt, ls2 in ((np.log([0.3, 0.02, 1.5, 1e-3]), np.log(4e-3)), (np.log([1e-6, 2.0, 1e-4, 0.5]), np.log(0.1))):
        lp, g_tau, g_s2 = log_evidence_grad(A, y, group_of, lt, ls2)
        assert lp == pytest.approx(log_evidence(A, y, group_of, lt, ls2), rel=1e-12)
        h = 1e-6
        fd = [(log_evidence(A, y, group_of, lt + h * e, ls2) - log_evidence(A, y, group_of, lt - h * e, ls2)) / (2 * h)
              for e in np.eye(4)]
        np.testing.assert_allclose(g_tau, fd, rtol=1e-6, atol=1e-5)
        fd_s2 = (log_evidence(A, y, group_of, lt, ls2 + h) - log_evidence(A, y, group_of, lt, ls2 - h)) / (2 * h)
        assert g_s2 == pytest.approx(fd_s2, rel=1e-6, abs=1e-5)
