"""Resumable MCMC (docs/reliability.md): the chain lives in an HDF5 file (emcee's backend, written
in atomic blocks); ``kill -9`` mid-run, run again: the stored part is kept bit for bit and sampling
continues; a chain of other data is refused."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app

runner = CliRunner()
ESTCAL = str(Path(sys.executable).parent / "estcal")
FREE = "offset_1,offset_2,offset_3,a_2,d_3"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("chain")
    path = d / "pos.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "40", "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "2", "-o", str(path)])
    assert r.exit_code == 0, r.output
    return path


def _args(data, chain, max_steps):
    return ["calibrate", str(data), "--robot", "puma560", "--free", FREE, "--estimator", "mcmc", "--chain", str(chain),
            "--option", f"max_steps={max_steps}", "--option", "target_ess=100000000", "--option", "check_every=10",
            "--allow-ill-conditioned"]


def _iteration(path):
    try:
        with h5py.File(path, "r", locking=False) as f:
            return int(f["mcmc"].attrs["iteration"])
    except (OSError, KeyError):
        return 0


def test_kill_9_then_continue_the_chain(data, tmp_path):
    chain = tmp_path / "c.h5"
    kill_at = int(np.random.default_rng().integers(20, 80))
    p = subprocess.Popen([ESTCAL, *_args(data, chain, 1_000_000)], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE)
    t0 = time.time()
    while time.time() - t0 < 60 and _iteration(chain) < kill_at:
        time.sleep(0.005)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    assert p.returncode == -signal.SIGKILL
    n0 = _iteration(chain)
    assert n0 >= kill_at
    with h5py.File(chain, "r") as f:  # complete and readable after the kill
        saved = f["mcmc/chain"][:n0].copy()
        saved_lp = f["mcmc/log_prob"][:n0].copy()
    r = runner.invoke(app, _args(data, chain, n0 + 30))
    assert r.exit_code == 0, r.output
    with h5py.File(chain, "r") as f:
        assert int(f["mcmc"].attrs["iteration"]) == n0 + 30  # sampling continued
        assert np.array_equal(f["mcmc/chain"][:n0], saved) and np.array_equal(f["mcmc/log_prob"][:n0], saved_lp)
        new = f["mcmc/chain"][n0:]
    assert np.all(np.isfinite(new)) and not np.array_equal(new[0], new[-1])


def test_continued_chain_equals_an_uninterrupted_one_and_other_data_refused(data, tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    assert runner.invoke(app, _args(data, a, 40)).exit_code == 0
    assert runner.invoke(app, _args(data, a, 70)).exit_code == 0  # extended by 30 steps
    assert runner.invoke(app, _args(data, b, 70)).exit_code == 0  # in one go
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        assert np.array_equal(fa["mcmc/chain"][...], fb["mcmc/chain"][...])
    other = tmp_path / "other.csv"
    lines = data.read_text().splitlines(keepends=True)
    other.write_text("".join(lines[:-1]))
    keep = a.read_bytes()
    r = runner.invoke(app, _args(other, a, 100))
    assert r.exit_code == 2 and "other data or sampling options" in r.output, r.output
    assert a.read_bytes() == keep  # never overwritten
    r = runner.invoke(app, ["calibrate", str(data), "--robot", "puma560", "--free", FREE, "--chain", str(a)])
    assert r.exit_code == 2 and "needs --estimator mcmc" in r.output
