"""The Python API (docs/api.md): lazy top-level names, `estcal.calibrate` / `estcal.diagnose`
on paths and objects, the `noise=` forms, and `save_model` from Python."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import estcal
from estcal.workflows.calibrate import run_calibration
from estcal.io import write_dataset
from estcal.methods import NoiseModel
from estcal.simulate import simulate


def test_import_is_lazy_and_names_resolve():
    code = ("import sys, estcal; assert 'numpy' not in sys.modules, 'numpy imported'; "
            "f = estcal.calibrate; assert 'gtsam' not in sys.modules and 'emcee' not in sys.modules; "
            "print(sorted(n for n in estcal.__all__ if n != '__version__'))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    for name in estcal.__all__:
        assert getattr(estcal, name) is not None
    with pytest.raises(AttributeError, match="no attribute 'nosuch'"):
        estcal.nosuch  # noqa: B018


def test_noise_forms():
    from estcal.api import as_noise

    assert as_noise(None) == NoiseModel()
    n = as_noise(5e-5)
    assert (n.position, n.orientation, n.scalar, n.known) == (5e-5, 5e-4, 5e-5, False)
    n = as_noise((2e-5, 3e-4), known=True)
    assert (n.position, n.orientation, n.known) == (2e-5, 3e-4, True)
    n = as_noise({"position": 1e-4, "known": True})
    assert (n.position, n.scalar, n.orientation, n.known) == (1e-4, 1e-4, NoiseModel.orientation, True)
    given = NoiseModel(position=1.0)
    assert as_noise(given) is given
    with pytest.raises(ValueError, match="unknown key"):
        as_noise({"pos": 1e-4})
    with pytest.raises(ValueError, match="> 0 m"):
        as_noise(-1.0)


def test_calibrate_on_paths_equals_the_cli_entry_point(tmp_path):
    """`estcal.calibrate` on CSV paths of point data (unknown markers) gives the result of
    run_calibration on the same loaded objects, and save_model round-trips its predictions."""
    sim = simulate("puma560", n_poses=30, measure="points", n_points=2, seed=7, errors="random",
                   noise={"position": 1e-4})
    val = simulate("puma560", n_poses=10, measure="points", markers=sim.true_robot.params.values[
        sim.true_robot.marker_idx], errors=sim.truth["errors"], seed=8, noise={"position": 1e-4})
    tr, va = write_dataset(tmp_path / "tr.csv", sim.dataset), write_dataset(tmp_path / "va.csv", val.dataset)
    res = estcal.calibrate("puma560", tr, validate=[va], noise=1e-4, max_iter=60)
    robot = estcal.load_robot("puma560", n_markers=2)
    ref, _, _ = run_calibration(robot, estcal.load_dataset(tr, robot, points=2),
                                validate=[estcal.load_dataset(va, robot, points=2)],
                                noise=NoiseModel(position=1e-4, orientation=1e-3, scalar=1e-4),
                                options={"max_iter": 60})
    assert res.names == ref.names
    np.testing.assert_allclose(res.estimate, ref.estimate, rtol=0, atol=1e-12)
    assert res.extra["options"] == {"max_iter": 60}
    assert len(res.accuracy["validation"]) == 1
    fitted = res.robot()
    assert fitted.n_markers == 2
    model = estcal.load_robot(res.save_model(tmp_path / "m.yaml"))
    q = val.dataset.readings
    d = np.abs(model.kinematics(q, jacobian=False).points - fitted.kinematics(q, jacobian=False).points).max()
    assert d < 1e-12
    names, C = estcal.calibration_covariance(model)
    assert names == res.names
    np.testing.assert_array_equal(C, res.covariance)
    with pytest.raises(ValueError, match="has no option 'max_iters'"):
        estcal.calibrate("puma560", tr, max_iters=3)


def test_saved_model_from_an_estimator_called_directly(tmp_path):
    """A result made by an estimator function (not the workflow) still knows its problem."""
    from estcal.estimate import calibrate_lsq
    from estcal.estimate.testproblems import simulated_problem

    sim = simulated_problem("puma560", n_poses=25, seed=1)
    res = calibrate_lsq(sim.problem, "lm", free=sim.free)
    path = res.save_model(tmp_path / "direct.yaml")
    back = estcal.load_robot(path)
    q = sim.problem.terms[0].data.readings
    assert np.abs(back.kinematics(q, jacobian=False).p - res.robot().kinematics(q, jacobian=False).p).max() < 1e-12
    block = back.meta["calibration"]
    assert block["data"] == [{"file": None, "sha256": None, "n_poses": 25, "role": "train"}]
    assert block["estimator"] == "lm" and block["free"] == list(res.names)


def test_diagnose_from_python_and_save(tmp_path):
    robot = estcal.load_robot("puma560_masses")
    sim = simulate(robot, n_poses=30, measure="position", noise={"position": 5e-5}, seed=3,
                   effects=[{"effect": "joint_compliance", "joints": ["j3"], "params": {"compliance_j3": 3e-5}}])
    path = write_dataset(tmp_path / "d.csv", sim.dataset)
    diag = estcal.diagnose(robot, path, noise=5e-5, effects=["joint_compliance"], folds=3)
    assert [(c.effect, c.joints) for c in diag.causes] == [("joint_compliance", ["j3"])]
    model = estcal.load_robot(diag.save_model(tmp_path / "diag.yaml"))
    kin = model.kinematics(sim.dataset.readings, jacobian=False)
    ref = diag.robot.kinematics(sim.dataset.readings, jacobian=False)
    assert np.abs(kin.p - ref.p).max() < 1e-12
    est = model.params["compliance_j3"]
    std = diag.causes[0].parameters["compliance_j3"]["std"]
    assert abs(est - 3e-5) < 4 * std
