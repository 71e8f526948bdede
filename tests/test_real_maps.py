"""docs/dataset.md: the published files of ../shared/data go through check, frames and calibrate with one
column map each (docs/maps/*.yaml) and no other conversion (skipped when ../shared is absent)."""
from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from estcal.cli.main import app

from conftest import REPO, SHARED

runner = CliRunner()
D = SHARED / "data"
MAPS = REPO / "docs" / "maps"

ROBOTS = {
    "talos": [str(D / "talos" / "talos_reduced.urdf"), "--root", "base_link", "--tip", "arm_left_7_link"],
    "tiago": [str(D / "tiago" / "tiago_48_schunk.urdf"), "--tip", "wrist_ft_tool_link"],
    "ur10": [str(D / "ur10" / "ur10_robot.urdf"), "--root", "world", "--tip", "camera_color_optical_frame"],
}
FILES = [("talos", "talos_feb_arm_02_07_crane.csv"), ("talos", "talos_feb_arm_02_10_contact.csv"),
         ("talos", "talos_feb_arm_2_contact.csv"), ("tiago", "qualisys_2021-11-30_static_postures.csv"),
         ("tiago", "qualisys_2021-11-26_static_postures.csv"), ("ur10", "calibration.csv")]


def _need(path):
    if not path.exists():
        pytest.skip(f"{path} not found (real data live in ../shared next to the repository)")
    return path


@pytest.mark.parametrize("folder, name", FILES, ids=[n for _, n in FILES])
def test_check_reads_the_published_file(folder, name, tmp_path):
    data = _need(D / folder / name)
    out = tmp_path / "f.json"
    r = runner.invoke(app, ["check", str(data), "--robot", *ROBOTS[folder], "--map", str(MAPS / f"{folder}.yaml"),
                            "--json", str(out)])
    assert r.exit_code == 0, r.output
    findings = json.loads(out.read_text())["findings"]
    flagged = sorted({ln for f in findings if f["kind"] not in ("repeated_pose", "unused_column") for ln in f["lines"]})
    assert flagged == ([2] if name == "talos_feb_arm_02_10_contact.csv" else [])


def test_frames_on_the_published_ur10():
    data = _need(D / "ur10" / "calibration.csv")
    r = runner.invoke(app, ["frames", str(data), "--robot", ROBOTS["ur10"][0], "--map", str(MAPS / "ur10.yaml")])
    assert r.exit_code == 0, r.output
    assert "   1  world            camera_color_optical_frame" in r.output


CALIBRATE = [("ur10", "calibration.csv", "joint_offset", 4.0), ("talos", "talos_feb_arm_02_10_contact.csv",
             "joint_offset", 2.0), ("talos", "talos_feb_arm_2_contact.csv", "registration", 12.0),
             ("tiago", "qualisys_2021-11-30_static_postures.csv", "joint_offset", 4.0)]


@pytest.mark.parametrize("folder, name, level, rmse_mm", CALIBRATE, ids=[n for _, n, _, _ in CALIBRATE])
def test_calibrate_reads_the_published_file(folder, name, level, rmse_mm, tmp_path):
    """docs/dataset.md's calibrations: the file as published, its map, TALOS 02-10's first row left out by default
    and named first; the RMSE after the fit as printed there (to a margin)."""
    data = _need(D / folder / name)
    out = tmp_path / "c.json"
    r = runner.invoke(app, ["calibrate", str(data), "--robot", *ROBOTS[folder], "--map", str(MAPS / f"{folder}.yaml"),
                            "--level", level, "--json", str(out)])
    assert r.exit_code == 0, r.output
    acc = json.loads(out.read_text())
    left = [(d["line"], d["kind"]) for d in acc.get("left_out", {}).get("rows", [])]
    assert left == ([(2, "outlier")] if name == "talos_feb_arm_02_10_contact.csv" else [])
    if left:
        assert r.output.startswith("left out: 1 of 62 rows")
        assert f"{data} line 2: residual" in r.output
    train = acc["accuracy"]["train"]["after"]["rmse_mm"]
    assert train < rmse_mm, train
