"""Crash-safe online calibration (docs/reliability.md): ``kill -9`` mid-stream, ``--resume``,
bit-identical estimate and covariance; refusals when the input or the options differ."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app

runner = CliRunner()
FREE = "offset_1,offset_2,offset_3,a_2,d_3,alpha_3"
N = 80
ESTCAL = str(Path(sys.executable).parent / "estcal")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpt")
    path = d / "pos.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", str(N), "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "4", "-o", str(path)])
    assert r.exit_code == 0, r.output
    return path


def _args(path, *extra):
    return ["online", str(path), "--robot", "puma560", "--free", FREE, "--q-mm", "1e-4", *extra]


def test_kill_9_and_resume_is_bit_identical(data, tmp_path):
    full = tmp_path / "full.json"
    r = runner.invoke(app, _args(data, "--json", str(full)))  # the uninterrupted reference
    assert r.exit_code == 0, r.output
    state = tmp_path / "state.json"
    kill_at = int(np.random.default_rng().integers(10, N - 20))  # a random row
    p = subprocess.Popen([ESTCAL, *_args(data, "--state", str(state), "--checkpoint-every", "3",
                                         "--throttle", "0.03")],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.time()
    seen = 0
    while time.time() - t0 < 60:
        if state.exists():
            seen = json.loads(state.read_text())["rows"]  # atomic writes: always a complete file
            if seen >= kill_at:
                break
        time.sleep(0.01)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    assert p.returncode == -signal.SIGKILL
    ck = json.loads(state.read_text())
    assert kill_at <= ck["rows"] < N and not ck["finished"], (kill_at, ck["rows"])
    resumed = tmp_path / "resumed.json"
    r = runner.invoke(app, _args(data, "--resume", str(state), "--json", str(resumed)))
    assert r.exit_code == 0, r.output
    assert f"resuming after row {ck['rows']}" in " ".join(r.output.split())  # rich may wrap the line
    a, b = json.loads(full.read_text()), json.loads(resumed.read_text())
    ea = np.array([v["estimate"] for v in a["parameters"].values()])
    eb = np.array([v["estimate"] for v in b["parameters"].values()])
    assert np.array_equal(ea, eb)
    assert np.array_equal(np.array(a["covariance"]), np.array(b["covariance"]))
    assert a["innovation"] == b["innovation"] and a["history"] == b["history"]
    final = json.loads(state.read_text())
    assert final["finished"] and final["rows"] == N
    assert np.array_equal(np.array(final["covariance"]), np.array(a["covariance"]))
    # the checkpoint is a next-pose state
    r = runner.invoke(app, ["next-pose", "--robot", "puma560", "--state", str(state), "--n-candidates", "30",
                            "--no-refine"])
    assert r.exit_code == 0, r.output


def test_resume_refuses_other_input_or_options(data, tmp_path):
    state = tmp_path / "s.json"
    short = tmp_path / "short.csv"
    lines = data.read_text().splitlines(keepends=True)
    short.write_text("".join(lines[:31]))  # header + 30 rows
    r = runner.invoke(app, _args(short, "--state", str(state)))
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, _args(short, "--state", str(state)))
    assert r.exit_code == 2 and "--resume" in r.output  # an existing checkpoint is never overwritten
    r = runner.invoke(app, _args(short, "--resume", str(state), "--noise-pos-mm", "0.2"))
    assert r.exit_code == 2 and "noise-pos (m): 0.0002 (checkpoint: 0.0001)" in r.output, r.output
    changed = tmp_path / "changed.csv"
    lines2 = list(lines)
    vals = lines2[5].rstrip("\n").split(",")
    vals[-1] = repr(float(vals[-1]) + 1e-3)  # one processed row edited (still a valid row)
    lines2[5] = ",".join(vals) + "\n"
    changed.write_text("".join(lines2))
    r = runner.invoke(app, _args(changed, "--resume", str(state)))
    assert r.exit_code == 2 and "differs from the checkpointed input" in r.output, r.output
    # the original file has grown (a stream appended to): accepted, and it continues from row 30
    grown = tmp_path / "grown.csv"
    grown.write_text("".join(lines))
    before = state.read_bytes()
    r = runner.invoke(app, _args(grown, "--resume", str(state), "--json", str(tmp_path / "g.json")))
    assert r.exit_code == 0, r.output
    assert json.loads(state.read_text())["rows"] == N and state.read_bytes() != before


def _final(path):
    d = json.loads(Path(path).read_text())
    est = np.array([v["estimate"] for v in d["parameters"].values()])
    return est, np.array(d["covariance"]), d["innovation"], d["history"]


def test_journal_tail_from_a_kill_is_cut_and_a_changed_journal_refused(data, tmp_path):
    """A kill between the journal append and the checkpoint rename leaves journal bytes the
    checkpoint does not name: resume ignores and cuts them. A journal that does not match its
    checkpoint (edited, missing) is refused with the file named; resuming into another --state
    path copies the checkpointed part of the journal."""
    from estcal.estimate.checkpoint import journal_path

    full = tmp_path / "full.json"
    assert runner.invoke(app, _args(data, "--every", "7", "--json", str(full))).exit_code == 0
    lines = data.read_text().splitlines(keepends=True)
    part = tmp_path / "part.csv"
    part.write_text("".join(lines[:41]))
    state = tmp_path / "s.json"
    r = runner.invoke(app, _args(part, "--every", "7", "--state", str(state)))
    assert r.exit_code == 0, r.output
    jp = journal_path(state)
    ck = json.loads(state.read_text())
    assert ck["journal"]["bytes"] == jp.stat().st_size > 0 and ck["journal"]["steps"] == 40
    good = jp.read_bytes()
    # a resume into another path copies the journal; the original pair stays untouched
    other = tmp_path / "other.json"
    r = runner.invoke(app, _args(data, "--every", "7", "--resume", str(state), "--state", str(other),
                                 "--json", str(tmp_path / "o.json")))
    assert r.exit_code == 0, r.output
    assert jp.read_bytes() == good and journal_path(other).read_bytes()[:len(good)] == good
    for x, y in zip(_final(full), _final(tmp_path / "o.json")):
        assert (np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y)
    # garbage after the checkpointed bytes (a half-written append): cut on resume
    jp.write_bytes(good + np.arange(13, dtype="<f8").tobytes()[:-3])
    resumed = tmp_path / "r.json"
    r = runner.invoke(app, _args(data, "--every", "7", "--resume", str(state), "--json", str(resumed)))
    assert r.exit_code == 0, r.output
    for x, y in zip(_final(full), _final(resumed)):
        assert (np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y)
    fin = json.loads(state.read_text())["journal"]
    assert jp.stat().st_size == fin["bytes"] and fin["steps"] == N
    # an edited journal, then a missing one: refused, naming the journal
    raw = bytearray(jp.read_bytes())
    raw[100] ^= 1
    jp.write_bytes(bytes(raw))
    r = runner.invoke(app, _args(data, "--resume", str(state)))
    assert r.exit_code == 2 and "does not match its checkpoint" in " ".join(r.output.split()), r.output
    jp.unlink()
    r = runner.invoke(app, _args(data, "--resume", str(state)))
    out = " ".join(r.output.split())
    assert r.exit_code == 2 and "cannot read the journal" in out and jp.name in out, r.output


def test_a_running_state_is_locked_against_a_second_run(data, tmp_path):
    """One writer per checkpoint: a second run on the state of a running one is refused with its pid;
    the lock goes with the run (no lock file left, and none needed after a kill -9: above)."""
    state = tmp_path / "state.json"
    p = subprocess.Popen([ESTCAL, *_args(data, "--state", str(state), "--throttle", "0.05")],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.time()
        while not (tmp_path / "state.json.lock").exists() and time.time() - t0 < 30:
            time.sleep(0.01)
        for extra in (["--resume", str(state)], ["--state", str(state)]):
            r = runner.invoke(app, _args(data, *extra))
            assert r.exit_code == 2, r.output
            assert f"in use by another running estcal process (pid {p.pid})" in " ".join(r.stderr.split())
    finally:
        p.wait(timeout=60)
    assert p.returncode == 0, p.stderr.read()
    assert not (tmp_path / "state.json.lock").exists()
    r = runner.invoke(app, _args(data, "--resume", str(state)))  # free again
    assert r.exit_code == 0, r.output
