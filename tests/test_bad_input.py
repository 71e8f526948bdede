"""A battery of malformed and degenerate inputs for every command (docs/reliability.md).

Every case is generated here in ``tmp_path`` (no fixture files): a bad dataset,
robot file, URDF, state file or option value, run through the real command with
typer's CliRunner. Each must end with no traceback, the documented exit code
(2 bad input / usage, 3 numerical refusal), nothing on stdout that looks like an
error, and a one-line message on stderr that names the problem (file, line,
column, option …). A few cases run the installed entry point in a subprocess to
check the real exit code and streams.
"""
from __future__ import annotations

import codecs
import json
import re
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.dataset import dataset_from_arrays, write_dataset
from estcal.io.robotfile import load_robot, save_robot

runner = CliRunner()

N_GOOD = 24


# ------------------------------------------------------------------ generated inputs
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Good files every case starts from: position and pose data of the PUMA 560, its robot file."""
    d = tmp_path_factory.mktemp("bad_input")
    rb = load_robot("puma560")
    q = rb.random_readings(N_GOOD, np.random.default_rng(0))
    k = rb.kinematics(q, jacobian=False)
    write_dataset(d / "pos.csv", dataset_from_arrays(rb.joint_names, q, points=k.p))
    write_dataset(d / "pose.csv", dataset_from_arrays(rb.joint_names, q, R=k.R, p=k.p))
    rb3 = load_robot("puma560", n_markers=3)
    k3 = rb3.kinematics(q, jacobian=False)
    write_dataset(d / "pts.csv", dataset_from_arrays(rb.joint_names, q, points=k3.points))
    save_robot(rb, d / "robot.yaml")
    (d / "folder").mkdir()
    return d


def lines_of(base, name="pos.csv"):
    return (base / name).read_text().splitlines()


def write(tmp_path, name, content) -> str:
    p = tmp_path / name
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    return str(p)


def csv_from(lines) -> str:
    return "\n".join(lines) + "\n"


def replace_value(lines, row, col, value):
    """``lines`` with field ``col`` of data row ``row`` (0 = first data row) replaced."""
    out = list(lines)
    f = out[row + 1].split(",")
    f[col] = value
    out[row + 1] = ",".join(f)
    return out


def scale_columns(lines, cols, factor):
    hdr = lines[0].split(",")
    idx = [hdr.index(c) for c in cols]
    out = [lines[0]]
    for ln in lines[1:]:
        f = ln.split(",")
        for i in idx:
            f[i] = repr(float(f[i]) * factor)
        out.append(",".join(f))
    return out


# ------------------------------------------------------------------ bad datasets
# name -> (builder(base, tmp_path) -> path, expected message regex (re.escape'd file name added), exit code)
def _d_folder(b, t):
    return str(b / "folder")


def _d_missing(b, t):
    return str(t / "nope.csv")


def _d_binary(b, t):
    return write(t, "bin.csv", bytes(range(256)) * 4)


def _d_latin1(b, t):
    return write(t, "latin.csv", csv_from(lines_of(b)).replace("j1", "j1é").encode("latin-1"))


def _d_empty(b, t):
    return write(t, "empty.csv", "")


def _d_blank_only(b, t):
    return write(t, "blank.csv", "\n\n  \n")


def _d_header_only(b, t):
    return write(t, "hdr.csv", lines_of(b)[0] + "\n")


def _d_dup_column(b, t):
    ls = lines_of(b)
    return write(t, "dup.csv", csv_from([ls[0] + ",x"] + [ln + ",0.1" for ln in ls[1:]]))


def _d_semicolon_decimal_comma(b, t):
    ls = [ln.replace(",", ";").replace(".", ",") for ln in lines_of(b)]
    return write(t, "semi.csv", csv_from(ls))


def _d_missing_joint(b, t):
    ls = [",".join(ln.split(",")[:5] + ln.split(",")[6:]) for ln in lines_of(b)]
    return write(t, "nojoint.csv", csv_from(ls))


def _d_case(b, t):
    ls = lines_of(b)
    return write(t, "case.csv", csv_from([ls[0].replace("j1", "J1")] + ls[1:]))


def _d_case_xyz(b, t):
    ls = lines_of(b)
    return write(t, "casexyz.csv", csv_from([ls[0].replace("x,y,z", "X,Y,Z")] + ls[1:]))


def _d_nan(b, t):
    return write(t, "nan.csv", csv_from(replace_value(lines_of(b), 1, 2, "nan")))


def _d_text(b, t):
    return write(t, "text.csv", csv_from(replace_value(lines_of(b), 1, 2, "abc")))


def _d_empty_value(b, t):
    return write(t, "emptyval.csv", csv_from(replace_value(lines_of(b), 1, 2, "")))


def _d_inf(b, t):
    return write(t, "inf.csv", csv_from(replace_value(lines_of(b), 4, 7, "inf")))


def _d_ragged(b, t):
    ls = lines_of(b)
    ls[3] = ls[3] + ",1"
    return write(t, "ragged.csv", csv_from(ls))


def _d_blank_then_bad(b, t):
    ls = replace_value(lines_of(b), 2, 0, "oops")  # physical line 4 … after a blank line: line 5
    return write(t, "blankbad.csv", csv_from(ls[:2] + [""] + ls[2:]))


def _d_degrees(b, t):
    return write(t, "deg.csv", csv_from(scale_columns(lines_of(b), ["j2"], 180 / np.pi)))


def _d_12_8_rad(b, t):
    return write(t, "big.csv", csv_from(replace_value(lines_of(b), 3, 1, "12.8")))


def _d_homoglyph(b, t):
    ls = lines_of(b)
    return write(t, "homoglyph.csv", csv_from([ls[0].replace("j1", "\u04581", 1)] + ls[1:]))


def _d_still(b, t):
    hdr = lines_of(b)[0].split(",")
    ix = [hdr.index(c) for c in "xyz"]
    out = [lines_of(b)[0]]
    for i, ln in enumerate(lines_of(b)[1:]):
        f = ln.split(",")
        for k, c in enumerate(ix):
            f[c] = repr(0.3 + 0.1 * k + 1e-5 * ((i * 7 + k) % 5))  # a marker that does not move (10 µm jitter)
        out.append(",".join(f))
    return write(t, "still.csv", csv_from(out))


def _d_mm(b, t):
    return write(t, "mm.csv", csv_from(scale_columns(lines_of(b), ["x", "y", "z"], 1000)))


def _d_ten_times(b, t):
    return write(t, "x10.csv", csv_from(scale_columns(lines_of(b), ["x", "y", "z"], 10)))


def _d_tenth(b, t):
    return write(t, "x01.csv", csv_from(scale_columns(lines_of(b), ["x", "y", "z"], 0.1)))


def _d_xy_only(b, t):
    ls = [",".join(ln.split(",")[:-1]) for ln in lines_of(b)]
    return write(t, "xy.csv", csv_from(ls))


def _d_partial_quat(b, t):
    ls = [",".join(ln.split(",")[:-1]) for ln in lines_of(b, "pose.csv")]
    return write(t, "quat3.csv", csv_from(ls))


def _d_bad_quat(b, t):
    return write(t, "quatn.csv", csv_from(replace_value(lines_of(b, "pose.csv"), 2, 9, "0.9")))


def _d_points_gap(b, t):
    ls = lines_of(b, "pts.csv")
    return write(t, "gap.csv", csv_from([ls[0].replace("x2,y2,z2", "x4,y4,z4")] + ls[1:]))


def _d_point_no_z(b, t):
    ls = lines_of(b, "pts.csv")
    return write(t, "noz2.csv", csv_from([ls[0].replace("z2", "w2")] + ls[1:]))


def _d_numpy_comment(b, t):
    ls = lines_of(b)
    return write(t, "comment.csv", csv_from(["# " + ls[0]] + ls[1:]))


def _d_ambiguous(b, t):
    ls = lines_of(b)
    hdr = ls[0] + ",x1,y1,z1"
    return write(t, "ambig.csv", csv_from([hdr] + [ln + "," + ",".join(ln.split(",")[-3:]) for ln in ls[1:]]))


def _d_control(b, t):
    ls = lines_of(b)
    ls[2] = ls[2][:5] + "\x07" + ls[2][5:]
    return write(t, "ctrl.csv", csv_from(ls))


def _d_spaces(b, t):
    return write(t, "spaces.csv", csv_from([ln.replace(",", " ") for ln in lines_of(b)]))


def _d_identical(b, t):
    ls = lines_of(b)
    return write(t, "same.csv", csv_from([ls[0]] + [ls[1]] * 12))


def _d_three_rows(b, t):
    return write(t, "three.csv", csv_from(lines_of(b)[:4]))


def _d_concatenated(b, t):
    ls = lines_of(b)
    return write(t, "cat.csv", csv_from(ls[:8] + ls))  # `cat a.csv b.csv`: a header on line 9


def _with_column(name, values):
    def build(b, t):
        ls = lines_of(b)
        out = [ls[0] + f",{name}"] + [f"{line},{values(i)}" for i, line in enumerate(ls[1:])]
        return write(t, f"ctx_{name}.csv", csv_from(out))
    return build


DATA_CASES = {
    # id: (builder, message regex, exit code)
    "concatenated-files": (_d_concatenated, r"cat\.csv, line 9, column 'j1': value is 'j1', not a finite number — "
                                            r"the header is repeated here \(files concatenated", 2),
    "temperature-kelvin": (_with_column("temperature", lambda i: 293.15 + 0.1 * i),
                           r"ctx_temperature\.csv, line 2, column 'temperature': 293\.15 is outside \[-90, 200\] °C "
                           r"\(Kelvin\? subtract 273\.15\)", 2),
    "payload-negative": (_with_column("payload", lambda i: 2.0 if i != 4 else -1.5),
                         r"ctx_payload\.csv, line 6, column 'payload': -1\.5 kg — a mass cannot be negative", 2),
    "approach-not-sign": (_with_column("approach_j2", lambda i: 1 if i != 2 else 0),
                          r"ctx_approach_j2\.csv, line 4, column 'approach_j2': value 0 — an approach direction is "
                          r"\+1 or -1", 2),
    "folder": (_d_folder, r"folder: is a folder, not a dataset file", 2),
    "missing": (_d_missing, r"nope\.csv: dataset file not found", 2),
    "binary": (_d_binary, r"bin\.csv: binary file \(NUL byte at line 1\)", 2),
    "latin1": (_d_latin1, r"latin\.csv, line 1, column 3: byte 0xe9 is not UTF-8", 2),
    "empty": (_d_empty, r"empty\.csv: empty file", 2),
    "blank-only": (_d_blank_only, r"blank\.csv: empty file", 2),
    "header-only": (_d_header_only, r"hdr\.csv: header only, no data rows", 2),
    "duplicate-column": (_d_dup_column, r"dup\.csv, line 1: columns 7 and 10 are both named 'x'", 2),
    "semicolon-decimal-comma": (_d_semicolon_decimal_comma,
                                r"semi\.csv, line 2, column 'j1': value is '[-0-9]+,[0-9]+', not a finite number "
                                r"\(decimal comma\?", 2),
    "missing-joint": (_d_missing_joint, r"nojoint\.csv: missing joint column\(s\) \['j6'\]", 2),
    "case-joint": (_d_case, r"case\.csv: missing joint column\(s\) \['j1'\] \(column 'J1' differs only in case", 2),
    "case-xyz": (_d_case_xyz, r"casexyz\.csv, line 1, column 'X': column names are case-sensitive — rename it to 'x'",
                 2),
    "nan": (_d_nan, r"nan\.csv, line 3, column 'j3': value is 'nan', not a finite number", 2),
    "text": (_d_text, r"text\.csv, line 3, column 'j3': value is 'abc', not a finite number", 2),
    "empty-value": (_d_empty_value, r"emptyval\.csv, line 3, column 'j3': value is empty", 2),
    "inf": (_d_inf, r"inf\.csv, line 6, column 'y': value is 'inf', not a finite number", 2),
    "ragged": (_d_ragged, r"ragged\.csv, line 4: 10 fields but the header has 9", 2),
    "line-after-blank": (_d_blank_then_bad, r"blankbad\.csv, line 5, column 'j1': value is 'oops'", 2),
    "degrees": (_d_degrees, r"deg\.csv, line \d+, column 'j2': .* readings look like degrees", 2),
    "12.8-rad": (_d_12_8_rad, r"big\.csv, line 5, column 'j2': 12\.8 rad is beyond ±4π \(two turns\) — not a "
                              r"plausible joint angle", 2),
    "homoglyph-header": (_d_homoglyph, r"homoglyph\.csv, line 1, column 'ј1': reads like 'j1' but its 'ј' is U\+0458 "
                                       r"CYRILLIC SMALL LETTER JE, not 'j' \(U\+006A\) — a look-alike letter", 2),
    "positions-still": (_d_still, r"still\.csv: the measured positions do not move with the joints — they are "
                                  r"[0-9.e-]+ m apart", 2),
    "millimetres": (_d_mm, r"mm\.csv, line \d+, column '[xyz]': measured coordinate .* looks like millimetres", 2),
    "ten-times": (_d_ten_times, r"x10\.csv: the measured positions are .* m apart .* \(10×\) — wrong unit", 2),
    "tenth": (_d_tenth, r"x01\.csv: the measured positions are .* m apart .* \(0\.1×\) — wrong unit", 2),
    "xy-only": (_d_xy_only, r"xy\.csv, line 1: column\(s\) x, y without z", 2),
    "partial-quaternion": (_d_partial_quat, r"quat3\.csv, line 1: quaternion column\(s\) qw, qx, qy without qz", 2),
    "quaternion-norm": (_d_bad_quat, r"quatn\.csv, line 4: quaternion \(qw,qx,qy,qz\) has norm", 2),
    "points-gap": (_d_points_gap, r"gap\.csv, line 1: measured points are numbered \[1, 3, 4\]", 2),
    "point-without-z": (_d_point_no_z, r"noz2\.csv, line 1: point 2 has no column z2", 2),
    "numpy-comment": (_d_numpy_comment, r"comment\.csv, line 1: the header starts with '#'", 2),
    "ambiguous-points": (_d_ambiguous, r"ambig\.csv, line 1: both x,y,z and x1,y1,z1", 2),
    "control-character": (_d_control, r"ctrl\.csv, line 3, column 6: control character 0x07", 2),
    "space-separated": (_d_spaces, r"spaces\.csv: missing joint column.*separate the columns with", 2),
}
# degenerate data: numerical refusals (exit 3) for the commands that fit
FIT_CASES = {
    "identical-rows": (_d_identical, r"same\.csv: all rows have the same joint readings \(12 rows, lines 2–13\)", 3),
    "dof-zero": (_d_three_rows, r"three\.csv: 3 poses give 9 equations for 9 free parameters \(degrees of freedom "
                                r"0 ≤ 0\)", 3),
    # calibrate's refusal (estcal.estimate.checks, the `state` work package) names the repeated lines
    "identical-rows-calibrate": (_d_identical, r"same\.csv: only 1 distinct joint configuration\(s\) among 12 poses "
                                               r"\(repeated lines 3, 4, 5", 3),
}

DATA_COMMANDS = {
    "calibrate": lambda p, t: ["calibrate", p, "--robot", "puma560"],
    "fk": lambda p, t: ["fk", p, "--robot", "puma560", "-o", str(t / "fk_out.csv")],
    "online": lambda p, t: ["online", p, "--robot", "puma560"],
    "diagnose": lambda p, t: ["diagnose", p, "--robot", "puma560"],
    "identifiable": lambda p, t: ["identifiable", "--robot", "puma560", "--data", p],
}
# the structural cases on every command, the value cases on the two main ones
STRUCTURAL = ("folder", "missing", "binary", "latin1", "empty", "duplicate-column", "semicolon-decimal-comma",
              "missing-joint", "line-after-blank", "ten-times", "degrees")


def _data_params():
    out = []
    for cid in DATA_CASES:
        cmds = DATA_COMMANDS if cid in STRUCTURAL else ("calibrate", "fk")
        out += [pytest.param(cmd, cid, id=f"{cmd}-{cid}") for cmd in cmds]
    out += [pytest.param("calibrate", "identical-rows-calibrate", id="calibrate-identical-rows"),
            pytest.param("diagnose", "identical-rows", id="diagnose-identical-rows"),
            pytest.param("online", "identical-rows", id="online-identical-rows"),
            pytest.param("calibrate", "dof-zero", id="calibrate-dof-zero")]
    return out


def check(r, code, pattern):
    """No traceback, the exit code, the message on stderr (one line), nothing error-like on stdout."""
    assert r.exception is None or isinstance(r.exception, SystemExit), \
        f"unexpected {type(r.exception).__name__}: {r.exception}\n{r.output}"
    assert "Traceback" not in r.output
    assert r.exit_code == code, f"exit {r.exit_code} (expected {code}):\n{r.output}"
    err = r.stderr
    assert re.search(pattern, err), f"message does not match {pattern!r}:\n{err}"
    assert "error" not in r.stdout.lower(), f"error text on stdout:\n{r.stdout}"
    msg = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(msg) == 1, err


@pytest.mark.parametrize("command,case", _data_params())
def test_bad_dataset(base, tmp_path, command, case):
    builder, pattern, code = {**DATA_CASES, **FIT_CASES}[case]
    path = builder(base, tmp_path)
    r = runner.invoke(app, DATA_COMMANDS[command](path, tmp_path))
    check(r, code, pattern)


def test_number_of_cases():
    """The battery holds at least 120 malformed or degenerate inputs."""
    n = (len(_data_params()) + len(ROBOT_CASES) * len(ROBOT_COMMANDS) + len(OPTION_CASES) + len(URDF_CASES)
         + len(OTHER_FILE_CASES))
    assert n >= 120, n


# ------------------------------------------------------------------ datasets that must load
@pytest.mark.parametrize("variant", ["bom", "utf16", "semicolon", "tab", "crlf", "trailing-blank-lines",
                                     "pandas-index"])
def test_accepted_variants(base, tmp_path, variant):
    """Spreadsheet-style files that mean the same data are read (fk reproduces the same poses)."""
    ls = lines_of(base)
    text = csv_from(ls)
    if variant == "bom":
        data = codecs.BOM_UTF8 + text.encode()
    elif variant == "utf16":
        data = text.encode("utf-16")
    elif variant == "semicolon":
        data = text.replace(",", ";").encode()
    elif variant == "tab":
        data = text.replace(",", "\t").encode()
    elif variant == "crlf":
        data = text.replace("\n", "\r\n").encode()
    elif variant == "trailing-blank-lines":
        data = (text + "\n\n\n").encode()
    else:
        data = csv_from([","+ls[0]] + [f"{i},{ln}" for i, ln in enumerate(ls[1:])]).encode()
    p = tmp_path / "v.csv"
    p.write_bytes(data)
    ref, out = tmp_path / "ref.csv", tmp_path / "out.csv"
    assert runner.invoke(app, ["fk", str(base / "pos.csv"), "-r", "puma560", "-o", str(ref)]).exit_code == 0
    r = runner.invoke(app, ["fk", str(p), "-r", "puma560", "-o", str(out)])
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(np.loadtxt(out, delimiter=",", skiprows=1),
                                  np.loadtxt(ref, delimiter=",", skiprows=1))


# ------------------------------------------------------------------ bad robot files
def _yaml(b):
    return (b / "robot.yaml").read_text()


def _r(name, text_fn, ext=".yaml"):
    def build(b, t):
        content = text_fn(b)
        return write(t, name + ext, content)
    return build


ROBOT_CASES = {
    "folder": (lambda b, t: str(b / "folder"), r"folder: is a folder, not a robot"),
    "unknown-name": (lambda b, t: "right_hand",
                     r"unknown robot 'right_hand': not a built-in robot \(5r1p, planar2, puma560, puma560_fu, "
                     r"puma560_masses, stanford, tiago; parallel: left_hand\)"),
    "missing-yaml": (lambda b, t: str(t / "nope.yaml"), r"nope\.yaml: robot file not found"),
    "txt-file": (lambda b, t: write(t, "robot.txt", "hello"), r"robot\.txt: unknown robot file type '\.txt'"),
    "yaml-syntax": (_r("syntax", lambda b: _yaml(b).replace("joints:\n", "joints: [\n", 1)),
                    r"syntax\.yaml, line \d+, column \d+: invalid YAML"),
    "yaml-binary": (lambda b, t: write(t, "bin.yaml", b"\x00\x01\x02" * 50), r"bin\.yaml: binary file"),
    "yaml-latin1": (lambda b, t: write(t, "lat.yaml", _yaml(b).replace("puma560", "pumaé").encode("latin-1")),
                    r"lat\.yaml, line \d+, column \d+: byte 0xe9 is not UTF-8"),
    "yaml-not-mapping": (_r("list", lambda b: "- 1\n- 2\n"), r"list\.yaml: a robot file must be a YAML mapping"),
    "yaml-no-version": (_r("nover", lambda b: _yaml(b).replace("estcal_robot: 1\n", "")),
                        r"nover\.yaml: missing top-level key 'estcal_robot: 1'"),
    "joint-no-parameters": (_r("nopar", lambda b: re.sub(r"  theta: 0\.0\n  d: 0\.0\n  a: 0\.43179999999999996\n"
                                                         r"  alpha: 0\.0\n  beta: 0\.0\n", "", _yaml(b), count=1)),
                            r"nopar\.yaml: joint 'j2': no geometric parameters \(theta, d, a, alpha, beta\)"),
    "unknown-key": (_r("key", lambda b: _yaml(b).replace("  gain: 1.0\n", "  gian: 1.0\n", 1)),
                    r"key\.yaml: joint 'j1': unknown key 'gian' \(did you mean 'gain'\?\)"),
    "duplicate-joint": (_r("dupj", lambda b: _yaml(b).replace("name: j2", "name: j1", 1)),
                        r"dupj\.yaml: joint 'j1': duplicate joint name"),
    "limits-reversed": (_r("lim", lambda b: re.sub(r"limits: \[(-[0-9.e-]+), ([0-9.e-]+)\]", r"limits: [\2, \1]",
                                                   _yaml(b), count=1)),
                        r"lim\.yaml: joint 'j1': 'limits' must be \[lower, upper\] with lower < upper"),
    "not-a-number": (_r("nan", lambda b: _yaml(b).replace("  d: 0.3728974\n", "  d: abc\n", 1)),
                     r"nan\.yaml: joint 'j1': 'd' must be a number, got 'abc'"),
    "infinite": (_r("inf", lambda b: _yaml(b).replace("  d: 0.3728974\n", "  d: .inf\n", 1)),
                 r"inf\.yaml: joint 'j1': 'd' must be finite"),
    "ragged-coupling": (_r("coup", lambda b: _yaml(b) + "coupling: {joint: [[1, 0], [0]]}\n"),
                        r"coup\.yaml: coupling: 'joint' must be a 6x6 matrix of numbers"),
    "gain-zero": (_r("gain0", lambda b: _yaml(b).replace("  gain: 1.0\n", "  gain: 0.0\n", 1)),
                  r"gain0\.yaml: joint 'j1': 'gain' must be non-zero"),
    "length-in-mm": (_r("mm", lambda b: _yaml(b).replace("  d: 0.3728974\n", "  d: 372.8974\n", 1)),
                     r"mm\.yaml: joint 'j1': 'd' reaches 372\.897 m, beyond 50 m — are the lengths in millimetres\? "
                     r"add `units: \{length: mm\}`"),
    "angle-in-degrees": (_r("deg", lambda b: re.sub(r"  alpha: -1\.5707963\d*\n", "  alpha: -90\n", _yaml(b), count=1)),
                         r"deg\.yaml: joint 'j1': 'alpha' reaches 90 rad, beyond ±2π — are the angles in degrees\?"),
    "limits-in-degrees": (_r("limdeg", lambda b: re.sub(r"limits: \[(-[0-9.e-]+), ([0-9.e-]+)\]", "limits: [-160, 160]",
                                                        _yaml(b), count=1)),
                          r"limdeg\.yaml: joint 'j1': 'limits' reaches 160 rad, beyond ±4π"),
    "tool-in-mm": (_r("toolmm", lambda b: re.sub(r"tool:\n  xyz: \[[^]]*\]", "tool:\n  xyz: [0, 0, 56.25]", _yaml(b),
                                                 count=1)),
                   r"toolmm\.yaml: tool: 'xyz' reaches 56\.25 m, beyond 50 m"),
    "unknown-unit": (_r("unit", lambda b: _yaml(b).replace("name: puma560\n", "name: p\nunits: {length: ft}\n")),
                     r"unit\.yaml: units: unknown length unit 'ft'"),
}
ROBOT_COMMANDS = {
    "calibrate": lambda rb, b, t: ["calibrate", str(b / "pos.csv"), "--robot", rb],
    "fk": lambda rb, b, t: ["fk", str(b / "pos.csv"), "--robot", rb, "-o", str(t / "o.csv")],
    "design": lambda rb, b, t: ["design", "--robot", rb, "--n", "30"],
    "identifiable": lambda rb, b, t: ["identifiable", "--robot", rb, "--measure", "position"],
    "simulate": lambda rb, b, t: ["simulate", "--robot", rb, "--n", "5"],
}


@pytest.mark.parametrize("command", ROBOT_COMMANDS)
@pytest.mark.parametrize("case", ROBOT_CASES)
def test_bad_robot(base, tmp_path, command, case):
    builder, pattern = ROBOT_CASES[case]
    r = runner.invoke(app, ROBOT_COMMANDS[command](builder(base, tmp_path), base, tmp_path))
    check(r, 2, pattern)


@pytest.mark.parametrize("command", ["fk", "design", "simulate", "demo"])
def test_parallel_platform_in_a_serial_command(base, tmp_path, command):
    """The built-in Gough platform is named as such where only serial robots make sense."""
    args = {"fk": ROBOT_COMMANDS["fk"]("left_hand", base, tmp_path),
            "design": ROBOT_COMMANDS["design"]("left_hand", base, tmp_path),
            "simulate": ROBOT_COMMANDS["simulate"]("left_hand", base, tmp_path),
            "demo": ["demo", "--robot", "left_hand"]}[command]
    check(runner.invoke(app, args), 2, r"left_hand: is a Gough–Stewart \(parallel\) platform — this command needs "
                                       r"a serial robot")


# ------------------------------------------------------------------ bad URDF
def urdf(joints: str, links=("base", "l1", "l2")) -> str:
    lk = "".join(f'<link name="{n}"/>' for n in links)
    return f'<?xml version="1.0"?><robot name="r">{lk}{joints}</robot>'


def _joint(name, parent, child, typ="revolute", limit='<limit lower="-1" upper="1" effort="1" velocity="1"/>'):
    return (f'<joint name="{name}" type="{typ}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="0 0 1"/>{limit}</joint>')


GOOD_URDF = urdf(_joint("a", "base", "l1") + _joint("b", "l1", "l2"))
URDF_CASES = {
    "two-parents": (urdf(_joint("a", "base", "l1") + _joint("b", "l1", "l2") + _joint("c", "base", "l2")),
                    [], r"two\.urdf: link 'l2' has two parent joints \('b' and 'c'\) — a URDF must be a tree"),
    "bad-xml": ("<robot name='r'><link name='a'></robot>", [],
                r"bad\.urdf, line 1, column \d+: not valid XML \(mismatched tag"),
    "not-a-robot": ("<?xml version='1.0'?><foo/>", [], r"foo\.urdf: the top element is <foo>, a URDF's is <robot>"),
    "joint-without-child": (urdf(_joint("a", "base", "l1").replace('<child link="l1"/>', "")), [],
                            r"nochild\.urdf: joint 'a' has no <child link=\"…\"/>"),
    "no-limit": (urdf(_joint("a", "base", "l1") + _joint("b", "l1", "l2", limit="")), [],
                 r"nolim\.urdf: joint 'b' \(revolute\) has no <limit lower=… upper=…>"),
    "undeclared-link": (urdf(_joint("a", "base", "l1") + _joint("b", "l1", "l9")), [],
                        r"undecl\.urdf: joint 'b': child link 'l9' is not declared"),
    "wrong-tip": (GOOD_URDF, ["--tip", "l3"], r"good\.urdf: tip link 'l3' is not in the URDF; links include "
                                              r"\['base', 'l1', 'l2'\]"),
    "wrong-root": (GOOD_URDF, ["--root", "bse", "--tip", "l2"],
                   r"root link 'bse' is not in the URDF \(did you mean 'base'\?\)"),
    "binary": (b"\x00\xff" * 100, [], r"bin\.urdf: binary file"),
    "zero-axis": (GOOD_URDF.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>', 1), [],
                  r"axis\.urdf: joint 'a': <axis xyz> must be a non-zero 3-vector"),
    "origin-in-mm": (GOOD_URDF.replace('<origin xyz="0 0 0.1"', '<origin xyz="0 0 100"', 1), [],
                     r"mm\.urdf: joint 'a': <origin xyz> reaches 100 m, beyond 50 m — URDF lengths are metres"),
    "limit-in-degrees": (GOOD_URDF.replace('lower="-1" upper="1"', 'lower="-170" upper="170"', 1), [],
                         r"deg\.urdf: joint 'a': <limit> \[-170, 170\] is beyond ±4π rad — URDF angles are radians"),
}
_URDF_FILE = {"two-parents": "two", "bad-xml": "bad", "not-a-robot": "foo", "joint-without-child": "nochild", "no-limit": "nolim", "undeclared-link": "undecl",
              "wrong-tip": "good", "wrong-root": "good", "binary": "bin", "zero-axis": "axis",
              "origin-in-mm": "mm", "limit-in-degrees": "deg"}


@pytest.mark.parametrize("case", URDF_CASES)
def test_bad_urdf(base, tmp_path, case):
    content, extra, pattern = URDF_CASES[case]
    path = write(tmp_path, _URDF_FILE[case] + ".urdf", content)
    data = write(tmp_path, "q.csv", "a,b\n0.1,0.2\n0.3,-0.4\n")
    r = runner.invoke(app, ["fk", data, "--robot", path, "-o", str(tmp_path / "o.csv")] + extra)
    check(r, 2, pattern)


def test_urdf_default_root_and_tip(tmp_path):
    """The documented defaults: root = the URDF's root link, tip = its only leaf."""
    path = write(tmp_path, "good.urdf", GOOD_URDF)
    data = write(tmp_path, "q.csv", "a,b\n0,0\n")
    out = tmp_path / "o.csv"
    r = runner.invoke(app, ["fk", data, "--robot", path, "-o", str(out)])
    assert r.exit_code == 0, r.output
    np.testing.assert_allclose(np.loadtxt(out, delimiter=",", skiprows=1)[:3], [0, 0, 0.2], atol=1e-12)


# ------------------------------------------------------------------ bad options
def _opt(cmd, b, t):
    """Argument lists of each command with good inputs; the case appends the bad option."""
    pos = str(b / "pos.csv")
    return {"calibrate": ["calibrate", pos, "-r", "puma560"],
            "fk": ["fk", pos, "-r", "puma560", "-o", str(t / "o.csv")],
            "online": ["online", pos, "-r", "puma560"],
            "diagnose": ["diagnose", pos, "-r", "puma560"],
            "design": ["design", "-r", "puma560", "--n", "30"],
            "identifiable": ["identifiable", "-r", "puma560", "--measure", "position"],
            "simulate": ["simulate", "-r", "puma560", "--n", "5"],
            "demo": ["demo"],
            "next-pose": ["next-pose", "-r", "puma560", "--state", str(t / "state.json")]}[cmd]


OPTION_CASES = {
    "online-every-0": ("online", ["--every", "0"], r"--every 0: must be an integer ≥ 1"),
    "online-q-negative": ("online", ["--q", "-1"], r"--q -1: must be a number ≥ 0"),
    "online-sigma-p-zero": ("online", ["--sigma-p", "0"], r"--sigma-p 0: must be a number > 0"),
    "online-prior-negative": ("online", ["--prior-std", "-0.1"], r"--prior-std -0\.1: must be a number > 0"),
    "online-show-negative": ("online", ["--show", "-1"], r"--show -1: must be an integer ≥ 0"),
    "online-filter": ("online", ["--filter", "pf"], r"pf"),
    "online-free-no-effect": ("online", ["--free", "offset_*"],
                              r"--free: .*pos\.csv: parameters without effect on these measurements: \['offset_6'\]"),
    "online-free-dependent": ("online", ["--free", "theta_2,theta_3,offset_2"],
                              r"--free: .*pos\.csv: 1 of the 3 free parameters are not identifiable from these data"),
    "online-free-unknown": ("online", ["--free", "nosuch"], r"--free: unknown parameter 'nosuch'"),
    "online-state-folder": ("online", ["--state", "{folder}"], r"--state .*folder: is a folder — give a file name"),
    "online-state-is-input": ("online", ["--state", "{pos}"], r"--state .*pos\.csv: is also an input file"),
    "calibrate-noise-zero": ("calibrate", ["--noise-pos", "0"], r"--noise-pos 0: must be a number > 0"),
    "calibrate-noise-negative": ("calibrate", ["--noise-pos", "-1e-4"], r"--noise-pos -0\.0001: must be a number > 0"),
    "calibrate-noise-nan": ("calibrate", ["--noise-rot", "nan"], r"--noise-rot nan: must be a finite number"),
    "calibrate-noise-inf": ("calibrate", ["--noise-pos", "inf"], r"--noise-pos inf: must be a finite number"),
    "calibrate-points-zero": ("calibrate", ["--points", "0"], r"--points 0: must be an integer ≥ 1"),
    "calibrate-json-folder": ("calibrate", ["--json", "{folder}"], r"--json .*folder: is a folder — give a file name"),
    "calibrate-json-under-file": ("calibrate", ["--json", "{pos}/r.json"], r"--json .*pos\.csv/r\.json: .*pos\.csv is a "
                                                                           r"file, not a folder"),
    "calibrate-json-is-input": ("calibrate", ["--json", "{pos}"], r"--json .*pos\.csv: is also an input file of this command"),
    "calibrate-level": ("calibrate", ["--level", "everything"], r"unknown --level 'everything'"),
    "calibrate-estimator": ("calibrate", ["--estimator", "magic"], r"unknown estimator 'magic'"),
    "calibrate-method": ("calibrate", ["--method", "magic"], r"unknown --method 'magic'"),
    "calibrate-free-empty": ("calibrate", ["--free", ","], r"--free is empty"),
    "calibrate-free-unknown": ("calibrate", ["--free", "nosuch_param"], r"--free: .*nosuch_param"),
    "calibrate-regularize": ("calibrate", ["--regularize", "-1"], r"--regularize"),
    "calibrate-option-syntax": ("calibrate", ["--option", "q"], r"--option 'q': expected KEY=VALUE"),
    "calibrate-robust": ("calibrate", ["--robust", "tukey"], r"--robust must be huber or cauchy"),
    "calibrate-option-count": ("calibrate", ["--option", "max_iter=-5"],
                               r"estimator 'lm', option max_iter=-5: must be an integer ≥ 1"),
    "calibrate-option-tol-nan": ("calibrate", ["--option", "tol=nan"], r"option tol=nan: must be a finite number > 0"),
    "calibrate-option-q": ("calibrate", ["--estimator", "kalman", "--option", "q=-1"],
                           r"estimator 'kalman', option q=-1: must be a finite number ≥ 0"),
    "calibrate-option-level": ("calibrate", ["--estimator", "mcmc", "--option", "level=1"],
                               r"option level=1: must be a number strictly between 0 and 1"),
    "calibrate-chain-folder": ("calibrate", ["--estimator", "mcmc", "--chain", "{folder}"],
                               r"--chain .*folder: is a folder — give a file name \(e\.g\. .*chain\.h5\)"),
    "calibrate-chain-is-input": ("calibrate", ["--estimator", "mcmc", "--chain", "{pos}"],
                                 r"--chain .*pos\.csv: is also an input file"),
    "calibrate-chain-not-hdf5": ("calibrate", ["--estimator", "mcmc", "--option", "chain={badjson}"],
                                 r"bad\.json: not an HDF5 file — estcal creates the chain file"),
    "calibrate-validate-missing": ("calibrate", ["--validate", "{tmp}/nope.csv"], r"nope\.csv: dataset file not found"),
    "calibrate-validate-folder": ("calibrate", ["--validate", "{folder}"], r"folder: is a folder, not a dataset file"),
    "calibrate-validate-is-data": ("calibrate", ["--validate", "{pos}"],
                                   r"--validate .*pos\.csv: all its 24 poses are also in .*pos\.csv .*held-out"),
    "calibrate-free-summary": ("calibrate", ["--free", "theta_9"],
                               r"--free: unknown parameter 'theta_9'.* 54 parameters: .*theta.*_\{1, 2, 3, 4, 5, 6\}"),
    "diagnose-validate-is-data": ("diagnose", ["--validate", "{pos}"], r"--validate .*pos\.csv: all its 24 poses"),
    "identifiable-free-unknown": ("identifiable", ["--free", "nosuch"], r"--free: unknown parameter 'nosuch'\. "
                                                                        r"This model has 54 parameters"),
    "fk-output-stdout": ("fk", ["-o", "-"], r"--output -: output files are written atomically and cannot go to "
                                            r"standard output"),
    "simulate-json-stdout": ("simulate", ["--json", "-"], r"--json -: .*give a file name"),
    "fk-output-is-input": ("fk", ["-o", "{pos}"], r"--output .*pos\.csv: is also an input file of this command"),
    "fk-output-folder": ("fk", ["-o", "{folder}"], r"--output .*folder: is a folder"),
    "fk-json-folder": ("fk", ["--json", "{folder}"], r"--json .*folder: is a folder"),
    "fk-json-same-as-output": ("fk", ["--json", "{tmp}/o.csv"], r"the same file as --output"),
    "diagnose-folds-1": ("diagnose", ["--folds", "1"], r"--folds 1: must be an integer ≥ 2"),
    "diagnose-alpha": ("diagnose", ["--alpha", "1.5"], r"belonged to the former diagnosis.*drop the option"),
    "diagnose-max-effects": ("diagnose", ["--max-effects", "0"], r"belonged to the former diagnosis.*drop the option"),
    "diagnose-width-zero": ("diagnose", ["--geometric-width-mm", "0"],
                            r"--geometric-width-mm 0: give auto \(the default\), inf \(unbounded\) or a number > 0"),
    "diagnose-effects": ("diagnose", ["--effects", "magic"], r"--effects: unknown effect\(s\) \['magic'\]"),
    "diagnose-noise-zero": ("diagnose", ["--noise-pos", "0"], r"--noise-pos 0: must be a number > 0"),
    "diagnose-json-folder": ("diagnose", ["--json", "{folder}"], r"--json .*folder: is a folder"),
    "diagnose-report-is-file": ("diagnose", ["--report", "{pos}"], r"--report .*pos\.csv: is a file — give a folder"),
    "design-n-zero": ("design", ["--n", "0"], r"--n 0: must be an integer ≥ 1"),
    "design-restarts-zero": ("design", ["--restarts", "0"], r"--restarts 0: must be an integer ≥ 1"),
    "design-sigma-zero": ("design", ["--sigma", "0"], r"--sigma 0: must be a number > 0"),
    "design-random-plans": ("design", ["--random-plans", "0"], r"--random-plans 0: must be an integer ≥ 1"),
    "design-candidates-count": ("design", ["--n-candidates", "-5"], r"--n-candidates -5: must be an integer ≥ 1"),
    "design-criterion": ("design", ["--criterion", "Q"], r"criterion"),
    "design-map": ("design", ["--map", "-1"], r"--map -1: must be an integer ≥ 0"),
    "design-test-pose": ("design", ["--test-pose", "1,2"], r"--test-pose '1,2': expected 6 values"),
    "design-candidates-missing": ("design", ["--candidates", "{tmp}/nope.csv"], r"nope\.csv"),
    "identifiable-n-poses": ("identifiable", ["--n-poses", "0"], r"--n-poses 0: must be an integer ≥ 1"),
    "identifiable-plane": ("identifiable", ["--plane", "a,b"], r"--plane expects three numbers"),
    "identifiable-method": ("identifiable", ["--measure", "magic"], r"magic"),
    "identifiable-seed": ("identifiable", ["--seed", "-3"], r"--seed -3: must be an integer ≥ 0"),
    "identifiable-plane-zero": ("identifiable", ["--measure", "plane-known", "--plane", "0,0,0"],
                                r"--plane 0,0,0: a, b, c must be finite and not all zero"),
    "identifiable-priority-folder": ("identifiable", ["--priority", "{folder}"],
                                     r"folder: is a folder, not a priority file"),
    "identifiable-priority-yaml": ("identifiable", ["--priority", "{badjson}"],
                                   r"bad\.json, line 1, column \d+: invalid YAML in the priority file"),
    "simulate-n-zero": ("simulate", ["--n", "0"], r"--n 0: must be an integer ≥ 1"),
    "simulate-noise-negative": ("simulate", ["--noise-pos", "-1"], r"--noise-pos -1: must be a number ≥ 0"),
    "simulate-margin": ("simulate", ["--margin", "0.7"], r"--margin 0\.7: must be a number in \[0, 0\.5\)"),
    "simulate-dt": ("simulate", ["--dt", "0"], r"--dt 0: must be a number > 0"),
    "simulate-errors-missing": ("simulate", ["--errors", "{tmp}/nope.json"],
                                r"--errors must be 'random', 'none' or a JSON/YAML file .*nope\.json' is none"),
    "simulate-errors-bad-json": ("simulate", ["--errors", "{badjson}"],
                                 r"bad\.json, line 1, column \d+: invalid JSON in the errors file"),
    "simulate-output-folder": ("simulate", ["-o", "{folder}"], r"--output .*folder: is a folder"),
    "demo-robot": ("demo", ["--robot", "nosuch"], r"unknown robot 'nosuch'"),
    "demo-n-zero": ("demo", ["--n", "0"], r"--n 0: must be an integer ≥ 1"),
    "next-pose-state-missing": ("next-pose", [], r"state\.json: state file not found"),
    "next-pose-state-bad-json": ("next-pose", ["--state", "{badjson}"],
                                 r"bad\.json, line 1, column \d+: invalid JSON in the state file"),
    "next-pose-state-binary": ("next-pose", ["--state", "{binjson}"], r"bin\.json: binary file"),
    "next-pose-state-other-robot": ("next-pose", ["--state", "{stanford_state}"],
                                    r"stanford_state\.json: 2 of the state's 3 parameters are not parameters of robot "
                                    r"'puma560' \(r_1, alpha_0\) — was the state written for another robot\?"),
    "next-pose-sigma": ("next-pose", ["--state", "{badjson}", "--sigma", "-1"], r"--sigma -1: must be a number > 0"),
}


@pytest.mark.parametrize("case", OPTION_CASES)
def test_bad_option(base, tmp_path, case):
    cmd, extra, pattern = OPTION_CASES[case]
    (tmp_path / "bad.json").write_text('{"parameters": [1, 2,,]}')
    (tmp_path / "bin.json").write_bytes(b"\x00" * 20)
    (tmp_path / "stanford_state.json").write_text(json.dumps({"parameters": ["r_1", "alpha_0", "theta_1"],
                                                               "estimate": [0, 0, 0], "covariance": np.eye(3).tolist(),
                                                               "robot": "stanford"}))
    fill = {"folder": str(base / "folder"), "pos": str(base / "pos.csv"), "tmp": str(tmp_path),
            "badjson": str(tmp_path / "bad.json"), "binjson": str(tmp_path / "bin.json"),
            "stanford_state": str(tmp_path / "stanford_state.json")}
    args = [a.format(**fill) for a in extra]
    base_args = _opt(cmd, base, tmp_path)
    if "--state" in extra and "--state" in base_args:  # the case's state file replaces the default one
        i = base_args.index("--state")
        base_args = base_args[:i] + base_args[i + 2:]
    r = runner.invoke(app, base_args + args)
    code = 2
    check(r, code, pattern)


# ------------------------------------------------------------------ other input files
OTHER_FILE_CASES = {
    "candidates-binary": (["design", "-r", "puma560", "--n", "30", "--candidates", "{f}"], b"\x00\x01" * 30,
                          r"binary file"),
    "errors-yaml-syntax": (["simulate", "--n", "5", "--errors", "{f}"], "a: [1,\n", r"invalid YAML"),
    "errors-not-number": (["simulate", "--n", "5", "--errors", "{f}"], '{"theta_2": "big"}',
                          r"error of 'theta_2' must be a finite number"),
    "from-fit-not-fit": (["simulate", "--n", "5", "--from-fit", "{f}"], '{"a": 1}', r"not a diagnosis fit"),
    "errors-degrees": (["simulate", "--n", "5", "--errors", "{f}"], '{"theta_2": 90}',
                       r"in\.json: the error of 'theta_2' is 90 rad \(degrees\?\) — the file is in SI units"),
    "errors-millimetres": (["simulate", "--n", "5", "--errors", "{f}"], '{"d_3": 2.5}',
                           r"in\.json: the error of 'd_3' is 2\.5 m \(millimetres\?\)"),
    "errors-unknown-name": (["simulate", "--n", "5", "--errors", "{f}"], '{"theta_9": 0.001}',
                            r"in\.json: unknown parameter 'theta_9'\. Did you mean"),
}
_OTHER_EXT = {"candidates-binary": ".csv", "errors-yaml-syntax": ".yaml", "errors-not-number": ".json",
              "from-fit-not-fit": ".json", "errors-degrees": ".json", "errors-millimetres": ".json",
              "errors-unknown-name": ".json"}


@pytest.mark.parametrize("case", OTHER_FILE_CASES)
def test_bad_other_file(tmp_path, case):
    args, content, pattern = OTHER_FILE_CASES[case]
    f = write(tmp_path, "in" + _OTHER_EXT[case], content)
    r = runner.invoke(app, [a.format(f=f) for a in args])
    check(r, 2, pattern)


@pytest.mark.parametrize("args,pattern", [
    (["compensate", "{folder}", "-r", "puma560", "-o", "{tmp}/c.csv"], r"folder: is a folder, not a targets file"),
    (["compensate", "{bin}", "-r", "puma560", "-o", "{tmp}/c.csv"], r"bin\.csv: binary file"),
    (["compensate", "{pos}", "-r", "puma560", "-o", "{pos}"], r"--output .*pos\.csv: is also an input"),
    (["compensate", "{pos}", "-r", "puma560", "-o", "{tmp}/c.csv", "--tol-mm", "0"], r"--tol-mm 0: must be a number > 0"),
    (["export", "-r", "puma560", "--urdf", "{folder}"], r"--urdf .*folder: is a folder — give a file name \(e\.g\. "
                                                         r".*robot\.urdf\)"),
    (["export", "-r", "{folder}", "--urdf", "{tmp}/r.urdf"], r"folder: is a folder, not a robot"),
    (["simulate", "--fleet", "2", "--out", "{pos}"], r"--out .*pos\.csv: is a file — give a folder"),
    (["sessions", "{pos}", "{copy}", "-r", "puma560"], r"session .*copy\.csv: all its 24 poses are also in "
                                                        r".*pos\.csv .*give each session's own file"),
    (["sessions", "{pos}", "-r", "puma560", "--validate", "{copy}"], r"--validate .*copy\.csv: all its 24 poses"),
], ids=["compensate-folder", "compensate-binary", "compensate-output-is-input", "compensate-tol", "export-urdf-folder",
        "export-robot-folder", "fleet-out-is-file", "sessions-same-file-twice", "sessions-validate-copy"])
def test_other_commands_share_the_checks(base, tmp_path, args, pattern):
    """Commands of other work packages get the same input layer and option checks."""
    (tmp_path / "bin.csv").write_bytes(b"\x00" * 30)
    (tmp_path / "copy.csv").write_bytes((base / "pos.csv").read_bytes())
    fill = {"folder": str(base / "folder"), "pos": str(base / "pos.csv"), "tmp": str(tmp_path),
            "bin": str(tmp_path / "bin.csv"), "copy": str(tmp_path / "copy.csv")}
    check(runner.invoke(app, [a.format(**fill) for a in args]), 2, pattern)


def test_validation_sharing_some_fitted_rows_is_named(base, tmp_path):
    """A validation file that repeats some fitted poses is scored, with a warning naming their lines."""
    lines = lines_of(base)
    rb = load_robot("puma560")
    q = rb.random_readings(10, np.random.default_rng(7))
    new = tmp_path / "new.csv"
    write_dataset(new, dataset_from_arrays(rb.joint_names, q, points=rb.kinematics(q, jacobian=False).p))
    mixed = new.read_text().splitlines() + [lines[3], lines[5]]  # fitted rows 3 and 5 appended as lines 12, 13
    v = write(tmp_path, "mixed.csv", csv_from(mixed))
    r = runner.invoke(app, ["calibrate", str(base / "pos.csv"), "-r", "puma560", "--level", "joint_offset",
                            "--validate", v])
    assert r.exit_code == 0, r.output
    assert re.search(r"warning: --validate .*mixed\.csv: 2 of its 12 poses \(lines 12, 13\) are also in .*pos\.csv",
                     r.stderr), r.stderr


# ------------------------------------------------------------------ outputs
def _strict(text):
    def no(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=no)


def test_json_is_strict_when_values_are_undefined(base, tmp_path):
    """online's first status lines have an undefined running NIS (NaN): the JSON still parses strictly."""
    out = tmp_path / "o.json"
    r = runner.invoke(app, ["online", str(base / "pos.csv"), "-r", "puma560", "--every", "1", "--free",
                            "base_*", "--json", str(out)])
    assert r.exit_code == 0, r.output
    d = _strict(out.read_text())
    assert any(h["nis_per_row"] is None for h in d["history"])  # NaN written as null
    assert len(d["history"]) == N_GOOD


def test_write_json_strict(tmp_path):
    from estcal.base.jsonio import write_json

    p = write_json(tmp_path / "a.json", {"a": float("nan"), "b": [np.inf, 1.0], "c": np.array([np.nan, 2.0]),
                                         "d": np.float64("-inf")})
    assert _strict(p.read_text()) == {"a": None, "b": [None, 1.0], "c": [None, 2.0], "d": None}


def test_failed_check_leaves_no_output_and_input_intact(base, tmp_path):
    """A refused output path is refused before the work; the input is never touched."""
    src = tmp_path / "in.csv"
    src.write_bytes((base / "pos.csv").read_bytes())
    before = src.read_bytes()
    r = runner.invoke(app, ["fk", str(src), "-r", "puma560", "-o", str(src)])
    check(r, 2, r"is also an input")
    assert src.read_bytes() == before
    out = tmp_path / "new.csv"
    r = runner.invoke(app, ["fk", str(src), "-r", "puma560", "-o", str(out), "--json", str(base / "folder")])
    check(r, 2, r"--json .*folder: is a folder")
    assert not out.exists()  # checked before the work: nothing half-written


# ------------------------------------------------------------------ real process: exit codes and streams
def _run(*args, stdin=None):
    return subprocess.run([sys.executable, "-m", "estcal.cli.main", *args], capture_output=True, text=True,
                          input=stdin, timeout=120)


def test_subprocess_exit_codes_and_streams(base, tmp_path):
    r = _run("calibrate", str(base / "folder"), "--robot", "puma560")
    assert r.returncode == 2 and r.stdout == "" and "Traceback" not in r.stderr
    assert r.stderr.startswith("error: ") and "is a folder, not a dataset file" in r.stderr
    same = _d_identical(base, tmp_path)
    r = _run("calibrate", same, "--robot", "puma560")
    assert r.returncode == 3 and "only 1 distinct joint configuration" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("args,pattern", [
    (["calibrate", "--nosuch"], r"error: estcal calibrate: No such option: --nosuch — see `estcal calibrate --help`"),
    (["calibrate", "d.csv", "--robot", "puma560", "--noise-pos-mm", "abc"],
     r"error: estcal calibrate: Invalid value for '--noise-pos-mm': .*number — see `estcal calibrate --help`"),
    (["nosuchcommand"], r"error: estcal: No such command 'nosuchcommand' — see `estcal --help`"),
    (["fk", "d.csv", "--robot", "puma560"], r"error: estcal fk: Missing option '--output' / '-o' — see `estcal fk --help`"),
])
def test_usage_errors_are_one_line(args, pattern):
    """Click's own usage errors (unknown option or command, a value of the wrong type, a missing
    option) come as one line on stderr with exit code 2, like estcal's own messages."""
    r = _run(*args)
    assert r.returncode == 2 and r.stdout == "", r
    assert len(r.stderr.strip().splitlines()) == 1 and re.fullmatch(pattern, r.stderr.strip()), r.stderr


def test_help_and_bare_command_still_show_help():
    r = _run("fk", "--help")
    assert r.returncode == 0 and "Usage: estcal fk" in r.stdout
    r = _run()
    assert "Usage: estcal" in r.stdout and "Traceback" not in r.stderr


def test_subprocess_online_stdin(base):
    """The streaming path gets the loader's checks: a row in degrees is refused with its line."""
    ls = lines_of(base)
    bad = replace_value(ls, 3, 1, "57.3")
    bad = replace_value(bad, 3, 2, "-80")
    r = _run("online", "-", "--robot", "puma560", "--free", "base_*", stdin=csv_from(bad[:6]))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert re.search(r"<stdin>, line 5, column 'j2': 57\.3 rad is beyond ±4π", r.stderr), r.stderr


def test_online_stdin_binary():
    r = runner.invoke(app, ["online", "-", "--robot", "puma560"], input="j1,j2\n\x01\x02,3\n")
    check(r, 2, r"<stdin>, line 2, column 1: control character 0x01 — binary data")


def test_online_stdin_header_checked(base):
    ls = lines_of(base)
    r = runner.invoke(app, ["online", "-", "--robot", "puma560", "--free", "base_*"],
                      input=csv_from([ls[0] + ",x"] + ls[1:3]))
    check(r, 2, r"<stdin>, line 1: columns 7 and 10 are both named 'x'")


def test_next_pose_warns_when_the_state_names_another_robot(tmp_path):
    """A state whose names all exist in the robot but that was computed for another one is used, with a warning."""
    names = ["theta_2", "d_3"]
    f = tmp_path / "s.json"
    f.write_text(json.dumps({"parameters": names, "estimate": [0, 0], "covariance": (1e-6 * np.eye(2)).tolist(),
                             "robot": "puma560"}))
    r = runner.invoke(app, ["next-pose", "-r", "puma560_fu", "--state", str(f), "--n-candidates", "20"])
    assert r.exit_code == 0, r.output
    assert re.search(r"warning: .*s\.json: the state was computed for robot 'puma560', not 'puma560_fu'", r.stderr)
    r = runner.invoke(app, ["next-pose", "-r", "puma560", "--state", str(f), "--n-candidates", "20"])
    assert r.exit_code == 0 and "warning" not in r.stderr, r.stderr


@pytest.mark.parametrize("args,pattern", [
    (["demo", "--n", "4"], r"numerical refusal: --n 4: the simulated calibration set: 4 poses give 24 equations for "
                           r"24 free parameters \(degrees of freedom 0 ≤ 0\)"),
    (["design", "-r", "puma560", "--n", "30", "--candidates", "{five}"],
     r"numerical refusal: --candidates .*five\.csv: its 5 poses \(5 distinct\) determine only 15 of the 25 free "
     r"parameters"),
], ids=["demo-dof-zero", "design-candidates-rank"])
def test_degenerate_requests_are_refused(base, tmp_path, args, pattern):
    """Simulated or candidate data that cannot determine the parameters: exit 3, not a printed result."""
    five = write(tmp_path, "five.csv", csv_from(lines_of(base)[:6]))
    check(runner.invoke(app, [a.format(five=five) for a in args]), 3, pattern)


def test_identifiable_from_too_few_rows_warns(base, tmp_path):
    """A data-level analysis on fewer equations than parameters says that the data, not the robot, limit it."""
    two = write(tmp_path, "two.csv", csv_from(lines_of(base)[:3]))
    r = runner.invoke(app, ["identifiable", "-r", "puma560", "--data", two])
    assert r.exit_code == 0, r.output
    assert re.search(r"warning: .*two\.csv: 6 equations \(2 poses\) for 54 parameters — at most 6 can be identifiable",
                     r.stderr), r.stderr
    assert "6 of 54 parameters identifiable" in r.stdout
    r = runner.invoke(app, ["identifiable", "-r", "puma560", "--data", str(base / "pos.csv")])
    assert r.exit_code == 0 and "warning" not in r.stderr, r.stderr


def test_simulate_refuses_what_memory_cannot_hold(tmp_path, monkeypatch):
    """The estimate (bytes per pose × --n) against the memory available: refused before the work."""
    import estcal.workflows.simulate as sim

    monkeypatch.setattr(sim, "available_memory", lambda: 10 * 1000 * sim.BYTES_PER_POSE)  # room for 8,000 poses
    out = tmp_path / "s.csv"
    r = runner.invoke(app, ["simulate", "--n", "9000", "-o", str(out)])
    check(r, 2, r"--n 9000: simulating 9,000 poses needs about 0\.0 GB of memory and 0\.0 GB are available")
    assert not out.exists()
    r = runner.invoke(app, ["simulate", "--n", "7000", "-o", str(out)])
    assert r.exit_code == 0 and out.exists(), r.output


def test_available_memory_reads_meminfo():
    import estcal.workflows.simulate as sim

    avail = sim.available_memory()
    if avail is None:
        pytest.skip("no /proc/meminfo")
    import os

    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")  # an independent reading
    assert 0 < avail <= total


def test_fleet_outputs_never_land_on_a_robots_inputs(tmp_path):
    """The files the fleet's robots read are inputs; a broken robot is reported by its loader's message."""
    fl = tmp_path / "fl"
    assert runner.invoke(app, ["simulate", "--fleet", "2", "--out", str(fl), "--n", "20"]).exit_code == 0
    data = fl / "robot_0000" / "data.csv"
    before = data.read_bytes()
    check(runner.invoke(app, ["fleet", str(fl), "--json", str(data)]), 2,
          r"--json .*robot_0000/data\.csv: is also an input file of this command")
    check(runner.invoke(app, ["fleet", str(fl), "--save-models", str(data)]), 2,
          r"--save-models .*data\.csv: is a file — give a folder")
    assert data.read_bytes() == before
    (fl / "robot_0001" / "data.csv").write_bytes(b"\x00\x00")
    r = runner.invoke(app, ["fleet", str(fl), "--json", str(fl / "summary.json")])
    assert r.exit_code == 0, r.output
    assert re.search(r"failed: robot_0001 .*DatasetError: .*robot_0001/data\.csv: binary file", r.stderr), r.stderr
    assert "Exit" not in r.stderr
    failures = json.loads((fl / "summary.json").read_text())["failures"]
    assert "binary file" in json.dumps(failures)


# ------------------------------------------------------------------ datasets built in Python
def _arrays():
    rb = load_robot("puma560")
    q = rb.random_readings(10, np.random.default_rng(0))
    k = rb.kinematics(q, jacobian=False)
    return rb.joint_names, q, k


@pytest.mark.parametrize("case,pattern", [
    ("joints", r"readings must have shape \(N, 6\) — one column per joint of .* got \(10, 5\)"),
    ("names", r"readings must have shape \(N, 2\) .* got \(10, 6\)"),
    ("repeated-name", r"joint names repeated: \['j1'\]"),
    ("points-rows", r"points must have shape \(N, 3\) or \(N, k, 3\) with N = 10 poses, got \(5, 3\)"),
    ("points-cols", r"points must have shape .* got \(10, 2\)"),
    ("nan-reading", r"readings of pose 3 is not finite \(1 pose\(s\) with NaN or inf\)"),
    ("inf-point", r"points of pose 7 is not finite"),
    ("R-shape", r"R must have shape \(N, 3, 3\) with N = 10 poses, got \(3, 3\)"),
    ("R-without-p", r"a full-pose dataset \(R given\) needs the positions p"),
    ("context-length", r"context\['t'\] must have one value per pose \(N = 10\), got shape \(9,\)"),
])
def test_dataset_from_arrays_refuses_inconsistent_arrays(case, pattern):
    """The checks of the CSV loader, for data built in Python (notebooks): a DatasetError naming the array."""
    from estcal.io.dataset import DatasetError

    names, q, k = _arrays()
    args = {"joint_names": names, "readings": q, "points": k.p}
    if case == "joints":
        args["readings"] = q[:, :5]
    elif case == "names":
        args["joint_names"] = ["a", "b"]
    elif case == "repeated-name":
        args["joint_names"] = ["j1"] + names[1:5] + ["j1"]
    elif case == "points-rows":
        args["points"] = k.p[:5]
    elif case == "points-cols":
        args["points"] = k.p[:, :2]
    elif case == "nan-reading":
        args["readings"] = q.copy()
        args["readings"][3, 2] = np.nan
    elif case == "inf-point":
        args["points"] = k.p.copy()
        args["points"][7, 0] = np.inf
    elif case == "R-shape":
        args.update(points=None, R=np.eye(3), p=k.p)
    elif case == "R-without-p":
        args.update(points=None, R=k.R)
    elif case == "context-length":
        args["context"] = {"t": np.arange(9.0)}
    with pytest.raises(DatasetError, match=pattern):
        dataset_from_arrays(**args)


def test_dataset_from_arrays_accepts_consistent_arrays():
    names, q, k = _arrays()
    ds = dataset_from_arrays(names, q, R=k.R, p=k.p, context={"t": np.arange(10.0)})
    assert ds.kind == "pose" and ds.n == 10
    ds = dataset_from_arrays(names, q, points=k.p)
    assert ds.kind == "position" and ds.points.shape == (10, 1, 3)


def test_python_calibrate_refuses_like_the_command(base):
    """estcal.calibrate (notebooks) runs the numerical refusals by default; checks=False opts out."""
    import estcal
    from estcal.base.errors import NumericalRefusal

    rb = estcal.load_robot("puma560")
    few = estcal.load_dataset(base / "pos.csv", rb).subset(slice(0, 3))
    with pytest.raises(NumericalRefusal, match=r"3 poses give 9 equations for 9 free parameters"):
        estcal.calibrate(rb, few)
    res = estcal.calibrate(rb, few, checks=False)
    assert res.dof == 0


def test_time_running_backwards_is_a_warning_in_every_command(base, tmp_path):
    ls = lines_of(base)
    ts = [0, 1, 2, 1.5] + list(range(3, len(ls) - 4))
    path = write(tmp_path, "t.csv", csv_from([ls[0] + ",t"] + [f"{line},{t}" for line, t in zip(ls[1:], ts)]))
    for args in (["calibrate", path, "-r", "puma560"], ["online", path, "-r", "puma560"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, r.output
        assert re.search(r"warning: .*t\.csv: column 't' goes back in time at line 5 \(2 s, then 1\.5 s\)", r.stderr)


def test_python_results_never_write_over_their_inputs(base, tmp_path):
    """result.save_model / to_json and export_urdf refuse the files the result came from."""
    import shutil

    import estcal

    data = tmp_path / "d.csv"
    shutil.copy(base / "pos.csv", data)
    robot = tmp_path / "r.yaml"
    shutil.copy(base / "robot.yaml", robot)
    before = data.read_bytes(), robot.read_bytes()
    res = estcal.calibrate(str(robot), str(data), level="joint_offset")
    for write_it, target in ((res.save_model, data), (res.to_json, data), (res.save_model, robot),
                             (lambda p: estcal.export_urdf(estcal.load_robot(str(robot)), p), robot)):
        with pytest.raises(ValueError, match=r"inputs are never overwritten"):
            write_it(str(target))
    assert (data.read_bytes(), robot.read_bytes()) == before
    assert res.to_json(tmp_path / "r.json").exists()


@pytest.mark.parametrize("kw,pattern", [({"tol_mm": -1}, r"tol_mm must be a finite number > 0, got -1"),
                                        ({"tol_mrad": float("nan")}, r"tol_mrad must be a finite number > 0"),
                                        ({"max_iter": 0}, r"max_iter must be an integer ≥ 1, got 0")])
def test_python_compensate_checks_its_numbers(kw, pattern):
    import estcal

    rb = estcal.load_robot("puma560")
    q = rb.random_readings(3, np.random.default_rng(0))
    with pytest.raises(ValueError, match=pattern):
        estcal.compensate(rb, rb.kinematics(q, jacobian=False).p, q, **kw)


def test_python_entry_points_check_effects_and_points(base):
    import estcal

    with pytest.raises(ValueError, match=r"unknown effect\(s\) \['nosuch'\]; registered: backlash"):
        estcal.diagnose("puma560", str(base / "pos.csv"), effects=["nosuch"])
    with pytest.raises(ValueError, match=r"points must be an integer ≥ 1 .* got 0"):
        estcal.calibrate("puma560", str(base / "pos.csv"), points=0)
    res = estcal.calibrate("puma560", str(base / "pts.csv"), points=np.int64(2), level="joint_offset")
    assert res.dof > 0
