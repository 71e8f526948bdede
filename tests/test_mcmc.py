"""Posterior sampling with emcee; the vectorised residuals it relies on."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("emcee")

from estcal.estimate.lsq import calibrate_lsq  # noqa: E402
from estcal.estimate.mcmc import calibrate_mcmc, sample_posterior  # noqa: E402
from estcal.estimate.registry import get_estimator  # noqa: E402
from estcal.estimate.testproblems import simulated_problem  # noqa: E402
from estcal.io.dataset import dataset_from_arrays  # noqa: E402
from estcal.kinematics.robots import puma560, robot_5r1p, stanford  # noqa: E402
from estcal.methods.base import NoiseModel  # noqa: E402
from estcal.methods.problem import Problem  # noqa: E402


@pytest.mark.parametrize("make", [puma560, stanford, robot_5r1p])
def test_evaluate_many_equals_problem_evaluate(make):
    rob = make()
    rng = np.random.default_rng(0)
    q = rob.random_readings(15, rng)
    kin = rob.kinematics(q, jacobian=False)
    terms = [("location", dataset_from_arrays(rob.joint_names, q, R=kin.R, p=kin.p), NoiseModel(1e-4, 1e-3)),
             ("position", dataset_from_arrays(rob.joint_names, q, points=kin.p + 1e-3), NoiseModel(2e-4))]
    prob = Problem(rob, terms)
    TH = rob.params.values + 1e-2 * rng.standard_normal((7, rob.n_params))
    E = prob.evaluate_many(TH)
    ref = np.stack([prob.evaluate(t, jacobian=False).e for t in TH])
    np.testing.assert_allclose(E, ref, atol=1e-12)


def test_evaluate_many_with_effects_points_and_links():
    """A diagnosed model (geometry + effects) measured by points, plus a link method (θ by θ)."""
    from estcal.simulate import simulate

    sim = simulate("puma560_masses", n_poses=12, measure="points", seed=8,
                   effects=["joint_compliance:j2,j3", "gear_harmonic:j1"])
    rob, ds = sim.true_robot, sim.dataset
    pairs = {"pair": np.repeat(np.arange(3), 2).astype(float), "distance": np.full(6, 0.5)}
    terms = [("points", ds, NoiseModel(1e-4)),
             ("distance", dataset_from_arrays(rob.joint_names, ds.readings[:6], columns=pairs), NoiseModel(1e-4))]
    prob = Problem(rob, terms)
    rng = np.random.default_rng(1)
    TH = prob.params.values + 1e-3 * rng.standard_normal((5, prob.params.values.size))
    np.testing.assert_allclose(prob.evaluate_many(TH), np.stack([prob.evaluate(t, jacobian=False).e for t in TH]),
                               rtol=0, atol=1e-12)


def test_mcmc_samples_a_model_with_effects():
    """The walkers sample effect parameters (a gear harmonic) with the batched kinematics: the
    posterior mean is near the LM estimate and the spread matches the LM standard deviation
    (Laplace; the model is nearly linear in these parameters)."""
    from estcal.simulate import simulate

    sim = simulate("puma560", n_poses=40, measure="pose", seed=9, errors="none",
                   effects=["gear_harmonic:j2"], noise={"position": 1e-4, "orientation": 1e-4})
    prob = Problem(sim.true_robot, [(None, sim.dataset, NoiseModel(1e-4, 1e-4, known=True))])
    eff = sim.true_robot.effects[0]
    free = [sim.true_robot.params.names[i] for i in eff.indices] + ["offset_2", "offset_3"]
    lm = calibrate_lsq(prob, free=free)
    s = sample_posterior(prob, free, target_ess=150, max_steps=600, seed=2, tau_factor=20)
    z = (s.mean() - lm.estimate) / lm.std
    assert np.all(np.abs(z) < 0.5), z
    np.testing.assert_allclose(s.std() / lm.std, 1.0, atol=0.25)


@pytest.fixture(scope="module")
def posterior():
    sim = simulated_problem("puma560", n_poses=60, seed=21)
    lm = calibrate_lsq(sim.problem)
    # tau_factor 20 instead of emcee's conservative 50: τ ≈ 10 steps here, estimated from ≥ 200 steps
    res = calibrate_mcmc(sim.problem, target_ess=400, max_steps=3000, seed=1, min_steps=100, tau_factor=20)
    return sim, lm, res


def test_posterior_agrees_with_lm(posterior):
    sim, lm, res = posterior
    ess = res.extra["ess"]
    # Monte-Carlo error of a posterior mean is std/√ESS: allow 4.5 of it (max over 30 parameters)
    z = (res.estimate - lm.estimate) / lm.std
    assert np.all(np.abs(z) < 4.5 / np.sqrt(ess) + 0.02)
    # std of a sample std ≈ std/√(2 ESS)
    assert np.all(np.abs(res.std / lm.std - 1) < 4.5 / np.sqrt(2 * ess) + 0.02)
    assert res.converged and res.extra["min_ess"] >= 400
    assert 0.05 < res.extra["acceptance_fraction"] < 0.95


def test_result_json_has_intervals(posterior):
    sim, lm, res = posterior
    d = res.to_dict()
    assert d["method"] == "mcmc"
    ci = d["credible_intervals"]
    assert set(ci) == set(lm.names)
    for n, (lo, hi) in ci.items():
        e, s = res.parameter(n)
        assert lo < e < hi
        assert 0.7 < (hi - lo) / (2 * 1.96 * s) < 1.3  # near-Gaussian posterior


def test_noise_scale_sampled_when_noise_unknown():
    sim = simulated_problem("puma560", n_poses=60, seed=22, known=False, sigma_p=2e-4, sigma_r=2e-4)
    # the noise model says 1e-4: the true scale is 2 (known=False → λ is sampled)
    from estcal.methods.base import NoiseModel as NM

    t = sim.problem.terms[0]
    t.noise = NM(1e-4, 1e-4, known=False)
    smp = sample_posterior(sim.problem, target_ess=200, max_steps=2000, seed=3, min_steps=100, tau_factor=20)
    lam = smp.noise_scale
    lm = calibrate_lsq(sim.problem)
    # posterior of λ ≈ σ0 (1 ± 1/√(2 dof)); σ0 itself scatters around the true 2 with the same spread
    sd = 2.0 / np.sqrt(2 * lm.dof)
    assert lam is not None and abs(lam.mean() - lm.sigma0) < sd and abs(lam.mean() - 2.0) < 4 * sd
    assert abs(lam.std() / sd - 1) < 0.3


def test_stretch_move_and_registry():
    sim = simulated_problem("planar2", n_poses=30, seed=23, method="position", free=["a_1", "a_2", "offset_2"])
    lm = calibrate_lsq(sim.problem)
    r = get_estimator("mcmc")(sim.problem, free=sim.free, moves="stretch", target_ess=150, max_steps=1500,
                              tau_factor=20, n_walkers=16)
    assert np.all(np.abs((r.estimate - lm.estimate) / lm.std) < 0.4)


def test_arviz_and_corner(tmp_path):
    sim = simulated_problem("planar2", n_poses=30, seed=24, method="position", free=["a_1", "a_2", "offset_2"])
    smp = sample_posterior(sim.problem, target_ess=100, max_steps=1000, n_walkers=16)
    pytest.importorskip("corner")
    from estcal.report.figures import save_figure

    path = save_figure(smp.corner_figure(), tmp_path / "corner.png")
    assert path.exists() and path.stat().st_size > 1000
    az = pytest.importorskip("arviz")
    idata = smp.to_inference_data()
    assert isinstance(idata, az.InferenceData)
    assert idata.posterior["a_1"].shape == (16, smp.chain.shape[0])
