"""The residual GP (estcal.discrepancy.residual: scikit-learn's ARD GP to the bit, the joint-space GP, the
compensation through a residual layer of a saved model) and the error budget's figure."""
import numpy as np
import pytest

from estcal.discrepancy.residual import (ResidualGP, fit_joint_gp, fit_residual_gp, joint_gp_design,
                                        joint_gp_objective, residual_correction, residual_model_from_dict)
from estcal.kinematics.robots import puma560
from estcal.methods import NoiseModel
from estcal.simulate import simulate

SIGMA = 5e-5  # m per coordinate
NOISE = NoiseModel(position=SIGMA, known=True)


def _tilted(sim, joint: int, amp: float, readings=None):
    """Points of the true robot with alpha_<joint> += amp · sin(q_joint) at every pose."""
    rb = sim.true_robot
    Q = sim.dataset.readings if readings is None else readings
    th = rb.params.values.copy()
    i = rb.params.indices([f"alpha_{joint}"])[0]
    out = []
    for q in Q:
        t = th.copy()
        t[i] += amp * np.sin(q[joint - 1])
        out.append(rb.kinematics(q[None], t, jacobian=False).points[0, :sim.dataset.n_points])
    return np.array(out)


def _sim(n=40, seed=0, readings=None):
    return simulate(puma560(), n_poses=n, measure="points", errors="random", n_points=2, seed=seed,
                    readings=readings)


def _noisy(sim, points, seed):
    d = sim.dataset.subset(slice(None))
    d.points = points + SIGMA * np.random.default_rng(seed).standard_normal(points.shape)
    return d


def test_numpy_evaluation_equals_scikit_learn_and_round_trips():
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    rng = np.random.default_rng(0)
    X = rng.uniform(-2, 2, (40, 3))
    R = np.zeros((40, 2, 3))
    R[:, :, 1] = 1e-3 * np.sin(2 * X[:, [0]])
    R += 1e-4 * rng.standard_normal(R.shape)
    gp = fit_residual_gp(X, R, ["a", "b", "c"], "cartesian", restarts=0)
    # the same GP rebuilt in scikit-learn with the fitted hyperparameters, not refitted
    k = (ConstantKernel(gp.amplitude2, "fixed") * RBF(gp.length_scales, "fixed") + WhiteKernel(gp.noise2, "fixed"))
    sk = GaussianProcessRegressor(k, optimizer=None).fit(gp.X, R.reshape(40, -1) / gp.y_scale)
    Xt = rng.uniform(-2, 2, (7, 3))
    m_sk, s_sk = sk.predict(gp.standardise(Xt), return_std=True)
    m, s = gp.predict(Xt, return_std=True, include_noise=True)
    assert np.allclose(m.reshape(7, -1), m_sk * gp.y_scale, atol=1e-12)
    assert np.allclose(s, s_sk[:, 0] * gp.y_scale, rtol=1e-8)
    back = ResidualGP.from_dict(gp.to_dict())
    assert np.allclose(back.predict(Xt), m, rtol=1e-12, atol=1e-15)
    assert list(gp.relevance)[0] == "a"


@pytest.mark.parametrize("d,restarts,start", [(3, 2, None), (3, 0, (2.0, (0.3, 5.0, 0.07), 0.01)), (1, 1, None),
                                               (2, 3, None), (9, 0, None)])
def test_ard_fit_is_scikit_learns_to_the_bit(d, restarts, start):
    """_fit_ard_gp computes what scikit-learn's GaussianProcessRegressor fit computes (kernel, likelihood,
    L-BFGS-B runs, random restarts, the best run's factor and weights): the same bits."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    from estcal.discrepancy.residual import AMPLITUDE_BOUNDS, LENGTH_BOUNDS, NOISE_BOUNDS, _fit_ard_gp

    rng = np.random.default_rng(d + restarts)
    X = rng.uniform(-2, 2, (35, d))
    Y = np.sin(2 * X[:, [0]]) * np.array([[1.0, -0.5, 0.2]]) + 0.2 * rng.standard_normal((35, 3))
    a2, ls0, s2 = (0.5, np.ones(d), 0.5) if start is None else (start[0], np.array(start[1][:d]), start[2])
    ours = _fit_ard_gp(X, Y, a2, ls0, s2, restarts, np.random.RandomState(7))
    k = (ConstantKernel(a2, AMPLITUDE_BOUNDS) * RBF(ls0, [LENGTH_BOUNDS] * d) + WhiteKernel(s2, NOISE_BOUNDS))
    sk = GaussianProcessRegressor(k, n_restarts_optimizer=restarts, random_state=np.random.RandomState(7))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        sk.fit(X, Y)
    kern = sk.kernel_
    theirs = (float(kern.k1.k1.constant_value), np.atleast_1d(kern.k1.k2.length_scale), float(kern.k2.noise_level),
              sk.L_, sk.alpha_, float(sk.log_marginal_likelihood_value_))
    for name, a, b in zip(("a2", "length scales", "s2", "L", "alpha", "lml"), ours, theirs):
        assert np.array_equal(np.asarray(a), np.asarray(b)), name


def test_joint_gp_gradient_round_trip_and_recovery_at_new_postures():
    from scipy.optimize import approx_fprime

    sim = _sim(n=40, seed=11)
    rb = sim.true_robot
    R = _tilted(sim, 2, 3e-3) - sim.true_points[:, :2]
    R += SIGMA * np.random.default_rng(0).standard_normal(R.shape)
    Q, H, names, jo = joint_gp_design(rb, rb.params.values, sim.dataset.readings, n_points=2)
    f = joint_gp_objective(Q, H / np.sqrt(np.mean(H.reshape(-1, H.shape[2]) ** 2, 0)), R.reshape(-1), jo,
                           list(range(6)), 6)
    x = np.r_[np.log(np.full(6, 2e-4)), np.linspace(-0.5, 0.5, 6), np.log(1e-4)]
    _, g = f(x)
    assert np.allclose(g, approx_fprime(x, lambda z: f(z)[0], 1e-6), rtol=1e-4, atol=1e-6 * np.abs(g).max())
    gp = fit_joint_gp(Q, H, R, names, jo, rb.joint_names, restarts=0)
    assert list(gp.relevance)[0] == "j2"
    new = _sim(n=30, seed=12)
    truth = _tilted(new, 2, 3e-3) - new.true_points[:, :2]
    pred, sd = residual_correction(gp, rb, rb.params.values, new.dataset.readings, return_std=True)
    assert np.sqrt(np.mean((pred - truth) ** 2)) < 0.2 * np.sqrt(np.mean(truth ** 2))
    back = residual_model_from_dict(gp.to_dict())
    assert np.allclose(residual_correction(back, rb, rb.params.values, new.dataset.readings), pred, atol=1e-15)














def test_compensation_with_the_residual_layer_reaches_the_target_with_it():
    from estcal.discrepancy.residual import compensate_with_residual

    sim = _sim(n=40, seed=13)
    rb = sim.true_robot
    R = _tilted(sim, 2, 3e-3) - sim.true_points[:, :2]
    Q, H, names, jo = joint_gp_design(rb, rb.params.values, sim.dataset.readings, n_points=2)
    gp = fit_joint_gp(Q, H, R + SIGMA * np.random.default_rng(1).standard_normal(R.shape), names, jo,
                      rb.joint_names, restarts=0)
    q0 = sim.dataset.readings[:5]
    target = rb.kinematics(q0, jacobian=False).points[:, 0] + np.array([1e-3, -2e-3, 1e-3])
    res, sd = compensate_with_residual(rb, gp, target, q0)
    reached = rb.kinematics(res.readings, jacobian=False).points[:, 0] + residual_correction(gp, rb, rb.params.values,
                                                                                            res.readings)[:, 0]
    assert np.max(np.linalg.norm(reached - target, axis=1)) < 1e-6
    assert np.all(sd > 0) and np.all(sd < 0.5)


def test_budget_figure_draws_every_stage_and_the_lines():
    from estcal.plots.budget import budget_figure

    b = {"nominal_mm": 5.0, "geometry_mm": 3.5, "model_mm": 2.9, "time": {"model_mm": 3.1}, "repeatability_mm": 0.96,
         "expected_mm": 2.9}
    fig = budget_figure(b)
    ax = fig.axes[0]
    heights = sorted(round(p.get_height(), 6) for p in ax.patches)
    assert heights == [2.9, 3.1, 3.5, 5.0]
    assert {ln.get_gid() for ln in ax.lines} == {"predicted", "repeatability"}
    assert len(budget_figure(dict(b, repeatability_mm=None)).axes[0].lines) == 1


