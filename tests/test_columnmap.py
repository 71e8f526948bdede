"""Column maps (--map): a file read in its publisher's columns, units and conventions (docs/dataset.md)."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.io.dataset import DatasetError, load_dataset, write_dataset
from estcal.io.robotfile import load_robot
from estcal.kinematics.transforms import rot_x, rot_y, rot_z
from estcal.simulate.core import simulate

from conftest import SHARED, REPO

MAPS = REPO / "docs" / "maps"


def _sim(tmp_path, measure="pose", n=12):
    rb = load_robot("puma560")
    ds = simulate(rb, n, measure=measure, seed=3).dataset
    write_dataset(tmp_path / "std.csv", ds)
    return rb, ds


def test_rpy_is_rz_ry_rx(tmp_path):
    """A row with rpy = (r, p, y) loads as R = Rz(y)·Ry(p)·Rx(r), composed here from the elementary rotations."""
    rng = np.random.default_rng(0)
    a = rng.uniform(-3, 3, (20, 3))
    q = rng.uniform(-1, 1, (20, 1))
    np.savetxt(tmp_path / "r.csv", np.c_[q, rng.normal(size=(20, 3)) * 0.1, a], delimiter=",",
               header="a,px,py,pz,r,p,y", comments="", fmt="%.17g")
    (tmp_path / "m.yaml").write_text("joints: {j1: a}\npoints: [[px, py, pz]]\norientation: {rpy: [r, p, y]}\n")
    ds = load_dataset(tmp_path / "r.csv", joint_names=["j1"], column_map=tmp_path / "m.yaml")
    for i in range(20):
        assert np.allclose(ds.R[i], rot_z(a[i, 2]) @ rot_y(a[i, 1]) @ rot_x(a[i, 0]), atol=1e-12)


def _publisher_file(tmp_path, rb, ds, header=True):
    """The simulated poses written as a publisher would: renamed joints, mm, degrees, rpy."""
    from estcal.kinematics.transforms import matrix_to_rpy

    rpy = np.array([matrix_to_rpy(R) for R in ds.R])
    cols = {f"q{i + 1}": np.degrees(ds.readings[:, i]) for i in range(6)}
    cols.update({"X": ds.p[:, 0] * 1e3, "Y": ds.p[:, 1] * 1e3, "Z": ds.p[:, 2] * 1e3,
                 "roll": np.degrees(rpy[:, 0]), "pitch": np.degrees(rpy[:, 1]), "yaw": np.degrees(rpy[:, 2]),
                 "note": np.arange(ds.n)})
    M = np.column_stack(list(cols.values()))
    path = tmp_path / "pub.csv"
    with open(path, "w") as fh:
        if header:
            fh.write(",".join(cols) + "\n")
        np.savetxt(fh, M, delimiter=",", fmt="%.17g")
    return path, list(cols)


MAP = """joints: {j1: q1, j2: q2, j3: q3, j4: q4, j5: q5, j6: q6}
points: [[X, Y, Z]]
orientation: {rpy: [roll, pitch, yaw]}
units: {length: mm, angle: deg}
"""


@pytest.mark.parametrize("header", [True, False])
def test_publisher_file_equals_the_standard_one(tmp_path, header):
    rb, ds = _sim(tmp_path)
    path, cols = _publisher_file(tmp_path, rb, ds, header)
    m = tmp_path / "m.yaml"
    m.write_text(MAP + ("" if header else f"columns: [{', '.join(cols)}]\n"))
    got = load_dataset(path, rb, column_map=m)
    ref = load_dataset(tmp_path / "std.csv", rb)
    assert got.kind == "pose" and got.n == ref.n
    assert np.allclose(got.readings, ref.readings, atol=1e-12)
    assert np.allclose(got.p, ref.p, atol=1e-12)
    assert np.allclose(got.R, ref.R, atol=1e-9)
    assert list(got.lines) == list(ref.lines if header else ref.lines - 1)
    assert "note" in got.columns and got.source_header == cols


@pytest.mark.parametrize("text, line, words", [
    ("joints: {j1: q1}\npoints: [[X, Y, Z]]\nunit: {length: mm}\n", 3, ["unknown key 'unit'", "units"]),
    ("joints: {j1: q1, j2: qq2}\npoints: [[X, Y, Z]]\n", 1, ["column 'qq2' is not in", "q2"]),
    ("joints: {j1: q1, j2: q2, j3: q3, j4: q4, j5: q5, j6: q6}\npoints:\n  - [X, Y, Zed]\n", 3,
     ["column 'Zed' is not in", "'Z'"]),
    ("joints: {j1: q1}\npoints: [[X, Y, Z]]\n", 1, ["robot joint 'j2' is not mapped", "add `j2: <column>` under joints:"]),
    ("joints: {j1: q1, j7: q2}\n", 1, ["'j7' is not a joint of the robot"]),
    ("points: [[X, Y, Z]]\nunits: {length: feet}\n", 2, ["length unit 'feet'"]),
    ("points: [[X, Y, Z]]\norientation: {euler: [a, b, c]}\n", 2, ["orientation is {rpy"]),
    ("points: [[X, Y, Z]]\ncontext: {time: note}\n", 2, ["unknown context 'time'"]),
])
def test_bad_maps_name_the_line(tmp_path, text, line, words):
    rb, ds = _sim(tmp_path)
    path, _ = _publisher_file(tmp_path, rb, ds)
    m = tmp_path / "m.yaml"
    m.write_text(text)
    with pytest.raises(ValueError) as e:
        load_dataset(path, rb, column_map=m)
    msg = str(e.value)
    assert f"m.yaml, line {line}" in msg, msg
    for w in words:
        assert w in msg, msg


def test_bad_value_names_the_file_column(tmp_path):
    rb, ds = _sim(tmp_path)
    path, _ = _publisher_file(tmp_path, rb, ds)
    lines = path.read_text().splitlines()
    f = lines[3].split(",")
    f[1] = "oops"
    lines[3] = ",".join(f)
    path.write_text("\n".join(lines) + "\n")
    m = tmp_path / "m.yaml"
    m.write_text(MAP)
    with pytest.raises(DatasetError, match=r"line 4, column 'q2' \(as 'j2' by .*m.yaml, line 1\): value is 'oops'"):
        load_dataset(path, rb, column_map=m)


def test_headerless_file_without_map_is_explained(tmp_path):
    rb, ds = _sim(tmp_path)
    path, _ = _publisher_file(tmp_path, rb, ds, header=False)
    with pytest.raises(DatasetError, match="no header row; name its columns with a column map"):
        load_dataset(path, rb)


def _shared(*parts):
    p = SHARED.joinpath("data", *parts)
    if not p.exists():
        pytest.skip(f"{p} not found (real data live in ../shared next to the repository)")
    return p


def test_ur10_rpy_convention_checked_on_the_data():
    """The UR10 file's rpy is R = Rz·Ry·Rx: registered base + tool leave 3.8 mm / 9 mrad at the
    camera frame; the other order (Rx·Ry·Rz) leaves > 100 mm / > 1 rad."""
    from scipy.spatial.transform import Rotation

    from estcal.intake.registration import register_pose
    from estcal.kinematics.chunked import tool_poses

    data = _shared("ur10", "calibration.csv")
    rb = load_robot(str(_shared("ur10", "ur10_robot.urdf")), root="world", tip="camera_color_optical_frame")
    ds = load_dataset(data, rb, column_map=MAPS / "ur10.yaml")
    k = tool_poses(rb, ds.readings)
    good = register_pose(k["R"], k["p"], ds.R, ds.p)
    assert good.rmse_mm < 5 and good.rmse_mrad < 12
    raw = np.genfromtxt(data, delimiter=",", names=True)
    rpy = np.c_[raw["phix1"], raw["phiy1"], raw["phiz1"]]
    other = register_pose(k["R"], k["p"], Rotation.from_euler("XYZ", rpy).as_matrix(), ds.p)
    assert other.rmse_mm > 100 and other.rmse_mrad > 1000


@pytest.mark.parametrize("folder, robot, name, map_, n", [
    ("talos", ("talos_reduced.urdf", "base_link", "arm_left_7_link"), "talos_feb_arm_02_07_crane.csv", "talos", 18),
    ("talos", ("talos_reduced.urdf", "base_link", "arm_left_7_link"), "talos_feb_arm_02_10_contact.csv", "talos", 62),
    ("talos", ("talos_reduced.urdf", "base_link", "arm_left_7_link"), "talos_feb_arm_2_contact.csv", "talos", 21),
    ("ur10", ("ur10_robot.urdf", "world", "camera_color_optical_frame"), "calibration.csv", "ur10", 23),
    ("tiago", ("tiago_48_schunk.urdf", None, "wrist_ft_tool_link"), "qualisys_2021-11-30_static_postures.csv", "tiago", 37),
    ("tiago", ("tiago_48_schunk.urdf", None, "wrist_ft_tool_link"), "qualisys_2021-11-26_static_postures.csv", "tiago", 62),
])
def test_real_files_load_through_their_map(folder, robot, name, map_, n):
    urdf, root, tip = robot
    rb = load_robot(str(_shared(folder, urdf)), root=root, tip=tip)
    ds = load_dataset(_shared(folder, name), rb, column_map=MAPS / f"{map_}.yaml")
    assert ds.n == n
    if folder == "talos":
        assert ds.lines[0] == (1 if name == "talos_feb_arm_2_contact.csv" else 2)
        assert "t" in ds.context
