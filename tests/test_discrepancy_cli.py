"""`estcal diagnose` CLI, simulation feedback (`simulate_from_fit`) and experiment smoke tests."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.discrepancy import diagnose
from estcal.discrepancy.feedback import identified_robot, residual_comparison, simulate_from_fit, simulate_like
from estcal.discrepancy.hidden import simulate_hidden
from estcal.io import write_dataset
from estcal.io.robotfile import load_robot

REPO = Path(__file__).resolve().parents[1]
SIGMA = 5e-5


@pytest.fixture(scope="module")
def hidden_case():
    robot = load_robot("puma560_masses")
    sim, truth = simulate_hidden(robot, [("joint_compliance", ["j3"], 10.0)], SIGMA, n_poses=40,
                                 measure="position", seed=4)
    return sim, truth


def test_cli_diagnose_names_the_hidden_effect(hidden_case, tmp_path):
    sim, truth = hidden_case
    csv = write_dataset(tmp_path / "data.csv", sim.dataset.subset(slice(0, 32)))
    held = write_dataset(tmp_path / "held_out.csv", sim.dataset.subset(slice(32, None)))
    out = tmp_path / "fit.json"
    r = CliRunner().invoke(app, ["diagnose", str(csv), "--robot", "puma560_masses", "--noise-pos-mm", str(SIGMA * 1e3),
                                 "--json", str(out), "--report", str(tmp_path / "rep"),
                                 "--validate", str(held)])
    assert r.exit_code == 0, r.output
    assert "joint compliance of j3:" in r.output
    d = json.loads(out.read_text())
    assert [(c["effect"], c["joints"]) for c in d["causes"]] == [("joint_compliance", ["j3"])]
    assert d["budget"]["model_mm"] < d["budget"]["geometry_mm"]
    v = d["accuracy"]["validation"]
    assert len(v) == 1 and v[0]["n_new"] == 8 and v[0]["rmse_mm"] < 3 * d["answer"]["expected_mm"]
    assert (tmp_path / "rep" / "partial_residuals.png").exists()
    v = truth[0]["params"]["compliance_j3"]
    p = d["causes"][0]["parameters"]["compliance_j3"]
    assert abs(p["estimate"] - v) < 5 * p["std"] + 0.02 * v
    # closing the loop: `estcal simulate --from-fit` simulates the identified robot
    r = CliRunner().invoke(app, ["simulate", "--from-fit", str(out), "--n", "12", "--seed", "3",
                                 "-o", str(tmp_path / "sim.csv"), "--truth", str(tmp_path / "truth.json")])
    assert r.exit_code == 0, r.output
    t = json.loads((tmp_path / "truth.json").read_text())
    assert t["effects"][0]["effect"] == "joint_compliance"
    assert t["effects"][0]["params"]["compliance_j3"] == pytest.approx(p["estimate"])
    assert t["parameters"]["theta_3"] == pytest.approx(d["model"]["theta"]["theta_3"])
    assert t["noise"]["position"] == pytest.approx(SIGMA)  # the fit's known noise


def test_cli_diagnose_errors_name_the_problem(tmp_path):
    r = CliRunner().invoke(app, ["diagnose", str(tmp_path / "nope.csv"), "--robot", "puma560"])
    assert r.exit_code == 2 and "not found" in r.output
    csv = tmp_path / "bad.csv"
    csv.write_text("j1,j2,j3,j4,j5,j6,x,y,z\n0,0,0,0,0,0,1,1,1\n")
    r = CliRunner().invoke(app, ["diagnose", str(csv), "--robot", "puma560", "--effects", "compliance"])
    assert r.exit_code == 2 and "unknown effect" in r.output


def test_simulate_from_fit_reproduces_the_identified_robot(hidden_case, tmp_path):
    """The simulated truth is the identified robot: noise-free data simulated from the fit are
    reproduced exactly by the extended model at the fitted parameters, and the geometric
    residual statistics of measured and simulated data agree."""
    sim, _ = hidden_case
    res = diagnose(sim.nominal_robot, sim.dataset, noise=SIGMA, robot_spec="puma560_masses")
    path = res.to_json(tmp_path / "fit.json")
    s0 = simulate_from_fit(path, readings=sim.dataset.readings, noise=0.0)
    # the model's backlash terms by approach act with the directions the simulation drew (simulate_from_fit)
    ctx = {k: v for k, v in s0.dataset.columns.items() if k.startswith("approach_")}
    kin = res.robot.kinematics(sim.dataset.readings, context=ctx, jacobian=False)
    pred = kin.points[:, :1] if res.robot.n_markers else kin.p[:, None]
    np.testing.assert_allclose(s0.dataset.points, pred, atol=1e-12)
    assert s0.true_robot.params["compliance_j3"] == pytest.approx(res.causes[0].parameters["compliance_j3"]["estimate"])
    # with the fit's noise at the measured poses: same residual statistics as the measurement
    s1 = simulate_from_fit(path, readings=sim.dataset.readings, seed=9)
    cmp = residual_comparison(path, sim.dataset, s1.dataset)
    m, s = cmp["measured"], cmp["simulated"]
    assert s["rmse_mm"] == pytest.approx(m["rmse_mm"], rel=0.15)
    assert s["partial_rms"]["j3"] == pytest.approx(m["partial_rms"]["j3"], rel=0.25)
    sl = simulate_like(path, sim.dataset, noise=0.0)
    # simulate_like keeps the measurement's own context: the approach directions of its row order
    kin = res.robot.kinematics(sim.dataset.readings, context=res.prepare(sim.dataset).context, jacobian=False)
    np.testing.assert_allclose(sl.points, kin.points[:, :1] if res.robot.n_markers else kin.p[:, None], atol=1e-12)
    np.testing.assert_array_equal(sl.readings, sim.dataset.readings)
    geo, specs = identified_robot(path, geometric_only=True)
    assert specs == [] and not geo.effects


def test_simulate_like_draws_the_fitted_rigid_error_per_posture():
    """With the fit's rigid error per posture (Ψ) and no ``noise``, every row's body moves as one: the simulated
    points minus the prediction are ``δt + δφ × (x − c)`` for one ``(δt, δφ)`` per row, and over many rows their
    variances are Ψ (Monte Carlo against the values put in)."""
    robot = load_robot("puma560_masses")
    sim, _ = simulate_hidden(robot, [], SIGMA, n_poses=30, measure="points", seed=2)
    d = diagnose(sim.nominal_robot, sim.dataset, noise=SIGMA, budget=False).to_dict()
    psi = np.array([1e-6, 4e-6, 0.25e-6, 1e-4, 0.5e-4, 2e-4])  # 1, 2, 0.5 mm; 10, 7.1, 14 mrad
    d["random_effect"] = {"psi_si": psi.tolist(), "sigma_mm": 0.0}
    rows = sim.dataset.subset(np.tile(np.arange(sim.dataset.n), 60))  # 1800 rows: Monte Carlo to ~3 %
    pred = simulate_like(d, rows, noise=0.0).points
    D = simulate_like(d, rows, seed=5).points - pred
    c = pred.mean(axis=1, keepdims=True)
    # each row: D_i = δt + δφ × (x_i − c) = δt − [x_i − c]× δφ, six unknowns from the row's 3k coordinates
    arm = pred - c
    A = np.zeros(arm.shape[:2] + (3, 6))
    A[..., :3] = np.eye(3)
    A[..., 0, 4], A[..., 0, 5] = arm[..., 2], -arm[..., 1]
    A[..., 1, 3], A[..., 1, 5] = -arm[..., 2], arm[..., 0]
    A[..., 2, 3], A[..., 2, 4] = arm[..., 1], -arm[..., 0]
    A = A.reshape(len(rows.points), -1, 6)
    delta = np.linalg.solve(np.swapaxes(A, 1, 2) @ A, np.swapaxes(A, 1, 2) @ D.reshape(len(A), -1, 1))[..., 0]
    np.testing.assert_allclose((A @ delta[..., None])[..., 0], D.reshape(len(A), -1), atol=1e-12)  # rigid
    np.testing.assert_allclose(delta.var(axis=0), psi, rtol=0.12)


def test_detection_power_quick(tmp_path):
    out = tmp_path / "dp.json"
    p = subprocess.run([sys.executable, str(REPO / "experiments" / "detection_power.py"), "--quick", "--json",
                        str(out)], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert p.returncode == 0, p.stderr
    d = json.loads(out.read_text())
    assert {"power", "false_positive", "config"} <= set(d)
    assert all(0 <= x["rate"] <= 1 for x in d["power"])


def test_cli_diagnose_effects_none_is_the_geometry_alone(hidden_case, tmp_path):
    """``--effects none``: no effect term is a candidate, the model is the geometry and the budget's model line equals
    its geometry line; the hidden compliance stays in what is unexplained (far above the default's answer)."""
    sim, _ = hidden_case
    csv = write_dataset(tmp_path / "data.csv", sim.dataset)
    outs = {}
    for name, extra in (("none", ["--effects", "none"]), ("default", [])):
        out = tmp_path / f"{name}.json"
        r = CliRunner().invoke(app, ["diagnose", str(csv), "--robot", "puma560_masses", "--noise-pos-mm",
                                     str(SIGMA * 1e3), "--known-noise", "--json", str(out), *extra])
        assert r.exit_code == 0, r.output
        outs[name] = (r.output, json.loads(out.read_text()))
    text, d = outs["none"]
    assert "none considered" in text and d["causes"] == [] and d["terms"]["effects_considered"] == 0
    assert d["budget"]["model_mm"] == pytest.approx(d["budget"]["geometry_mm"], rel=1e-9)
    assert d["answer"]["expected_mm"] > 3 * outs["default"][1]["answer"]["expected_mm"]
