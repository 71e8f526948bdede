"""The result protocol (estcal/base/result.py): to_dict, to_json, save_model, table, a readable repr —
the same for a calibration and a sessions fit; parameter tables from the one builder."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estcal.base.result import Result
from estcal.base.tables import Table, parameter_table
from estcal.estimate.lsq import calibrate_lsq
from estcal.estimate.testproblems import simulated_problem
from estcal.io.dataset import write_dataset
from estcal.io.robotfile import calibration_covariance, load_robot
from estcal.kinematics.robots import puma560
from estcal.methods import NoiseModel
from estcal.sessions import fit_sessions, simulate_sessions

NOISE = NoiseModel(position=5e-5, known=True)


@pytest.fixture(scope="module")
def calibration():
    sim = simulated_problem("planar2", n_poses=20, method="position", free=["a_1", "a_2", "offset_2"])
    return calibrate_lsq(sim.problem)


@pytest.fixture(scope="module")
def session_fit():
    robot = puma560()
    ds, _ = simulate_sessions(robot, 3, 15, {"offset_2": 1e-3}, seed=2)
    free = ["offset_1", "offset_2", "offset_3", "base_tx", "base_ty", "base_tz"]
    return fit_sessions(robot, ds, free, ["offset_2"], noise=NOISE)


def _check_protocol(res, tmp_path, units):
    assert isinstance(res, Result)
    d = res.to_dict()
    assert json.loads(json.dumps(d)) == json.loads((res.to_json(tmp_path / "r.json")).read_text())
    t = res.table()
    assert isinstance(t, Table) and [r[0] for r in t.rows] == list(res.names)
    # the table's numbers are the result's, in display units
    est = [r[t.columns.index("estimate")] for r in t.rows]
    np.testing.assert_allclose(est, np.asarray(res.estimate) * units, rtol=1e-12)
    text = repr(res)
    assert text == str(res) and text.startswith(type(res).__name__) and "array(" not in text
    assert all(n in text for n in res.names)


def test_calibration_result_follows_the_protocol(calibration, tmp_path):
    _check_protocol(calibration, tmp_path, 1e3)
    assert calibration.table().rows[2][-1] == "mrad"  # offset of a revolute joint
    model = calibration.save_model(tmp_path / "m.yaml")
    names, C = calibration_covariance(load_robot(model))
    assert names == calibration.names and np.allclose(C, calibration.covariance)


def test_session_fit_follows_the_protocol(session_fit, tmp_path):
    _check_protocol(session_fit, tmp_path, 1e3)
    path = session_fit.save_model(tmp_path / "pop.yaml")
    robot = load_robot(path)
    names, C = calibration_covariance(robot)
    # a new session's covariance (population + between-session Q): what compensate should expect on a new day
    assert names == session_fit.names and np.allclose(C, session_fit.new_session_cov())
    assert np.allclose(robot.meta["calibration"]["population_covariance"], session_fit.cov)
    np.testing.assert_allclose(robot.params.values[robot.params.indices(names)], session_fit.estimate, rtol=1e-12)
    assert robot.meta["calibration"]["variance_components"][0]["parameter"] == "offset_2"


def test_to_json_never_writes_over_an_input(session_fit, tmp_path):
    d = write_dataset(tmp_path / "s.csv", session_fit.datasets[0])
    res = fit_sessions(session_fit.robot, [load_dataset_from(d, session_fit.robot)], session_fit.names, [],
                       noise=NOISE)
    with pytest.raises(ValueError, match="is an input"):
        res.to_json(d)
    with pytest.raises(ValueError, match="is an input"):
        res.save_model(d)


def load_dataset_from(path, robot):
    from estcal.io.dataset import load_dataset

    return load_dataset(path, robot)


def test_parameter_table_builder():
    class R:
        names = ["a", "b"]
        nominal = np.array([1.0, 2.0])
        estimate = np.array([1.5, 2.5])
        std = np.array([0.1, 0.2])

    t = parameter_table(R(), lambda n: ("mm", 1e3), label=lambda n: n + " [+1·c]" if n == "a" else n)
    assert t.columns == ["parameter", "initial", "estimate", "± std", "unit", "absorbs (regrouped)"]
    assert t.rows[0] == ["a", 1000.0, 1500.0, 100.0, "mm", "[+1·c]"] and t.rows[1][-1] == ""
    t2 = parameter_table(type("S", (), {"names": ["a"], "estimate": [1.0], "std": [0.5]})())
    assert t2.columns == ["parameter", "estimate", "± std", "unit"] and t2.rows == [["a", 1.0, 0.5, "SI"]]
    assert str(t2).splitlines()[-1].split() == ["a", "1", "0.5", "SI"]
