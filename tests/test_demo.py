"""The README's main job: `estcal demo` simulates, calibrates and validates at the noise floor."""
from __future__ import annotations

import json

import numpy as np
from scipy import stats
from typer.testing import CliRunner

from estcal.workflows.demo import run_demo
from estcal.cli.main import app


def test_demo_reaches_noise_floor_and_is_consistent():
    out = run_demo(n_poses=50, seed=0)
    # Position error norm of 3 independent N(0, σ²) coordinates: E‖e‖² = 3σ² -> RMSE = √3 σ.
    floor_mm = np.sqrt(3) * out["noise"]["position_mm"]
    assert out["converged"]
    assert out["validation"]["nominal"]["rmse_mm"] > 20 * floor_mm
    assert out["validation"]["calibrated"]["rmse_mm"] < 1.5 * floor_mm
    # NEES against the base-parameter truth is chi-square with p dof
    assert out["nees"] < stats.chi2.ppf(0.999, out["nees_dof"])


def test_demo_cli_json(tmp_path):
    path = tmp_path / "demo.json"
    r = CliRunner().invoke(app, ["demo", "--n", "30", "--json", str(path)])
    assert r.exit_code == 0, r.output
    assert "validation" in r.output and json.loads(path.read_text())["converged"] is True
