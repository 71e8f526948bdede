"""Integrity of what estcal reads and writes: checksums of saved models and checkpoints, URDF mimic
joints and closed loops, joint columns the robot does not have, cheap refusals before heavy work."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.dataset import load_dataset
from estcal.io.robotfile import RobotFileError, load_robot, save_robot

runner = CliRunner()
ESTCAL = str(Path(sys.executable).parent / "estcal")


def _saved_model(tmp_path):
    data = tmp_path / "pos.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "40", "--measure", "position",
                            "--noise-pos-mm", "0.05", "--seed", "2", "-o", str(data)])
    assert r.exit_code == 0, r.output
    model = tmp_path / "model.yaml"
    r = runner.invoke(app, ["calibrate", str(data), "--robot", "puma560", "--level", "joint_offset",
                            "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    return data, model


def test_saved_model_round_trips_and_refuses_a_changed_digit_or_a_cut(tmp_path):
    data, model = _saved_model(tmp_path)
    text = model.read_text()
    assert "# content-sha256: " in text
    load_robot(str(model))  # intact: loads
    # one digit changed
    i = text.index("offset:") + len("offset: ")
    digit = next(k for k in range(i, len(text)) if text[k].isdigit())
    bad = tmp_path / "digit.yaml"
    bad.write_text(text[:digit] + str((int(text[digit]) + 1) % 10) + text[digit + 1:])
    with pytest.raises(RobotFileError, match="differs from the checksum estcal wrote at line 3"):
        load_robot(str(bad))
    # cut at a line boundary after the third joint: it would parse as a valid 3-joint robot
    lines = text.splitlines(keepends=True)
    cut = next(k for k, ln in enumerate(lines) if "name: j4" in ln)
    short = tmp_path / "cut.yaml"
    short.write_text("".join(lines[:cut]))
    with pytest.raises(RobotFileError, match="changed or cut"):
        load_robot(str(short))
    r = runner.invoke(app, ["fk", str(data), "--robot", str(short), "-o", str(tmp_path / "fk.csv")])
    assert r.exit_code == 2 and "changed or cut" in r.output
    # a deliberate hand edit: removing the checksum line accepts it
    edited = tmp_path / "edited.yaml"
    edited.write_text("".join(ln for ln in lines[:cut] if not ln.startswith("# content-sha256")))
    assert load_robot(str(edited)).n_joints == 3


def test_joint_columns_the_robot_lacks_are_named(tmp_path):
    data, model = _saved_model(tmp_path)
    lines = model.read_text().splitlines(keepends=True)
    cut = next(k for k, ln in enumerate(lines) if "name: j4" in ln)
    short = tmp_path / "cut.yaml"
    short.write_text("".join(ln for ln in lines[:cut] if not ln.startswith("# content-sha256")))
    ds = load_dataset(data, load_robot(str(short)))
    assert any("j4, j5, j6 look like joints that the robot" in w for w in ds.warnings), ds.warnings
    r = runner.invoke(app, ["fk", str(data), "--robot", str(short), "-o", str(tmp_path / "fk.csv")])
    assert r.exit_code == 0 and "j4, j5, j6 look like joints" in r.output


def test_checkpoint_with_one_digit_changed_is_refused(tmp_path):
    data = tmp_path / "pos.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "30", "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "4", "-o", str(data)])
    assert r.exit_code == 0
    state = tmp_path / "state.json"
    args = ["online", str(data), "--robot", "puma560", "--free", "offset_1,offset_2,offset_3", "--q-mm", "1e-4"]
    r = runner.invoke(app, args + ["--state", str(state)])
    assert r.exit_code == 0, r.output
    d = json.loads(state.read_text())
    assert "content_sha256" in d
    text = state.read_text()
    key = '"line": '
    i = text.index(key) + len(key)
    changed = text[:i] + str((int(text[i]) + 1) % 10) + text[i + 1:]
    state.write_text(changed)
    r = runner.invoke(app, args + ["--resume", str(state)])
    assert r.exit_code == 2 and "differs from the checksum" in r.output, r.output


URDF = """<robot name="r">
  <link name="a"/><link name="b"/><link name="c"/><link name="d"/>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/>{mimic}</joint>
  {extra}
</robot>"""


def test_urdf_mimic_joint_on_the_chain_is_refused(tmp_path):
    p = tmp_path / "m.urdf"
    p.write_text(URDF.format(mimic='<mimic joint="j1" multiplier="2" offset="0.1"/>', extra=""))
    with pytest.raises(RobotFileError, match=r"'j2' .* is a <mimic> of 'j1' \(q = 2·q_j1 \+ 0.1\)"):
        load_robot(str(p), root="a", tip="c")
    assert load_robot(str(p), root="a", tip="b").n_joints == 1  # above it: fine


def test_urdf_closed_loop_is_refused_even_with_root(tmp_path):
    loop = ('<joint name="j3" type="fixed"><parent link="c"/><child link="d"/></joint>'
            '<link name="e"/><joint name="j4" type="fixed"><parent link="d"/><child link="e"/></joint>'
            '<joint name="j5" type="fixed"><parent link="e"/><child link="d2"/></joint><link name="d2"/>'
            '<joint name="j6" type="fixed"><parent link="d2"/><child link="e2"/></joint><link name="e2"/>'
            '<joint name="j7" type="fixed"><parent link="e2"/><child link="d2b"/></joint><link name="d2b"/>')
    p = tmp_path / "ok.urdf"
    p.write_text(URDF.format(mimic="", extra=loop))
    load_robot(str(p), root="a", tip="c")  # a tree: fine
    cyc = ('<link name="x"/><link name="y"/>'
           '<joint name="k1" type="fixed"><parent link="x"/><child link="y"/></joint>'
           '<joint name="k2" type="fixed"><parent link="y"/><child link="x"/></joint>')
    p2 = tmp_path / "loop.urdf"
    p2.write_text(URDF.format(mimic="", extra=cyc))
    with pytest.raises(RobotFileError, match="closed loop through links"):
        load_robot(str(p2), root="a", tip="c")


def test_a_million_identical_rows_refused_within_15_s(tmp_path):
    """Cheap refusals come before registration, selection and QR (docs/reliability.md)."""
    data = tmp_path / "same.csv"
    row = "0.1,-0.4,0.3,0.2,0.5,-0.1,0.45,0.12,0.33\n"
    with open(data, "w") as fh:
        fh.write("j1,j2,j3,j4,j5,j6,x,y,z\n")
        fh.write(row * 1_000_000)
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([ESTCAL, "calibrate", str(data), "--robot", "puma560"], capture_output=True, text=True,
                       timeout=300)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    assert p.returncode == 3, p.stderr
    assert "only 1 distinct joint configuration" in p.stderr and "refused before any estimation" in p.stderr
    # the command's own time (CPU: the wall clock of a shared 2-core machine also counts other jobs)
    assert cpu < 15, (cpu, wall)
