"""The intake commands: estcal check, estcal frames, estcal import-bag (docs/dataset.md)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.dataset import write_dataset
from estcal.io.robotfile import load_robot
from estcal.simulate.core import simulate

from conftest import REPO, SHARED

runner = CliRunner()


def test_check_json_names_the_lines(tmp_path):
    rb = load_robot("puma560")
    ds = simulate(rb, 60, measure="points", n_points=3, seed=2, noise={"position": 1e-4}).dataset
    P = ds.points.copy()
    P[9] = P[9][[1, 0, 2]]  # a swap on line 11
    P[30, 2] += 0.02  # a ghost marker on line 32
    P[44] += 0.006  # a 6√3 mm blunder on line 46
    ds.points = P
    ds2 = ds.subset(np.r_[np.arange(60), 5])  # line 62 copies line 7
    write_dataset(tmp_path / "d.csv", ds2, extra={"note": np.zeros(61)})
    out = tmp_path / "f.json"
    r = runner.invoke(app, ["check", str(tmp_path / "d.csv"), "--robot", "puma560", "--json", str(out)])
    assert r.exit_code == 0, r.output
    f = json.loads(out.read_text())["findings"]
    got = {(x["kind"], tuple(x["lines"])) for x in f}
    assert ("marker_swap", (11,)) in got and ("non_rigid", (32,)) in got and ("outlier", (46,)) in got
    assert ("duplicate_row", (62,)) in got and ("unused_column", ()) in got
    assert all(set(x) >= {"kind", "lines", "message"} for x in f)
    swap = next(x for x in f if x["kind"] == "marker_swap")
    assert swap["order"] == [2, 1, 3]
    assert "marker_swap: line 11" in r.output


def test_frames_ur10_json():
    d = SHARED / "data" / "ur10"
    if not (d / "calibration.csv").exists():
        pytest.skip(f"UR10 data not found in {d}")
    r = runner.invoke(app, ["frames", str(d / "calibration.csv"), "--robot", str(d / "ur10_robot.urdf"), "--map",
                            str(REPO / "docs" / "maps" / "ur10.yaml"), "--json", "/dev/null"])
    assert r.exit_code == 0, r.output
    assert r.output.splitlines()[2].split()[1:3] == ["world", "camera_color_optical_frame"]


def test_frames_refuses_a_robot_file(tmp_path):
    r = runner.invoke(app, ["frames", str(tmp_path / "x.csv"), "--robot", "puma560"])
    assert r.exit_code == 2 and "needs a URDF" in r.output


def test_import_bag_cli(tmp_path):
    pytest.importorskip("rosbags")
    from test_bags import _write

    bag = _write(tmp_path / "b.bag", 1)
    out = tmp_path / "rows.csv"
    r = runner.invoke(app, ["import-bag", str(bag), "--joints", "/joint_states", "--pose", "/mocap/pose", "-o",
                            str(out)])
    assert r.exit_code == 0, r.output
    assert "4 plateau(s)" in r.output and "+1234.56" in r.output
    header = out.read_text().splitlines()[0].split(",")
    assert header[:3] == ["j1", "j2", "j3"] and "marker_std_mm" in header and "t_start_robot" in header
    r = runner.invoke(app, ["import-bag", str(bag), "--joints", "/joint_states", "-o", str(out)])
    assert r.exit_code == 2 and "give either a pose topic" in r.output
