"""One task runner for serial / process / Dask execution, and fleet calibration (docs/scaling.md).

The Dask tests share one 2-worker LocalCluster (worker processes, one thread each):
the same pickling path as a real cluster, started once (~1–2 s).
"""
from __future__ import annotations

import json
import math
import os
import sys

import numpy as np
import pytest

from estcal.scale import run_tasks
from estcal.scale.runner import TaskError

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    import cloudpickle

    # this test module's functions travel by value (workers need not import the tests folder)
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster, distributed.Client(cluster) as c:
        yield c
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def _noisy_root(x, seed):
    """A task whose value depends on its own random stream; negative inputs fail."""
    return math.sqrt(x) + float(np.random.default_rng(seed).normal())


def test_same_seed_same_results_on_every_scheduler(client):
    tasks = [0.5 * k for k in range(23)]
    serial = run_tasks(_noisy_root, tasks, seed=42)
    # independent computation of what each task must return: its own SeedSequence child
    kids = np.random.SeedSequence(42).spawn(len(tasks))
    expected = [math.sqrt(x) + np.random.default_rng(k).normal() for x, k in zip(tasks, kids)]
    assert serial.values() == expected
    # a Dask Client, and the scheduler's address (what --scheduler tcp://host:8786 gives)
    for sched, kw in (("processes", {"n_workers": 2}), (client, {"chunksize": 3}), (client, {"chunksize": 1}),
                      (client.scheduler.address, {})):
        out = run_tasks(_noisy_root, tasks, scheduler=sched, seed=42, **kw)
        assert out.values() == serial.values(), sched
    assert run_tasks(_noisy_root, tasks, seed=43).values() != serial.values()


def test_failing_task_is_reported_with_its_inputs_and_the_others_finish(client):
    tasks = [4.0, -1.0, 9.0, {"pose": -2.5}]
    for sched in ("serial", client):
        out = run_tasks(math.sqrt, tasks, scheduler=sched, chunksize=2)
        assert out.results[0] == 2.0 and out.results[2] == 3.0
        assert [f.index for f in out.failures] == [1, 3]
        f1, f3 = out.failures
        assert f1.inputs == "-1.0" and "ValueError" in f1.error and "math domain error" in f1.error
        assert f3.inputs == "{'pose': -2.5}" and "TypeError" in f3.error
        assert "Traceback" in f1.traceback
        with pytest.raises(TaskError, match=r"task 1 \(-1.0\)"):
            out.values()


def test_unknown_scheduler_is_refused():
    with pytest.raises(ValueError, match="serial, processes, local"):
        run_tasks(math.sqrt, [1.0], scheduler="threads")


def test_monte_carlo_identical_on_dask(client):
    """The nonlinear Monte Carlo of a plan gives the same errors serially and on Dask; its RMS
    is close to the linear prediction ρ0 (independent check of the distributed computation)."""
    from estcal.design import DesignModel, identifiable_subset
    from estcal.design.montecarlo import monte_carlo_test_pose_error
    from estcal.kinematics.robots import puma560

    rob = puma560()
    model = DesignModel(rob, "pose", identifiable_subset(rob, "pose"), sigma=1e-4, sigma_rot=1e-3)
    Q = rob.random_readings(20, np.random.default_rng(1))
    q0 = rob.random_readings(3, np.random.default_rng(2))
    a = monte_carlo_test_pose_error(model, Q, q0, n_reps=12, rng=7, param_std=5e-4)
    b = monte_carlo_test_pose_error(model, Q, q0, n_reps=12, rng=7, param_std=5e-4, scheduler=client)
    assert a.to_dict() == b.to_dict()
    assert 0.6 < a.ratio < 1.5, a  # 12 reps: relative s.e. of the RMS ≈ 0.09


# ------------------------------------------------------------------ fleet
@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    from estcal.simulate.fleet import simulate_fleet

    root = tmp_path_factory.mktemp("fleet")
    sim = simulate_fleet(4, root, n_poses=25, n_validate=15, seed=3, p_effect=0.0)
    assert sim.ok
    (root / "robot_0002" / "data.csv").write_text("j1,j2\n1,2\n")  # the broken robot folder
    return root


def _check_models(root, models, rows):
    from estcal.io import load_dataset
    from estcal.io.robotfile import calibration_covariance, load_robot

    for r in rows:
        path = models / f"{r['robot']}.yaml"
        assert r["model"] == str(path)
        rob = load_robot(path)
        names, C = calibration_covariance(rob)
        assert len(names) == r["n_parameters"] and C.shape == (len(names), len(names))
        assert np.all(np.linalg.eigvalsh(C) > 0)
        # the saved model reproduces the reported validation RMSE (independent evaluation)
        val = load_dataset(root / r["robot"] / "validate.csv", rob)
        kin = rob.kinematics(val.readings, jacobian=False)
        rmse = float(np.sqrt(np.mean(np.sum((kin.p - val.p) ** 2, -1)))) * 1e3
        assert rmse == pytest.approx(r["validation_rmse_mm"], rel=1e-9)
        # and is close to the simulated truth
        truth = json.loads((root / r["robot"] / "truth.json").read_text())
        true_theta = np.array([truth["parameters"][n] for n in rob.params.names])
        err = rob.kinematics(val.readings, jacobian=False).p - rob.kinematics(val.readings, true_theta,
                                                                               jacobian=False).p
        assert np.sqrt(np.mean(np.sum(err ** 2, -1))) * 1e3 < 0.1 * r["validation_rmse_before_mm"]


def test_fleet_cli_summary_models_and_broken_robot(fleet, tmp_path):
    from typer.testing import CliRunner

    from estcal.cli.main import app

    models, summary = tmp_path / "models", tmp_path / "summary.json"
    res = CliRunner().invoke(app, ["fleet", str(fleet), "--save-models", str(models), "--json", str(summary)])
    assert res.exit_code == 0, res.output
    assert "3 of 4 robots calibrated" in res.output and "FAILED" in res.output
    s = json.loads(summary.read_text())
    assert (s["n_robots"], s["n_ok"], s["n_failed"]) == (4, 3, 1)
    assert [r["robot"] for r in s["robots"]] == ["robot_0000", "robot_0001", "robot_0003"]
    (f,) = s["failures"]
    assert f["robot"] == "robot_0002" and "data.csv" in f["inputs"] and f["error"]
    for r in s["robots"]:
        assert r["poses"] == 25 and r["rmse_after_mm"] < 0.1 * r["rmse_before_mm"]
    assert sorted(p.name for p in models.iterdir()) == ["robot_0000.yaml", "robot_0001.yaml", "robot_0003.yaml"]
    _check_models(fleet, models, s["robots"])
    strict = CliRunner().invoke(app, ["fleet", str(fleet), "--strict"])
    assert strict.exit_code == 1


def test_fleet_on_dask_equals_serial(fleet, client, tmp_path):
    from estcal.workflows.fleet import FleetOptions, run_fleet

    a = run_fleet(fleet, FleetOptions(save_models=str(tmp_path / "a")), progress=False)
    b = run_fleet(fleet, FleetOptions(save_models=str(tmp_path / "b")), scheduler=client, progress=False)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "model"} for r in rows]  # noqa: E731
    assert strip(a.rows) == strip(b.rows) and a.failures == b.failures
    from estcal.io.robotfile import calibration_covariance, load_robot

    for r in a.rows:  # same saved models (the files differ only by their write date)
        ma, mb = (load_robot(tmp_path / d / f"{r['robot']}.yaml") for d in "ab")
        assert np.array_equal(ma.params.values, mb.params.values)
        (na, Ca), (nb, Cb) = calibration_covariance(ma), calibration_covariance(mb)
        assert na == nb and np.array_equal(Ca, Cb)


def test_fleet_discovery_errors(tmp_path):
    from typer.testing import CliRunner

    from estcal.cli.main import app

    res = CliRunner().invoke(app, ["fleet", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "not a folder" in res.output
    (tmp_path / "r1").mkdir()
    (tmp_path / "r1" / "data.csv").write_text("j1\n0\n")
    res = CliRunner().invoke(app, ["fleet", str(tmp_path)])
    assert res.exit_code == 2 and "no robot file" in res.output  # every robot failed
    res = CliRunner().invoke(app, ["fleet", str(tmp_path), "--scheduler", "threads"])
    assert res.exit_code == 2 and "--scheduler" in res.output


def test_design_restarts_identical_on_dask(client):
    from estcal.design import DesignModel
    from estcal.design.plans import optimise_continuous
    from estcal.kinematics.robots import planar2

    model = DesignModel(planar2(), "position", ["a_1", "a_2", "offset_1", "offset_2"], sigma=1e-3)
    q0 = np.array([[-0.8, 0.35]])
    a = optimise_continuous(model, 3, "test-pose", n_starts=4, rng=0, q_test=q0, scheduler="serial")
    b = optimise_continuous(model, 3, "test-pose", n_starts=4, rng=0, q_test=q0, scheduler=client)
    np.testing.assert_array_equal(a.readings, b.readings)
    assert a.info == b.info and a.value == b.value and not a.info["failed_starts"]


def test_on_done_sees_every_task_once_as_it_arrives(client):
    tasks = [4.0, -1.0, 9.0, 16.0, 25.0, -4.0, 36.0]
    for sched in ("serial", client):
        seen = []
        out = run_tasks(math.sqrt, tasks, scheduler=sched, chunksize=2, on_done=lambda *a: seen.append(a))
        assert sorted(i for i, _, _ in seen) == list(range(len(tasks)))
        for i, value, failure in seen:
            assert (value, failure) == ((out.results[i], None) if i not in out.failed else
                                        (None, out.failures[[f.index for f in out.failures].index(i)]))
        assert {i for i, _, f in seen if f is not None} == {1, 5}


# ------------------------------------------------------------ fleets generated on demand, resumed runs
def test_generated_fleet_is_the_folder_fleet_without_files(tmp_path):
    """The same seed gives the same robots generated in memory as written to folders (up to the CSV's
    15 digits), and the same calibrations."""
    from estcal.io import load_dataset
    from estcal.io.robotfile import load_robot
    from estcal.simulate.fleet import FleetSpec, simulate_fleet
    from estcal.workflows.fleet import discover_fleet, run_fleet

    simulate_fleet(3, tmp_path / "files", n_poses=20, n_validate=10, seed=4, p_effect=1.0, progress=False)
    spec = simulate_fleet(3, tmp_path / "gen", n_poses=20, n_validate=10, seed=4, p_effect=1.0, on_demand=True)
    assert sorted(p.name for p in (tmp_path / "gen").iterdir()) == ["fleet.yaml", "robot.yaml"]
    assert FleetSpec.read(tmp_path / "gen" / "fleet.yaml") == spec
    rob = load_robot(tmp_path / "files" / "robot.yaml")
    for i in range(3):
        g, folder = spec.generate(i), tmp_path / "files" / spec.name(i)
        for name, ds in (("data.csv", g.dataset), ("validate.csv", g.validation)):
            ref = load_dataset(folder / name, rob)
            assert ds.n == ref.n
            np.testing.assert_allclose(ds.readings, ref.readings, rtol=0, atol=1e-13)
            np.testing.assert_allclose(ds.p, ref.p, rtol=0, atol=1e-13)
            np.testing.assert_allclose(ds.R, ref.R, rtol=0, atol=1e-13)
        assert g.effects == json.loads((folder / "truth.json").read_text())["fleet"]["effects"]
    assert [j.name for j in discover_fleet(tmp_path / "gen")] == [j.name for j in discover_fleet(tmp_path / "files")]
    a, b = run_fleet(tmp_path / "files", progress=False), run_fleet(tmp_path / "gen", progress=False)
    assert b.n_ok == 3
    for ra, rb in zip(a.rows, b.rows):
        assert ra["robot"] == rb["robot"] and ra["n_parameters"] == rb["n_parameters"]
        for k in ("rmse_before_mm", "rmse_after_mm", "validation_rmse_mm"):
            assert rb[k] == pytest.approx(ra[k], rel=1e-7), k


def test_fleet_description_errors(tmp_path):
    from estcal.base.errors import InputError
    from estcal.simulate.fleet import simulate_fleet
    from estcal.workflows.fleet import discover_fleet

    simulate_fleet(2, tmp_path, on_demand=True)
    spec_file = tmp_path / "fleet.yaml"
    good = spec_file.read_text()
    for text, message in ((good.replace("poses: 50", "pozes: 50", 1), "unknown key.*pozes"),
                          (good.replace("p_effect: 0.5", "p_effect: 2"), "p_effect = 2.0 is out of range"),
                          (good.replace("robots: 2", "robots: many"), "fleet.yaml: simulated_fleet"),
                          ("robots: 3\n", "expected a 'simulated_fleet:' mapping")):
        spec_file.write_text(text)
        with pytest.raises(InputError, match=message):
            discover_fleet(tmp_path)
    spec_file.write_text(good)
    (tmp_path / "robot_0000").mkdir()
    with pytest.raises(InputError, match="both fleet.yaml .*and robot folders"):
        discover_fleet(tmp_path)


def test_fleet_rerun_skips_only_what_is_done_with_the_same_options_and_inputs(fleet, tmp_path):
    from estcal.workflows.fleet import FleetOptions, run_fleet

    res = tmp_path / "results"
    first = run_fleet(fleet, results=res, progress=False)
    assert (first.n_ok, first.n_skipped, [f["robot"] for f in first.failures]) == (3, 0, ["robot_0002"])
    assert sorted(p.name for p in res.iterdir()) == ["robot_0000.json", "robot_0001.json", "robot_0003.json"]
    again = run_fleet(fleet, results=res, progress=False)
    assert (again.n_ok, again.n_skipped) == (3, 3) and again.rows == first.rows
    assert [f["robot"] for f in again.failures] == ["robot_0002"]  # a failed robot is tried again
    other = run_fleet(fleet, FleetOptions(level="joint_offset"), results=res, progress=False)
    assert (other.n_ok, other.n_skipped) == (3, 0)  # other options: nothing reused
    assert other.rows[0]["n_parameters"] < first.rows[0]["n_parameters"]
    # changed data, and an unreadable saved row, are redone; the others are skipped
    data = fleet / "robot_0001" / "data.csv"
    text = data.read_text()
    try:
        run_fleet(fleet, results=res, progress=False)  # the default options' rows again
        os.utime(data, ns=(data.stat().st_atime_ns, data.stat().st_mtime_ns + 10 ** 9))  # as if rewritten
        (res / "robot_0003.json").write_text('{"robot": "robot_0003", "key": ')
        third = run_fleet(fleet, results=res, progress=False)
        assert (third.n_ok, third.n_skipped) == (3, 1) and third.rows == first.rows
    finally:
        data.write_text(text)


def test_fleet_rows_cut_by_a_crash_are_redone_and_a_failed_write_is_named(fleet, tmp_path, monkeypatch):
    """The rows are renamed into place without an fsync each: what a power failure can leave under a row's
    name — an empty file, or one cut anywhere — is done again by the rerun, never read as a result; a row that
    cannot be written is listed as a failure with the file, and the rerun does that robot again."""
    from estcal.workflows import fleet_results
    from estcal.workflows.fleet import run_fleet

    res = tmp_path / "results"
    first = run_fleet(fleet, results=res, progress=False)
    full = (res / "robot_0003.json").read_text()
    for cut in ("", full[: len(full) // 2], full[:-3]):
        (res / "robot_0003.json").write_text(cut)
        again = run_fleet(fleet, results=res, progress=False)
        assert (again.n_ok, again.n_skipped) == (3, 2) and again.rows == first.rows
        assert (res / "robot_0003.json").read_text() == full
    real = os.replace

    def refuse(src, dst):
        if str(dst).endswith("robot_0001.json"):
            raise OSError(28, "No space left on device")
        return real(src, dst)

    (res / "robot_0001.json").unlink()
    monkeypatch.setattr(fleet_results.os, "replace", refuse)
    lost = run_fleet(fleet, results=res, progress=False)
    monkeypatch.undo()
    assert [r["robot"] for r in lost.rows] == ["robot_0000", "robot_0003"]
    msg = {f["robot"]: f["error"] for f in lost.failures}["robot_0001"]
    assert "result not saved to" in msg and "robot_0001.json" in msg and "No space left" in msg, msg
    assert not [p for p in res.iterdir() if p.name.startswith(".")]  # no temporary file left behind
    final = run_fleet(fleet, results=res, progress=False)
    assert (final.n_ok, final.n_skipped) == (3, 2) and final.rows == first.rows


def test_fleet_cli_says_how_many_it_skipped(tmp_path):
    from typer.testing import CliRunner

    from estcal.cli.main import app

    gen = tmp_path / "gen"
    res = CliRunner().invoke(app, ["simulate", "--fleet", "3", "--on-demand", "--out", str(gen), "--n", "15"])
    assert res.exit_code == 0 and "fleet of 3 robots described in" in res.output, res.output
    res = CliRunner().invoke(app, ["fleet", str(gen)])
    assert res.exit_code == 0 and "3 of 3 robots calibrated; 3 run on serial" in res.output, res.output
    assert sorted(p.name for p in (gen / "_results").iterdir()) == [f"robot_000{i}.json" for i in range(3)]
    res = CliRunner().invoke(app, ["fleet", str(gen)])
    assert res.exit_code == 0 and "3 of 3 robots calibrated (3 skipped: done earlier" in res.output, res.output
    assert CliRunner().invoke(app, ["simulate", "--on-demand"]).exit_code == 2


def test_local_cluster_workers_run_with_the_documented_settings():
    """The LocalCluster's workers get the settings docs/scaling.md measured and recommends: glibc's trim
    threshold at 32 MiB (the nanny's 64 kB cost 8–14 % of a robot's CPU), no statistical profiler, the event
    loop's check and the memory monitor every second."""
    import dask

    from estcal.scale.runner import TRIM_THRESHOLD

    before = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    # as after a LocalCluster of Dask's defaults in this process (its nanny writes its value into our environment)
    os.environ["MALLOC_TRIM_THRESHOLD_"] = "65536"
    try:
        env = run_tasks(os.getenv, ["MALLOC_TRIM_THRESHOLD_"], scheduler="local", n_workers=1, progress=False)
        assert env.values() == [str(TRIM_THRESHOLD)] and TRIM_THRESHOLD == 32 * 2 ** 20
        assert os.environ["MALLOC_TRIM_THRESHOLD_"] == "65536"  # this process's environment as it was
        os.environ["MALLOC_TRIM_THRESHOLD_"] = "1048576"  # a user's own choice is kept
        env = run_tasks(os.getenv, ["MALLOC_TRIM_THRESHOLD_"], scheduler="local", n_workers=1, progress=False)
        assert env.values() == ["1048576"]
    finally:
        if before is None:
            os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        else:
            os.environ["MALLOC_TRIM_THRESHOLD_"] = before
    keys = ["distributed.worker.profile.enabled", "distributed.admin.tick.interval",
            "distributed.worker.memory.monitor-interval"]
    cfg = run_tasks(dask.config.get, keys, scheduler="local", n_workers=1, progress=False).values()
    assert cfg == [False, "1s", "1s"], cfg
