"""Gough platform model: IK, analytic Jacobians (vs finite differences), FK, robot files."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estcal.parallel._rot import euler_zyx_to_matrix, make_T, matrix_to_euler_zyx, so3_exp, so3_log
from estcal.parallel.daney import generate_random_poses
from estcal.parallel.gough import gough_parameter_names, is_gough_file, left_hand, load_gough


@pytest.fixture(scope="module")
def robot():
    return left_hand()


def test_left_hand_units_and_names(robot):
    # paper table in cm -> SI
    np.testing.assert_allclose(robot.a[2], [0.1276, 0.039, 0.0])
    np.testing.assert_allclose(robot.b[2], [0.07822, -0.01052, 0.0])
    np.testing.assert_allclose(robot.drho, 0.1525)
    pv = robot.parameter_vector(42)
    assert pv.names[:7] == ["a1_x", "a1_y", "a1_z", "b1_x", "b1_y", "b1_z", "drho_1"]
    assert len(pv) == 42 and pv.free.sum() == 42
    assert robot.parameter_vector(36).free.sum() == 36
    assert pv["a3_x"] == pytest.approx(0.1276) and pv["drho_3"] == pytest.approx(0.1525)
    assert gough_parameter_names() == pv.names


def test_ik_matches_independent_loop(robot):
    rng = np.random.default_rng(0)
    T = generate_random_poses(robot, 20, rng)
    rho = robot.leg_lengths(T)
    for i in range(3):
        for k in range(6):
            B = T[i, :3, :3] @ robot.b[k] + T[i, :3, 3]
            assert rho[i, k] == pytest.approx(np.linalg.norm(B - robot.a[k]) - robot.drho[k], abs=1e-15)
    assert np.all(robot.in_workspace(T))


def test_jacobians_match_finite_differences(robot):
    rng = np.random.default_rng(1)
    T = generate_random_poses(robot, 5, rng)
    Jt, Jp = robot.leg_jacobians(T)
    th, eps = robot.theta, 1e-6
    E = np.eye(42)
    Jfd = np.stack([(robot.leg_lengths(T, th + eps * E[i]) - robot.leg_lengths(T, th - eps * E[i])) / (2 * eps)
                    for i in range(42)], -1)
    np.testing.assert_allclose(Jt, Jfd, atol=1e-8)
    P, R = T[:, :3, 3], T[:, :3, :3]
    cols = []
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        Tp = make_T(P + d[:3], so3_exp(d[3:]) @ R)
        Tm = make_T(P - d[:3], so3_exp(-d[3:]) @ R)
        cols.append((robot.leg_lengths(Tp) - robot.leg_lengths(Tm)) / (2 * eps))
    np.testing.assert_allclose(Jp, np.stack(cols, -1), atol=1e-8)


def test_rotation_helpers_roundtrip():
    rng = np.random.default_rng(2)
    e = rng.uniform(-1.2, 1.2, (50, 3))
    np.testing.assert_allclose(matrix_to_euler_zyx(euler_zyx_to_matrix(e)), e, atol=1e-12)
    w = rng.normal(size=(50, 3))
    w *= (rng.uniform(0, 3.1, 50) / np.linalg.norm(w, axis=1))[:, None]
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-9)
    # ZYX = Rz(psi) Ry(theta) Rx(phi)
    psi, th, ph = 0.3, -0.2, 0.5
    Rz = so3_exp(np.array([0, 0, psi]))
    Ry = so3_exp(np.array([0, th, 0]))
    Rx = so3_exp(np.array([ph, 0, 0]))
    np.testing.assert_allclose(euler_zyx_to_matrix(np.array([psi, th, ph])), Rz @ Ry @ Rx, atol=1e-15)


def test_fk_recovers_random_poses(robot):
    rng = np.random.default_rng(3)
    T = generate_random_poses(robot, 300, rng)
    fk = robot.forward_kinematics(robot.leg_lengths(T))
    assert fk.success.all()
    np.testing.assert_allclose(fk.T, T, atol=1e-8)
    assert np.all(fk.residual < 1e-10)


def test_fk_reports_failures_instead_of_wrong_pose(robot):
    rng = np.random.default_rng(4)
    T = generate_random_poses(robot, 4, rng)
    rho = robot.leg_lengths(T)
    rho[1, 0] += 0.5  # leg 1 half a metre longer: no assembly reaches it with the others
    rho[2] = -0.2  # negative physical lengths
    fk = robot.forward_kinematics(rho)
    assert list(fk.success) == [True, False, False, True]
    assert np.isnan(fk.T[1]).all() and np.isnan(fk.T[2]).all()
    assert fk.residual[1] > 1e-6
    # the mirror assembly (platform below the base) reproduces the lengths but is rejected
    M = np.diag([1.0, 1.0, -1.0])
    Tm = T[[0]].copy()
    Tm[0, :3, 3] = M @ Tm[0, :3, 3]
    Tm[0, :3, :3] = M @ Tm[0, :3, :3] @ M
    np.testing.assert_allclose(robot.leg_lengths(Tm), rho[[0]], atol=1e-14)
    fk2 = robot.forward_kinematics(rho[[0]], guess=Tm[0])
    assert fk2.success[0] and fk2.T[0, 2, 3] > 0
    np.testing.assert_allclose(fk2.T[0], T[0], atol=1e-8)


def test_robot_file_roundtrip(robot, tmp_path):
    import yaml

    p = tmp_path / "lh.yaml"
    p.write_text(yaml.safe_dump(robot.to_dict("cm")))
    assert is_gough_file(p) and is_gough_file("left_hand")
    r2 = load_gough(p)
    np.testing.assert_allclose(r2.theta, robot.theta, atol=1e-15)
    np.testing.assert_allclose(r2.length_limits, robot.length_limits)
    np.testing.assert_allclose(r2.home, robot.home, atol=1e-15)
    np.testing.assert_allclose(r2.workspace.position_max, robot.workspace.position_max)
    pj = tmp_path / "lh.json"
    pj.write_text(json.dumps(robot.to_dict("mm")))
    np.testing.assert_allclose(load_gough(pj).theta, robot.theta, atol=1e-15)
    bad = tmp_path / "bad.yaml"
    bad.write_text("type: gough\nbase_points: [[0,0,0]]\n")
    assert is_gough_file(bad)
    with pytest.raises(ValueError, match="bad.yaml.*base_points"):
        load_gough(bad)
    serial = tmp_path / "serial.yaml"
    serial.write_text("type: khalil\n")
    assert not is_gough_file(serial)


def test_robot_file_units_mapping_like_serial_files(robot, tmp_path):
    import yaml

    d = robot.to_dict("mm")
    assert d["estcal_robot"] == 1
    del d["length_unit"]
    d["units"] = {"length": "mm", "angle": "deg"}
    p = tmp_path / "u.yaml"
    p.write_text(yaml.safe_dump(d))
    np.testing.assert_allclose(load_gough(p).theta, robot.theta, atol=1e-15)


def test_minimal_robot_file_defaults(robot):
    """Only the attachment points: default home above the base, FK works from it."""
    d = {"type": "gough", "base_points": robot.a.tolist(), "platform_points": robot.b.tolist()}
    r = load_gough(d)
    assert r.home[2, 3] > 0.05 and np.all(r.drho == 0)
    T = robot.home.copy()
    fk = r.forward_kinematics(r.leg_lengths(T))
    assert fk.success[0]
    np.testing.assert_allclose(fk.T[0], T, atol=1e-8)
