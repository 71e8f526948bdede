"""`estcal export --ur-kinematics`: a UR arm's calibration as ur_description's kinematics file (docs/export.md).

Independent checks: the file is read with plain ``yaml.safe_load`` and its origins composed by hand —
``Trans(x, y, z) · Rz(yaw) · Ry(pitch) · Rx(roll)`` (URDF fixed-axis rpy) then ``Rz(q)`` for each joint,
the fixed joints of the URDF read with ElementTree and composed the same way, the base and tool frames
from the robot spec's numbers — and compared with the calibrated model's forward kinematics on random
joint readings (1e-9 m); the hash recomputed from its documented definition; reading back and exporting
again byte-identical; a UR10e calibrated on the shared UR10 data (skipped when ../shared is absent).
"""
from __future__ import annotations

import hashlib
import math
import re
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.robotfile import load_robot, save_robot
from estcal.kinematics.ur_kinematics import ENTRIES, rpy_near
from estcal.workflows.export import export_ur_kinematics

from conftest import REPO, SHARED

runner = CliRunner()
UR10 = SHARED / "data" / "ur10"
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
          "wrist_3_joint"]
KEYS = ["x", "y", "z", "roll", "pitch", "yaw"]
PI = math.pi
#: ur_description's nominal UR10 (CB3) kinematics (../shared/reference/peers.md, "UR kinematics file")
CB3_UR10 = {"shoulder": [0, 0, 0.1273, 0, 0, 0], "upper_arm": [0, 0, 0, 1.570796327, 0, 0],
            "forearm": [-0.612, 0, 0, 0, 0, 0], "wrist_1": [-0.5723, 0, 0.163941, 0, 0, 0],
            "wrist_2": [0, -0.1157, 0, 1.570796327, 0, 0], "wrist_3": [0, 0.0922, 0, 1.570796326589793, PI, PI]}


# ------------------------------------------------------------------ independent composition
def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _T(xyz, rpy):
    """URDF origin: translation, then R = Rz(yaw) Ry(pitch) Rx(roll)."""
    T = np.eye(4)
    T[:3, :3] = _rz(rpy[2]) @ _ry(rpy[1]) @ _rx(rpy[0])
    T[:3, 3] = xyz
    return T


def _Rz4(q):
    T = np.eye(4)
    T[:3, :3] = _rz(q)
    return T


def _fixed_path(urdf_path, start, end):
    """Product of the fixed-joint origins from link ``start`` down to ``end`` (ElementTree, not estcal)."""
    root = ET.parse(urdf_path).getroot()
    parent = {j.find("child").get("link"): j for j in root.findall("joint")}
    T, cur = np.eye(4), end
    while cur != start:
        j = parent[cur]
        assert j.get("type") == "fixed", j.get("name")
        o = j.find("origin")
        xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
        rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        T = _T(xyz, rpy) @ T
        cur = j.find("parent").get("link")
    return T


def _compose(kin_file, spec_file, urdf_path, root, tip, q, prefix=""):
    """T_root_tip(q) from the files alone: base frame · fixed joints to base_link_inertia · Π origin·Rz(q)
    · fixed joints from wrist_3_link to the tip · tool frame."""
    kin = yaml.safe_load(open(kin_file))["kinematics"]
    spec = yaml.safe_load(open(spec_file))
    base = _T(spec["base"]["xyz"], spec["base"]["rpy"]) if "base" in spec else np.eye(4)
    tool = _T(spec["tool"]["xyz"], spec["tool"]["rpy"]) if "tool" in spec else np.eye(4)
    head = base @ _fixed_path(urdf_path, root, prefix + "base_link_inertia")
    tail = _fixed_path(urdf_path, prefix + "wrist_3_link", tip) @ tool
    out = np.empty((len(q), 4, 4))
    for n, qn in enumerate(q):
        T = head
        for e, qk in zip(ENTRIES, qn):
            v = [float(x) for x in (kin[e][k] for k in KEYS)]
            T = T @ _T(v[:3], v[3:]) @ _Rz4(qk)
        out[n] = T @ tail
    return out


# ------------------------------------------------------------------ a UR description written here
def _ur_urdf(path, entries=CB3_UR10, prefix="", name="ur10"):
    """A URDF as ur_description's xacro writes it: world → base_link (a mount) → base_link_inertia (Rz π) →
    the six joints with the entries' origins → flange → tool0."""
    links = ["world", "base_link", "base_link_inertia", "shoulder_link", "upper_arm_link", "forearm_link",
             "wrist_1_link", "wrist_2_link", "wrist_3_link", "flange", "tool0"]
    p = {lk: (lk if lk == "world" else prefix + lk) for lk in links}

    def joint(n, typ, a, b, v, extra=""):
        xyz, rpy = " ".join(repr(float(x)) for x in v[:3]), " ".join(repr(float(x)) for x in v[3:])
        return (f'<joint name="{n}" type="{typ}"><parent link="{p[a]}"/><child link="{p[b]}"/>'
                f'<origin xyz="{xyz}" rpy="{rpy}"/>{extra}</joint>')

    lim = '<axis xyz="0 0 1"/><limit lower="-6.283185307179586" upper="6.283185307179586" effort="1" velocity="1"/>'
    js = [joint(prefix + "base_joint", "fixed", "world", "base_link", [0.1, -0.2, 0.9, 0, 0, 0.3]),
          joint(prefix + "base_link-base_link_inertia", "fixed", "base_link", "base_link_inertia", [0, 0, 0, 0, 0, PI])]
    for e, j, a, b in zip(ENTRIES, JOINTS, links[2:8], links[3:9]):
        js.append(joint(prefix + j, "revolute", a, b, entries[e], lim))
    js += [joint(prefix + "wrist_3-flange", "fixed", "wrist_3_link", "flange", [0, 0, 0, 0, -PI / 2, -PI / 2]),
           joint(prefix + "flange-tool0", "fixed", "flange", "tool0", [0, 0, 0.05, PI / 2, 0, PI / 2])]
    text = (f'<?xml version="1.0"?><robot name="{name}">' + "".join(f'<link name="{p[lk]}"/>' for lk in links)
            + "".join(js) + "</robot>")
    path.write_text(text)
    return path


def _calibrate(robot, seed=0, mm=2.0, mrad=3.0):
    """The robot with every joint's tx…rz, every offset and the base and tool frames perturbed."""
    rng = np.random.default_rng(seed)
    v = robot.params.values.copy()
    for i, (n, k) in enumerate(zip(robot.params.names, robot.params.kinds)):
        if k in ("geometric", "base", "tool"):
            length = n[:2] in ("tx", "ty", "tz") or n[-3:] in ("_tx", "_ty", "_tz")
            v[i] += rng.normal(0, (mm if length else mrad) * 1e-3)
        elif k == "offset":
            v[i] += rng.normal(0, 5e-3)
    return robot.with_values(v)


@pytest.fixture
def ur_model(tmp_path):
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    nominal = load_robot(urdf, root="world", tip="tool0")
    model = _calibrate(nominal)
    path = save_robot(model, tmp_path / "ur_cal.yaml")
    return urdf, model, path


def _export(tmp_path, model, urdf, kin="kin.yaml", spec="spec.yaml"):
    return export_ur_kinematics(model, tmp_path / kin, from_urdf=urdf, robot_spec=tmp_path / spec)


# ------------------------------------------------------------------ the round trip
def test_composed_file_origins_reproduce_the_calibrated_fk(ur_model, tmp_path):
    urdf, model, _ = ur_model
    ex = _export(tmp_path, model, urdf)
    q = model.random_readings(500, rng=1)
    T = _compose(tmp_path / "kin.yaml", tmp_path / "spec.yaml", urdf, "world", "tool0", q)
    ref = model.fk(q)
    assert np.abs(T[:, :3, 3] - ref[:, :3, 3]).max() < 1e-9
    assert np.abs(T[:, :3, :3] - ref[:, :3, :3]).max() < 1e-9
    # every origin moved (offsets folded in), and the nominal file would not do: the test can fail
    assert sorted(ex.origins.changed) == sorted(ENTRIES)
    nominal = load_robot(urdf, root="world", tip="tool0")
    assert np.abs(nominal.fk(q)[:, :3, 3] - ref[:, :3, 3]).max() > 1e-3


def test_offsets_alone_are_rotations_of_the_origins_about_their_axes(tmp_path):
    """Only joint offsets calibrated: each origin is the nominal one times Rz(offset) (translation unchanged)."""
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    model = load_robot(urdf, root="world", tip="tool0")
    off = np.array([0.01, -0.02, 0.003, 0.04, -0.005, 0.5])
    for j, o in zip(JOINTS, off):
        model.params[f"offset_{j}"] = o
    export_ur_kinematics(model, tmp_path / "k.yaml", from_urdf=urdf)
    kin = yaml.safe_load(open(tmp_path / "k.yaml"))["kinematics"]
    for e, o in zip(ENTRIES, off):
        v = [kin[e][k] for k in KEYS]
        nominal = CB3_UR10[e]
        assert v[:3] == pytest.approx(nominal[:3], abs=1e-15)
        want = _T(nominal[:3], nominal[3:]) @ _Rz4(o)
        assert np.abs(_T(v[:3], v[3:]) - want).max() < 1e-14
        # and the numbers stay near the nominal triple (wrist_3: near roll π/2, pitch π, yaw π)
        assert np.abs(np.array(v[3:]) - nominal[3:]).max() <= abs(o) + 1e-12


def test_reading_back_and_exporting_again_is_byte_identical(ur_model, tmp_path):
    urdf, model, path = ur_model
    _export(tmp_path, path, urdf)
    back = load_robot(tmp_path / "spec.yaml")
    q = model.random_readings(300, rng=2)
    assert np.abs(back.fk(q)[:, :3, 3] - model.fk(q)[:, :3, 3]).max() < 1e-9
    r = runner.invoke(app, ["export", "--robot", str(tmp_path / "spec.yaml"), "--ur-kinematics",
                            str(tmp_path / "again.yaml"), "--robot-spec", str(tmp_path / "spec2.yaml")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "again.yaml").read_bytes() == (tmp_path / "kin.yaml").read_bytes()
    # the spec of the re-export names the same URDF, chain and frames
    s1, s2 = (yaml.safe_load(open(tmp_path / n)) for n in ("spec.yaml", "spec2.yaml"))
    assert {k: v for k, v in s1.items() if k != "ur_kinematics"} == {k: v for k, v in s2.items()
                                                                      if k != "ur_kinematics"}
    assert "origins changed from" in r.output and ": none" in r.output


def test_hash_is_the_sha256_of_the_numbers_as_written(ur_model, tmp_path):
    urdf, model, _ = ur_model
    ex = _export(tmp_path, model, urdf)
    lines = (tmp_path / "kin.yaml").read_text().splitlines()
    # "entry.key=number" lines, the number text exactly as in the file
    text, entry = "", None
    for ln in lines:
        s = ln.strip()
        if ln.startswith("  ") and not ln.startswith("    ") and s.endswith(":"):
            entry = s[:-1]
        elif ln.startswith("    "):
            k, v = s.split(": ")
            text += f"{entry}.{k}={v}\n"
    want = "calib_estcal_" + hashlib.sha256(text.encode()).hexdigest()[:16]
    assert yaml.safe_load(open(tmp_path / "kin.yaml"))["kinematics"]["hash"] == want == ex.origins.kinematics.hash
    # another calibration, another hash
    other = export_ur_kinematics(_calibrate(load_robot(urdf, root="world", tip="tool0"), seed=5),
                                 tmp_path / "k5.yaml", from_urdf=urdf)
    assert other.origins.kinematics.hash != want


def test_an_edited_file_is_warned_and_its_hash_recomputed(ur_model, tmp_path):
    urdf, model, _ = ur_model
    _export(tmp_path, model, urdf)
    kin = tmp_path / "kin.yaml"
    text = kin.read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("    x: "))  # the shoulder's x
    kin.write_text(text.replace(line, "    x: 0.001", 1))
    with pytest.warns(UserWarning, match=r"kinematics.hash .* does not name the numbers"):
        back = load_robot(tmp_path / "spec.yaml")
    assert back is not None


def test_the_shared_ur10_calibrated_from_its_file_round_trips(tmp_path):
    """The path of docs/export.md: calibrate the shared UR10 file, export, compose by hand, read back."""
    data = UR10 / "calibration.csv"
    if not data.exists():
        pytest.skip(f"{data} not found (the shared data live in ../shared next to the repository)")
    urdf = UR10 / "ur10_robot.urdf"
    model_path = tmp_path / "ur10_cal.yaml"
    r = runner.invoke(app, ["calibrate", str(data), "--robot", str(urdf), "--root", "world", "--tip",
                            "camera_color_optical_frame", "--map", str(REPO / "docs" / "maps" / "ur10.yaml"),
                            "--level", "joint_offset", "--save-model", str(model_path)])
    assert r.exit_code == 0, r.output
    kin, spec = tmp_path / "ur10_kinematics.yaml", tmp_path / "ur10_spec.yaml"
    r = runner.invoke(app, ["export", "--robot", str(model_path), "--ur-kinematics", str(kin), "--robot-spec",
                            str(spec)])
    assert r.exit_code == 0, r.output
    # the base and tool frames are said, one line each, never dropped
    assert r.output.count("warning: the base frame") == 1 and r.output.count("warning: the tool frame") == 1
    model = load_robot(model_path)
    q = model.random_readings(1000, rng=0)
    T = _compose(kin, spec, urdf, "world", "camera_color_optical_frame", q)
    assert np.abs(T[:, :3, 3] - model.fk(q)[:, :3, 3]).max() < 1e-9
    back = load_robot(spec)
    assert np.abs(back.fk(q)[:, :3, 3] - model.fk(q)[:, :3, 3]).max() < 1e-9
    r = runner.invoke(app, ["export", "--robot", str(spec), "--ur-kinematics", str(tmp_path / "again.yaml")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "again.yaml").read_bytes() == kin.read_bytes()
    # the joint-offset level moves origins only by rotations about their axes: the translations are the
    # URDF's numbers, bit for bit
    entries = yaml.safe_load(open(kin))["kinematics"]
    joints = {j.get("name"): j for j in ET.parse(urdf).getroot().findall("joint")}
    for e, name in zip(ENTRIES, JOINTS):
        xyz = [float(v) for v in joints[name].find("origin").get("xyz").split()]
        assert [entries[e][k] for k in "xyz"] == xyz


def test_rpy_near_gives_the_rotation_near_the_nominal_triple():
    rng = np.random.default_rng(4)
    for nominal in ([1.570796326589793, PI, PI], [1.570796327, 0, 0], [0.3, -0.4, 2.9], [0, 0, 0]):
        for _ in range(50):
            d = rng.normal(0, 0.02, 3)
            R = _T([0, 0, 0], np.add(nominal, d))[:3, :3]
            got = rpy_near(R, nominal)
            assert np.abs(_T([0, 0, 0], got)[:3, :3] - R).max() < 1e-13
            assert np.abs(got - np.add(nominal, d)).max() < 1e-9


# ------------------------------------------------------------------ reading: --robot with a kinematics file
def _kin_file(path, entries, hash_="calib_12345"):
    d = {"kinematics": {e: dict(zip(KEYS, entries[e])) for e in ENTRIES}}
    d["kinematics"]["hash"] = hash_
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def _spec(path, urdf, kin=None, **kw):
    d = {"estcal_robot": 1, "urdf": str(urdf), **({"ur_kinematics": str(kin)} if kin else {}), **kw}
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def test_a_factory_file_is_read_with_its_urdf(tmp_path):
    """A ur_calibration-style file (ints, a calib_<digits> hash) on the UR description: the model's origins
    are the file's, composed as a URDF holding those numbers."""
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    factory = {e: list(v) for e, v in CB3_UR10.items()}
    factory["shoulder"][2] = 0.12741
    factory["forearm"][0] = -0.61213
    factory["wrist_1"][5] = 0.0021
    kin = _kin_file(tmp_path / "factory.yaml", factory)
    spec = _spec(tmp_path / "s.yaml", urdf, kin, root="world", tip="tool0")
    robot = load_robot(spec)
    same = load_robot(_ur_urdf(tmp_path / "as_urdf.urdf", factory), root="world", tip="tool0")
    q = robot.random_readings(50, rng=0)
    assert np.array_equal(robot.fk(q), same.fk(q))
    assert robot.meta["ur_kinematics_hash"] == "calib_12345"


def test_a_model_calibrated_from_a_factory_file_is_expressed_in_it(tmp_path):
    """Calibrating from a spec (URDF + factory file) and exporting: the origins the calibration did not move
    keep the factory numbers exactly; the moved one is the factory origin times Rz(offset)."""
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    factory = {e: list(v) for e, v in CB3_UR10.items()}
    factory["forearm"] = [-0.61213, 0.0003, 0.00012, 0.0011, -0.0007, 0.0021]
    spec = _spec(tmp_path / "s.yaml", urdf, _kin_file(tmp_path / "factory.yaml", factory), root="world", tip="tool0")
    model = load_robot(spec)
    model.params["offset_elbow_joint"] = 0.004
    save_robot(model, tmp_path / "m.yaml")
    r = runner.invoke(app, ["export", "--robot", str(tmp_path / "m.yaml"), "--ur-kinematics", str(tmp_path / "k.yaml"),
                            "--from-urdf", str(spec), "--json", str(tmp_path / "k.json")])
    assert r.exit_code == 0, r.output
    kin = yaml.safe_load(open(tmp_path / "k.yaml"))["kinematics"]
    for e in ENTRIES:
        if e != "forearm":
            assert [kin[e][k] for k in KEYS] == [float(x) for x in factory[e]], e
    got = _T([kin["forearm"][k] for k in KEYS[:3]], [kin["forearm"][k] for k in KEYS[3:]])
    want = _T(factory["forearm"][:3], factory["forearm"][3:]) @ _Rz4(0.004)
    assert np.abs(got - want).max() < 1e-14
    summary = yaml.safe_load(open(tmp_path / "k.json"))
    assert list(summary["changed"]) == ["forearm"] and summary["changed"]["forearm"]["mrad"] == pytest.approx(4.0)
    assert summary["hash"] == kin["hash"] and summary["warnings"] == []


def test_a_prefixed_arm(tmp_path):
    urdf = _ur_urdf(tmp_path / "left.urdf", prefix="left_")
    model = _calibrate(load_robot(urdf, root="world", tip="left_tool0"), seed=3)
    ex = export_ur_kinematics(model, tmp_path / "k.yaml", robot_spec=tmp_path / "s.yaml")
    assert ex.origins.joints["shoulder"] == "left_shoulder_pan_joint"
    q = model.random_readings(100, rng=1)
    T = _compose(tmp_path / "k.yaml", tmp_path / "s.yaml", urdf, "world", "left_tool0", q, prefix="left_")
    assert np.abs(T[:, :3, 3] - model.fk(q)[:, :3, 3]).max() < 1e-9


@pytest.mark.parametrize("change, message", [
    (lambda k: k["kinematics"]["forearm"].pop("yaw"), r"kin\.yaml: kinematics\.forearm: missing key 'yaw'"),
    (lambda k: k["kinematics"]["wrist_2"].update(yaww=0.0), r"kin\.yaml: kinematics\.wrist_2: unknown key 'yaww'"),
    (lambda k: k["kinematics"].pop("hash"), r"kin\.yaml: kinematics: missing key 'hash'"),
    (lambda k: k["kinematics"].pop("wrist_3"), r"kin\.yaml: kinematics: missing key 'wrist_3'"),
    (lambda k: k["kinematics"]["upper_arm"].update(roll="ninety"),
     r"kin\.yaml: kinematics\.upper_arm\.roll: expected a number \(rad\), got 'ninety'"),
    (lambda k: k["kinematics"]["forearm"].update(x=-612.0), r"kinematics\.forearm\.x: -612 m is not a UR link length"),
    (lambda k: k.update(calibration=1), r"kin\.yaml: unknown top-level key 'calibration'"),
], ids=["missing-yaw", "unknown-key", "no-hash", "no-wrist_3", "not-a-number", "millimetres", "top-key"])
def test_a_broken_kinematics_file_is_one_line_naming_file_and_key(tmp_path, change, message):
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    d = {"kinematics": {e: dict(zip(KEYS, CB3_UR10[e])) for e in ENTRIES}}
    d["kinematics"]["hash"] = "calib_1"
    change(d)
    (tmp_path / "kin.yaml").write_text(yaml.safe_dump(d))
    spec = _spec(tmp_path / "s.yaml", urdf, tmp_path / "kin.yaml", tip="tool0")
    q = tmp_path / "q.csv"
    q.write_text(",".join(JOINTS) + "\n" + ",".join(["0.1"] * 6) + "\n")
    r = runner.invoke(app, ["fk", str(q), "--robot", str(spec), "-o", str(tmp_path / "o.csv")])
    assert r.exit_code == 2, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and len(r.output.strip().splitlines()) == 1, r.output
    assert re.search(message, err[0]), err[0]


def test_a_kinematics_file_of_another_robot_is_refused(tmp_path):
    """The CB3 UR10's file on a UR10e description (and the reverse): the shoulder is 53 mm away."""
    ur10e = {e: list(v) for e, v in CB3_UR10.items()}
    ur10e.update(shoulder=[0, 0, 0.1807, 0, 0, 0], forearm=[-0.6127, 0, 0, 0, 0, 0],
                 wrist_1=[-0.57155, 0, 0.17415, 0, 0, 0], wrist_2=[0, -0.11985, 0, 1.570796327, 0, 0],
                 wrist_3=[0, 0.11655, 0, 1.570796326589793, PI, PI])
    urdf = _ur_urdf(tmp_path / "ur10e.urdf", ur10e, name="ur10e")
    kin = _kin_file(tmp_path / "ur10_cb3.yaml", CB3_UR10)
    spec = _spec(tmp_path / "s.yaml", urdf, kin, tip="tool0")
    r = runner.invoke(app, ["export", "--robot", str(spec), "--ur-kinematics", str(tmp_path / "o.yaml")])
    assert r.exit_code == 2
    assert ("ur10_cb3.yaml: kinematics.shoulder.z 0.1273 m is 53.4 mm from" in r.output
            and "ur10e.urdf's shoulder_pan_joint origin (0.1807 m) — a kinematics file of another robot?" in r.output)


def test_the_cb3_ur10_file_on_the_shared_ur10e_description_as_the_page_shows(tmp_path, monkeypatch):
    """The message docs/export.md quotes, with the spec beside the kinematics file and the data in ../shared."""
    work = _docs_layout(tmp_path)
    monkeypatch.chdir(work)
    _kin_file(work / "ur10_cb3.yaml", CB3_UR10)
    (work / "s.yaml").write_text("estcal_robot: 1\nurdf: ../shared/data/ur10/ur10_robot.urdf\nur_kinematics: "
                                 "ur10_cb3.yaml\nroot: world\ntip: camera_color_optical_frame\n")
    r = runner.invoke(app, ["export", "--robot", "s.yaml", "--ur-kinematics", "o.yaml"])
    assert r.exit_code == 2
    page = (REPO / "docs" / "export.md").read_text()
    quoted = next(ln for ln in page.splitlines() if ln.startswith("error: ur10_cb3.yaml"))
    assert r.output.strip() == quoted


def _docs_layout(tmp_path):
    """``tmp/work`` with ``docs/maps/ur10.yaml`` and ``tmp/shared/data/ur10`` (copies of the shared files), so
    that the page's relative paths (``../shared/…``, ``docs/maps/…``) hold and the outputs stay in ``tmp``."""
    if not (UR10 / "calibration.csv").exists():
        pytest.skip(f"{UR10} not found (the shared data live in ../shared next to the repository)")
    shutil.copytree(UR10, tmp_path / "shared" / "data" / "ur10")
    (tmp_path / "work" / "docs" / "maps").mkdir(parents=True)
    shutil.copy(REPO / "docs" / "maps" / "ur10.yaml", tmp_path / "work" / "docs" / "maps")
    return tmp_path / "work"


def test_the_page_path_runs_and_prints_what_the_page_shows(tmp_path):
    """docs/export.md, "From the shared UR10 file to the kinematics file": every command runs (the installed
    entry point, 80 columns) and prints the page's lines (tests/console_runner.py). The hash is compared
    for its form here (it changes with the last bit of any number) and, exactly, with the file's."""
    from console_runner import console_commands, missing_lines, run

    work = _docs_layout(tmp_path)
    page = (REPO / "docs" / "export.md").read_text()
    start = page.index("### From the shared UR10 file to the kinematics file")
    section = page[start:page.index("\n### ", start + 10)]
    commands = console_commands(section)
    assert [c.cmd.split()[:2] for c in commands][:3] == [["estcal", "calibrate"], ["estcal", "export"], ["cat",
                                                                                                         "ur10_kinematics.yaml"]]
    form = lambda text: re.sub(r"calib_estcal_[0-9a-f]{16}", "calib_estcal_HASH", text)  # noqa: E731
    for c in commands:
        p = run(c.cmd, work, timeout=120)
        assert p.returncode == c.exit_code, f"{c.cmd}: exit {p.returncode}\n{p.stderr[-2000:]}"
        miss = missing_lines([form(e) for e in c.expected], form(p.stdout + p.stderr))
        assert not miss, f"{c.cmd[:80]}: not in the output:\n" + "\n".join(miss) + "\n---\n" + p.stdout[-3000:]
    written = yaml.safe_load(open(work / "ur10_kinematics.yaml"))["kinematics"]["hash"]
    assert re.fullmatch(r"calib_estcal_[0-9a-f]{16}", written)
    m, s = (np.loadtxt(work / n, delimiter=",", skiprows=1) for n in ("model_fk.csv", "spec_fk.csv"))
    assert np.abs(m - s).max() < 1e-12  # "differ by at most 1e-15 m"


def test_a_tilted_axis_is_another_robot(tmp_path):
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    bad = {e: list(v) for e, v in CB3_UR10.items()}
    bad["forearm"][3] = 0.3
    spec = _spec(tmp_path / "s.yaml", urdf, _kin_file(tmp_path / "k.yaml", bad), tip="tool0")
    with pytest.raises(ValueError, match=r"k\.yaml: kinematics\.forearm: roll/pitch/yaw tilt the joint axis by 0\.3 rad"):
        load_robot(spec)


def test_spec_errors_name_the_file_and_key(tmp_path):
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    cases = [({"estcal_robot": 1, "urdf": str(urdf), "tipp": "tool0"}, r"unknown key 'tipp' \(did you mean 'tip'\?\)"),
             ({"estcal_robot": 1, "urdf": str(tmp_path / "nope.urdf")}, r"s\.yaml: urdf: .*nope\.urdf: URDF file not found"),
             ({"estcal_robot": 1, "urdf": str(urdf), "tip": "tool0", "base": {"xyz": [0, 0]}},
              r"s\.yaml: base\.xyz: expected 3 finite numbers"),
             ({"estcal_robot": 2, "urdf": str(urdf)}, r"s\.yaml: estcal_robot: expected 1")]
    for d, msg in cases:
        (tmp_path / "s.yaml").write_text(yaml.safe_dump(d))
        with pytest.raises(ValueError, match=msg):
            load_robot(tmp_path / "s.yaml")
    _spec(tmp_path / "s.yaml", urdf, tip="tool0")
    with pytest.raises(ValueError, match=r"s\.yaml: tip: the file says 'tool0', --tip 'flange'"):
        load_robot(tmp_path / "s.yaml", tip="flange")


# ------------------------------------------------------------------ what the file cannot hold; refusals
def test_what_the_file_cannot_hold_is_said(ur_model, tmp_path):
    urdf, model, _ = ur_model
    model = model.copy()
    model.params["gain_elbow_joint"] = 1.001
    ex = export_ur_kinematics(model, tmp_path / "k.yaml", from_urdf=urdf)
    w = "\n".join(ex.warnings)
    assert "the base frame (base_tx … base_rz) is not part of a UR kinematics file: world -> base_link" in w
    assert "the tool frame (tool_tx … tool_rz) is not part of a UR kinematics file: wrist_3_link -> tool0" in w
    assert "joint gains cannot be expressed in a UR kinematics file" in w and "elbow_joint (gain 1.001)" in w
    # the nominal model has nothing to say
    nominal = load_robot(urdf, root="world", tip="tool0")
    assert export_ur_kinematics(nominal, tmp_path / "n.yaml").warnings == []


def test_a_calibration_moving_an_origin_by_centimetres_is_refused(tmp_path):
    urdf = _ur_urdf(tmp_path / "ur10.urdf")
    model = load_robot(urdf, root="world", tip="tool0")
    model.params["tx_elbow_joint"] = 0.02
    save_robot(model, tmp_path / "m.yaml")
    r = runner.invoke(app, ["export", "--robot", str(tmp_path / "m.yaml"), "--ur-kinematics", str(tmp_path / "k.yaml"),
                            "--from-urdf", str(urdf)])
    assert r.exit_code == 3, r.output
    assert "the calibrated origin of elbow_joint (forearm) is 20.0 mm" in r.output
    assert not (tmp_path / "k.yaml").exists()


def test_inputs_are_never_overwritten_and_options_go_together(ur_model, tmp_path):
    urdf, model, path = ur_model
    _export(tmp_path, path, urdf)
    for out in (tmp_path / "kin.yaml", urdf):  # the spec's kinematics file, its URDF
        before = out.read_bytes()
        r = runner.invoke(app, ["export", "--robot", str(tmp_path / "spec.yaml"), "--ur-kinematics", str(out)])
        assert r.exit_code == 2 and "inputs are never overwritten" in r.output, r.output
        assert out.read_bytes() == before
    r = runner.invoke(app, ["export", "--robot", str(path), "--ur-kinematics", str(path)])
    assert r.exit_code == 2 and "is also an input file" in r.output
    r = runner.invoke(app, ["export", "--robot", str(path), "--robot-spec", str(tmp_path / "x.yaml"),
                            "--urdf", str(tmp_path / "x.urdf")])
    assert r.exit_code == 2 and "--robot-spec goes with --ur-kinematics" in r.output
    r = runner.invoke(app, ["export", "--robot", str(path)])
    assert r.exit_code == 2 and "give one of --urdf OUT.urdf and --ur-kinematics" in r.output


def test_models_that_are_not_a_ur_arm(tmp_path):
    r = runner.invoke(app, ["export", "--robot", "puma560", "--ur-kinematics", str(tmp_path / "k.yaml")])
    assert r.exit_code == 2 and "the UR description the model was calibrated from is not known" in r.output
    r = runner.invoke(app, ["export", "--robot", "puma560", "--ur-kinematics", str(tmp_path / "k.yaml"),
                            "--from-urdf", str(_ur_urdf(tmp_path / "ur10.urdf"))])
    assert r.exit_code == 2 and "needs a model whose frames are the URDF's joints" in r.output
    two = tmp_path / "two.urdf"
    two.write_text('<?xml version="1.0"?><robot name="r"><link name="a"/><link name="b"/>'
                   '<joint name="j" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>'
                   '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    r = runner.invoke(app, ["export", "--robot", str(two), "--ur-kinematics", str(tmp_path / "k.yaml")])
    assert r.exit_code == 2 and "no UR arms (joints shoulder_pan_joint" in r.output


def test_numbers_are_written_so_that_yaml_reads_floats():
    from estcal.kinematics.ur_kinematics import _num

    for v in (1e-05, -2.458164590756244e-11, 0.0, -0.0, 1e16, 3.141592653589793, 0.1807):
        text = _num(v)
        back = yaml.safe_load(f"a: {text}")["a"]
        assert isinstance(back, float) and back == v and text != "-0.0"
