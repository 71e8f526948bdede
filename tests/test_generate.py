"""Generator of constraint-satisfying configurations: constraints hold to 1e-9, limits respected."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.kinematics.robots import puma560, stanford
from estcal.methods.generate import (branch_report, default_plane, distance_data, joint_distance, link_data,
                                     measurement_data, plane_data, solve_ik)


@pytest.fixture(scope="module")
def robot():
    return stanford()


def _within_limits(robot, r):
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    return np.all((r >= lo - 1e-12) & (r <= hi + 1e-12))


@pytest.mark.parametrize("mode", ["point", "frame"])
def test_link_groups_reach_the_same_point_or_pose(robot, mode):
    ds = link_data(robot, 15, 3, mode, rng=1, min_separation=0.5)
    assert ds.n == 45 and ds.kind == "none"
    kin = robot.kinematics(ds.readings, jacobian=False)
    g = ds.columns["group"].astype(int)
    first = np.array([np.flatnonzero(g == k)[0] for k in g])
    assert np.abs(kin.p - kin.p[first]).max() < 1e-9
    if mode == "frame":
        assert np.abs(kin.R - kin.R[first]).max() < 1e-9
    assert _within_limits(robot, ds.readings)
    others = np.arange(ds.n) != first
    assert joint_distance(robot, ds.readings[others], ds.readings[first[others]]).min() > 0.5
    # members of one group are distinct from each other too
    r = ds.readings.reshape(15, 3, -1)
    assert joint_distance(robot, r[:, 1], r[:, 2]).min() > 0.5


def test_frame_link_branches_are_reported(robot):
    ds = link_data(robot, 30, 2, "frame", rng=2)
    rep = branch_report(robot, ds)
    assert sum(rep["signatures"].values()) == 30
    # The Stanford arm's prismatic joint keeps its length between two solutions of one pose
    # (shoulder flip θ1+π and/or wrist flip); the wrist always changes.
    assert rep["changed_fraction"]["j3"] == 0.0
    assert rep["changed_fraction"]["j5"] == 1.0


def test_plane_points_lie_on_the_plane(robot):
    plane = default_plane(robot, 0)
    ds = plane_data(robot, 40, plane, rng=3)
    p = robot.kinematics(ds.readings, jacobian=False).p
    dist = (p @ plane + 1.0) / np.linalg.norm(plane)
    assert np.abs(dist).max() < 1e-9
    assert _within_limits(robot, ds.readings)
    # two planes: rows alternate, each on its own plane
    planes = [plane, plane * 1.1]
    ds2 = plane_data(robot, 20, planes, rng=4)
    p2 = robot.kinematics(ds2.readings, jacobian=False).p
    P = np.c_[ds2.columns["plane_a"], ds2.columns["plane_b"], ds2.columns["plane_c"]]
    assert np.abs(np.einsum("ni,ni->n", P, p2) + 1).max() < 1e-9
    assert set(ds2.columns["group"]) == {0.0, 1.0}


def test_distance_pairs(robot):
    ds = distance_data(robot, 25, rng=5)
    p = robot.kinematics(ds.readings, jacobian=False).p
    d = np.linalg.norm(p[1::2] - p[0::2], axis=1)
    np.testing.assert_allclose(ds.columns["distance"][1::2], d, atol=1e-12)
    assert np.all(ds.columns["pair"][0::2] == ds.columns["pair"][1::2])
    assert d.min() >= 0.05


def test_solve_ik_batched_pose_targets():
    robot = puma560()
    rng = np.random.default_rng(6)
    r_true = robot.random_readings(50, rng, margin=0.1)
    kin = robot.kinematics(r_true, jacobian=False)
    start = np.clip(r_true + rng.normal(0, 0.2, r_true.shape), robot.limits[:, 0], robot.limits[:, 1])
    r, ok, err = solve_ik(robot, start, (kin.R, kin.p), "pose")
    assert ok.mean() > 0.9
    k2 = robot.kinematics(r[ok], jacobian=False)
    assert np.abs(k2.p - kin.p[ok]).max() < 1e-9 and np.abs(k2.R - kin.R[ok]).max() < 1e-9


def test_generation_with_true_parameters_and_noise(robot):
    truth = robot.params.values.copy()
    truth[robot.params.index("d_3")] += 0.01
    ds = link_data(robot, 5, 2, "point", rng=7, theta=truth)
    p_true = robot.kinematics(ds.readings, truth, jacobian=False).p
    p_nom = robot.kinematics(ds.readings, jacobian=False).p
    assert np.abs(p_true[0::2] - p_true[1::2]).max() < 1e-9
    assert np.abs(p_nom[0::2] - p_nom[1::2]).max() > 1e-4  # the nominal model violates the constraint
    noisy = measurement_data(robot, 200, "position", 8, position_noise=1e-3)
    clean = measurement_data(robot, 200, "position", 8)
    dev = (noisy.points - clean.points).ravel()
    # sample std of 600 N(0, 1e-3) draws: within ±4 standard errors (σ/√(2·600))
    assert abs(dev.std() - 1e-3) < 4 * 1e-3 / np.sqrt(1200)
