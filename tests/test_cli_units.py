"""One unit convention on the command line (docs/conventions.md, "Units on the command line").

* every numeric option of every subcommand names its unit (or is dimensionless by the
  documented list);
* the same noise given to `design` and `calibrate` gives the same parameter covariance
  (design's (JᵀWJ)⁻¹ at the plan against calibrate's known-noise covariance on exact
  data at the plan's poses), and `simulate`'s noise is what `calibrate` assumes (σ0 ≈ 1);
* the deprecated SI spellings are converted, warned about, and give identical results;
* `online` prints mm / mrad and writes SI.
"""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.cli.units import DIMENSIONLESS, UNIT_PATTERN
from estcal.io.robotfile import load_robot
from estcal.kinematics.transforms import matrix_to_quat

from conftest import REPO

runner = CliRunner()

# String options that carry numbers (checked like the numeric ones).
NUMERIC_TEXT = {"--test-pose", "--map-box", "--temperature", "--payload", "--plane", "--regularize",
                "--effect-param"}


def _subcommands() -> list[str]:
    out = runner.invoke(app, ["--help"], env={"COLUMNS": "300"}).output
    return re.findall(r"^│ (\w[\w-]*)\s", out, flags=re.M)


_ROW = re.compile(r"^\s*\*?\s*(--[\w-]+)(?:\s+--[\w-]+)?(?:\s+-\w)?\s+<([\w\[\]]+)>\s*(.*)$")


def _options(help_text: str) -> dict:
    """{option: (type, help)} parsed from the rich ``--help`` box (continuation lines joined)."""
    opts, last = {}, None
    for line in help_text.splitlines():
        if not line.startswith("│"):
            last = None if line.startswith("╰") else last
            continue
        body = line.strip().strip("│").strip()
        m = _ROW.match(body)
        if m:
            last = m.group(1)
            opts[last] = [m.group(2), m.group(3)]
        elif last and body:
            opts[last][1] += " " + body
    return opts


def test_every_numeric_option_names_its_unit():
    unit = re.compile(UNIT_PATTERN)
    names = _subcommands()
    assert {"simulate", "calibrate", "design", "online", "export"} <= set(names)
    missing, seen_dimless, n_checked = [], set(), 0
    for name in names:
        r = runner.invoke(app, [name, "--help"], env={"COLUMNS": "300"})
        assert r.exit_code == 0, (name, r.output)
        for opt, (typ, text) in _options(r.output).items():
            if not (typ in ("float", "int") or opt in NUMERIC_TEXT):
                continue
            n_checked += 1
            if opt in DIMENSIONLESS:
                seen_dimless.add(opt)
                continue
            if re.search(r"-(mm|mrad|deg|s|kg)$", opt) or unit.search(re.sub(r"\[default:[^]]*\]", "", text)):
                continue
            missing.append(f"{name} {opt}: {text!r}")
    assert not missing, "numeric options without a unit:\n" + "\n".join(missing)
    assert n_checked > 40
    # the dimensionless list is documented (docs/conventions.md names every entry in use)
    doc = (REPO / "docs" / "conventions.md").read_text()
    section = doc[doc.index("## Units on the command line"):]
    assert [o for o in sorted(seen_dimless) if f"`{o}`" not in section] == []


def test_the_help_parser_sees_the_options():
    """Guard for the walk above: it must find the typed options of a known command."""
    opts = _options(runner.invoke(app, ["simulate", "--help"], env={"COLUMNS": "300"}).output)
    assert opts["--noise-pos-mm"][0] == "float" and "(mm)" in opts["--noise-pos-mm"][1]
    assert opts["--n"][0] == "int" and "--noise-pos" not in opts  # hidden alias


def test_noise_options_have_one_name_everywhere():
    """`--noise-pos-mm` / `--noise-rot-mrad` wherever a measurement noise is an option."""
    for name in ("simulate", "calibrate", "online", "design", "next-pose", "fleet"):
        out = runner.invoke(app, [name, "--help"], env={"COLUMNS": "400"}).output
        assert "--noise-pos-mm" in out and "--noise-rot-mrad" in out, name
        assert "--sigma " not in out and "--noise-pos " not in out


def _plan_dataset(tmp_path, d, robot, pose: bool):
    q = np.asarray(d["plan"]["readings_rad"])
    T = robot.fk(q)
    cols = [q, T[:, :3, 3]] + ([matrix_to_quat(T[:, :3, :3])] if pose else [])
    names = robot.joint_names + ["x", "y", "z"] + (["qw", "qx", "qy", "qz"] if pose else [])
    path = tmp_path / "plan.csv"
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(names), comments="", fmt="%.17g")
    return path


@pytest.mark.parametrize("method", ["position", "pose"])
def test_same_noise_in_design_and_calibrate_gives_the_same_covariance(tmp_path, method):
    robot = load_robot("puma560")
    noise = ["--noise-pos-mm", "0.07", "--noise-rot-mrad", "0.4"]
    dj = tmp_path / "design.json"
    r = runner.invoke(app, ["design", "--robot", "puma560", "--measure", method, "--n", "10", *noise,
                            "--random-plans", "5", "--n-candidates", "150", "--restarts", "1", "--json", str(dj)])
    assert r.exit_code == 0, r.output
    d = json.loads(dj.read_text())
    data = _plan_dataset(tmp_path, d, robot, pose=method == "pose")
    cj = tmp_path / "cal.json"
    r = runner.invoke(app, ["calibrate", str(data), "--robot", "puma560", "--free", ",".join(d["free"]), *noise,
                            "--known-noise", "--json", str(cj)])
    assert r.exit_code == 0, r.output
    c = json.loads(cj.read_text())["parameters"]
    design_std = d["criteria"]["param_std"]
    for n in d["free"]:
        assert c[n]["std"] == pytest.approx(design_std[n], rel=1e-6), n
    # … and the printed tables agree in mm / mrad
    std_mm = design_std["a_2"] * 1e3
    assert f"{std_mm:.4g} mm" in runner.invoke(app, ["design", "--robot", "puma560", "--measure", method, "--n", "10",
                                                     *noise, "--random-plans", "5", "--n-candidates", "150",
                                                     "--restarts", "1"]).output


def test_simulated_noise_is_the_noise_calibrate_assumes(tmp_path):
    data = tmp_path / "sim.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "80", "--measure", "pose", "--errors", "none",
                            "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--seed", "2", "-o", str(data)])
    assert r.exit_code == 0, r.output
    cj = tmp_path / "c.json"
    r = runner.invoke(app, ["calibrate", str(data), "--robot", "puma560", "--level", "joint_offset",
                            "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--json", str(cj)])
    assert r.exit_code == 0, r.output
    s0 = json.loads(cj.read_text())["sigma0"]
    # σ0² = χ²_ν / ν with ν ≈ 480 − p: within ±4 standard deviations (√(2/ν) ≈ 0.065) of 1
    assert abs(s0 ** 2 - 1) < 0.26


def test_deprecated_si_options_convert_and_warn(tmp_path):
    data = tmp_path / "sim.csv"
    new = runner.invoke(app, ["simulate", "--robot", "planar2", "--n", "20", "--noise-pos-mm", "0.2",
                              "--error-length-mm", "2", "--seed", "1", "-o", str(data)])
    old_data = tmp_path / "old.csv"
    old = runner.invoke(app, ["simulate", "--robot", "planar2", "--n", "20", "--noise-pos", "2e-4",
                              "--error-length", "2e-3", "--seed", "1", "-o", str(old_data)])
    assert new.exit_code == old.exit_code == 0, old.output
    assert data.read_text() == old_data.read_text()
    assert "warning: --noise-pos (m) is deprecated; use --noise-pos-mm 0.2" in old.output
    assert "--error-length-mm 2" in old.output and "warning:" not in new.output
    outs = {}
    for label, noise in (("new", ["--noise-pos-mm", "0.2"]), ("old", ["--noise-pos", "0.0002"])):
        js = tmp_path / f"{label}.json"
        r = runner.invoke(app, ["calibrate", str(data), "--robot", "planar2", "--level", "full", *noise,
                                "--known-noise", "--json", str(js)])
        assert r.exit_code == 0, r.output
        outs[label] = json.loads(js.read_text())["parameters"]
    assert outs["new"] == outs["old"]
    both = runner.invoke(app, ["calibrate", str(data), "--robot", "planar2", "--noise-pos", "1e-4",
                               "--noise-pos-mm", "0.3"])
    assert both.exit_code == 2 and "not both" in both.output
    # design's old names were already mm / mrad: same value, renamed
    r = runner.invoke(app, ["design", "--robot", "planar2", "--n", "4", "--sigma", "0.5", "--random-plans", "5",
                            "--n-candidates", "50", "--restarts", "1"])
    assert r.exit_code == 0 and "use --noise-pos-mm 0.5" in r.output and "σ = 0.5 mm" in r.output


def test_regularize_takes_a_unit(tmp_path):
    data = tmp_path / "sim.csv"
    runner.invoke(app, ["simulate", "--robot", "planar2", "--n", "15", "--noise-pos-mm", "0.1", "-o", str(data)])
    res = {}
    for label, val in (("unit", "2mm"), ("si", "0.002")):
        js = tmp_path / f"{label}.json"
        r = runner.invoke(app, ["calibrate", str(data), "--robot", "planar2", "--regularize", val, "--json", str(js)])
        assert r.exit_code == 0, r.output
        res[label] = (json.loads(js.read_text())["parameters"], r.output)
    assert res["unit"][0] == res["si"][0]
    assert "prior (MAP): std 2 mm / mrad" in res["unit"][1]
    assert "is read as SI" in res["si"][1] and "warning:" not in res["unit"][1]


def test_online_prints_mm_mrad_and_writes_si(tmp_path):
    data = tmp_path / "sim.csv"
    runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "30", "--measure", "pose", "--noise-pos-mm", "0.05",
                        "--noise-rot-mrad", "0.5", "--seed", "4", "-o", str(data)])
    js = tmp_path / "o.json"
    r = runner.invoke(app, ["online", str(data), "--robot", "puma560", "--free", "offset_2,d_3", "--noise-pos-mm",
                            "0.05", "--noise-rot-mrad", "0.5", "--every", "100", "--json", str(js)],
                      env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    p = json.loads(js.read_text())["parameters"]
    rows = {ln.split()[1]: ln for ln in r.output.splitlines() if ln.startswith("│ offset_2") or
            ln.startswith("│ d_3")}
    # printed estimate (3rd number) = JSON (SI) × 1000, with its unit
    est_offset = float(rows["offset_2"].split("│")[3])
    est_d3 = float(rows["d_3"].split("│")[3])
    assert est_offset == pytest.approx(p["offset_2"]["estimate"] * 1e3, rel=1e-5) and "mrad" in rows["offset_2"]
    assert est_d3 == pytest.approx(p["d_3"]["estimate"] * 1e3, rel=1e-5) and "mm" in rows["d_3"]
