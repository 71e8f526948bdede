"""Non-geometric effects: closed forms, finite-difference Jacobian columns, registry, robot files."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.effects import EFFECTS, Effect, JointEffect, effect_context, make_effect, register_effect
from estcal.io.robotfile import load_robot, robot_from_dict, robot_to_dict, save_robot
from estcal.kinematics import planar2, puma560
from estcal.kinematics.builder import build_robot
from estcal.kinematics.transforms import so3_log


def heavy_puma(markers=2):
    """PUMA 560 with link masses/centres of mass, a payload and markers (documented test values)."""
    d = robot_to_dict(puma560())
    masses = [0.0, 17.4, 4.8, 0.82, 0.34, 0.09]
    coms = [[0, 0, 0], [-0.3638, 0.006, 0.2275], [-0.0203, -0.0141, 0.070], [0, 0.019, 0], [0, 0, 0], [0, 0, 0.032]]
    for jd, m, c in zip(d["joints"], masses, coms):
        jd["mass"], jd["com"] = m, c
    d["payload"] = {"mass": 2.0, "com": [0.0, 0.0, 0.1]}
    d["markers"] = [[0.05, 0.0, 0.1], [0.0, -0.07, 0.12]][:markers]
    return robot_from_dict(d, "heavy_puma")


def context_for(N, rng):
    return {"t": np.sort(rng.uniform(0, 3600, N)), "temperature": rng.uniform(15, 35, N),
            "payload": rng.uniform(0, 5, N),
            **{f"approach_j{i}": rng.choice([-1.0, 1.0], N) for i in (1, 3)}}


def fd_columns(robot, q, theta, ctx, cols, eps=1e-6):
    Jp = np.empty((q.shape[0], 6, len(cols)))
    Jm = np.empty((q.shape[0], robot.n_markers, 3, len(cols)))
    for c, i in enumerate(cols):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += eps
        tm[i] -= eps
        kp, km = robot.kinematics(q, tp, ctx, jacobian=False), robot.kinematics(q, tm, ctx, jacobian=False)
        Jp[:, :3, c] = (kp.p - km.p) / (2 * eps)
        Jp[:, 3:, c] = so3_log(kp.R @ np.swapaxes(km.R, 1, 2)) / (2 * eps)
        Jm[..., c] = (kp.points - km.points) / (2 * eps)
    return Jp, Jm


EFFECT_CASES = [
    ("joint_compliance", dict(joints=["j2", "j3", "j5"]), 1e-4),
    ("backlash", dict(joints=["j1", "j2", "j3"]), 1e-3),
    ("gear_harmonic", dict(joints=["j1", "j4"], orders=[1, 2, 3]), 1e-3),
    ("gear_harmonic", dict(joints=["j2"], orders=[1, 5], gear_ratio=50.0), 1e-4),
    ("encoder_gain", dict(joints=None), 1e-3),
    ("thermal_expansion", dict(), 1.2e-5),
    ("drift", dict(joints=["j2", "j6"], t0=100.0), 1e-7),
    ("link_tilt", dict(joints=["j1", "j2", "j3"]), 1e-4),
]


@pytest.mark.parametrize("name,kw,scale", EFFECT_CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(EFFECT_CASES)])
def test_effect_parameter_columns_match_finite_differences(name, kw, scale):
    base = heavy_puma()
    robot = base.add_effect(make_effect(name, base, **kw))
    eff = robot.effects[-1]
    rng = np.random.default_rng(7)
    theta = robot.params.values.copy()
    theta[eff.indices] = rng.normal(0, scale, len(eff.indices))
    q = robot.random_readings(12, rng)
    ctx = context_for(12, rng)
    k = robot.kinematics(q, theta, ctx)
    # perturb δq by ~1e-6 rad whatever the feature scale (drift features are t ~ 1e3 s)
    Jp, Jm = fd_columns(robot, q, theta, ctx, eff.indices, eps=1e-9 if name == "drift" else 1e-6)
    assert np.abs(Jp).max() > 0 or np.abs(Jm).max() > 0  # the effect does something
    tol = 1e-7 * max(1.0, np.abs(Jp).max())
    np.testing.assert_allclose(k.J[..., eff.indices], Jp, rtol=0, atol=tol)
    np.testing.assert_allclose(k.J_points[..., eff.indices], Jm, rtol=0, atol=1e-7 * max(1.0, np.abs(Jm).max()))


def _rigid(robot, q, ctx=None):
    return robot.kinematics(q, context=ctx, jacobian=False)


def test_compliance_closed_form_planar_vertical():
    """Two-link arm in a vertical plane: δq = c·τ with τ in closed form (masses at mid-links)."""
    frames = [{"name": "a", "a": 1.0, "mass": 2.0, "com": [-0.5, 0, 0]},
              {"name": "b", "a": 0.8, "mass": 1.0, "com": [-0.4, 0, 0]}]
    rigid = build_robot("v", frames, convention="dh", gravity=(0, -9.81, 0))
    robot = rigid.add_effect(make_effect("joint_compliance", rigid))
    robot.params["compliance_a"], robot.params["compliance_b"] = 2e-3, 5e-3
    q = np.random.default_rng(0).uniform(-3, 3, (10, 2))
    c1, c12, g = np.cos(q[:, 0]), np.cos(q.sum(1)), 9.81
    tau = np.c_[-g * (2.0 * 0.5 * c1 + 1.0 * (c1 + 0.4 * c12)), -g * 0.4 * c12]
    k = _rigid(robot, q)
    np.testing.assert_allclose(k.q, q + tau * [2e-3, 5e-3], atol=1e-13)
    qq = q + tau * [2e-3, 5e-3]
    x = np.cos(qq[:, 0]) + 0.8 * np.cos(qq.sum(1))
    np.testing.assert_allclose(k.p[:, 0], x, atol=1e-12)
    # a payload column adds its own torque (mass at the tool origin, lever l1 c1 + l2 c12)
    ctx = {"payload": np.full(10, 3.0)}
    kp = _rigid(robot, q, ctx)
    tau_p = tau + np.c_[-g * 3.0 * (c1 + 0.8 * c12), -g * 3.0 * 0.8 * c12]
    np.testing.assert_allclose(kp.q, q + tau_p * [2e-3, 5e-3], atol=1e-12)


def test_backlash_signs():
    base = heavy_puma()
    robot = base.add_effect(make_effect("backlash", base, joints=["j2", "j3"]))
    robot.params["backlash_j2"], robot.params["backlash_j3"] = 1e-3, 2e-3
    rng = np.random.default_rng(1)
    q = robot.random_readings(20, rng)
    tau = base.gravity_torques(q)
    k = _rigid(robot, q)
    np.testing.assert_allclose(k.q[:, 1:3] - q[:, 1:3], np.sign(tau[:, 1:3]) * [1e-3, 2e-3], atol=1e-15)
    appr = rng.choice([-1.0, 1.0], 20)
    k2 = _rigid(robot, q, {"approach_j3": appr})
    np.testing.assert_allclose(k2.q[:, 2] - q[:, 2], -appr * 2e-3, atol=1e-15)  # link lags the motor
    np.testing.assert_allclose(k2.q[:, 1] - q[:, 1], np.sign(tau[:, 1]) * 1e-3, atol=1e-15)



def test_backlash_by_load_and_by_approach_side_by_side():
    """``by="load"`` ignores an approach column, ``by="approach"`` reads only it (0 without it: either side as
    likely), and both act on one joint at once with their own parameters; their columns match finite
    differences."""
    base = heavy_puma()
    robot = base.add_effect(make_effect("backlash", base, joints=["j2"], by="load"))
    robot = robot.add_effect(make_effect("backlash", robot, joints=["j2"], by="approach"))
    assert robot.params.select("backlash*") == ["backlash_j2", "backlash_approach_j2"]
    robot.params["backlash_j2"], robot.params["backlash_approach_j2"] = 1e-3, 3e-3
    rng = np.random.default_rng(4)
    q = robot.random_readings(25, rng)
    tau = base.gravity_torques(q)
    appr = rng.choice([-1.0, 0.0, 1.0], 25)
    k = _rigid(robot, q, {"approach_j2": appr})
    np.testing.assert_allclose(k.q[:, 1] - q[:, 1], np.sign(tau[:, 1]) * 1e-3 - appr * 3e-3, atol=1e-15)
    k0 = _rigid(robot, q)
    np.testing.assert_allclose(k0.q[:, 1] - q[:, 1], np.sign(tau[:, 1]) * 1e-3, atol=1e-15)
    theta = robot.params.values.copy()
    eidx = np.array(robot.params.indices(["backlash_j2", "backlash_approach_j2"]))
    ctx = {"approach_j2": appr}
    kk = robot.kinematics(q, theta, ctx)
    Jp, _ = fd_columns(robot, q, theta, ctx, eidx, eps=1e-7)
    np.testing.assert_allclose(kk.J[..., eidx], Jp, rtol=0, atol=1e-6 * np.abs(Jp).max())
    with pytest.raises(ValueError, match="by must be one of auto, load, approach"):
        make_effect("backlash", base, joints=["j2"], by="gravity")
    # the option survives the robot file (a diagnosed model's backlash keeps its meaning)
    d = [e.to_dict() for e in robot.effects]
    assert [x.get("options") for x in d] == [{"by": "load"}, {"by": "approach"}]
    again = robot_from_dict(robot_to_dict(robot))
    np.testing.assert_array_equal(_rigid(again, q, {"approach_j2": appr}).q, k.q)

def test_harmonic_gain_drift_closed_forms():
    base = puma560()
    base.meta["gear_ratio"] = {"j1": 100.0}
    robot = base.add_effect(make_effect("gear_harmonic", base, joints=["j1", "j2"], orders=[2]))
    robot = robot.add_effect(make_effect("encoder_gain", robot, joints=["j3"]))
    robot = robot.add_effect(make_effect("drift", robot, joints=["j4"], t0=10.0))
    vals = {"harmonic2_sin_j1": 1e-4, "harmonic2_cos_j1": -2e-4, "harmonic2_sin_j2": 3e-4,
            "harmonic2_cos_j2": 5e-5, "encgain_j3": 1e-3, "drift_j4": 1e-6}
    for n, v in vals.items():
        robot.params[n] = v
    rng = np.random.default_rng(2)
    q = robot.random_readings(15, rng)
    t = rng.uniform(0, 1000, 15)
    k = _rigid(robot, q, {"t": t})
    dq = k.q - q
    np.testing.assert_allclose(dq[:, 0], 1e-4 * np.sin(200 * q[:, 0]) - 2e-4 * np.cos(200 * q[:, 0]), atol=1e-15)
    np.testing.assert_allclose(dq[:, 1], 3e-4 * np.sin(2 * q[:, 1]) + 5e-5 * np.cos(2 * q[:, 1]), atol=1e-15)
    np.testing.assert_allclose(dq[:, 2], 1e-3 * q[:, 2], atol=1e-15)
    np.testing.assert_allclose(dq[:, 3], 1e-6 * (t - 10.0), atol=1e-15)
    np.testing.assert_allclose(dq[:, [4, 5]], 0.0, atol=0)
    # the FK is the nominal FK at the corrected joint values
    np.testing.assert_allclose(k.p, _rigid(base, q + dq).p, atol=1e-14)
    with pytest.raises(ValueError, match="needs the time column 't'"):
        _rigid(robot, q)


def test_thermal_equals_scaled_lengths():
    """Expansion about the base origin = every length (d, a, tool, markers) scaled by 1 + αΔT."""
    base = heavy_puma()
    robot = base.add_effect(make_effect("thermal_expansion", base))
    alpha = 1.2e-5
    robot.params["thermal_alpha"] = alpha
    rng = np.random.default_rng(3)
    q = robot.random_readings(10, rng)
    temp = rng.uniform(10, 40, 10)
    pts = _rigid(robot, q, {"temperature": temp}).points
    for i in range(10):
        s = 1 + alpha * (temp[i] - 20.0)
        scaled = base.copy()
        for n in base.params.names:
            if n.split("_")[0] in ("d", "a") or n.startswith("marker") or n in ("tool_tx", "tool_ty", "tool_tz"):
                scaled.params[n] = base.params[n] * s
        np.testing.assert_allclose(pts[i], _rigid(scaled, q[i:i + 1]).points[0], atol=1e-15)
    # fall-back to t, and nothing without either column
    pt = _rigid(robot, q, {"t": np.full(10, 5.0)}).points
    p0 = _rigid(base, q).points
    o = base.params.values[base.params.indices(["base_tx", "base_ty", "base_tz"])]
    np.testing.assert_allclose(pt, p0 + alpha * 5.0 * (p0 - o), atol=1e-15)
    np.testing.assert_allclose(_rigid(robot, q).points, p0, atol=0)


def test_registry_and_user_effect():
    assert {"joint_compliance", "backlash", "gear_harmonic", "encoder_gain", "thermal_expansion",
            "drift"} <= set(EFFECTS)

    class Quadratic(JointEffect):
        """δq_j = w_j · r_j² (a user effect)."""

        name = "quadratic"
        prefixes = ("quad",)

        def features(self, robot, readings, q, theta, context):
            return readings[:, None, self.joint_index] ** 2

    register_effect("quadratic", Quadratic, overwrite=True)
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_effect("quadratic", Quadratic)
        r = planar2()
        r = r.add_effect(make_effect("quadratic", r, joints=["q2"]))
        assert r.params.names[-1] == "quad_q2"
        r.params["quad_q2"] = 0.01
        q = np.array([[0.3, 0.5]])
        np.testing.assert_allclose(r.kinematics(q, jacobian=False).q, [[0.3, 0.5 + 0.01 * 0.25]])
        Jp, _ = fd_columns(r, q, r.params.values, {}, r.params.indices(["quad_q2"]))
        np.testing.assert_allclose(r.kinematics(q).J[..., -1:], Jp, atol=1e-8)
    finally:
        EFFECTS.pop("quadratic", None)


def test_effect_errors():
    r = puma560()
    with pytest.raises(ValueError, match="unknown effect 'joint_complaince' \\(did you mean 'joint_compliance'"):
        make_effect("joint_complaince", r)
    with pytest.raises(ValueError, match="unknown joint 'j9'.*j1"):
        make_effect("backlash", r, joints=["j9"])
    from estcal.kinematics import robot_5r1p

    r5 = robot_5r1p()
    with pytest.raises(ValueError, match="joint 'j3' is prismatic"):
        make_effect("gear_harmonic", r5, joints=["j3"])
    assert make_effect("gear_harmonic", r5).joints == ["j1", "j2", "j4", "j5", "j6"]
    with pytest.raises(ValueError, match="takes no joints"):
        make_effect("thermal_expansion", r, joints=["j1"])
    with pytest.raises(RuntimeError, match="not bound"):
        make_effect("drift", r).values(np.zeros(3))
    assert isinstance(make_effect("drift", r, joints="j1,j2"), Effect)


def test_effects_in_robot_file_roundtrip(tmp_path):
    base = heavy_puma()
    robot = base
    for name, kw, _ in EFFECT_CASES[:5] + EFFECT_CASES[6:]:
        robot = robot.add_effect(make_effect(name, robot, **kw)) if name != "gear_harmonic" or \
            "gear_ratio" not in kw else robot
    rng = np.random.default_rng(4)
    eidx = [i for i, k in enumerate(robot.params.kinds) if k == "effect"]
    robot.params.values[eidx] = rng.normal(0, 1e-4, len(eidx))
    back = load_robot(save_robot(robot, tmp_path / "eff.yaml"))
    assert back.params.names == robot.params.names
    np.testing.assert_array_equal(back.params.values, robot.params.values)
    q = robot.random_readings(10, rng)
    ctx = context_for(10, rng)
    np.testing.assert_allclose(back.kinematics(q, context=ctx, jacobian=False).points,
                               robot.kinematics(q, context=ctx, jacobian=False).points, atol=1e-15)
    assert [type(e) for e in back.effects] == [type(e) for e in robot.effects]


def test_effect_context_picks_requested_columns():
    r = puma560()
    r = r.add_effect(make_effect("backlash", r, joints=["j2"]))

    class DS:
        context = {"t": np.arange(3.0)}
        columns = {"approach_j2": np.array([1.0, -1.0, 1.0]), "other": np.zeros(3)}

    ctx = effect_context(r, DS())
    assert set(ctx) == {"t", "approach_j2"}


# ---------------------------------------------------------------- property-based
from hypothesis import given, settings, strategies as st  # noqa: E402


@st.composite
def robot_with_effects(draw):
    """Random Khalil/DH chains with masses, markers and a random subset of effects on random joints."""
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    n = draw(st.integers(2, 6))
    frames = []
    for j in range(n):
        jt = "prismatic" if rng.random() < 0.2 else "revolute"
        f = {"name": f"q{j}", "type": jt, "convention": ["khalil", "dh"][j % 2], "label": f"L{j}",
             "limits": [-2.5, 2.5] if jt == "revolute" else [0.1, 0.6], "mass": rng.uniform(0, 5),
             "com": rng.normal(0, 0.1, 3), "alpha": rng.uniform(-2, 2), "d": rng.normal(0, 0.3),
             "theta": rng.uniform(-2, 2), "beta": rng.normal(0, 0.05)}
        f["r" if f["convention"] == "khalil" else "a"] = rng.normal(0, 0.3)
        frames.append(f)
    robot = build_robot("rand", frames, base={"xyz": rng.normal(0, 0.5, 3), "rpy": rng.uniform(-2, 2, 3)},
                        markers=rng.normal(0, 0.1, (2, 3)), payload={"mass": 1.0, "com": [0, 0, 0.05]},
                        gravity=rng.normal(0, 5, 3))
    robot.meta["gear_ratio"] = {"q0": 50.0}
    # thermal expansion alone or not at all: combined with joint effects the chain's point columns of
    # the other parameters are exact only to O(αΔT) (see test_thermal_combined_with_joint_effects)
    names = draw(st.sampled_from([["thermal_expansion"]]) | st.lists(
        st.sampled_from(sorted(EFFECTS_UNDER_TEST - {"thermal_expansion"})), min_size=1, max_size=4, unique=True))
    for name in names:
        allowed = [j for j, t in zip(robot.joint_names, robot.joint_types)
                   if name != "gear_harmonic" or t == "revolute"]
        if name == "thermal_expansion":
            robot = robot.add_effect(make_effect(name, robot))
        elif allowed:
            k = int(rng.integers(1, len(allowed) + 1))
            robot = robot.add_effect(make_effect(name, robot, joints=list(rng.choice(allowed, k, replace=False))))
    theta = robot.params.values.copy()
    eidx = np.array([i for i, kd in enumerate(robot.params.kinds) if kd == "effect"], int)
    theta[eidx] = rng.normal(0, 1e-4, eidx.size)
    N = draw(st.integers(1, 5))
    q = robot.random_readings(N, rng)
    ctx = {"t": rng.uniform(0, 100, N), "temperature": rng.uniform(10, 40, N), "payload": rng.uniform(0, 3, N)}
    return robot, q, theta, ctx, eidx


EFFECTS_UNDER_TEST = {"joint_compliance", "backlash", "gear_harmonic", "encoder_gain", "thermal_expansion", "drift",
                      "link_tilt"}


@settings(max_examples=30, deadline=None)
@given(robot_with_effects())
def test_effect_columns_random_robots(case):
    robot, q, theta, ctx, eidx = case
    k = robot.kinematics(q, theta, ctx)
    Jp, Jm = fd_columns(robot, q, theta, ctx, eidx, eps=1e-7)
    np.testing.assert_allclose(k.J[..., eidx], Jp, rtol=0, atol=1e-6 * max(1.0, np.abs(Jp).max(initial=0.0)))
    np.testing.assert_allclose(k.J_points[..., eidx], Jm, rtol=0, atol=1e-6 * max(1.0, np.abs(Jm).max(initial=0.0)))


def test_thermal_combined_with_joint_effects():
    """Thermal expansion + joint effects. The chain differentiates the expanded points as rigid, so the
    other columns of J_points are off by s·(v(x') + ω × (o − x') − ∂o/∂θ), s = αΔT; the effect's
    ``correct_jacobian`` (the chain passes the pose Jacobian J) removes exactly that:
    checked on every column for thermal expansion alone, and on the effect columns with compliance
    and harmonics (whose geometric columns neglect d(gravity torque)/dθ by design)."""
    base = heavy_puma()
    rng = np.random.default_rng(9)
    alone = base.add_effect(make_effect("thermal_expansion", base))
    mixed = base.add_effect(make_effect("joint_compliance", base, joints=["j2", "j3"]))
    mixed = mixed.add_effect(make_effect("gear_harmonic", mixed, joints=["j1"], orders=[1]))
    mixed = mixed.add_effect(make_effect("thermal_expansion", mixed))
    N = 6
    q = base.random_readings(N, rng)
    ctx = {"temperature": rng.uniform(25, 40, N)}
    for robot, check in ((alone, None), (mixed, "effect")):
        theta = robot.params.values + rng.normal(0, 1e-3, robot.n_params)
        theta[robot.params.index("thermal_alpha")] = 2e-4  # large, so the O(αΔT) term is visible
        for n in robot.params.select("compliance_*"):
            theta[robot.params.index(n)] = 1e-5
        cols = np.arange(robot.n_params) if check is None else np.array(
            [i for i, kd in enumerate(robot.params.kinds) if kd == check])
        k = robot.kinematics(q, theta, ctx)
        _, Jm = fd_columns(robot, q, theta, ctx, cols)
        # the chain passes the pose Jacobian J to the effect, which corrects the other columns
        scale = np.abs(Jm).max()
        np.testing.assert_allclose(k.J_points[..., cols], Jm, rtol=0, atol=1e-7 * scale)
