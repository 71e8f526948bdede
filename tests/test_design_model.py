"""The design model's information matrix is the one the measurement models / estimators use."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.design.model import DesignModel, identifiable_subset
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.robots import puma560, stanford
from estcal.methods.base import NoiseModel
from estcal.methods.problem import Problem


@pytest.mark.parametrize("method", ["position", "pose"])
def test_information_equals_problem_rows(method):
    robot = stanford()
    free = identifiable_subset(robot, method)
    model = DesignModel(robot, method, free, sigma=2e-4, sigma_rot=1e-3 if method == "pose" else None)
    Q = model.random_readings(15, np.random.default_rng(0))
    kin = robot.kinematics(Q, jacobian=False)
    data = (dataset_from_arrays(robot.joint_names, Q, R=kin.R, p=kin.p) if method == "pose"
            else dataset_from_arrays(robot.joint_names, Q, points=kin.p))
    prob = Problem(robot, [(method, data, NoiseModel(position=2e-4, orientation=1e-3, known=True))])
    rows = prob.evaluate()
    idx = robot.params.indices(free)
    A = rows.H[:, idx] / rows.sigma[:, None]
    ref = A.T @ A
    np.testing.assert_allclose(model.information(Q), ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())


def test_points_method_and_markers():
    from estcal.kinematics.builder import build_robot

    frames = [{"name": "j1", "d": 0.3, "a": 0.1, "alpha": -np.pi / 2, "limits": [-3, 3]},
              {"name": "j2", "a": 0.4, "limits": [-2, 2]}, {"name": "j3", "a": 0.3, "limits": [-2, 2]}]
    robot = build_robot("r3", frames, convention="dh", markers=[[0.05, 0, 0], [0, 0.05, 0.02]])
    model = DesignModel(robot, "points", ["a_2", "a_3", "offset_2", "marker2_x"], sigma=1e-4)
    Q = model.random_readings(5, 1)
    J = model.jacobian(Q)
    assert J.shape == (5, 6, 4)
    kin = robot.kinematics(Q)
    np.testing.assert_allclose(J[:, 3:], kin.J_points[:, 1][..., robot.params.indices(model.free)])
    # position = marker 1 when the robot has markers (as estcal.methods.PositionMethod)
    pos = DesignModel(robot, "position", ["a_2"], sigma=1e-4).jacobian(Q)
    np.testing.assert_allclose(pos[..., 0], kin.J_points[:, 0][..., robot.params.index("a_2")])


def test_covariance_equals_lsq_estimator():
    """The predicted covariance of a plan is the covariance calibrate_lsq reports (known noise)."""
    from estcal.estimate.lsq import calibrate_lsq

    robot = puma560()
    free = identifiable_subset(robot, "position")
    model = DesignModel(robot, "position", free, sigma=1e-4)
    Q = model.random_readings(30, np.random.default_rng(2))
    rng = np.random.default_rng(3)
    p = robot.kinematics(Q, jacobian=False).p + rng.normal(0, 1e-4, (30, 3))
    prob = Problem(robot.copy(robot.params.with_free(free)),
                   [("position", dataset_from_arrays(robot.joint_names, Q, points=p),
                     NoiseModel(position=1e-4, known=True))])
    res = calibrate_lsq(prob)
    order = [res.names.index(n) for n in free]
    C_est = np.asarray(res.covariance)[np.ix_(order, order)]
    # the estimator linearises at its solution: evaluate the design model there too
    at_solution = DesignModel(robot, "position", free, sigma=1e-4, theta=np.asarray(res.theta)[:robot.n_params])
    C_pred = at_solution.covariance(Q)
    np.testing.assert_allclose(C_est, C_pred, rtol=1e-6, atol=1e-9 * np.abs(C_pred).max())
    # at the nominal values it differs only to first order in the estimated corrections
    C_nom = model.covariance(Q)
    assert np.allclose(np.sqrt(np.diag(C_nom)), np.sqrt(np.diag(C_est)), rtol=0.05)


def test_identifiable_subset_is_full_rank():
    for robot in (puma560(), stanford()):
        free = identifiable_subset(robot, "position")
        model = DesignModel(robot, "position", free, sigma=1.0)
        J = model.jacobian(model.random_readings(40, 9)).reshape(-1, model.p)
        assert np.linalg.matrix_rank(J / np.linalg.norm(J, axis=0)) == len(free)
        assert len(free) == 25  # Mooring (4.397): position-only PUMA has 25; Stanford also 25 here


def test_accuracy_map_region_grid_and_box():
    from estcal.design.criteria import accuracy_map
    from estcal.design.model import ToolBox
    from estcal.kinematics.robots import planar2

    model = DesignModel(planar2(), "position", ["a_1", "a_2"], sigma=1e-3)
    C = np.diag([1e-6, 4e-6])
    amap = model.accuracy_map(C, region=[[0, np.pi / 2], [0, np.pi / 2]], grid=3)
    assert len(amap.std) == 9
    # hand value: at q = (0, 0) the x error is Δl1 + Δl2 → std sqrt(1e-6 + 4e-6); y has none
    k = int(np.flatnonzero(np.all(amap.q == 0, axis=1))[0])
    assert amap.std[k] == pytest.approx(np.sqrt(5e-6))
    # Cartesian box: keep poses with x ≥ 1.0 m
    box = ToolBox(model.robot, lower=(1.0, None, None))
    sub = model.accuracy_map(C, region=[[0, np.pi / 2], [0, np.pi / 2]], grid=3, constraint=box)
    assert np.all(sub.xyz[:, 0] >= 1.0) and 0 < len(sub.std) < 9
    ref = accuracy_map(C, model.position_jacobian(sub.q))
    np.testing.assert_allclose(sub.std, ref.std)
