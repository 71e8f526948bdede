"""Forward kinematics against closed forms and published values."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.kinematics import ParameterError, planar2, puma560, puma560_fu, stanford
from estcal.kinematics.transforms import (matrix_to_quat, matrix_to_rpy, quat_to_matrix, rot_axis, rpy_to_matrix,
                                          so3_exp, so3_log)


def test_puma_table_6_1_zero_pose():
    """Mooring §9.1: the Table 6.1 model at zero joints is at (0.609, 33.944, 27.008) in."""
    k = puma560().kinematics(np.zeros((1, 6)), jacobian=False)
    np.testing.assert_allclose(k.p[0] / 0.0254, [0.609, 33.944, 27.008], atol=6e-4)


def test_planar2_closed_form():
    rng = np.random.default_rng(1)
    q = rng.uniform(-3, 3, (20, 2))
    p = planar2().kinematics(q, jacobian=False).p
    x = 1.0 * np.cos(q[:, 0]) + 0.8 * np.cos(q.sum(1))
    y = 1.0 * np.sin(q[:, 0]) + 0.8 * np.sin(q.sum(1))
    np.testing.assert_allclose(p[:, :2], np.c_[x, y], atol=1e-14)


def _dh(theta, d, a, alpha):
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d], [0, 0, 0, 1]])


def test_puma_fu_against_textbook_matrix_2_12():
    """Standard DH products with the textbook's closed-form link matrix (2.12)."""
    rows = [(0, 0, -90), (149.09, 431.8, 0), (0, -20.32, 90), (433.07, 0, -90), (0, 0, 90), (56.25, 0, 0)]
    rng = np.random.default_rng(2)
    q = rng.uniform(-2, 2, (5, 6))
    k = puma560_fu().kinematics(q, jacobian=False)
    for n in range(5):
        T = np.eye(4)
        for j, (d, a, al) in enumerate(rows):
            T = T @ _dh(q[n, j], d * 1e-3, a * 1e-3, np.radians(al))
        np.testing.assert_allclose(k.T[n], T, atol=1e-12)


def test_khalil_stanford_against_matrix_product():
    """GECARO eq. [3] link by link with explicit 4x4 matrices."""
    def rx(a):
        return np.array([[1, 0, 0, 0], [0, np.cos(a), -np.sin(a), 0], [0, np.sin(a), np.cos(a), 0], [0, 0, 0, 1]])

    def rz(a):
        return np.array([[np.cos(a), -np.sin(a), 0, 0], [np.sin(a), np.cos(a), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])

    def tr(x, z):
        T = np.eye(4)
        T[0, 3], T[2, 3] = x, z
        return T

    h = np.pi / 2
    table = [(0, 0, h, 0.5), (0.1, 0, None, 0), (-h, 0, None, 0.2), (h, 0, 0, None), (0, 0, None, 0),
             (-h, 0, None, 0), (h, 0, None, 0), (1.3, 0.2, h, 0.1)]
    q = np.array([[0.3, -0.4, 0.55, 1.0, -0.7, 2.0]])
    T = np.eye(4)
    jq = iter(q[0])
    for al, d, th, r in table:
        if th is None:
            th = next(jq)
        elif r is None:
            r = next(jq)
        T = T @ rx(al) @ tr(d, 0) @ rz(th) @ tr(0, r)
    np.testing.assert_allclose(stanford().fk(q)[0], T, atol=1e-12)


def test_transform_roundtrips():
    rng = np.random.default_rng(0)
    R = so3_exp(rng.normal(size=(200, 3)) * 1.5)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    np.testing.assert_allclose(rpy_to_matrix(matrix_to_rpy(R)), R, atol=1e-12)
    np.testing.assert_allclose(so3_exp(so3_log(R)), R, atol=1e-10)
    # near pi
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    Rpi = rot_axis(axis, np.pi - 1e-7)
    np.testing.assert_allclose(so3_exp(so3_log(Rpi[None]))[0], Rpi, atol=1e-7)


def test_quat_to_matrix_is_scipys_rotation():
    """The numpy closed form equals scipy's ``Rotation.from_quat`` (scalar first) on unnormalised
    quaternions of any leading shape, both signs of w."""
    from scipy.spatial.transform import Rotation

    q = np.random.default_rng(1).normal(size=(4, 5, 4)) * 3.0
    ref = Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(4, 5, 3, 3)
    np.testing.assert_allclose(quat_to_matrix(q), ref, atol=1e-15)
    np.testing.assert_allclose(quat_to_matrix(-q[0, 0]), ref[0, 0], atol=1e-15)


def test_parameter_vector_names_and_errors():
    pv = puma560().params
    assert "alpha_3" in pv and "offset_2" in pv and "base_tz" in pv and "tool_rx" in pv and "gain_6" in pv
    sub = pv.with_free(["offset_*"])
    assert sub.free_names == [f"offset_{i}" for i in range(1, 7)]
    x = sub.to_flat() + 0.1
    full = sub.from_flat(x)
    assert np.allclose(full[sub.free_indices], x) and np.allclose(np.delete(full, sub.free_indices),
                                                                   np.delete(pv.values, sub.free_indices))
    with pytest.raises(ParameterError, match="unknown parameter 'ofset_2'. Did you mean 'offset_2'"):
        pv.index("ofset_2")


def test_gravity_torque_planar_closed_form():
    """Two-link arm in a vertical plane: τ1 = -g (m1 l1/2 c1 + m2 (l1 c1 + l2/2 c12)) about z."""
    from estcal.kinematics.builder import build_robot

    frames = [{"name": "a", "a": 1.0, "mass": 2.0, "com": [-0.5, 0, 0]},
              {"name": "b", "a": 0.8, "mass": 1.0, "com": [-0.4, 0, 0]}]
    robot = build_robot("v", frames, convention="dh", gravity=(0, -9.81, 0))
    q = np.random.default_rng(0).uniform(-3, 3, (10, 2))
    tau = robot.gravity_torques(q)
    c1, c12 = np.cos(q[:, 0]), np.cos(q.sum(1))
    g = 9.81
    np.testing.assert_allclose(tau[:, 0], -g * (2.0 * 0.5 * c1 + 1.0 * (c1 + 0.4 * c12)), atol=1e-12)
    np.testing.assert_allclose(tau[:, 1], -g * (1.0 * 0.4 * c12), atol=1e-12)


def test_tiago_urdf_link_masses_include_everything_attached(tiago_dir):
    """Every inertial below the torso lift (hand, F/T sensor, fingers included) is carried by some
    actuated link: the masses sum to the total URDF mass of the torso_lift_link subtree."""
    import yourdfpy

    from estcal.kinematics import tiago

    robot = tiago(1)
    urdf = yourdfpy.URDF.load(str(tiago_dir / "tiago_48_schunk.urdf"), build_scene_graph=False, load_meshes=False)
    children = {}
    for j in urdf.robot.joints:
        children.setdefault(j.parent, []).append(j.child)
    mass = {lk.name: (lk.inertial.mass if lk.inertial is not None and lk.inertial.mass else 0.0)
            for lk in urdf.robot.links}
    stack, total = ["torso_lift_link"], 0.0
    while stack:
        name = stack.pop()
        total += mass[name]
        stack += children.get(name, [])
    assert sum(lk.mass for lk in robot.links) == pytest.approx(total, rel=1e-12)
    # the hand (> 1 kg) hangs from arm_7
    assert robot.links[robot._joint_link[7]].mass > 1.0


def _expand_summary(text: str) -> list[str]:
    """Inverse of ``summarize_names``, written from its documented grammar only."""
    import re

    out = []
    for part in re.split(r",\s*(?![^{]*\})", text):
        m = re.fullmatch(r"(.*)_(\d+)…(\d+)", part)
        if m:
            out += [f"{m[1]}_{i}" for i in range(int(m[2]), int(m[3]) + 1)]
            continue
        m = re.fullmatch(r"([^{]*)_\{(.*)\}", part)
        if m:
            out += [f"{k}_{t}" for k in m[1].split("/") for t in m[2].split(", ")]
            continue
        head, sep, tails = part.rpartition("_")
        if sep and "/" in tails:
            out += [f"{head}_{t}" for t in tails.split("/")]
        elif "/" in part and "_" in part:  # keys merged before one suffix: a/b_T
            keys, tail = part.split("_", 1)
            out += [f"{k}_{tail}" for k in keys.split("/")]
        else:
            out.append(part)
    return out


@pytest.mark.parametrize("factory", [planar2, puma560, puma560_fu, stanford])
def test_summarized_names_recover_every_name(factory):
    """The one-line summary in an unknown-parameter message names each parameter exactly once."""
    from estcal.kinematics.parameters import summarize_names

    names = factory().params.names
    text = summarize_names(names)
    assert sorted(_expand_summary(text)) == sorted(names)
    assert len(text) < sum(len(n) + 2 for n in names)


def test_summarized_urdf_names_recover_every_name():
    from estcal.kinematics.parameters import summarize_names

    joints = ["torso_lift_joint", "arm_1_joint", "arm_2_joint"]
    names = [f"base_{c}" for c in ("tx", "ty", "rz")] + [f"{k}_{j}" for j in joints for k in ("tx", "rz")] \
        + [f"offset_{j}" for j in joints] + ["compliance_2"]
    assert sorted(_expand_summary(summarize_names(names))) == sorted(names)


def _check_loads_link_by_link(robot, q, ctx):
    """``gravity_moments`` and ``gravity_torques`` against the sums over every moved link and the payload, one
    pose and one joint at a time: M_j = Σ_{i ⪰ j} (c_i − o_j) × m_i g; τ_j = a_jᵀ M_j (revolute) or a_jᵀ Σ m_i g
    (prismatic)."""
    tau, M = robot.gravity_torques(q, context=ctx), robot.gravity_moments(q, context=ctx)
    kin = robot.kinematics(q, jacobian=False)
    g = np.asarray(robot.gravity, float)
    pay_c = kin.p + kin.R @ robot.payload_com
    for n in range(len(q)):
        for j in range(robot.n_joints):
            a, o = kin.joint_axis[n, j], kin.joint_origin[n, j]
            force, moment = ctx["payload"][n] * g, np.cross(pay_c[n] - o, ctx["payload"][n] * g)
            for i in range(robot._joint_link[j], len(robot.links)):
                lk = robot.links[i]
                force = force + lk.mass * g
                moment = moment + np.cross(kin.link_p[n, i] + kin.link_R[n, i] @ lk.com - o, lk.mass * g)
            np.testing.assert_allclose(M[n, j], moment, rtol=1e-12, atol=1e-12)
            want = a @ (force if robot.joint_types[j] == "prismatic" else moment)
            assert abs(tau[n, j] - want) <= 1e-12 * max(1.0, abs(want)), (n, j)
    return tau


def test_gravity_torques_are_the_moments_of_every_moved_link_and_the_payload(tiago_dir):
    """On TIAGo (a prismatic torso: a_jᵀ Σ m_i g) with a per-pose payload."""
    from estcal.kinematics import tiago

    robot = tiago(n_markers=1)
    rng = np.random.default_rng(4)
    q = robot.random_readings(9, rng)
    tau = _check_loads_link_by_link(robot, q, {"payload": rng.uniform(0, 2, 9)})
    assert robot.joint_types[0] == "prismatic" and np.ptp(tau[:, 0]) > 0


def test_gravity_moments_of_a_heavy_puma():
    """The same sums on a PUMA 560 with link masses and a payload (no shared data needed)."""
    from test_effects import heavy_puma

    robot = heavy_puma()
    rng = np.random.default_rng(2)
    _check_loads_link_by_link(robot, robot.random_readings(6, rng), {"payload": rng.uniform(0, 3, 6)})


def test_cross_at_an_inner_axis_is_numpys_cross_bit_for_bit():
    """transforms.cross_at (the Jacobian corrections' cross product along the coordinate axis of (N, k, 3, P)
    columns, broadcast) against numpy's np.cross on moved axes — equal to the last bit, as the corrections were
    before it (the diagnosis's figures are unchanged by it)."""
    from estcal.kinematics.transforms import cross, cross_at

    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 1, 3, 7))
    b = rng.normal(size=(5, 4, 3, 1))
    got = cross_at(a, b, 2)
    ref = np.moveaxis(np.cross(np.moveaxis(a, 2, -1), np.moveaxis(b, 2, -1)), -1, 2)
    assert got.shape == (5, 4, 3, 7)
    np.testing.assert_allclose(got, ref, rtol=1e-15, atol=1e-15)
    assert np.array_equal(got, np.moveaxis(cross(np.moveaxis(a, 2, -1), np.moveaxis(b, 2, -1)), -1, 2))
    out = np.empty((5, 4, 3, 7))
    assert cross_at(a, b, 2, out=out) is out and np.array_equal(out, got)
