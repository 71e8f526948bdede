"""Loader fuzzing (hypothesis): any bytes, any mutation of a good dataset, robot file or URDF
gives either a valid object or a DatasetError / RobotFileError that starts with the file name
and names a line within the file — never another exception (docs/reliability.md).

Bounded for CI: a few hundred examples in total, no per-example deadline (shared machines)."""
from __future__ import annotations

import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from estcal.io.dataset import Dataset, DatasetError, dataset_from_arrays, load_dataset, write_dataset
from estcal.io.robotfile import RobotFileError, load_robot, save_robot
from estcal.kinematics.chain import SerialRobot

SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
ROBOT = load_robot("puma560")
_DIR = Path(tempfile.mkdtemp(prefix="estcal_fuzz_"))


def _good_csv() -> str:
    q = ROBOT.random_readings(6, np.random.default_rng(1))
    k = ROBOT.kinematics(q, jacobian=False)
    p = write_dataset(_DIR / "good.csv", dataset_from_arrays(ROBOT.joint_names, q, R=k.R, p=k.p))
    return p.read_text()


GOOD_CSV = _good_csv()
save_robot(ROBOT, _DIR / "good.yaml")
GOOD_YAML = (_DIR / "good.yaml").read_text()
GOOD_URDF = ('<?xml version="1.0"?>\n<robot name="r">\n  <link name="base"/>\n  <link name="l1"/>\n'
             '  <link name="l2"/>\n'
             '  <joint name="a" type="revolute">\n    <parent link="base"/>\n    <child link="l1"/>\n'
             '    <origin xyz="0 0 0.1" rpy="0 0 0"/>\n    <axis xyz="0 0 1"/>\n'
             '    <limit lower="-1" upper="1" effort="1" velocity="1"/>\n  </joint>\n'
             '  <joint name="b" type="prismatic">\n    <parent link="l1"/>\n    <child link="l2"/>\n'
             '    <origin xyz="0.2 0 0" rpy="0 1.57 0"/>\n    <axis xyz="1 0 0"/>\n'
             '    <limit lower="0" upper="0.3" effort="1" velocity="1"/>\n  </joint>\n</robot>\n')


def _check_error(exc: Exception, path: Path, content: bytes) -> None:
    msg = str(exc)
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg, msg
    n_lines = content.count(b"\n") + 1
    for m in re.finditer(r"\bline (\d+)\b", msg):
        assert 1 <= int(m.group(1)) <= n_lines, (msg, n_lines)


def _load(loader, path: Path, content: bytes, errors):
    path.write_bytes(content)
    try:
        return loader(path)
    except errors as exc:
        _check_error(exc, path, content)
        return None


# ------------------------------------------------------------------ mutations
TOKENS = ["", ",", ";", "\t", "\n", "\r\n", "\ufeff", "nan", "inf", "-", "e", "1e400", "abc", "x", "qw", "j1",
          '"', "#", " ", "0", "90", "1000", "é", "\x00", "\x7f", "[", "]", "{", "}", ":", "- ", "<", ">", "/>",
          "</joint>", "<link name=\"l1\"/>", "&", "&amp;", "'", "*", "!!python/object", "&a", "*a"]


@st.composite
def mutated(draw, text: str):
    """``text`` after 1–4 random edits (insert / delete / replace a span, duplicate or drop a line)."""
    s = text
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["insert", "delete", "replace", "dup-line", "drop-line", "truncate"]))
        i = draw(st.integers(0, len(s)))
        if op == "insert":
            s = s[:i] + draw(st.sampled_from(TOKENS)) + s[i:]
        elif op == "delete":
            s = s[:i] + s[i + draw(st.integers(1, 12)):]
        elif op == "replace":
            s = s[:i] + draw(st.text(max_size=6)) + s[i + draw(st.integers(1, 6)):]
        elif op in ("dup-line", "drop-line"):
            lines = s.splitlines(keepends=True)
            if lines:
                k = draw(st.integers(0, len(lines) - 1))
                lines[k:k + 1] = [lines[k]] * (2 if op == "dup-line" else 0)
                s = "".join(lines)
        else:
            s = s[:i]
    return s.encode("utf-8", errors="surrogatepass") if "\ud800" not in s else s.encode("utf-8", "replace")


# ------------------------------------------------------------------ datasets
@settings(max_examples=150, **SETTINGS)
@given(st.binary(max_size=400))
def test_dataset_random_bytes(data):
    ds = _load(lambda p: load_dataset(p, ROBOT), _DIR / "bytes.csv", data, DatasetError)
    assert ds is None or isinstance(ds, Dataset)


@settings(max_examples=200, **SETTINGS)
@given(mutated(GOOD_CSV))
def test_dataset_mutations(content):
    ds = _load(lambda p: load_dataset(p, ROBOT), _DIR / "mut.csv", content, DatasetError)
    if ds is not None:
        assert ds.n >= 1 and np.all(np.isfinite(ds.readings))
        assert ds.kind in ("pose", "position", "points", "none")


@settings(max_examples=60, **SETTINGS)
@given(st.lists(st.integers(0, 6), max_size=4), st.integers(0, 5), st.integers(0, 5))
def test_dataset_line_numbers_count_blank_lines(blanks, row, col):
    """A bad value on any row is reported on its physical line, blank lines included."""
    lines = GOOD_CSV.splitlines()
    fields = lines[row + 1].split(",")
    fields[col] = "bad"
    lines[row + 1] = ",".join(fields)
    for b in sorted(blanks, reverse=True):
        lines.insert(b + 1, "")
    target = lines.index(",".join(fields)) + 1
    path = _DIR / "lines.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=rf"lines\.csv, line {target}, column 'j{col + 1}': value is 'bad'"):
        load_dataset(path, ROBOT)


# ------------------------------------------------------------------ robot files
@settings(max_examples=120, **SETTINGS)
@given(mutated(GOOD_YAML))
def test_robot_yaml_mutations(content):
    rb = _load(load_robot, _DIR / "mut.yaml", content, RobotFileError)
    assert rb is None or isinstance(rb, SerialRobot)


@settings(max_examples=60, **SETTINGS)
@given(st.binary(max_size=300))
def test_robot_yaml_random_bytes(data):
    rb = _load(load_robot, _DIR / "bytes.yaml", data, RobotFileError)
    assert rb is None or isinstance(rb, SerialRobot)


@settings(max_examples=100, **SETTINGS)
@given(mutated(GOOD_URDF))
def test_urdf_mutations(content):
    rb = _load(load_robot, _DIR / "mut.urdf", content, RobotFileError)
    if rb is not None:
        assert isinstance(rb, SerialRobot) and 1 <= rb.n_joints <= 2
        assert np.all(np.isfinite(rb.kinematics(np.zeros((1, rb.n_joints)), jacobian=False).p))
