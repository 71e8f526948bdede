"""Analytic identification Jacobians against central finite differences (GECARO App. II).

Property-based: hypothesis draws random robots (Khalil with β, standard DH with
Hayati β, URDF with 6-D placement errors, prismatic joints, gains, coupling,
markers), random parameter values and random configurations.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from estcal.kinematics import planar2, puma560, puma560_fu, robot_5r1p, stanford
from estcal.kinematics.builder import build_robot
from estcal.kinematics.transforms import make_transform, rpy_to_matrix, so3_log


def numeric_jacobian(robot, q, theta, eps=1e-6):
    """Central differences of the tool pose (position + world rotation vector) and marker points."""
    P = robot.n_params
    Jp = np.empty((q.shape[0], 6, P))
    Jm = np.empty((q.shape[0], robot.n_markers, 3, P))
    for i in range(P):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += eps
        tm[i] -= eps
        kp = robot.kinematics(q, tp, jacobian=False)
        km = robot.kinematics(q, tm, jacobian=False)
        Jp[:, :3, i] = (kp.p - km.p) / (2 * eps)
        Jp[:, 3:, i] = so3_log(kp.R @ np.swapaxes(km.R, 1, 2)) / (2 * eps)
        Jm[..., i] = (kp.points - km.points) / (2 * eps)
    return Jp, Jm


def assert_jacobian_matches(robot, q, theta):
    k = robot.kinematics(q, theta)
    Jp, Jm = numeric_jacobian(robot, q, theta)
    scale = max(1.0, np.abs(Jp).max())
    # Central differences are O(eps^2) ~ 1e-12 plus rounding ~ 1e-10: 1e-7 relative is a real check.
    assert np.abs(k.J - Jp).max() <= 1e-7 * scale
    if robot.n_markers:
        assert np.abs(k.J_points - Jm).max() <= 1e-7 * max(1.0, np.abs(Jm).max())


@st.composite
def random_robot(draw):
    n = draw(st.integers(1, 7))
    conv = draw(st.sampled_from(["khalil", "dh", "urdf", "mixed"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    frames = []
    for j in range(n):
        c = conv if conv != "mixed" else ["khalil", "dh", "urdf"][j % 3]
        jt = "prismatic" if rng.random() < 0.25 else "revolute"
        f = {"name": f"j{j}", "type": jt, "convention": c, "label": f"L{j}",
             "offset": rng.normal(0, 0.1), "gain": 1 + rng.normal(0, 0.05),
             "limits": [-2.5, 2.5] if jt == "revolute" else [0.1, 0.6]}
        if c == "khalil":
            f.update(alpha=rng.uniform(-2, 2), d=rng.normal(0, 0.3), theta=rng.uniform(-2, 2),
                     r=rng.normal(0, 0.3), beta=rng.normal(0, 0.1))
        elif c == "dh":
            f.update(theta=rng.uniform(-2, 2), d=rng.normal(0, 0.3), a=rng.normal(0, 0.3),
                     alpha=rng.uniform(-2, 2), beta=rng.normal(0, 0.1))
        else:
            f["origin"] = make_transform(rpy_to_matrix(rng.uniform(-2, 2, 3)), rng.normal(0, 0.3, 3))
            ax = rng.normal(size=3)
            f["axis"] = ax if rng.random() < 0.5 else np.array([0, 0, 1.0])
        frames.append(f)
    if rng.random() < 0.3:
        frames.insert(0, {"name": "f0", "type": "fixed", "convention": "khalil", "label": "F0",
                          "theta": rng.uniform(-2, 2), "r": rng.normal(0, 0.3)})
    markers = rng.normal(0, 0.1, (draw(st.integers(0, 3)), 3))
    coupling = None
    if n >= 2 and rng.random() < 0.3:
        coupling = (np.eye(n) + 0.1 * rng.normal(size=(n, n)), np.eye(n) + 0.1 * rng.normal(size=(n, n)))
    robot = build_robot("random", frames, base={"xyz": rng.normal(0, 0.5, 3), "rpy": rng.uniform(-2, 2, 3)},
                        tool={"xyz": rng.normal(0, 0.2, 3), "rpy": rng.uniform(-2, 2, 3)},
                        markers=markers if len(markers) else None, coupling=coupling, convention="khalil")
    theta = robot.params.values + rng.normal(0, 0.02, robot.n_params)
    q = robot.random_readings(draw(st.integers(1, 6)), rng)
    return robot, q, theta


@settings(max_examples=40, deadline=None)
@given(random_robot())
def test_jacobian_random_robots(case):
    robot, q, theta = case
    assert_jacobian_matches(robot, q, theta)


@pytest.mark.parametrize("factory", [stanford, puma560, puma560_fu, robot_5r1p, planar2])
def test_jacobian_builtin_robots(factory):
    robot = factory()
    rng = np.random.default_rng(3)
    theta = robot.params.values + rng.normal(0, 0.01, robot.n_params)
    assert_jacobian_matches(robot, robot.random_readings(8, rng), theta)


def test_jacobian_tiago_urdf(tiago_dir):
    from estcal.kinematics import tiago

    robot = tiago(n_markers=4)
    rng = np.random.default_rng(4)
    theta = robot.params.values + rng.normal(0, 0.01, robot.n_params)
    assert_jacobian_matches(robot, robot.random_readings(6, rng), theta)


def test_joint_values_gain_offset_coupling():
    """q = Cj diag(K) Cm r + offset (GECARO eq. 4), checked against a direct evaluation."""
    rng = np.random.default_rng(0)
    Cj, Cm = np.eye(3) + 0.2 * rng.normal(size=(3, 3)), np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    frames = [{"name": f"j{i}", "offset": 0.1 * i, "gain": 1.0 + 0.1 * i} for i in range(3)]
    robot = build_robot("c", frames, coupling=(Cj, Cm))
    r = rng.normal(size=(5, 3))
    q, dq = robot.joint_values(r, derivatives=True)
    K = np.array([1.0, 1.1, 1.2])
    off = np.array([0.0, 0.1, 0.2])
    np.testing.assert_allclose(q, (Cj @ (K[:, None] * (Cm @ r.T))).T + off, atol=1e-14)
    gi = robot.gain_idx
    # dq_l/dK_j = Cj[l, j] (Cm r)_j
    np.testing.assert_allclose(dq[:, :, gi], Cj[None] * (r @ Cm.T)[:, None, :], atol=1e-14)


def test_joint_values_derivative_of_joint_effects_by_their_columns():
    """Joint effects' dq/dθ enter by their one joint per parameter (JointEffect.param_joints, the 'cols' blocks):
    the dense derivative of joint_values against central finite differences of q, on a PUMA 560 with a gear
    harmonic (two parameters per joint), a compliance and an encoder gain on several joints at once, and the
    many-θ path equal to single calls."""
    from estcal.effects import make_effect

    robot = puma560()
    for name, joints, kw in (("gear_harmonic", ["j2", "j3"], {"orders": [1]}), ("joint_compliance", ["j2", "j3"], {}),
                             ("encoder_gain", ["j1", "j5"], {})):
        robot = robot.add_effect(make_effect(name, robot, joints=joints, **kw))
    rng = np.random.default_rng(5)
    theta = robot.params.values.copy()
    eff = np.flatnonzero(np.array(robot.params.kinds) == "effect")
    theta[eff] = rng.normal(0, 1e-3, eff.size)
    r = robot.random_readings(4, rng)
    q, dq = robot.joint_values(r, theta, derivatives=True)
    fd = np.empty_like(dq)
    h = 1e-6
    for k in range(robot.n_params):
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        fd[:, :, k] = (robot.joint_values(r, tp)[0] - robot.joint_values(r, tm)[0]) / (2 * h)
    assert np.abs(dq[:, :, eff]).max() > 1e-2
    # the effects' columns and the gains' and offsets' (the joint variable's own geometric parameter is the chain's)
    cols = np.r_[eff, robot.gain_idx, robot.offset_idx]
    np.testing.assert_allclose(dq[:, :, cols], fd[:, :, cols], atol=1e-7)
    many = robot.kinematics(r, np.stack([theta, theta + 1e-4]))
    for w, th in enumerate((theta, theta + 1e-4)):
        np.testing.assert_allclose(many.J[w], robot.kinematics(r, th).J, atol=1e-12)


def test_pose_residual_rows_exact_at_large_residual():
    """Location-method rows are the exact derivative of −e even far from the solution."""
    from estcal.io import dataset_from_arrays
    from estcal.kinematics.transforms import so3_exp
    from estcal.methods import NoiseModel, PoseMethod

    robot = puma560()
    rng = np.random.default_rng(5)
    q = robot.random_readings(5, rng)
    k = robot.kinematics(q, jacobian=False)
    data = dataset_from_arrays(robot.joint_names, q, R=so3_exp(rng.normal(0, 0.5, (5, 3))) @ k.R, p=k.p + 0.1)
    m, noise = PoseMethod(), NoiseModel()
    theta = robot.params.values
    rows = m.rows(robot, theta, data, noise)
    eps = 1e-6
    for i in range(robot.n_params):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += eps
        tm[i] -= eps
        de = (m.rows(robot, tp, data, noise, False).e - m.rows(robot, tm, data, noise, False).e) / (2 * eps)
        np.testing.assert_allclose(-de, rows.H[:, i], atol=1e-7)
