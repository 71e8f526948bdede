"""Every estimator's JSON is a valid state for the next-pose loop (docs/design.md, sequential design).

The active loop is calibrate/online → next-pose → measure → … ; the state file
is the JSON the estimator wrote. Filter covariances are symmetric only to
round-off, so the state must be judged symmetric on the correlation scale.
"""
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.design.sequential import CalibrationState

runner = CliRunner()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("handoff")
    path = d / "pose.csv"
    r = runner.invoke(app, ["simulate", "--robot", "puma560", "--n", "40", "--measure", "position",
                            "--noise-pos-mm", "0.1", "--seed", "3", "-o", str(path)])
    assert r.exit_code == 0, r.output
    return path


FREE = "offset_1,offset_2,offset_3,a_2,d_3"
ESTIMATORS = ["lm", "gauss-newton", "iterated-lls", "scipy-lm", "gtsam", "isam2", "gtsam-timevarying",
              "kalman", "ukf", "mcmc"]


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_calibrate_json_feeds_next_pose(data, tmp_path, estimator):
    out = tmp_path / f"{estimator}.json"
    args = ["calibrate", str(data), "--robot", "puma560", "--free", FREE, "--estimator", estimator,
            "--json", str(out)]
    if estimator == "mcmc":
        args += ["--option", "max_steps=400", "--option", "target_ess=200"]
    if estimator == "gtsam-timevarying":
        args += ["--option", "q=0.0000001"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    st = CalibrationState.from_json(out)
    assert np.array_equal(st.covariance, st.covariance.T)
    assert np.all(np.linalg.eigvalsh(st.covariance) > 0)
    r = runner.invoke(app, ["next-pose", "--robot", "puma560", "--state", str(out), "--n-candidates", "50",
                            "--no-refine"])
    assert r.exit_code == 0, r.output


def test_online_json_feeds_next_pose(data, tmp_path):
    out = tmp_path / "online.json"
    r = runner.invoke(app, ["online", str(data), "--robot", "puma560", "--free", FREE, "--json", str(out)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["next-pose", "--robot", "puma560", "--state", str(out), "--n-candidates", "50",
                            "--no-refine"])
    assert r.exit_code == 0, r.output


def test_round_off_asymmetry_accepted_real_asymmetry_refused():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 4))
    C = (A @ A.T) * np.array([1e-12, 1e-6, 1.0, 1e-8])[:, None] * np.array([1e-12, 1e-6, 1.0, 1e-8])[None, :]
    s01 = np.sqrt(C[0, 0] * C[1, 1])
    C[0, 1] = C[1, 0] = 1e-12 * s01  # a near-zero correlation …
    C[1, 0] += 1e-16 * s01  # … with the EKF's round-off: far above rtol 1e-8 of the entry itself
    assert not np.allclose(C, C.T, rtol=1e-8, atol=0)  # the old test refused this state
    st = CalibrationState(list("abcd"), np.zeros(4), C)
    assert np.array_equal(st.covariance, st.covariance.T)
    B = C.copy()
    B[0, 2] += 0.5 * np.sqrt(C[0, 0] * C[2, 2])  # half a correlation unit: a corrupted file
    with pytest.raises(ValueError, match=r"not symmetric \(entries \[a, c\]"):
        CalibrationState(list("abcd"), np.zeros(4), B)
    with pytest.raises(ValueError, match="finite"):
        CalibrationState(["a"], [np.nan], [[1.0]])


def test_state_from_json_file_with_result_layout(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps({"parameters": {"a": {"estimate": 1.0}, "b": {"estimate": 2.0}},
                             "covariance": [[1.0, 0.1], [0.1 + 1e-18, 2.0]]}))
    st = CalibrationState.from_json(p)
    assert st.parameters == ["a", "b"] and st.estimate.tolist() == [1.0, 2.0]
