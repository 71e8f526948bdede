"""Issue 2 acceptance: the TIAGo URDF chain reproduces FIGAROH's registration-only figures.

Published (../shared/data/tiago/README.md): fitting only the base (6) and the BL
point in wrist_ft_tool_link (3) on the 11-30 file gives 3.37 mm norm RMSE, and
4.87 mm on the 11-26 file.
"""
from __future__ import annotations

import pytest

from estcal.estimate import calibrate_lsq, register_base
from estcal.io import load_dataset
from estcal.kinematics import tiago
from estcal.methods import Problem


@pytest.mark.parametrize("method", ["lm", "gauss-newton", "iterated-lls", "scipy-lm"])
def test_registration_only_matches_published(tiago_dir, method):
    robot = tiago(n_markers=1)
    train = load_dataset(tiago_dir / "qualisys_2021-11-30_static_postures.csv", robot, points=1)
    valid = load_dataset(tiago_dir / "qualisys_2021-11-26_static_postures.csv", robot, points=1)
    problem = Problem(robot.with_values(register_base(robot, train)), [(None, train)])
    res = calibrate_lsq(problem, method, free=["base_*", "marker1_*"], validation=[valid])
    assert res.converged
    assert res.accuracy["train"]["after"]["rmse_mm"] == pytest.approx(3.37, abs=0.005)
    assert res.accuracy["validation"][0]["after"]["rmse_mm"] == pytest.approx(4.87, abs=0.005)
