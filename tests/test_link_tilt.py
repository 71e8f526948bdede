"""The link-tilt effect: a bearing / link turning under the gravity moment across its joint's axis.

Checked against a closed form (a horizontal arm on a vertical axis droops by t·m·g·L²), finite differences (tests/test_effects.py runs its columns with the other effects),
and a simulated calibration that recovers the tilt compliances which no joint-space effect or geometric
parameter can stand in for. The gravity moments themselves are summed link by link in
tests/test_kinematics_models.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from test_effects import heavy_puma as _heavy_puma

from estcal.effects import make_effect
from estcal.io.robotfile import robot_from_dict, robot_to_dict
from estcal.kinematics.builder import build_robot


def test_horizontal_arm_on_a_vertical_axis_droops_by_t_m_g_l_squared():
    """One revolute joint about the vertical z, a link of length L along x with its mass m at the end:
    the gravity moment about the joint is m g L across the axis (none along it, so joint compliance sees
    nothing), the arm turns by t m g L about the horizontal normal and its end drops by t m g L²."""
    L, m, t, g = 0.8, 3.0, 2e-4, 9.81
    # DH: the link frame sits at the end of the link (a = L along the new x), its mass at the frame origin
    frames = [{"name": "yaw", "a": L, "mass": m, "com": [0, 0, 0]}]
    rigid = build_robot("yaw", frames, convention="dh", gravity=(0, 0, -g))
    robot = rigid.add_effect(make_effect("link_tilt", rigid))
    robot.params["tilt_yaw"] = t
    q = np.linspace(-3, 3, 7)[:, None]
    k0, k = rigid.kinematics(q, jacobian=False), robot.kinematics(q, jacobian=False)
    np.testing.assert_allclose(rigid.gravity_torques(q), 0.0, atol=1e-12)  # nothing along the axis
    M = rigid.gravity_moments(q)[:, 0]
    horiz = np.c_[np.cos(q[:, 0]), np.sin(q[:, 0])]
    np.testing.assert_allclose(np.linalg.norm(M, axis=1), m * g * L, rtol=1e-12)
    np.testing.assert_allclose(np.einsum("ni,ni->n", M[:, :2], horiz), 0.0, atol=1e-12)  # about the normal
    d = k.p - k0.p
    # first order: a drop of t m g L², no horizontal motion to first order (t m g L = 4.7 mrad here)
    np.testing.assert_allclose(d[:, 2], -t * m * g * L ** 2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(d[:, :2], 0.0, atol=1e-15)


def test_tilt_moves_points_by_the_small_rotation_about_each_joint_origin():
    """δx = Σ_j t_j M⊥_j × (x − o_j) at every marker, with M⊥ the moment minus its axial part."""
    base = _heavy_puma()
    robot = base.add_effect(make_effect("link_tilt", base, joints=["j2", "j3"]))
    rng = np.random.default_rng(5)
    q = base.random_readings(5, rng)
    t = np.array([3e-5, 7e-5])
    robot.params["tilt_j2"], robot.params["tilt_j3"] = t
    k0, k = base.kinematics(q, jacobian=False), robot.kinematics(q, jacobian=False)
    M = base.gravity_moments(q)
    expect = np.zeros_like(k0.points)
    for c, j in zip(t, (1, 2)):
        a, o = k0.joint_axis[:, j], k0.joint_origin[:, j]
        Mp = M[:, j] - np.sum(M[:, j] * a, -1, keepdims=True) * a
        expect += np.cross(c * Mp[:, None, :], k0.points - o[:, None, :])
    np.testing.assert_allclose(k.points - k0.points, expect, rtol=0, atol=1e-14)
    assert np.abs(expect).max() > 1e-4  # a visible effect (0.1 mm and more)


def test_a_simulated_tilt_is_recovered_where_joint_compliance_and_geometry_cannot_stand_in():
    """Markers on a PUMA with tilting shoulder and elbow bearings, 0.02 mm noise: least squares with the
    geometry, joint compliance and tilt free recovers the tilts within 3 σ; without the tilt terms
    (geometry and compliance free) the residual stays far above the noise."""
    from estcal.estimate import calibrate_lsq
    from estcal.identify.select import select_identifiable
    from estcal.io.dataset import Dataset
    from estcal.methods import NoiseModel, Problem

    base = _heavy_puma()
    truth = base.add_effect(make_effect("joint_compliance", base, joints=["j2", "j3"]))
    truth = truth.add_effect(make_effect("link_tilt", truth, joints=["j2", "j3"]))
    t_true = {"tilt_j2": 4e-5, "tilt_j3": 1.5e-4, "compliance_j2": 2e-5, "compliance_j3": 5e-5}
    for n, v in t_true.items():
        truth.params[n] = v
    rng = np.random.default_rng(11)
    q = base.random_readings(60, rng)
    sigma = 2e-5
    pts = truth.kinematics(q, jacobian=False).points + rng.normal(0, sigma, (60, base.n_markers, 3))
    data = Dataset(list(base.joint_names), q, "points", points=pts)
    noise = NoiseModel(position=sigma, known=True)
    model = base.add_effect(make_effect("joint_compliance", base, joints=["j2", "j3"]))
    no_tilt = model
    model = model.add_effect(make_effect("link_tilt", model, joints=["j2", "j3"]))

    def fit(rb):
        problem = Problem(rb, [(None, data, noise)])
        geo = [n for n, kd in zip(rb.params.names, rb.params.kinds) if kd in ("geometric", "offset", "base")]
        eff = [n for n, kd in zip(rb.params.names, rb.params.kinds) if kd == "effect"]
        from estcal.discrepancy.geometric import weighted_system
        _, A, _ = weighted_system(problem, rb.params.values, geo)
        free = select_identifiable(A, names=geo).identifiable + eff
        return calibrate_lsq(problem, "lm", free=free, max_iter=60)

    res = fit(model)
    for n in ("tilt_j2", "tilt_j3"):
        i = res.names.index(n)
        assert abs(res.theta[model.params.index(n)] - t_true[n]) < 3 * res.std[i], n
        assert res.std[i] < 0.2 * t_true[n]
    # σ0 = √(χ²/dof) with the noise known: 1 for a right model
    assert res.sigma0 < 1.2
    assert fit(no_tilt).sigma0 > 3


def test_diagnosis_screens_link_tilt_only_on_loaded_joints():
    """``default_candidates`` offers ``link_tilt`` (a load term of the diagnosis, screened by default) on every
    joint with a moment across its axis — not on a joint that carries no mass (the PUMA's wrist with the payload
    and the last links massless)."""
    from estcal.discrepancy.diagnose import default_candidates
    from estcal.io.dataset import Dataset

    base = _heavy_puma()
    q = base.random_readings(20, np.random.default_rng(3))
    data = Dataset(list(base.joint_names), q, "points", points=base.kinematics(q, jacobian=False).points)
    assert [c.joints for c in default_candidates(base, data) if c.effect == "link_tilt"] == \
        [[j] for j in base.joint_names]
    asked = default_candidates(base, data, effects=["link_tilt"], families=False)
    assert [c.joints for c in asked] == [[j] for j in base.joint_names]
    light = robot_to_dict(base)
    for jd in light["joints"][3:]:
        jd["mass"] = 0.0
    light["payload"] = {"mass": 0.0, "com": [0.0, 0.0, 0.0]}
    light = robot_from_dict(light, "light_wrist")
    asked = default_candidates(light, data, effects=["link_tilt"], families=False)
    assert [c.joints[0] for c in asked] == list(base.joint_names[:3])


@pytest.mark.parametrize("kind", ["position", "location", "point-link", "frame-link", "plane-unknown", "distance"])
def test_link_tilt_reaches_every_measurement_kind(kind):
    """The tilt moves the tool origin as well as the markers, so every measurement kind sees it: its columns
    against central differences of the stacked residuals exactly, the others to the loads' own first-order
    variation with the geometry (neglected by design, relative ~t·|M| here)."""
    from test_effects_every_kind import _data, _method

    from estcal.methods import Problem

    base = _heavy_puma()
    robot = base.add_effect(make_effect("link_tilt", base))
    ds = _data(base, kind)
    prob = Problem(robot, [(_method(kind), ds)])
    theta = prob.params.values.copy()
    it = np.array([prob.params.index(n) for n in robot.params.select("tilt_*")])
    theta[it] = 2e-5
    rows = prob.evaluate(theta)
    fd = np.empty_like(rows.H)
    for k in range(theta.size):
        step = 1e-7 * max(1.0, abs(theta[k])) if k not in it else 1e-8
        tp, tm = theta.copy(), theta.copy()
        tp[k] += step
        tm[k] -= step
        fd[:, k] = -(prob.evaluate(tp, jacobian=False).e - prob.evaluate(tm, jacobian=False).e) / (2 * step)
    assert np.abs(fd[:, it]).max() > 1e-3
    np.testing.assert_allclose(rows.H[:, it], fd[:, it], rtol=0, atol=1e-6 * np.abs(fd[:, it]).max())
    np.testing.assert_allclose(rows.H, fd, rtol=0, atol=2e-2 * np.abs(fd).max())
