"""`estcal fleet` on a real Dask cluster — `dask scheduler` and two `dask worker` processes over
TCP on the loopback interface (tests/dask_cluster.py) — losing no robot when a worker is killed
during the run, nor when the command itself is killed and rerun (docs/scaling.md).

Each run is the command a user types, in its own process, on a fleet generated on demand;
its rows are compared with a serial run of the same fleet in this process, computed independently
of the cluster, the results folder and the JSON summary.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

distributed = pytest.importorskip("distributed")
sys.path.insert(0, str(Path(__file__).resolve().parent))
from dask_cluster import LoopbackCluster  # noqa: E402

pytestmark = pytest.mark.slow

N_ROBOTS, POSES = 40, 30


@pytest.fixture(scope="module")
def cluster():
    with LoopbackCluster(2, nanny=False) as cl:  # a killed worker stays dead: its tasks must go elsewhere
        yield cl


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A fleet of 40 robots generated on demand, and its rows computed serially here."""
    from estcal.simulate.fleet import simulate_fleet
    from estcal.workflows.fleet import run_fleet

    root = tmp_path_factory.mktemp("fleet") / "fleet"
    simulate_fleet(N_ROBOTS, root, n_poses=POSES, n_validate=10, seed=11, on_demand=True)
    ref = run_fleet(root, progress=False)
    assert ref.n_ok == N_ROBOTS and not ref.failures
    return root, {r["robot"]: r for r in ref.rows}


def _command(root, cluster, results, summary):
    return [sys.executable, "-m", "estcal.cli.main", "fleet", str(root), "--scheduler", cluster.address,
            "--results", str(results), "--json", str(summary)]


def _rows(results: Path) -> list:
    return sorted(results.glob("*.json"))


def _wait_for_rows(results: Path, k: int, proc, timeout=120.0) -> None:
    t0 = time.monotonic()
    while len(_rows(results)) < k:
        assert proc.poll() is None, f"the command ended before {k} robots were saved:\n{proc.stderr.read()}"
        assert time.monotonic() - t0 < timeout, f"fewer than {k} robots saved after {timeout} s"
        time.sleep(0.01)


def _check_complete(summary: Path, results: Path, expected: dict) -> dict:
    s = json.loads(summary.read_text())
    names = [r["robot"] for r in s["robots"]]
    assert (s["n_robots"], s["n_ok"], s["n_failed"]) == (N_ROBOTS, N_ROBOTS, 0), s["failures"]
    assert sorted(names) == sorted(expected) and len(set(names)) == len(names)  # each robot once
    assert [p.stem for p in _rows(results)] == sorted(expected)                 # one saved row per robot
    assert not [p for p in results.iterdir() if p.name.startswith(".")]         # no partial file left
    for r in s["robots"]:  # the same numbers as the serial run, whoever computed them
        assert r == expected[r["robot"]], r["robot"]
    saved = {p.stem: json.loads(p.read_text())["row"] for p in _rows(results)}
    assert saved == expected
    return s


def test_worker_killed_during_the_run_loses_no_robot(cluster, fleet, tmp_path):
    root, expected = fleet
    results, summary = tmp_path / "results", tmp_path / "summary.json"
    proc = subprocess.Popen(_command(root, cluster, results, summary), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_rows(results, 1, proc)
        busy = [w for w, keys in cluster.client.processing().items() if keys]
        assert busy, "no worker was running a task: the run ended before the kill"
        victim = cluster.worker_pids()[busy[0]]
        os.kill(victim, signal.SIGKILL)
        at_kill = len(_rows(results))
        out, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert at_kill < N_ROBOTS  # robots were still to come when the worker died
    assert len(cluster.client.nthreads()) == 1  # the rest ran on the other worker (asked of the scheduler now)
    _check_complete(summary, results, expected)
    assert f"{N_ROBOTS} of {N_ROBOTS} robots calibrated" in out


def test_command_killed_then_rerun_skips_the_finished_robots(cluster, fleet, tmp_path):
    root, expected = fleet
    results, summary = tmp_path / "results", tmp_path / "summary.json"
    cmd = _command(root, cluster, results, summary)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_rows(results, 5, proc)
        os.kill(proc.pid, signal.SIGKILL)  # the client dies mid-run
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    first = {p.stem: p.stat().st_ino for p in _rows(results)}
    assert 5 <= len(first) < N_ROBOTS and not summary.exists()
    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert rerun.returncode == 0, rerun.stderr
    s = _check_complete(summary, results, expected)
    assert s["n_skipped"] == len(first)
    assert f"({len(first)} skipped: done earlier" in rerun.stdout
    # the finished robots were not redone: their files are the ones the killed run wrote
    assert {n: (results / f"{n}.json").stat().st_ino for n in first} == first
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=240)  # a third run: nothing to do
    assert again.returncode == 0 and f"({N_ROBOTS} skipped: done earlier" in again.stdout
