"""A least-squares fit's accuracy before/after read from its own first and last residuals
(:func:`estcal.estimate.result.point_errors_from_rows`) against the kinematics pass it replaces
(:func:`estcal.estimate.result.pose_errors` at both parameter vectors)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import estcal.estimate.lsq as lsq
from estcal.estimate import calibrate_lsq
from estcal.estimate.result import accuracy, point_errors_from_rows, pose_errors
from estcal.estimate.testproblems import simulated_problem

TIAGO = Path(__file__).resolve().parents[2] / "shared" / "data" / "tiago"


def _fit_both_ways(problem, free, monkeypatch):
    res = calibrate_lsq(problem, "lm", free=free)
    with monkeypatch.context() as m:
        m.setattr(lsq, "_train_errors", lambda *a: None)  # the kinematics pass at both θ, as before
        ref = calibrate_lsq(problem, "lm", free=free)
    return res, ref


def test_position_fit_accuracy_equals_the_kinematics_pass(monkeypatch):
    sim = simulated_problem("puma560", n_poses=40, seed=2, method="position")
    res, ref = _fit_both_ways(sim.problem, sim.free, monkeypatch)
    th0 = sim.problem.params.values
    for k, th in (("before", th0), ("after", res.theta)):
        direct = accuracy(sim.problem.robot, th, sim.problem.terms[0].data)  # independent: the kinematics at θ
        for f, v in direct.items():
            assert np.allclose(res.accuracy["train"][k][f], v, rtol=1e-10), (k, f)
            assert np.allclose(ref.accuracy["train"][k][f], v, rtol=1e-10), (k, f)
    assert res.accuracy["train"]["after"]["rmse_mm"] < res.accuracy["train"]["before"]["rmse_mm"]


def test_pose_data_keeps_the_kinematics_pass():
    sim = simulated_problem("puma560", n_poses=30, seed=1, method="location")
    rows = sim.problem.evaluate()
    assert point_errors_from_rows(sim.problem, rows.e) is None  # orientation rows: not point errors


@pytest.mark.skipif(not TIAGO.exists(), reason="shared TIAGo data not found")
def test_four_markers_from_rows_equal_pose_errors():
    from estcal.io import load_dataset
    from estcal.io.robotfile import load_robot
    from estcal.methods import NoiseModel, Problem

    robot = load_robot(TIAGO / "tiago_48_schunk.urdf", root="base_footprint", tip="wrist_ft_tool_link", n_markers=4)
    data = load_dataset(TIAGO / "qualisys_2021-11-30_static_postures.csv", robot)
    prob = Problem(robot, [(None, data, NoiseModel(position=1e-3))])
    th = robot.params.values + 1e-4 * np.random.default_rng(0).standard_normal(robot.n_params)
    pos, _ = pose_errors(robot, th, data)
    np.testing.assert_allclose(point_errors_from_rows(prob, prob.evaluate(th).e), pos, rtol=1e-12, atol=1e-15)
