"""Sensor noise from the data: per-row weights from a column (NoiseModel.row_sigma, --row-sigma-mm) and
the REML noise per measurement kind and axis, printed and in JSON by calibrate and diagnose."""
import json

import numpy as np
import pytest

from estcal.methods import NoiseModel, Problem
from estcal.simulate import simulate


def _hetero(seed=5, n=60):
    """PUMA position data whose rows have their own noise σ_i (0.02–0.5 mm), recorded in a column (mm)."""
    from estcal.kinematics.robots import puma560

    sim = simulate(puma560(), n_poses=n, measure="position", errors="random", seed=seed)
    rng = np.random.default_rng(seed)
    sig = np.exp(rng.uniform(np.log(2e-5), np.log(5e-4), n))
    d = sim.dataset.subset(slice(None))
    d.points = sim.true_points[:, :1] + sig[:, None, None] * rng.standard_normal(d.points.shape)
    d.columns["sig_mm"] = sig * 1e3
    return sim, d, sig


def test_row_weights_change_the_fit_as_weighted_least_squares_does():
    from scipy.optimize import least_squares

    from estcal.estimate import calibrate_lsq
    from estcal.kinematics.chunked import tool_poses

    sim, d, sig = _hetero()
    robot = sim.nominal_robot
    free = [n for n in robot.params.names if n.startswith(("offset_", "base_t")) and n != "offset_6"]
    nm_w = NoiseModel(position=1e-4, row_sigma="sig_mm", row_sigma_unit_m=1e-3)
    rows = Problem(robot, [(None, d, nm_w)]).evaluate(robot.params.values)
    np.testing.assert_allclose(rows.sigma, np.repeat(sig, 3))  # every coordinate of a row carries its σ
    w = calibrate_lsq(Problem(robot, [(None, d, nm_w)]), "lm", free=free)
    u = calibrate_lsq(Problem(robot, [(None, d, NoiseModel(position=1e-4))]), "lm", free=free)
    idx = robot.params.indices(free)

    def resid(x):  # the weighted residual written out directly: (measured − predicted) / σ_row
        th = robot.params.values.copy()
        th[idx] = x
        p = tool_poses(robot, d.readings, th, d.context, fields=("p",)).p
        return ((d.points[:, 0] - p) / sig[:, None]).ravel()

    direct = least_squares(resid, robot.params.values[idx], xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    std = np.sqrt(np.diag(w.covariance))
    assert np.max(np.abs(w.theta[idx] - direct) / std) < 1e-3
    assert np.max(np.abs(u.theta[idx] - direct) / std) > 0.1  # the weights matter


def test_bad_row_sigma_columns_are_named():
    from estcal.base.errors import InputError

    from estcal.kinematics.robots import puma560

    _, d, _ = _hetero(n=12)

    robot = puma560()
    with pytest.raises(InputError, match="no column 'nope'"):
        NoiseModel(row_sigma="nope").position_sigma(d)
    d.columns["sig_mm"][3] = 0.0
    with pytest.raises(InputError, match="line 5: column 'sig_mm' = 0.0 is not a positive noise std"):
        Problem(robot, [(None, d, NoiseModel(row_sigma="sig_mm", row_sigma_unit_m=1e-3))]).evaluate(
            robot.params.values)


def test_reml_recovers_the_per_axis_noise_with_row_weights():
    # σ of row i on axis a = s_i · f_a (s_i from a column, f_a per axis): REML with the rows' relative σ
    # recovers f_a at the median row within its standard error
    from estcal.discrepancy.geometric import fit_geometric
    from estcal.discrepancy.noise import measurement_noise
    from estcal.kinematics.robots import puma560

    sim = simulate(puma560(), n_poses=150, measure="position", errors="random", seed=3)
    rng = np.random.default_rng(7)
    s = np.exp(rng.uniform(np.log(0.5), np.log(2.0), sim.dataset.n))
    f = np.array([5e-5, 5e-5, 2e-4])
    d = sim.dataset.subset(slice(None))
    d.points = sim.true_points[:, :1] + (s[:, None] * f)[:, None, :] * rng.standard_normal(d.points.shape)
    d.columns["rel"] = s
    pb, res, free, _ = fit_geometric(sim.nominal_robot, d, NoiseModel(position=1e-4, row_sigma="rel",
                                                                      row_sigma_unit_m=1e-4), level="full")
    out = measurement_noise(pb, res.theta, free)
    med = np.median(s)
    for ax, fa in zip("xyz", f):
        c = out[f"position_{ax}_mm"]
        assert abs(c["std"] - fa * med * 1e3) < 3 * c["std_se"], (ax, c, fa * med * 1e3)
    assert "rows weighted by their own σ" in out["estimated"]


def test_calibrate_and_diagnose_print_and_write_the_noise_per_axis(tmp_path):
    from typer.testing import CliRunner

    from estcal.cli.main import app
    from estcal.io.dataset import write_dataset

    _, d, _ = _hetero(n=40)
    path = tmp_path / "hetero.csv"
    write_dataset(path, d)
    runner = CliRunner()
    for cmd in (["calibrate", str(path), "--robot", "puma560", "--level", "joint_offset"],):
        out = tmp_path / f"{cmd[0]}.json"
        r = runner.invoke(app, cmd + ["--row-sigma-mm", "sig_mm", "--json", str(out)])
        assert r.exit_code == 0, r.output
        assert "measurement noise (REML, per axis of the measuring frame): position x" in r.output
        mn = json.loads(out.read_text())["measurement_noise"]
        assert {"position_x_mm", "position_y_mm", "position_z_mm"} <= set(mn) and "REML" in mn["estimated"]
    # diagnose weighs the rows by the column too (its noise is the rows' weights; the scale is fitted)
    out = tmp_path / "diagnose.json"
    r = runner.invoke(app, ["diagnose", str(path), "--robot", "puma560", "--no-budget", "--folds", "3",
                            "--row-sigma-mm", "sig_mm", "--json", str(out)])
    assert r.exit_code == 0, r.output
    assert json.loads(out.read_text())["noise"]["row_sigma"] == "sig_mm"
    r = runner.invoke(app, ["calibrate", str(path), "--robot", "puma560", "--row-sigma-mm", "nope"])
    assert r.exit_code == 2 and "no column 'nope'" in r.output
