"""Gough simulator built on the shared simulator's NoiseModel/ErrorModel."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estcal.parallel.data import load_gough_data
from estcal.parallel.gough import load_gough
from estcal.workflows.gough import calibrate_gough, simulate_gough


def test_noise_free_random_errors_are_recovered(tmp_path):
    sim = simulate_gough("left_hand", 40, errors="random", error_std={"length": 1e-3, "offset": 2e-3}, seed=3)
    assert len(sim.errors) == 42 and np.std(list(sim.errors.values())) > 5e-4
    res = calibrate_gough(sim.nominal_robot, sim.data)
    np.testing.assert_allclose(res.theta, sim.true_robot.theta, atol=1e-10)
    csv, truth, rob = tmp_path / "d.csv", tmp_path / "t.json", tmp_path / "true.yaml"
    sim.write(csv, truth, rob)
    assert json.loads(truth.read_text())["true_parameters"]["a3_x"] == pytest.approx(sim.true_robot.a[2, 0])
    np.testing.assert_allclose(load_gough(rob).theta, sim.true_robot.theta, atol=1e-15)
    np.testing.assert_allclose(load_gough_data(csv).rho, sim.data.rho, atol=1e-12)


def test_noise_statistics_match_the_noise_model():
    n = 4000
    sim = simulate_gough("left_hand", n, noise={"position": 1e-4, "orientation": 1e-3, "joint": 2e-5,
                                                "distribution": "uniform"}, seed=1)
    dp = sim.data.T[:, :3, 3] - sim.true_T[:, :3, 3]
    dr = sim.data.rho - sim.true_rho
    # uniform half-width a: bounded by a, variance a²/3 (relative s.e. of a variance ≈ sqrt(0.8/n))
    assert np.abs(dp).max() <= 1e-4 and np.abs(dr).max() <= 2e-5
    assert np.var(dp) / (1e-8 / 3) == pytest.approx(1.0, abs=5 * np.sqrt(0.8 / dp.size))
    assert np.var(dr) / (4e-10 / 3) == pytest.approx(1.0, abs=5 * np.sqrt(0.8 / dr.size))
    assert sim.data.sigma_rho == pytest.approx(2e-5 / np.sqrt(3))
    with pytest.raises(KeyError, match="a9_x"):
        simulate_gough("left_hand", 3, errors={"a9_x": 1e-3})
