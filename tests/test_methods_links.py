"""GECARO link, plane and distance methods: analytic Jacobian rows vs finite differences,
zero residual at the generating parameters, dataset errors, combined problems."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.robots import puma560, stanford
from estcal.methods import NoiseModel, Problem, get_method
from estcal.methods.generate import distance_data, link_data, measurement_data, plane_data
from estcal.methods.links import GECARO_METHODS, PlaneKnown, so3_left_jacobian_inv

NEW = ("point-link", "frame-link", "plane-known", "plane-unknown", "plane-normal-known", "plane-normal-unknown",
       "distance")


def _perturbed(robot, seed=0, scale=1e-3):
    """'True' parameters: nominal + small errors on the geometric parameters, offsets and gains."""
    rng = np.random.default_rng(seed)
    th = robot.params.values.copy()
    pv = robot.params
    for i, k in enumerate(pv.kinds):
        if k in ("geometric", "offset", "gain"):
            th[i] += rng.normal(0, scale)
    return th


def _data(robot, method, theta, seed=1, n=24):
    if method in ("point-link", "frame-link"):
        return link_data(robot, n // 2, 2 if method == "point-link" else 3, method.split("-")[0], seed, theta)
    if method.startswith("plane"):
        return plane_data(robot, n, None, seed, theta)
    if method == "distance":
        return distance_data(robot, n // 2, seed, theta)
    return measurement_data(robot, n, "position" if method == "position" else "location", seed, theta)


@pytest.fixture(scope="module")
def robot():
    return stanford()


@pytest.mark.parametrize("method", NEW)
def test_jacobian_matches_finite_differences(robot, method):
    """H = ∂predicted/∂θ = −∂e/∂θ, checked by central differences at parameters where the
    residuals are not zero (data from a perturbed robot, model at nominal)."""
    truth = _perturbed(robot, 0, 3e-3)
    ds = _data(robot, method, truth)
    prob = Problem(robot, [(method, ds)])
    theta = prob.params.values.copy()
    rows = prob.evaluate(theta)
    assert np.abs(rows.e).max() > 1e-5, "residuals should be non-zero at the nominal model"
    h = 1e-6
    fd = np.empty_like(rows.H)
    for k in range(theta.size):
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd[:, k] = -(prob.evaluate(tp, jacobian=False).e - prob.evaluate(tm, jacobian=False).e) / (2 * h)
    scale = np.abs(rows.H).max()
    np.testing.assert_allclose(rows.H, fd, atol=1e-7 * scale, rtol=1e-6)


@pytest.mark.parametrize("method", NEW)
def test_zero_residual_at_generating_parameters(robot, method):
    truth = _perturbed(robot, 2, 2e-3)
    ds = _data(robot, method, truth, seed=3)
    prob = Problem(robot, [(method, ds)])
    theta = prob.params.values.copy()
    theta[: robot.n_params] = truth
    if method == "plane-unknown":  # the true plane is the one used by the generator
        theta[prob.params.indices(["plane_a", "plane_b", "plane_c"])] = [ds.columns[f"plane_{c}"][0] for c in "abc"]
    if method == "plane-normal-unknown":
        from estcal.methods.links import _normal_from_angles

        m = prob.terms[0].method
        n = np.array([ds.columns[f"plane_{c}"][0] for c in "abc"])
        n /= np.linalg.norm(n)
        B = m._B(0, prob.robot, ds, np.zeros(ds.n, int))
        nl = B.T @ n * np.sign((B.T @ n)[2])
        theta[prob.params.indices(["normal_u", "normal_v"])] = [-np.arcsin(nl[1]), np.arctan2(nl[0], nl[2])]
        assert np.allclose(abs(_normal_from_angles(B, theta[-2], theta[-1])[0] @ n), 1.0)
    e = prob.evaluate(theta, jacobian=False).e
    assert np.abs(e).max() < 1e-9


def test_rows_layout_and_sigma(robot):
    ds = link_data(robot, 4, 3, "frame", 0)
    noise = NoiseModel(position=2e-4, orientation=3e-3)
    rows = get_method("frame-link").rows(robot, robot.params.values, ds, noise)
    assert rows.e.shape == (4 * 2 * 6,)  # two comparisons per group of three, six rows each
    np.testing.assert_allclose(rows.sigma[:6], np.sqrt(2) * np.r_[[2e-4] * 3, [3e-3] * 3])
    assert set(rows.pose.tolist()) == {1, 2, 4, 5, 7, 8, 10, 11}


def test_left_jacobian_inverse_against_expm():
    from estcal.kinematics.transforms import so3_exp, so3_log

    rng = np.random.default_rng(4)
    for ang in (1e-6, 0.3, 2.5):  # angles below π (the logarithm's range)
        phi = rng.normal(size=3)
        phi *= ang / np.linalg.norm(phi)
        c = rng.normal(size=3) * 1e-7
        lhs = so3_log(so3_exp(c) @ so3_exp(phi))
        np.testing.assert_allclose(lhs - phi, so3_left_jacobian_inv(phi) @ c, atol=1e-12)


def test_every_gecaro_method_is_registered():
    for m in GECARO_METHODS:
        assert get_method(m).name in (m, "pose")  # GECARO's "location" is the pose measurement


def test_dataset_errors_name_the_problem(robot):
    ds = dataset_from_arrays(robot.joint_names, robot.random_readings(4, 0))
    with pytest.raises(ValueError, match="'group'"):
        get_method("point-link").rows(robot, robot.params.values, ds, NoiseModel())
    ds.columns["pair"] = np.array([0, 0, 0, 1.0])
    ds.columns["distance"] = np.ones(4)
    with pytest.raises(ValueError, match="pair id 0 occurs on 3 rows"):
        get_method("distance").rows(robot, robot.params.values, ds, NoiseModel())
    ds.columns["pair"] = np.array([0, 0, 1, 1.0])
    ds.columns["distance"] = np.array([1.0, 2.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="different distances"):
        get_method("distance").rows(robot, robot.params.values, ds, NoiseModel())
    with pytest.raises(ValueError, match="plane"):
        get_method("plane-known").rows(robot, robot.params.values, ds, NoiseModel())


def test_known_plane_option_equals_columns(robot):
    ds = plane_data(robot, 10, None, 5)
    abc = [ds.columns[f"plane_{c}"][0] for c in "abc"]
    r1 = PlaneKnown(*abc).rows(robot, robot.params.values, ds, NoiseModel())
    r2 = get_method("plane-known").rows(robot, robot.params.values, ds, NoiseModel())
    np.testing.assert_allclose(r1.H, r2.H)
    np.testing.assert_allclose(r1.e, r2.e, atol=1e-15)


def test_unknown_plane_initialised_by_best_fit(robot):
    ds = plane_data(robot, 20, None, 6)
    prob = Problem(robot, [("plane-unknown", ds)])
    est = prob.params.values[prob.params.indices(["plane_a", "plane_b", "plane_c"])]
    np.testing.assert_allclose(est, [ds.columns[f"plane_{c}"][0] for c in "abc"], rtol=1e-9)


def test_combined_position_and_distance_problem_recovers_truth():
    """A weighted two-term problem (position + distance): noise-free data from a PUMA whose
    identifiable parameters (chosen by QR) are perturbed are fitted exactly by LM."""
    from estcal.estimate.lsq import calibrate_lsq
    from estcal.identify import select_identifiable

    robot = puma560()
    noise_d = NoiseModel(scalar=5e-5)
    cands = ["theta_*", "d_*", "a_*", "alpha_*", "beta_*", "base_*", "tool_*", "gain_*"]
    probe = Problem(robot, [("position", measurement_data(robot, 30, "position", 8)),
                            ("distance", distance_data(robot, 40, 9), noise_d)])
    free = select_identifiable(probe, cands).identifiable
    assert len(free) == 30  # 25 geometric (tool origin on axis 6) + gains 1-5
    truth = robot.params.values.copy()
    idx = robot.params.indices(free)
    truth[idx] += np.random.default_rng(7).normal(0, 1e-3, idx.size)
    dpos = measurement_data(robot, 30, "position", 8, truth)
    ddist = distance_data(robot, 40, 9, truth)
    prob = Problem(robot, [("position", dpos), ("distance", ddist, noise_d)])
    rows = prob.evaluate()
    assert rows.e.size == 30 * 3 + 40
    np.testing.assert_allclose(rows.sigma[-40:], 5e-5)
    np.testing.assert_allclose(rows.sigma[:90], NoiseModel().position)
    res = calibrate_lsq(prob, "lm", free=free)
    final = prob.evaluate(res.theta, jacobian=False)
    assert np.abs(final.e).max() < 1e-9
    np.testing.assert_allclose(res.theta[idx], truth[idx], atol=1e-7)
