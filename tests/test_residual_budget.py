"""The residual GP and the error budget (estcal.discrepancy.residual, estcal.discrepancy.budget).

Hidden effects outside the effect library — an axis whose tilt varies with its own joint
angle, a tracker error that varies with the measured x — must show as structured unnamed
error with the right joint / axis first; clean data must not; repeated postures make a
row-wise cross-validation optimistic and the posture-grouped one is not.
"""
import numpy as np
import pytest

from estcal.discrepancy.budget import error_budget, measured_points, predicted_points
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


def test_axis_tilt_varying_with_its_own_joint_is_structured_and_located():
    sim = _sim(seed=1)
    data = _noisy(sim, _tilted(sim, 3, 5e-3), seed=1)
    b = error_budget(sim.nominal_robot, data, NOISE, level="full", k_folds=4, gp_restarts=0)
    assert b.structured_unnamed_mm > 2 * np.sqrt(3) * SIGMA * 1e3, b  # noise: √3 σ per point
    assert b.structured_unnamed_mm > b.unstructured_mm
    assert b.unnamed["space"] == "joints"
    assert list(b.unnamed["relevance"])[0] == "j3", b.unnamed


def test_tracker_error_along_measured_x_is_structured_and_located():
    sim = _sim(seed=2)
    P = sim.true_points[:, :2].copy()
    P[..., 2] += 2e-3 * np.sin(2 * np.pi * P[..., 0] / 0.8)  # ripple of z along the tracker's x
    data = _noisy(sim, P, seed=2)
    b = error_budget(sim.nominal_robot, data, NOISE, level="full", k_folds=4, gp_restarts=0)
    assert b.structured_unnamed_mm > 2 * np.sqrt(3) * SIGMA * 1e3, b
    assert b.unnamed["space"] == "cartesian"
    assert list(b.unnamed["relevance"])[0] == "x", b.unnamed


def test_clean_data_have_no_structured_unnamed_error():
    for seed in (3,):
        sim = _sim(seed=seed)
        data = _noisy(sim, sim.true_points[:, :2], seed=seed)
        b = error_budget(sim.nominal_robot, data, NOISE, level="full", k_folds=4, gp_restarts=0)
        assert b.structured_unnamed_mm <= 0.3 * b.unstructured_mm, b
        assert b.repeatability_mm is None  # no posture repeats


def test_repeated_postures_make_row_wise_cv_optimistic_and_grouped_cv_is_not():
    # 16 postures measured in 3 sessions (readings agree to 1e-4 rad), tilt error outside the library
    sim = _sim(n=16, seed=5)
    rng = np.random.default_rng(5)
    Q = np.repeat(sim.dataset.readings, 3, axis=0) + rng.uniform(-1e-4, 1e-4, (48, 6))
    rep = _sim(n=48, seed=5, readings=Q)
    data = _noisy(rep, _tilted(rep, 3, 3e-3), seed=6)
    data.columns["session"] = np.tile(np.arange(3.0), 16)
    rob = rep.nominal_robot
    kw = dict(level="full", k_folds=4, residual_model="gp", gp_restarts=0, spaces=("joints",))
    grouped = error_budget(rob, data, NOISE, **kw)
    row_wise = error_budget(rob, data, NOISE, groups=np.arange(data.n), **kw)
    # the truth: the same model (fitted on everything) at 200 new postures
    new = _sim(n=200, seed=7)
    new = simulate(puma560(), readings=new.dataset.readings, measure="points", errors="random", n_points=2,
                   seed=5)
    dnew = _noisy(new, _tilted(new, 3, 3e-3), seed=8)
    rb, th = grouped.extra["fitted_robot"], grouped.extra["fitted_theta"]
    pred = predicted_points(rb, th, dnew)
    e = measured_points(dnew) - pred - residual_correction(grouped.residual_model, rb, th, dnew.readings)
    truth = float(np.sqrt(np.mean(np.sum(e ** 2, -1))) * 1e3)
    assert row_wise.predicted_validation_mm < 0.6 * truth, (row_wise.predicted_validation_mm, truth)
    assert grouped.predicted_validation_mm == pytest.approx(truth, rel=0.3)
    assert grouped.repeatability_mm == pytest.approx(np.sqrt(3) * SIGMA * 1e3, rel=0.3)


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

    b = {"nominal_mm": 5.0, "geometric_mm": 3.5, "named_mm": 2.9, "unstructured_mm": 2.6, "repeatability_mm": 0.96,
         "predicted_validation_mm": 2.9}
    fig = budget_figure(b)
    ax = fig.axes[0]
    heights = sorted(round(p.get_height(), 6) for p in ax.patches)
    assert heights == [2.6, 2.9, 3.5, 5.0]
    assert {ln.get_gid() for ln in ax.lines} == {"predicted", "repeatability"}
    assert len(budget_figure(dict(b, repeatability_mm=None)).axes[0].lines) == 1


def test_saved_model_carries_the_residual_layer_to_compensate_and_export(tmp_path):
    from estcal.discrepancy import diagnose
    from estcal.discrepancy.residual import residual_model_from_dict
    from estcal.io.dataset import write_dataset
    from estcal.io.robotfile import load_robot
    from estcal.workflows.compensate import compensate_file
    from estcal.workflows.export import export

    sim = _sim(n=40, seed=1)
    data = _noisy(sim, _tilted(sim, 3, 5e-3), seed=1)
    res = diagnose(sim.nominal_robot, data, noise=SIGMA, k_folds=3, max_effects=0, residual_model="gp")
    assert res.residual_model is not None and res.budget["recommended"].endswith("+ GP")
    path = res.save_model(tmp_path / "m.yaml")
    rb = load_robot(path)
    layer = rb.meta["calibration"]["residual_model"]
    assert layer["cost_mm"] == pytest.approx(res.budget["structured_unnamed_mm"])
    gp = residual_model_from_dict(layer)
    q = data.readings[:4]
    assert np.allclose(residual_correction(gp, rb, rb.params.values, q),
                       residual_correction(res.residual_model, rb, rb.params.values, q), atol=1e-12)
    # targets a few mm away from where the saved model (with its layer) puts marker 1
    tgt = data.subset(np.arange(4)).with_points(1)
    tgt.points = (rb.kinematics(q, jacobian=False).points[:, :1]
                  + residual_correction(gp, rb, rb.params.values, q)[:, :1] + np.array([1e-3, 0, -1e-3]))
    write_dataset(tmp_path / "targets.csv", tgt)
    run = compensate_file(path, tmp_path / "targets.csv")
    reached = (rb.kinematics(run.result.readings, jacobian=False).points[:, 0]
               + residual_correction(gp, rb, rb.params.values, run.result.readings)[:, 0])
    assert np.max(np.linalg.norm(reached - tgt.points[:, 0], axis=1)) < 1e-5
    ex = export(path, tmp_path / "m.urdf")
    assert any("residual Gaussian-process layer" in w for w in ex.result.warnings)


@pytest.mark.parametrize("markers,per_session", [
    ([(0, 0, 0), (0.03, 0.02, -0.01), (-0.02, 0.04, 0.02)], "registration+points"),
    ([(0, 0, 0)] * 3, "registration")])
def test_budget_repeatability_removes_what_the_model_treats_per_session(markers, per_session):
    # 20 postures measured in three sessions, each session rigidly moved, with its own tool point (3–5 cm
    # apart) or the same one; σ = 0.1 mm per coordinate, so the floor is √3 σ. A model with a per-session
    # point: the repeatability is what remains after each session's registration *and* point (within
    # 20 %), not the distance between the points; with one point for all: today's rigid figure.
    from estcal.sessions.data import stack_sessions
    from estcal.validation import posture_groups, repeatability_floor

    sigma = 1e-4
    from estcal.kinematics.chunked import tool_poses

    sim = _sim(n=20, seed=4)
    R_tool = tool_poses(sim.true_robot, sim.dataset.readings, fields=("R",)).R
    rng = np.random.default_rng(9)
    parts = []
    for sv, d in enumerate(markers):
        w = rng.standard_normal(3) * 2e-3 if sv else np.zeros(3)
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        R = np.eye(3) + K + K @ K / 2
        pts = sim.true_points + np.einsum("nij,j->ni", R_tool, np.asarray(d, float))[:, None, :]
        part = sim.dataset.subset(slice(None))
        part.points = pts @ R.T + (rng.standard_normal(3) * 2e-3 if sv else 0.0) + sigma * rng.standard_normal(pts.shape)
        parts.append(part)
    data = stack_sessions(parts)
    b = error_budget(sim.nominal_robot, data, NoiseModel(position=sigma, known=False), level="full", k_folds=3,
                     spaces=(), per_session=per_session, nested=False)
    floor = np.sqrt(3) * sigma * 1e3
    rigid = repeatability_floor(measured_points(data), posture_groups(data.readings), data.columns["session"])
    if per_session == "registration+points":
        assert rigid["registered_mm"] > 10 * floor  # the distance between the points, not a floor
        assert b.repeatability_mm == pytest.approx(floor, rel=0.2)
    else:
        assert b.repeatability_mm == rigid["registered_mm"]
        assert b.repeatability_mm == pytest.approx(floor, rel=0.2)
    assert "repeatability_reason" not in b.to_dict()
