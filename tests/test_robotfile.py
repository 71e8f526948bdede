"""Robot files (YAML): loading, validation messages, units, round-trips, packaged built-ins."""
from __future__ import annotations

import textwrap

import numpy as np
import pytest

from estcal.io.robotfile import RobotFileError, load_robot, robot_from_dict, robot_to_dict, save_robot
from estcal.kinematics import BUILTIN
from estcal.kinematics.builder import build_robot
from estcal.robots import available, robot_file


def _same_robot(a, b, n=40, seed=0, atol=0.0):
    assert a.params.names == b.params.names
    np.testing.assert_allclose(b.params.values, a.params.values, rtol=0, atol=atol)
    np.testing.assert_allclose(b.limits, a.limits, rtol=0, atol=atol)
    assert a.joint_names == b.joint_names and a.joint_types == b.joint_types
    q = a.random_readings(n, np.random.default_rng(seed))
    ka, kb = a.kinematics(q, jacobian=False), b.kinematics(q, jacobian=False)
    np.testing.assert_allclose(kb.p, ka.p, rtol=0, atol=max(atol, 1e-12))
    np.testing.assert_allclose(kb.R, ka.R, rtol=0, atol=max(atol, 1e-12))
    np.testing.assert_allclose(kb.points, ka.points, rtol=0, atol=max(atol, 1e-12))
    np.testing.assert_allclose(b.gravity_torques(q), a.gravity_torques(q), rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["stanford", "puma560", "puma560_fu", "5r1p", "planar2"])
def test_packaged_yaml_matches_python_builtin(name):
    """The packaged files are written in the source tables' units (in/mm, deg): an
    independent transcription of the tables, checked against the Python built-ins."""
    assert name in available()
    _same_robot(BUILTIN[name](), load_robot(robot_file(name)))


@pytest.mark.parametrize("name", ["stanford", "puma560", "puma560_fu", "5r1p", "planar2"])
def test_save_load_roundtrip_builtins(name, tmp_path):
    robot = BUILTIN[name]()
    rng = np.random.default_rng(1)
    # a "calibrated" robot: every parameter perturbed
    robot = robot.with_values(robot.params.values + rng.normal(0, 1e-3, robot.n_params))
    back = load_robot(save_robot(robot, tmp_path / f"{name}.yaml"))
    _same_robot(robot, back)


def test_roundtrip_rich_robot(tmp_path):
    """Masses, payload, markers, gravity, coupling, gear ratios, mixed conventions, fixed frames."""
    rng = np.random.default_rng(5)
    frames = [
        {"name": "f0", "type": "fixed", "theta": 0.3, "r": 0.4},
        {"name": "a", "convention": "khalil", "alpha": 0.2, "d": 0.1, "beta": 0.01, "mass": 3.0,
         "com": [0.1, 0.0, 0.05], "limits": [-2, 2]},
        {"name": "b", "convention": "dh", "type": "prismatic", "a": 0.2, "alpha": -1.0, "limits": [0.1, 0.5],
         "mass": 1.5, "com": [0, 0.02, 0]},
        {"name": "c", "convention": "khalil", "alpha": 1.1, "r": 0.3, "offset": 0.05, "gain": 1.01,
         "limits": [-3, 3], "mass": 0.7},
    ]
    robot = build_robot("rich", frames, base={"xyz": [0.1, 0.2, 0.3], "rpy": [0.1, -0.2, 0.3]},
                        tool={"xyz": [0, 0, 0.1], "rpy": [0.0, 0.5, 0]}, markers=rng.normal(0, 0.1, (3, 3)),
                        gravity=(0.0, -9.81, 0.0), payload={"mass": 2.0, "com": [0, 0, 0.05]},
                        coupling=(np.eye(3) + 0.1 * rng.normal(size=(3, 3)), np.eye(3)),
                        meta={"gear_ratio": {"a": 100.0}})
    back = load_robot(save_robot(robot, tmp_path / "rich.yaml"))
    _same_robot(robot, back)
    assert back.meta["gear_ratio"] == {"a": 100.0}
    assert back.payload_mass == 2.0
    np.testing.assert_array_equal(back.coupling[0], robot.coupling[0])


def test_units_are_converted(tmp_path):
    """A file in mm/deg equals the same file in m/rad (conversion by hand here)."""
    mm = textwrap.dedent("""\
        estcal_robot: 1
        name: u
        convention: dh
        units: {length: mm, angle: deg}
        base: {xyz: [100, 0, 500], rpy: [0, 0, 90]}
        joints:
          - {name: j1, d: 300, a: 50, alpha: -90, offset: 1, limits: [-170, 170], com: [0, 0, -10], mass: 2}
          - {name: j2, type: prismatic, alpha: 90, limits: [100, 400], offset: 5}
        markers: [[10, 20, 30]]
        """)
    si = textwrap.dedent(f"""\
        estcal_robot: 1
        name: u
        convention: dh
        base: {{xyz: [0.1, 0, 0.5], rpy: [0, 0, {np.pi / 2!r}]}}
        joints:
          - {{name: j1, d: 0.3, a: 0.05, alpha: {-np.pi / 2!r}, offset: {float(np.radians(1))!r},
              limits: [{float(np.radians(-170))!r}, {float(np.radians(170))!r}], com: [0, 0, -0.01], mass: 2}}
          - {{name: j2, type: prismatic, alpha: {np.pi / 2!r}, limits: [0.1, 0.4], offset: 0.005}}
        markers: [[0.01, 0.02, 0.03]]
        """)
    (tmp_path / "mm.yaml").write_text(mm)
    (tmp_path / "si.yaml").write_text(si)
    _same_robot(load_robot(tmp_path / "si.yaml"), load_robot(tmp_path / "mm.yaml"), atol=1e-15)


GOOD = """\
estcal_robot: 1
name: t
convention: khalil
joints:
  - {name: j1, type: revolute, alpha: 0, limits: [-1, 1]}
  - {name: j2, type: revolute, alpha: 1.57, limits: [-1, 1]}
  - {name: j3, type: prismatic, alpha: 1.57, limits: [0, 1]}
"""


@pytest.mark.parametrize("old,new,message", [
    ("type: prismatic", "type: prismatc",
     r"robot.yaml: joint 'j3': unknown type 'prismatc' \(did you mean 'prismatic'\?\)"),
    ("alpha: 1.57, limits: [0, 1]", "alfa: 1.57, limits: [0, 1]", r"robot.yaml: joint 'j3': unknown key 'alfa'.*alpha"),
    ("estcal_robot: 1\n", "", r"robot.yaml: missing top-level key 'estcal_robot: 1'"),
    ("estcal_robot: 1", "estcal_robot: 7", r"robot.yaml: estcal_robot: unsupported format version 7"),
    ("limits: [0, 1]", "limits: [1, 0]", r"robot.yaml: joint 'j3': 'limits' must be \[lower, upper\]"),
    ("limits: [0, 1]", "limits: [0]", r"robot.yaml: joint 'j3': 'limits' must be a list of 2 numbers"),
    ("{name: j2, type: revolute, alpha: 1.57", "{name: j2, type: revolute, alpha: abc",
     r"robot.yaml: joint 'j2': 'alpha' must be a number"),
    ("name: j2", "name: j1", r"robot.yaml: joint 'j1': duplicate joint name"),
    ("convention: khalil", "convention: dhh", r"robot.yaml: convention: unknown convention 'dhh'"),
    ("name: t\n", "name: t\ngravty: [0, 0, -9.81]\n", r"robot.yaml: unknown key 'gravty' \(did you mean 'gravity'\?\)"),
    (", limits: [0, 1]}", "}", r"robot.yaml: joint 'j3': a prismatic joint needs 'limits'"),
    ("name: t\n", "name: t\nunits: {length: furlong}\n", r"robot.yaml: units: unknown length unit 'furlong'"),
    ("{name: j1, type: revolute, alpha: 0, limits: [-1, 1]}", "{name: j1, type: revolute, alpha: 0, mass: -1}",
     r"robot.yaml: joint 'j1': 'mass' must be >= 0"),
])
def test_errors_name_file_and_key(tmp_path, old, new, message):
    assert old in GOOD
    p = tmp_path / "robot.yaml"
    p.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(RobotFileError, match=message):
        load_robot(p)


def test_good_file_loads(tmp_path):
    p = tmp_path / "robot.yaml"
    p.write_text(GOOD)
    r = load_robot(p)
    assert r.joint_names == ["j1", "j2", "j3"] and r.joint_types[2] == "prismatic"
    assert "alpha_3" in r.params and "offset_3" in r.params


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("estcal_robot: 1\njoints: [\n")
    with pytest.raises(RobotFileError, match=r"bad.yaml, line 3, column 1: invalid YAML in the robot file \(expected the node"):
        load_robot(p)
    with pytest.raises(RobotFileError, match="nope.yaml: robot file not found"):
        load_robot(tmp_path / "nope.yaml")
    with pytest.raises(ValueError, match="unknown robot 'pumma'.*puma560"):
        load_robot("pumma")


def test_builtin_names_and_markers():
    r = load_robot("puma560")
    assert r.name == "puma560" and r.n_markers == 0
    r3 = load_robot("PUMA560", n_markers=3)
    assert r3.n_markers == 3 and "marker3_z" in r3.params
    q = r.random_readings(5, 0)
    # markers at the tool origin coincide with the tool position
    np.testing.assert_allclose(r3.kinematics(q, jacobian=False).points[:, 2], r.kinematics(q, jacobian=False).p)
    with pytest.raises(ValueError, match="defines 3 markers but 2"):
        load_robot(r3, n_markers=2)


def test_gear_ratio_and_fixed_frame_rules():
    d = {"estcal_robot": 1, "name": "g", "joints": [
        {"name": "f0", "type": "fixed", "r": 0.3},
        {"name": "j1", "gear_ratio": 120, "limits": [-1, 1]},
        {"name": "f2", "type": "fixed", "d": 0.1}]}
    r = robot_from_dict(d, "g.yaml")
    assert r.meta["gear_ratio"] == {"j1": 120.0}
    assert "r_0" in r.params and "d_2" in r.params and r.n_joints == 1
    d["joints"][0]["offset"] = 0.1
    with pytest.raises(RobotFileError, match="g.yaml: joint 'f0': 'offset' is not allowed on a fixed frame"):
        robot_from_dict(d, "g.yaml")


def test_root_tip_rejected_for_non_urdf():
    with pytest.raises(ValueError, match="only apply to URDF"):
        load_robot("puma560", tip="x")


def test_urdf_via_load_robot_and_roundtrip(tiago_dir, tmp_path):
    urdf = tiago_dir / "tiago_48_schunk.urdf"
    r = load_robot(urdf, root="base_footprint", tip="wrist_ft_tool_link", n_markers=2)
    assert r.n_markers == 2 and r.joint_names[0] == "torso_lift_joint"
    r = r.with_values(r.params.values + np.random.default_rng(0).normal(0, 1e-3, r.n_params))
    back = load_robot(save_robot(r, tmp_path / "tiago.yaml"))
    # gimbal-locked URDF origins (pitch ±90°) included: matrix_to_rpy keeps every digit
    _same_robot(r, back, atol=1e-14)
    d = robot_to_dict(back)
    assert d["convention"] == "urdf" and d["joints"][0]["type"] == "prismatic"


def test_packaged_puma_with_masses():
    """Same geometry and names as puma560; gravity torque on j2 from the upper arm and everything
    beyond it (a check of the mass bookkeeping against a hand sum at the zero pose)."""
    heavy, plain = load_robot("puma560_masses"), BUILTIN["puma560"]()
    q = plain.random_readings(20, np.random.default_rng(0))
    np.testing.assert_array_equal(heavy.fk(q), plain.fk(q))
    assert heavy.params.names == plain.params.names
    tau = heavy.gravity_torques(q)
    assert np.all(tau[:, 0] == 0) or np.abs(tau[:, 0]).max() < 1e-9  # vertical first axis
    assert np.abs(tau[:, 1]).max() > 50  # N·m: 17.4 kg at ~0.2 m plus the forearm
    # τ2 = a2ᵀ Σ (c_i − o2) × m_i g over links 2..6 computed here from the link frames directly
    k = heavy.kinematics(q[:1], jacobian=False)
    a2, o2 = k.joint_axis[0, 1], k.joint_origin[0, 1]
    tot = 0.0
    for li, link in enumerate(heavy.links):
        if link.mass:
            c = k.link_p[0, li] + k.link_R[0, li] @ link.com
            tot += a2 @ np.cross(c - o2, link.mass * heavy.gravity) if li >= 2 else 0.0
    assert tau[0, 1] == pytest.approx(tot, rel=1e-12)


# ---------------------------------------------------------------- property-based
from hypothesis import given, settings, strategies as st  # noqa: E402

from estcal.kinematics.transforms import make_transform, rpy_to_matrix  # noqa: E402


@st.composite
def random_robot(draw):
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    top = draw(st.sampled_from(["khalil", "dh", "urdf"]))
    n = draw(st.integers(1, 6))
    frames = []
    if top != "urdf" and rng.random() < 0.5:
        frames.append({"name": "f_first", "type": "fixed", "theta": rng.uniform(-2, 2), "r": rng.normal(0, .3)})
    for j in range(n):
        conv = top if rng.random() < 0.7 else ["khalil", "dh", "urdf"][j % 3]
        jt = "prismatic" if rng.random() < 0.25 else "revolute"
        f = {"name": f"joint_{j}", "type": jt, "convention": conv, "offset": rng.normal(0, .1),
             "gain": 1 + rng.normal(0, .01), "limits": sorted(rng.uniform(-3, 3, 2)) if jt == "revolute"
             else [0.1, 0.5]}
        if top == "urdf" or conv == "urdf":
            f["label"] = f["name"]
        if conv == "khalil":
            f.update(alpha=rng.uniform(-2, 2), d=rng.normal(0, .3), theta=rng.uniform(-2, 2), r=rng.normal(0, .3),
                     beta=rng.normal(0, .1))
        elif conv == "dh":
            f.update(theta=rng.uniform(-2, 2), d=rng.normal(0, .3), a=rng.normal(0, .3), alpha=rng.uniform(-2, 2))
        else:
            f["origin"] = make_transform(rpy_to_matrix(rng.uniform(-1.4, 1.4, 3)), rng.normal(0, .3, 3))
            f["axis"] = rng.normal(size=3)
        if rng.random() < 0.5:
            f.update(mass=rng.uniform(0, 5), com=rng.normal(0, .1, 3))
        frames.append(f)
    if top != "urdf" and rng.random() < 0.5:
        frames.append({"name": "f_last", "type": "fixed", "alpha": rng.uniform(-2, 2), "d": rng.normal(0, .3)})
    k = int(rng.integers(0, 3))
    robot = build_robot("rnd", frames, base={"xyz": rng.normal(0, .5, 3), "rpy": rng.uniform(-2, 2, 3)},
                        tool={"xyz": rng.normal(0, .2, 3), "rpy": rng.uniform(-2, 2, 3)},
                        markers=rng.normal(0, .1, (k, 3)) if k else None, convention=top,
                        payload={"mass": 1.5, "com": [0, 0, .1]} if rng.random() < .5 else None,
                        tool_const=make_transform(rpy_to_matrix(rng.uniform(-1, 1, 3)), rng.normal(0, .1, 3))
                        if top == "urdf" else None,
                        meta={"gear_ratio": {"joint_0": 80.0}} if frames[0]["type"] != "prismatic" else None)
    return robot.with_values(robot.params.values + rng.normal(0, 1e-3, robot.n_params))


@settings(max_examples=40, deadline=None)
@given(random_robot())
def test_roundtrip_random_robots(tmp_path_factory, robot):
    path = tmp_path_factory.mktemp("rt") / "r.yaml"
    back = load_robot(save_robot(robot, path))
    # rpy of constant (URDF) origins is re-evaluated: exact up to rounding
    _same_robot(robot, back, atol=1e-12)
    assert back.payload_mass == robot.payload_mass


def test_calibration_block_round_trips_and_is_checked(tmp_path):
    """A saved model's ``calibration:`` block (provenance + covariance of the free
    parameters) survives save → load, and an inconsistent covariance is refused
    naming the key."""
    import numpy as np
    import pytest

    from estcal.io.robotfile import RobotFileError, calibration_covariance, load_robot, save_robot

    robot = load_robot("puma560")
    free = ["d_1", "a_2"] if "a_2" in robot.params.names else list(robot.params.names[:2])
    C = np.array([[4e-8, 1e-9], [1e-9, 9e-8]])
    robot.meta["calibration"] = {"estimator": "lm", "free": free, "covariance": C, "n": np.int64(5)}
    path = save_robot(robot, tmp_path / "m.yaml")
    back = load_robot(str(path))
    names, C2 = calibration_covariance(back)
    assert names == free and np.array_equal(C2, C)
    assert back.meta["calibration"]["estimator"] == "lm" and back.meta["calibration"]["n"] == 5
    assert calibration_covariance(load_robot("puma560")) is None
    text = path.read_text().replace("covariance: [[", "covariance: [[1.0, ")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(RobotFileError, match="calibration.covariance"):
        load_robot(str(bad))
