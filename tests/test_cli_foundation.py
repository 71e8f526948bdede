"""`estcal simulate` and `estcal fk` through typer's CliRunner."""
from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io.dataset import load_dataset
from estcal.io.robotfile import load_robot, robot_from_dict
from estcal.kinematics.transforms import quat_to_matrix

runner = CliRunner()


def test_help():
    for cmd in (["--help"], ["simulate", "--help"], ["fk", "--help"]):
        r = runner.invoke(app, cmd)
        assert r.exit_code == 0, r.output
    assert "--noise-pos-mm" in runner.invoke(app, ["simulate", "--help"]).output


def test_simulate_then_fk(tmp_path):
    data, truth, summ = tmp_path / "data.csv", tmp_path / "truth.json", tmp_path / "s.json"
    r = runner.invoke(app, ["simulate", "--robot", "puma560_masses", "--n", "30", "--strategy", "S4",
                            "--measure", "pose", "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5", "--errors",
                            "random", "--effects", "joint_compliance:j2,j3", "--payload", "0,5", "--seed", "0",
                            "-o", str(data), "--truth", str(truth), "--json", str(summ)])
    assert r.exit_code == 0, r.output
    assert "nominal vs true, RMS (mm)" in r.output and "poses" in r.output
    s = json.loads(summ.read_text())
    assert s["n_poses"] == 30 and s["measure"] == "pose" and s["nominal_rms_mm"] > 0.5
    assert s["columns"][:9] == ["j1", "j2", "j3", "j4", "j5", "j6", "x", "y", "z"]
    t = json.loads(truth.read_text())
    assert set(t["effects"][0]["params"]) == {"compliance_j2", "compliance_j3"}
    nominal = load_robot("puma560_masses")
    ds = load_dataset(data, nominal)
    assert ds.kind == "pose" and ds.n == 30 and "payload" in ds.context

    # fk of the nominal robot equals the nominal model evaluated here; fk of the saved true
    # robot reproduces the (noisy) measurements to within the noise
    out = tmp_path / "fk.csv"
    r = runner.invoke(app, ["fk", "--robot", "puma560_masses", str(data), "-o", str(out)])
    assert r.exit_code == 0, r.output
    M = np.loadtxt(out, delimiter=",", skiprows=1)
    assert open(out).readline().strip() == "x,y,z,qw,qx,qy,qz"
    k = nominal.kinematics(ds.readings, jacobian=False)
    np.testing.assert_allclose(M[:, :3], k.p, atol=1e-13)
    np.testing.assert_allclose(quat_to_matrix(M[:, 3:]), k.R, atol=1e-13)

    import yaml

    true_file = tmp_path / "true.yaml"
    true_file.write_text(yaml.safe_dump(t["true_robot"]))
    out2 = tmp_path / "fk_true.csv"
    r = runner.invoke(app, ["fk", "--robot", str(true_file), str(data), "-o", str(out2), "--with-joints"])
    assert r.exit_code == 0, r.output
    M2 = np.loadtxt(out2, delimiter=",", skiprows=1)
    np.testing.assert_allclose(M2[:, :6], ds.readings, atol=1e-14)
    assert np.abs(M2[:, 6:9] - ds.p).max() < 6 * 5e-5  # only the measurement noise remains
    truth_robot = robot_from_dict(t["true_robot"])
    assert truth_robot.effects and truth_robot.params["compliance_j2"] == t["effects"][0]["params"]["compliance_j2"]


def test_simulate_errors(tmp_path):
    r = runner.invoke(app, ["simulate", "--robot", "nope_robot"])
    assert r.exit_code == 2 and "unknown robot 'nope_robot'" in r.output
    r = runner.invoke(app, ["simulate", "--effects", "joint_complaince:j2"])
    assert r.exit_code == 2 and "did you mean 'joint_compliance'" in r.output
    r = runner.invoke(app, ["simulate", "--effects", "drift:j2", "--effect-param", "compliance_j2=1"])
    assert r.exit_code == 2 and "belong to none of the requested effects" in r.output
    err = tmp_path / "err.json"
    err.write_text(json.dumps({"offset_2": 0.002}))
    out = tmp_path / "s.json"
    r = runner.invoke(app, ["simulate", "--n", "5", "--errors", str(err), "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["n_parameters_with_error"] == 1


def test_fk_missing_joint_column(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("j1,j2,j3,j4,j5\n0,0,0,0,0\n")
    r = runner.invoke(app, ["fk", "--robot", "puma560", str(p), "-o", str(tmp_path / "o.csv")])
    assert r.exit_code == 2 and "missing joint column" in r.output and "j6" in r.output


def test_benchmark_quick_smoke(tmp_path):
    """The kinematics benchmark runs and writes its documented keys (timing is not asserted)."""
    from conftest import load_experiment

    mod = load_experiment("bench_kinematics", folder="benchmarks")
    out = tmp_path / "b.json"
    mod.main(["--quick", "--poses", "200", "--json", str(out)])
    r = json.loads(out.read_text())
    for key in ("fk_ms", "fk_jac_ms", "poses_per_s", "fd_jac_ms", "fd_over_analytic", "max_abs_diff", "n_params"):
        assert key in r
    assert r["max_abs_diff"] < 1e-6 and r["n_poses"] == 200
