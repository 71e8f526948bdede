"""The workflow layer under both faces (docs/architecture.md) and the users' surface it serves.

* a whole ``estcal.calibrate`` call imports nothing of ``estcal.cli``; its errors are the typed
  errors (``estcal.calibrate(robot, "bad.csv")`` raises ``DatasetError``), never the CLI's exit;
* ``sessions --save-model/--report``; ``diagnose --noise-rot-mrad/--known-noise``;
  ``design``/``next-pose -o plan.csv``; ``compensate --json`` names the unit of every value;
* a model exported to URDF recalibrates with the default options;
* ``estcal.compensate(result.robot(), …)`` keeps the covariance;
* ``estimator=`` / ``measure=`` in Python, ``method=`` deprecated with a warning.
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

import estcal
from estcal.base.errors import EstcalWarning
from estcal.cli.main import app
from estcal.io.dataset import DatasetError

runner = CliRunner()


@pytest.fixture(scope="module")
def pose_data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("wf")
    train, valid = folder / "train.csv", folder / "valid.csv"
    for path, seed in ((train, 1), (valid, 2)):
        r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "40", "--measure", "pose", "--noise-pos-mm",
                                "0.05", "--noise-rot-mrad", "0.5", "--seed", str(seed), "--errors",
                                str(folder / "errors.json") if seed == 2 else "random", "-o", str(path),
                                "--truth", str(folder / f"truth{seed}.json")])
        if seed == 1:
            truth = json.loads((folder / "truth1.json").read_text())
            (folder / "errors.json").write_text(json.dumps(truth["errors"]))
        assert r.exit_code == 0, r.output
    return folder, train, valid


def test_python_calibration_imports_nothing_of_the_command_line(pose_data):
    _, train, valid = pose_data
    code = ("import sys, estcal\n"
            f"res = estcal.calibrate('puma560', {str(train)!r}, validate=[{str(valid)!r}], noise=(5e-5, 5e-4),\n"
            "                      known_noise=True)\n"
            "res.to_dict(); res.robot()\n"
            "print(len(res.names), sorted(m for m in sys.modules if m == 'estcal.cli' or m.startswith('estcal.cli.')))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    n, mods = p.stdout.split(" ", 1)
    assert int(n) == 30 and mods.strip() == "[]"


def test_python_errors_are_typed_not_the_cli_exit(tmp_path):
    missing = tmp_path / "bad.csv"
    with pytest.raises(DatasetError, match="bad.csv: dataset file not found"):
        estcal.calibrate("puma560", str(missing))
    missing.write_text("j1,j2,j3\n0,0,0\n")
    with pytest.raises(DatasetError, match="missing joint column"):
        estcal.calibrate("puma560", str(missing))
    missing.write_text("j1,j2,j3,j4,j5,j6,x,y,z\n0,0,0,0,0,0,1,2,nope\n")
    with pytest.raises(DatasetError, match="line 2"):
        estcal.calibrate("puma560", str(missing))


def test_python_estimator_measure_and_the_deprecated_method(pose_data):
    _, train, _ = pose_data
    free = ["offset_2", "offset_3", "a_2"]
    a = estcal.calibrate("puma560", str(train), "gauss-newton", free=free)
    b = estcal.calibrate("puma560", str(train), estimator="gauss-newton", measure="location", free=free)
    with pytest.warns(EstcalWarning, match="method= is deprecated; use estimator='gauss-newton'"):
        c = estcal.calibrate("puma560", str(train), free=free, method="gauss-newton")
    assert a.method == b.method == c.method == "gauss-newton" and b.extra["measure"] == "pose"
    np.testing.assert_array_equal(a.estimate, c.estimate)
    np.testing.assert_allclose(a.estimate, b.estimate, rtol=0, atol=1e-12)


def test_compensating_with_result_robot_keeps_the_covariance(pose_data):
    folder, train, _ = pose_data
    res = estcal.calibrate("puma560", str(train), noise=(5e-5, 5e-4), known_noise=True)
    rb = res.robot()
    cal = rb.meta["calibration"]
    assert cal["free"] == list(res.names) and np.allclose(cal["covariance"], res.covariance)
    ds = estcal.load_dataset(train, rb)
    comp = estcal.compensate(rb, ds.p[:5], ds.readings[:5])
    assert comp.std_mm is not None and np.all(comp.std_mm > 0)
    # the same prediction as the saved model's
    res.save_model(folder / "m.yaml")
    saved = estcal.compensate(estcal.load_robot(folder / "m.yaml"), ds.p[:5], ds.readings[:5])
    np.testing.assert_allclose(comp.std_mm, saved.std_mm, rtol=1e-9)
    np.testing.assert_allclose(comp.readings, saved.readings, rtol=0, atol=1e-12)


def test_exported_urdf_recalibrates_with_the_default_options(pose_data, tmp_path):
    """The identifiable set is judged at the design structure (estcal.kinematics.design): the
    calibrated URDF's axes are off their right angles by milliradians, which made regrouped
    parameters look separable (31 'identifiable', rank-deficient for the estimator)."""
    _, train, _ = pose_data
    cal, urdf = tmp_path / "cal.yaml", tmp_path / "cal.urdf"
    common = ["--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--known-noise"]
    r = runner.invoke(app, ["calibrate", str(train), "-r", "puma560", *common, "--save-model", str(cal),
                            "--json", str(tmp_path / "a.json")])
    assert r.exit_code == 0, r.output
    assert runner.invoke(app, ["export", "-r", str(cal), "--urdf", str(urdf)]).exit_code == 0
    r = runner.invoke(app, ["calibrate", str(train), "-r", str(urdf), "--root", "world", "--tip", "tool", *common,
                            "--json", str(tmp_path / "b.json")])
    assert r.exit_code == 0, r.output
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json"))
    assert b["n_parameters"] == a["n_parameters"] == 30
    assert b["selection"]["condition_number"] < 100
    # the URDF already carries the calibration: the fit stays where it is, to the same residual
    assert b["rmse_mm"]["train"] == pytest.approx(a["rmse_mm"]["train"], rel=1e-6)
    assert b["n_iterations"] <= 2


def test_design_structure_snaps_only_calibration_sized_tilts():
    from estcal.io.robotfile import load_robot
    from estcal.kinematics.design import design_structure

    assert design_structure(load_robot("puma560")) is None  # twists are parameters: nothing to snap
    rb = load_robot("puma560")
    import tempfile
    from pathlib import Path

    from estcal.kinematics.urdf_export import export_urdf

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "p.urdf"
        noisy = rb.with_values(rb.params.values + np.where(np.char.startswith(rb.params.names, "alpha_"), 2e-3, 0.0))
        export_urdf(noisy, path, warn=False)
        ur = load_robot(path, root="world", tip="tool")
        des = design_structure(ur)
        assert des is not None
        prev = None
        for lk in des.links:
            if lk.joint is None:
                continue
            if prev is not None:
                c = abs(float(prev @ (lk.const[:3, :3] @ lk.joint_axis)))
                assert min(c, abs(1 - c)) < 1e-12  # parallel or perpendicular, exactly
            prev = lk.joint_axis
        np.testing.assert_array_equal(des.params.values, ur.params.values)


def test_sessions_save_model_and_report(tmp_path):
    from estcal.io.dataset import write_dataset
    from estcal.kinematics.robots import puma560
    from estcal.sessions.simulate import simulate_sessions

    ds, _ = simulate_sessions(puma560(), 3, 12, {"offset_2": 2e-3}, noise=5e-5, seed=5, error_std=0.0)
    files = []
    for i, d in enumerate(ds):
        files.append(tmp_path / f"day{i + 1}.csv")
        write_dataset(files[-1], d)
    model, rep = tmp_path / "pop.yaml", tmp_path / "rep"
    r = runner.invoke(app, ["sessions", *map(str, files), "-r", "puma560", "--free", "offset_2,offset_3",
                            "--vary", "offset_2", "--noise-pos-mm", "0.05", "--known-noise", "--save-model",
                            str(model), "--report", str(rep), "--json", str(tmp_path / "s.json")])
    assert r.exit_code == 0, r.output
    out = json.loads((tmp_path / "s.json").read_text())
    rb = estcal.load_robot(model)
    cal = rb.meta["calibration"]
    assert cal["free"] == ["offset_2", "offset_3"] and cal["sessions"]["vary"] == ["offset_2"]
    # the saved covariance is a new session's: the population's plus the between-session variance
    C = np.asarray(cal["covariance"])
    std = [out["parameters"][n]["std"] for n in cal["free"]]
    q = out["q"][0]
    assert C[0, 0] == pytest.approx(std[0] ** 2 + q, rel=1e-9) and C[1, 1] == pytest.approx(std[1] ** 2, rel=1e-9)
    assert rb.params["offset_2"] == pytest.approx(out["parameters"]["offset_2"]["estimate"], abs=1e-15)
    html = (rep / "index.html").read_text()
    assert "Between-session variation" in html and (rep / "parameters.png").stat().st_size > 1000


def test_diagnose_noise_rot_and_known_noise(tmp_path):
    data = tmp_path / "d.csv"
    r = runner.invoke(app, ["simulate", "-r", "puma560_masses", "--n", "60", "--measure", "pose", "--noise-pos-mm",
                            "0.05", "--noise-rot-mrad", "0.5", "--seed", "4", "-o", str(data)])
    assert r.exit_code == 0, r.output
    common = ["diagnose", str(data), "-r", "puma560_masses", "--folds", "3", "--no-budget"]
    r = runner.invoke(app, [*common, "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--known-noise",
                            "--json", str(tmp_path / "k.json")])
    assert r.exit_code == 0, r.output
    assert "warning" not in r.stderr, r.stderr
    k = json.loads((tmp_path / "k.json").read_text())
    assert k["noise"] == pytest.approx({"position": 5e-5, "orientation": 5e-4, "scalar": 5e-5, "known": True,
                                        **{x: v for x, v in k["noise"].items()
                                           if x not in ("position", "orientation", "scalar", "known")}})
    # a noise without --known-noise is still taken as known, as before, with a deprecation warning
    r = runner.invoke(app, [*common, "--noise-pos-mm", "0.05", "--json", str(tmp_path / "d.json")])
    assert r.exit_code == 0 and "write --known-noise" in r.stderr, r.output
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["noise"]["known"] and d["noise"]["orientation"] == pytest.approx(5e-5)
    r = runner.invoke(app, [*common, "--json", str(tmp_path / "u.json")])
    assert r.exit_code == 0 and not json.loads((tmp_path / "u.json").read_text())["noise"]["known"]
    # an option of the former diagnosis is refused with what replaced it, not silently ignored
    for former in (["--max-effects", "1"], ["--geometric", "prior"], ["--alpha", "0.05"]):
        r = runner.invoke(app, [*common, *former])
        assert r.exit_code == 2 and "docs/discrepancy.md" in r.stderr, (former, r.output)
    # the link frames' prior width: a positive width in SI from Python, refused otherwise before any work
    from estcal.base.errors import InputError

    for bad in (0.0, -1e-3, float("nan"), "1mm", True):
        with pytest.raises(InputError, match=r"geometric_width must be 'auto' \(the default\), a positive width"):
            estcal.diagnose("puma560", "/nonexistent.csv", geometric_width=bad)


def test_design_and_next_pose_write_a_plan_in_the_dataset_layout(tmp_path):
    from estcal.io.robotfile import load_robot

    plan, js = tmp_path / "plan.csv", tmp_path / "plan.json"
    r = runner.invoke(app, ["design", "-r", "puma560", "--measure", "position", "--n", "12", "--random-plans", "20",
                            "--free", "offset_*,a_2,d_3", "-o", str(plan), "--json", str(js)])
    assert r.exit_code == 0, r.output
    rb = load_robot("puma560")
    ds = estcal.load_dataset(plan, rb)
    d = json.loads(js.read_text())
    assert ds.kind == "none" and ds.n == 12 and d["measure"] == "position"
    np.testing.assert_array_equal(ds.readings, np.asarray(d["plan"]["readings_rad"]))
    # a plan is a candidate file and the input of fk (targets)
    r = runner.invoke(app, ["fk", str(plan), "-r", "puma560", "-o", str(tmp_path / "t.csv"), "--with-joints"])
    assert r.exit_code == 0, r.output
    state = tmp_path / "state.json"
    state.write_text(json.dumps({"parameters": ["offset_2", "offset_3"], "estimate": [0.0, 0.0],
                                 "covariance": [[1e-6, 0.0], [0.0, 1e-6]]}))
    nxt = tmp_path / "next.csv"
    r = runner.invoke(app, ["next-pose", "-r", "puma560", "--state", str(state), "--candidates", str(plan),
                            "--no-refine", "-o", str(nxt), "--json", str(tmp_path / "n.json")])
    assert r.exit_code == 0, r.output
    one = estcal.load_dataset(nxt, rb)
    assert one.n == 1
    np.testing.assert_array_equal(one.readings[0], json.loads((tmp_path / "n.json").read_text())["next"]["readings_rad"])
    assert any(np.array_equal(one.readings[0], q) for q in ds.readings)


def test_compensate_json_names_the_unit_of_every_value(pose_data, tmp_path):
    folder, train, _ = pose_data
    cal = tmp_path / "cal.yaml"
    r = runner.invoke(app, ["calibrate", str(train), "-r", "puma560", "--save-model", str(cal)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["compensate", str(train), "-r", str(cal), "-o", str(tmp_path / "c.csv"), "--json",
                            str(tmp_path / "c.json")])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "c.json").read_text())
    assert set(d["joint_std_median"]) == {f"j{i}_rad" for i in range(1, 7)}
    assert set(d["readings_changed_max"]) == {f"j{i}_rad" for i in range(1, 7)}
    q0 = estcal.load_dataset(train, estcal.load_robot("puma560")).readings
    q1 = np.genfromtxt(tmp_path / "c.csv", delimiter=",", names=True)
    change = {f"j{i}_rad": float(np.abs(q1[f"j{i}"] - q0[:, i - 1]).max()) for i in range(1, 7)}
    assert d["readings_changed_max"] == pytest.approx(change, rel=1e-12)
