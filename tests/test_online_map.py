"""``estcal online --map FILE.yaml`` and ``OnlineCalibrator(column_map=...)`` (docs/dataset.md, "Files as
published"): a file in its publisher's columns and units, with or without a header row, streams to the
estimate of the same rows in estcal's layout; the checkpoint keeps the map; the published files of
../shared/data stream through their maps (skipped when ../shared is absent)."""
from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import estcal
from estcal.base.errors import InputError
from estcal.cli.main import app
from online_cli import FREE, run_online

from conftest import REPO, SHARED

runner = CliRunner()
N = 120
COLUMNS = ["mx", "my", "mz", "stamp", "q1", "q2", "q3", "q4", "q5", "q6"]
MAP = """\
# the publisher's names, mm and degrees
joints: {j1: q1, j2: q2, j3: q3, j4: q4, j5: q5, j6: q6}
points: [[mx, my, mz]]
units: {length: mm, angle: deg}
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The same simulated rows in estcal's layout and as a publisher would write them: other column
    names and order, mm and degrees, an unused column — with a header row and without one."""
    d = tmp_path_factory.mktemp("omap")
    ref = d / "ref.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", str(N), "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "11", "-o", str(ref)])
    assert r.exit_code == 0, r.output
    ds = estcal.load_dataset(ref, estcal.load_robot("puma560"))
    body = np.c_[ds.points[:, 0] * 1e3, np.arange(N) * 0.5, np.degrees(ds.readings)]
    lines = [",".join(repr(float(v)) for v in row) for row in body]
    named, bare = d / "pub.csv", d / "pub_noheader.csv"
    named.write_text(",".join(COLUMNS) + "\n" + "\n".join(lines) + "\n")
    bare.write_text("\n".join(lines) + "\n")
    (d / "pub.yaml").write_text(MAP)
    (d / "pub_noheader.yaml").write_text(MAP + f"columns: [{', '.join(COLUMNS)}]\n")
    return d


def _estimate(res):
    return np.array([v["estimate"] for v in res["parameters"].values()])


def _same(res, ref):
    """The same estimate (1e-9 SI: mm and degrees converted back to SI round the last digit) and NIS."""
    assert res["n_rows"] == ref["n_rows"] == N
    assert np.max(np.abs(_estimate(res) - _estimate(ref))) < 1e-9
    assert res["innovation"]["nis_total"] == pytest.approx(ref["innovation"]["nis_total"], rel=1e-8)


@pytest.mark.parametrize("name", ["pub", "pub_noheader"])
def test_online_map_reads_the_published_layout(files, tmp_path, name):
    ref = run_online(files / "ref.csv", tmp_path / "ref.json")
    res = run_online(files / f"{name}.csv", tmp_path / "map.json", "--map", str(files / f"{name}.yaml"))
    _same(res, ref)
    if name == "pub_noheader":  # the first line is a data row: line numbers as an editor shows them
        assert res["history"][0]["line"] == 10


def test_online_calibrator_takes_the_map_and_its_checkpoint_keeps_it(files, tmp_path):
    ref = run_online(files / "ref.csv", tmp_path / "ref.json")
    kw = dict(free=FREE, q=1e-7, noise=(1e-4, 1e-3), prior_std=0.1)
    cal = estcal.OnlineCalibrator("puma560", column_map=files / "pub_noheader.yaml", **kw)
    cal.update(files / "pub_noheader.csv")
    _same(cal.result().to_dict(), ref)
    # the checkpoint carries the map: a resumed object reads the publisher's files without being told
    half = estcal.OnlineCalibrator("puma560", column_map=files / "pub.yaml", **kw)
    half.update(files / "pub.csv")
    half.save(tmp_path / "s.json")
    half.close()
    again = estcal.OnlineCalibrator.resume(tmp_path / "s.json")
    assert again.column_map is not None and again.column_map.length == "mm"
    again.close()
    with pytest.raises(InputError, match="--map"):  # another map: another run
        estcal.OnlineCalibrator.resume(tmp_path / "s.json", column_map=files / "pub_noheader.yaml")


def test_online_map_resumes_a_headerless_stream(files, tmp_path):
    """A checkpoint of the first rows of a headerless file continues on the whole file, bit for bit
    the run that read it at once (the first data line is hashed as input, not as a header)."""
    lines = (files / "pub_noheader.csv").read_text().splitlines(keepends=True)
    first = tmp_path / "first.csv"
    first.write_text("".join(lines[:50]))
    m = ["--map", str(files / "pub_noheader.yaml")]
    run_online(first, tmp_path / "a.json", *m, "--state", str(tmp_path / "s.json"), "--checkpoint-every", "25")
    res = run_online(files / "pub_noheader.csv", tmp_path / "b.json", *m, "--resume", str(tmp_path / "s.json"))
    whole = run_online(files / "pub_noheader.csv", tmp_path / "c.json", *m)
    assert res["n_rows"] == N and _estimate(res).tolist() == _estimate(whole).tolist()


def test_online_map_errors_name_the_map_line(files, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(MAP.replace("q6}", "q7}"))
    r = runner.invoke(app, ["online", str(files / "pub.csv"), "--robot", "puma560", "--free", FREE,
                            "--map", str(bad)])
    assert r.exit_code == 2
    assert "bad.yaml, line 2: column 'q7' is not in" in " ".join(r.output.split())


D = SHARED / "data"
REAL = {"talos": (D / "talos" / "talos_feb_arm_2_contact.csv",
                  [str(D / "talos" / "talos_reduced.urdf"), "--root", "base_link", "--tip", "arm_left_7_link"]),
        "ur10": (D / "ur10" / "calibration.csv",
                 [str(D / "ur10" / "ur10_robot.urdf"), "--root", "world", "--tip", "camera_color_optical_frame"])}


@pytest.mark.parametrize("source", sorted(REAL))
def test_online_streams_the_published_file_through_its_map(source, tmp_path):
    """TALOS's headerless session and the UR10's rpy poses, as published, through docs/maps/*.yaml:
    ``estcal online`` and the Python object fed row by row agree (1e-9 SI)."""
    data, robot = REAL[source]
    if not data.exists():
        pytest.skip(f"{data} not found (real data live in ../shared next to the repository)")
    cmap = REPO / "docs" / "maps" / f"{source}.yaml"
    out = tmp_path / "o.json"
    r = runner.invoke(app, ["online", str(data), "--robot", *robot, "--map", str(cmap), "--free",
                            "base_tx,base_ty,base_tz,base_rx,base_ry,base_rz", "--noise-pos-mm", "1",
                            "--json", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads(out.read_text())
    rb = estcal.load_robot(robot[0], root=robot[2], tip=robot[4])
    cal = estcal.OnlineCalibrator(rb, column_map=cmap, free=list(res["parameters"]), noise=(1e-3, 1e-3),
                                  prior_std=0.1)
    ds = estcal.load_dataset(data, rb, column_map=cmap)
    for i in range(ds.n):
        cal.update(ds.subset(slice(i, i + 1)))
    assert cal.n_rows == res["n_rows"] == ds.n
    assert np.max(np.abs(cal.estimate - _estimate(res))) < 1e-9


#: commands that read no measured data: what they read instead
NO_MEASURED_DATA = {"compensate": "target poses to reach", "demo": "nothing (simulates)", "design": "nothing",
                    "estimators": "nothing", "export": "a robot file", "import-bag": "a ROS bag (writes the CSV)",
                    "next-pose": "a filter state", "robots": "nothing", "simulate": "nothing (writes data)"}


def test_every_command_that_reads_measured_data_takes_map():
    """docs/dataset.md's table of commands taking --map is the CLI's: a new data command without the
    shared option (estcal.cli.options.map_option), or one missing from the table, fails here."""
    import inspect
    import re

    from estcal.cli.main import app as cli

    takes = {c.name for c in cli.registered_commands if "column_map" in inspect.signature(c.callback).parameters}
    assert takes | set(NO_MEASURED_DATA) == {c.name for c in cli.registered_commands}
    doc = (REPO / "docs" / "dataset.md").read_text()
    table = doc[doc.index("| command | reads through `--map`"):]
    table = table[:table.index("\n\n")]
    assert set(re.findall(r"^\| `(?:estcal )?([a-z-]+)", table, re.M)) == takes


def test_fleet_and_identifiable_read_through_the_map(files, tmp_path):
    from estcal.io.robotfile import save_robot

    fl = tmp_path / "fleet"
    for name in ("a", "b"):
        (fl / name).mkdir(parents=True)
        (fl / name / "data.csv").write_bytes((files / "pub.csv").read_bytes())
    save_robot(estcal.load_robot("puma560"), fl / "robot.yaml")
    r = runner.invoke(app, ["fleet", str(fl), "--level", "joint_offset", "--map", str(files / "pub.yaml"),
                            "--json", str(tmp_path / "f.json")])
    assert r.exit_code == 0, r.output
    ref = runner.invoke(app, ["calibrate", str(files / "ref.csv"), "--robot", "puma560", "--level", "joint_offset",
                              "--json", str(tmp_path / "c.json")])
    assert ref.exit_code == 0, ref.output
    after = json.loads((tmp_path / "c.json").read_text())["accuracy"]["train"]["after"]["rmse_mm"]
    rows = json.loads((tmp_path / "f.json").read_text())["robots"]
    assert [r_["rmse_after_mm"] for r_ in rows] == pytest.approx([after, after], rel=1e-6)
    out = tmp_path / "i.json"
    r = runner.invoke(app, ["identifiable", "--robot", "puma560", "--data", str(files / "pub_noheader.csv"),
                            "--map", str(files / "pub_noheader.yaml"), "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["n_rows"] == 3 * N
