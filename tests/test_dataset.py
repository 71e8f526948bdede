"""Dataset loading: formats, and errors that name file, line and column."""
from __future__ import annotations

import numpy as np
import pytest

from estcal.io import DatasetError, dataset_from_arrays, load_dataset, write_dataset
from estcal.kinematics import puma560_fu
from estcal.kinematics.transforms import so3_exp


@pytest.fixture
def robot():
    return puma560_fu()


def _csv(tmp_path, text):
    p = tmp_path / "d.csv"
    p.write_text(text)
    return p


def test_roundtrip_pose_points_position(tmp_path, robot):
    rng = np.random.default_rng(0)
    q = robot.random_readings(7, rng)
    R = so3_exp(rng.normal(size=(7, 3)))
    p = rng.normal(size=(7, 3))
    for ds in (dataset_from_arrays(robot.joint_names, q, R=R, p=p, context={"t": np.arange(7.0)}),
               dataset_from_arrays(robot.joint_names, q, points=rng.normal(size=(7, 3, 3))),
               dataset_from_arrays(robot.joint_names, q, points=p)):
        path = write_dataset(tmp_path / f"{ds.kind}.csv", ds)
        back = load_dataset(path, robot, check_units=False)  # random positions: not physical
        assert back.kind == ds.kind and back.n == 7
        np.testing.assert_allclose(back.readings, q, atol=1e-9)
        if ds.kind == "pose":
            np.testing.assert_allclose(back.R, R, atol=1e-8)
            np.testing.assert_allclose(back.context["t"], np.arange(7.0))
        else:
            np.testing.assert_allclose(back.points, ds.points, atol=1e-9)


def test_missing_joint_column(tmp_path, robot):
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,x,y,z\n" + "0,0,0,0,0,1,2,3\n")
    with pytest.raises(DatasetError, match=r"d\.csv: missing joint column\(s\) \['j6'\]"):
        load_dataset(path, robot)


def test_nan_names_line_and_column(tmp_path, robot):
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,j6,x,y,z\n0,0,0,0,0,0,1,2,3\n0,0,nan,0,0,0,1,2,3\n")
    with pytest.raises(DatasetError, match=r"line 3, column 'j3'"):
        load_dataset(path, robot)


def test_ragged_row(tmp_path, robot):
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,j6,x,y,z\n0,0,0,0,0,0,1,2\n")
    with pytest.raises(DatasetError, match=r"line 2: 8 fields but the header has 9"):
        load_dataset(path, robot)


def test_degrees_and_millimetres_suspected(tmp_path, robot):
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,j6,x,y,z\n90,0,0,0,0,0,1,2,3\n45,0,0,0,0,0,1,2,3\n-60,0,0,0,0,0,1,2,3\n")
    with pytest.raises(DatasetError, match="look like degrees"):
        load_dataset(path, robot)
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,j6,x,y,z\n90,0,0,0,0,0,1,2,3\n")  # one reading: a wild value
    with pytest.raises(DatasetError, match=r"90 rad is beyond ±4π \(two turns\) — not a plausible joint angle"):
        load_dataset(path, robot)
    path = _csv(tmp_path, "j1,j2,j3,j4,j5,j6,x,y,z\n0,0,0,0,0,0,100,200,300\n")
    with pytest.raises(DatasetError, match="millimetres"):
        load_dataset(path, robot)


def test_tiago_files_load_as_they_are(tiago_dir):
    from estcal.kinematics import tiago

    robot = tiago(4)
    for name, n in (("qualisys_2021-11-30_static_postures.csv", 37), ("qualisys_2021-11-26_static_postures.csv", 62)):
        ds = load_dataset(tiago_dir / name, robot)
        assert ds.kind == "points" and ds.n == n and ds.n_points == 4 and "t" in ds.context
