"""``estcal.OnlineCalibrator`` (docs/probabilistic.md, "Online calibration in Python"): the object behind
``estcal online`` — chunked updates, the result schema, checkpoints (also after ``kill -9``), the
segmented linearisation against the row-by-row EKF, and the exact block update."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from typer.testing import CliRunner

import estcal
from estcal.cli.main import app
from online_cli import FREE, run_online

runner = CliRunner()
N = 300


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("oc")
    path = d / "pos.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", str(N), "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "7", "-o", str(path)])
    assert r.exit_code == 0, r.output
    return path


def _cal(**kw):
    return estcal.OnlineCalibrator("puma560", free=FREE, q=1e-7, noise=(1e-4, 1e-3), prior_std=0.1, **kw)


@pytest.mark.parametrize("cuts", ["whole", "rows", "uneven", "arrays"])
def test_chunked_updates_give_the_estimate_of_estcal_online(data, tmp_path, cuts):
    """Fed in chunks — the path at once, one row at a time, uneven chunks, arrays — the object ends
    where ``estcal online`` ends (1e-9 in SI units; the chunking changes only the rounding)."""
    ref = run_online(data, tmp_path / "cli.json")
    cal = _cal()
    ds = estcal.load_dataset(data, cal.robot)
    if cuts == "whole":
        cal.update(str(data))
    elif cuts == "arrays":
        for a in range(0, N, 97):
            cal.update(ds.readings[a:a + 97], ds.points[a:a + 97, 0])
    else:
        edges = np.arange(N + 1) if cuts == "rows" else np.unique(np.r_[0, np.cumsum([1, 2, 3, 50, 7, 128, 1]), N])
        for a, b in zip(edges[:-1], edges[1:]):
            cal.update(ds.subset(slice(a, b)))
    res = cal.result().to_dict()
    assert set(ref) <= set(res) and res["n_rows"] == ref["n_rows"] == N
    est = np.array([v["estimate"] for v in res["parameters"].values()])
    ref_est = np.array([v["estimate"] for v in ref["parameters"].values()])
    std = np.array([v["std"] for v in ref["parameters"].values()])
    assert np.max(np.abs(est - ref_est)) < 1e-9 and np.max(np.abs(est - ref_est) / std) < 1e-6
    assert np.allclose(res["covariance"], ref["covariance"], rtol=1e-6, atol=1e-18)
    assert res["innovation"]["nis_total"] == pytest.approx(ref["innovation"]["nis_total"], rel=1e-8)
    assert [h["row"] for h in res["history"]] == [h["row"] for h in ref["history"]] == list(range(10, N + 1, 10))
    assert np.allclose([h["nis"] for h in res["history"]], [h["nis"] for h in ref["history"]], rtol=1e-6)


def test_segments_agree_with_the_row_by_row_ekf(data):
    """The segmented linearisation (the default) against the classical EKF, every row linearised at
    the current estimate (relinearize=1, filterpy step by step): the estimate within 0.01 σ, every
    row's NIS and the innovation tests alike (the difference is second order in the move of the
    estimate within a segment: docs/probabilistic.md, "Online at sensor rate")."""
    ds = estcal.load_dataset(data, estcal.load_robot("puma560"))
    long = ds.subset(np.r_[np.arange(N), np.arange(N), np.arange(N)])  # 900 rows: segments of up to 32
    fast, slow = _cal(), _cal(relinearize=1)
    fast.update(long)
    slow.update(long)
    dz = np.abs(fast.estimate - slow.estimate) / slow.std
    assert dz.max() < 0.01, dz
    assert np.allclose(fast.std, slow.std, rtol=1e-4)
    assert np.allclose(fast.nis, slow.nis, rtol=1e-3, atol=1e-6)
    a, b = fast.innovation_tests().to_dict(), slow.innovation_tests().to_dict()
    for k in ("nis_mean_per_row", "mean_chi2", "ljung_box"):
        assert a[k] == pytest.approx(b[k], rel=1e-3), k
    assert a["fires"] == b["fires"]


def test_block_update_is_the_sequential_filter(data):
    """One block of B groups linearised at one point equals B filterpy EKF steps with that
    linearisation point: innovations (whitened), NIS, estimate and covariance after every group,
    with and without process noise."""
    from estcal.estimate._common import GroupedProblem
    from estcal.estimate.kalman import ParameterFilter, process_noise
    from estcal.estimate.testproblems import simulated_problem

    sim = simulated_problem("puma560", n_poses=40, seed=3)
    prob = sim.problem.with_free(sim.free)
    pv = prob.params
    gp = GroupedProblem(prob)
    for q in (0.0, 1e-5):
        Q = process_noise(pv.free_names, q)
        seq, blk = (ParameterFilter(pv.values, pv.free_indices, np.eye(len(pv.free_names)) * 1e-2, Q,
                                    names=pv.free_names) for _ in range(2))
        for i in range(15):  # both determined first, row by row
            seq.step(gp.subproblem([i]))
            blk.step(gp.subproblem([i]))
        xl = seq.x
        xs, ps = [], []
        for i in range(15, 40):
            seq.step(gp.subproblem([i]), x_lin=xl)
            xs.append(seq.x)
            ps.append(np.diag(seq.P))
        r = gp.subproblem(list(range(15, 40))).evaluate(blk.full(xl))
        st = blk.update_block(r.H[:, pv.free_indices], r.e, r.sigma, np.bincount(r.pose), xl)
        scale = seq.std
        assert np.max(np.abs(st.estimate - np.array(xs)) / scale) < 1e-6
        assert np.allclose(st.var, np.array(ps), rtol=1e-6)
        assert np.max(np.abs(blk.P - seq.P) / np.outer(scale, scale)) < 1e-6  # on the correlation scale
        assert np.allclose(blk.monitor.nis, seq.monitor.nis, rtol=1e-6)
        assert np.allclose(blk.monitor.white_flat, seq.monitor.white_flat, atol=1e-6)


def test_result_protocol_next_pose_and_saved_model(data, tmp_path):
    cal = _cal()
    up = cal.update(str(data), trace=True)
    assert up.n == N and up.estimate.shape == (N, 8) and np.array_equal(up.estimate[-1], cal.estimate)
    res = cal.result()
    d = res.to_dict()
    for k in ("robot", "input", "filter", "q", "q_params", "n_rows", "parameters", "covariance", "innovation",
              "history"):
        assert k in d
    assert d["input"] == str(data) and d["robot"] == "puma560"
    assert json.loads(res.to_json(tmp_path / "r.json").read_text())["n_rows"] == N
    # the one result protocol (estcal.base.result.Result) and its parameter table (display units)
    from estcal.base.result import Result
    from estcal.base.tables import Table

    t = res.table()
    assert isinstance(res, Result) and isinstance(t, Table) and [r[0] for r in t.rows] == cal.names
    assert t.rows[cal.names.index("a_2")][t.columns.index("estimate")] == pytest.approx(res.parameter("a_2")[0] * 1e3)
    assert "innovations:" in t.note and repr(res) == str(res) and str(res).startswith("OnlineResult(")
    with pytest.raises(estcal.base.errors.InputError, match="is an input"):  # the input is never written over
        res.to_json(data)
    i = cal.names.index("a_2")
    assert res.parameter("a_2") == (pytest.approx(cal.estimate[i]), pytest.approx(cal.std[i]))
    model = res.save_model(tmp_path / "m.yaml")
    rb = estcal.load_robot(model)
    assert rb.params.values[rb.params.index("a_2")] == pytest.approx(cal.estimate[i], abs=1e-12)
    names, cov = estcal.calibration_covariance(rb)
    assert names == cal.names and np.allclose(cov, cal.covariance)
    nxt = cal.next_pose(n_candidates=50, rng=1)
    assert nxt.readings.shape == (6,) and nxt.value_after < nxt.value_before
    assert np.isfinite(cal.running_nis) and cal.nis.shape == (N,)


def test_resume_refuses_other_options_and_continues_from_the_checkpoint(data, tmp_path):
    ds = estcal.load_dataset(data, estcal.load_robot("puma560"))
    state = tmp_path / "s.json"
    with _cal() as cal:
        cal.update(ds.subset(slice(0, 100)))
        cal.save(state)
        with pytest.raises(ValueError, match="in use by"):
            estcal.OnlineCalibrator.resume(state)  # locked while the first object lives
    with pytest.raises(ValueError, match=r"noise-pos \(m\): 0.0002 \(checkpoint: 0.0001\)"):
        estcal.OnlineCalibrator.resume(state, noise=(2e-4, 1e-3))
    with pytest.raises(ValueError, match="the file exists"):
        _cal().save(state)  # a checkpoint is never overwritten by another run
    cal = estcal.OnlineCalibrator.resume(state)  # robot and options from the checkpoint
    assert cal.n_rows == 100 and set(cal.names) == set(FREE.split(","))
    cal.update(ds.subset(slice(100, N)))
    ref = _cal()
    ref.update(ds.subset(slice(0, 100)))
    ref.update(ds.subset(slice(100, N)))
    assert np.array_equal(cal.estimate, ref.estimate) and np.array_equal(cal.covariance, ref.covariance)
    cal.close()


_WRITER = r"""
import sys, time
import numpy as np
import estcal


def feed(path, state, mode):
    ds = estcal.load_dataset(path, estcal.load_robot("puma560"))
    cal = (estcal.OnlineCalibrator.resume(state) if mode == "resume" else
           estcal.OnlineCalibrator("puma560", free="{free}", q=1e-7, noise=(1e-4, 1e-3)))
    edges = list(range(0, ds.n, 7)) + [ds.n]          # chunks at multiples of 7 rows, whatever the start
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= cal.n_rows:
            continue
        cal.update(ds.subset(slice(max(a, cal.n_rows), b)))
        cal.save(state)
        if mode == "slow":
            time.sleep(0.02)
    cal.close()
    return np.r_[cal.estimate, cal.covariance.ravel(), cal.nis]


if __name__ == "__main__":
    np.save(sys.argv[2] + ".final.npy", feed(*sys.argv[1:4]))
"""


def test_kill_9_and_resume_through_the_python_object_is_bit_identical(data, tmp_path):
    """A script feeding the object and saving after every chunk is killed (SIGKILL) at a random
    chunk; ``OnlineCalibrator.resume`` continues it; estimate, covariance and every row's NIS equal
    the uninterrupted run bit for bit (the checkpoint is inside a linearisation segment most of the
    time: its linearisation state is in the checkpoint)."""
    import importlib.util

    script = tmp_path / "writer.py"
    script.write_text(_WRITER.replace("{free}", FREE))
    spec = importlib.util.spec_from_file_location("writer", script)
    writer = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(writer)
    full = writer.feed(str(data), str(tmp_path / "full.json"), "fresh")  # the uninterrupted run, in process
    state = tmp_path / "state.json"
    kill_at = int(np.random.default_rng().integers(40, N - 40))
    p = subprocess.Popen([sys.executable, str(script), str(data), str(state), "slow"], stderr=subprocess.PIPE)
    t0 = time.time()
    while time.time() - t0 < 60:
        if state.exists() and json.loads(state.read_text())["rows"] >= kill_at:
            break
        time.sleep(0.005)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    ck = json.loads(state.read_text())
    assert p.returncode == -signal.SIGKILL and kill_at <= ck["rows"] < N and not ck["finished"]
    resumed = writer.feed(str(data), str(state), "resume")
    assert full.shape == resumed.shape and np.array_equal(full, resumed)
