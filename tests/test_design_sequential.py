"""Sequential design: next-pose proposal, Kalman update, active loop, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from estcal.design import criteria as cr
from estcal.design.model import DesignModel, identifiable_subset
from estcal.design.sequential import (CalibrationState, active_calibration, kalman_update, model_for_state,
                                      propose_next_pose)
from estcal.kinematics.robots import puma560

DEG = np.pi / 180
Q0 = np.array([[10, -60, 120, 0, 30, 0]]) * DEG


def _setup():
    robot = puma560()
    free = identifiable_subset(robot, "position")
    return robot, DesignModel(robot, "position", free, sigma=1e-4)


def test_kalman_update_equals_information_form():
    rng = np.random.default_rng(0)
    p = 5
    A = rng.normal(size=(8, p))
    C = np.linalg.inv(A.T @ A + np.eye(p))
    x = rng.normal(size=p)
    H = rng.normal(size=(3, p))
    sig = np.array([0.3, 0.5, 0.7])
    e = rng.normal(size=3)
    xn, Cn = kalman_update(x, C, H, e, sig)
    W = np.diag(1 / sig ** 2)
    Cinf = np.linalg.inv(np.linalg.inv(C) + H.T @ W @ H)  # Mooring (4.70)
    np.testing.assert_allclose(Cn, Cinf, rtol=1e-9, atol=1e-12)
    # information-form mean (4.69) with prior mean x and "measurement" z = e + H x
    xinf = Cinf @ (H.T @ W @ (e + H @ x) + np.linalg.solve(C, x))
    np.testing.assert_allclose(xn, xinf, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("criterion", ["test-pose", "D", "A", "E", "O3"])
def test_next_pose_value_matches_direct_inversion(criterion):
    robot, model = _setup()
    st = CalibrationState.prior(model, 1e-3)
    nxt = propose_next_pose(model, st, criterion, q_test=Q0, n_candidates=300, rng=1, refine=False)
    mdl = model_for_state(model, st)
    H = mdl.jacobian(nxt.readings[None])[0] / model.sigma
    M = np.linalg.inv(st.covariance) + H.T @ H
    direct = float(cr.criterion_value(criterion, M, 1, mdl.position_jacobian(Q0)))
    assert nxt.value_after == pytest.approx(direct, rel=1e-7)
    # one 3-row measurement cannot lower λ_max(C) (= 1/s_min²) of an isotropic 25-parameter prior
    assert nxt.reduction > (-1e-9 if criterion in ("E", "O3") else 0)
    # it is the best of its candidates
    cand = mdl.random_readings(300, np.random.default_rng(1))
    B = mdl.jacobian(cand) / model.sigma
    Ms = np.linalg.inv(st.covariance)[None] + np.einsum("krp,krq->kpq", B, B)
    vals = cr.criterion_value(criterion, Ms, 1, mdl.position_jacobian(Q0))
    best = vals.max() if cr.larger_is_better(criterion) else vals.min()
    assert nxt.value_after == pytest.approx(best, rel=1e-7)


def test_refinement_does_not_worsen():
    robot, model = _setup()
    st = CalibrationState.prior(model, 1e-3)
    a = propose_next_pose(model, st, "test-pose", q_test=Q0, n_candidates=200, rng=3, refine=False)
    b = propose_next_pose(model, st, "test-pose", q_test=Q0, n_candidates=200, rng=3, refine=True)
    assert b.value_after <= a.value_after * (1 + 1e-12)
    lim = robot.limits
    assert np.all(b.readings >= lim[:, 0]) and np.all(b.readings <= lim[:, 1])


def test_state_json_roundtrip_and_result_format(tmp_path):
    robot, model = _setup()
    st = CalibrationState.prior(model, 2e-3)
    p = st.to_json(tmp_path / "s.json")
    st2 = CalibrationState.from_json(p)
    assert st2.parameters == st.parameters
    np.testing.assert_allclose(st2.covariance, st.covariance)
    # CalibrationResult.to_dict() layout
    d = {"parameters": {n: {"estimate": float(v), "std": 1.0} for n, v in zip(st.parameters, st.estimate)},
         "covariance": st.covariance.tolist()}
    (tmp_path / "r.json").write_text(json.dumps(d))
    st3 = CalibrationState.from_json(tmp_path / "r.json")
    np.testing.assert_allclose(st3.estimate, st.estimate)
    (tmp_path / "bad.json").write_text(json.dumps({"parameters": ["a"], "estimate": [1.0]}))
    with pytest.raises(ValueError, match="bad.json.*covariance"):
        CalibrationState.from_json(tmp_path / "bad.json")


def test_filter_covariance_equals_woodbury_prediction():
    """The EKF of estcal.estimate.kalman, after measuring the proposed pose, has the predicted C⁺."""
    robot, model = _setup()
    st = CalibrationState.prior(model, 1e-3)
    rng = np.random.default_rng(4)
    th = robot.params.values.copy()
    th[robot.params.indices(model.free)] += rng.normal(0, 1e-3, model.p)
    truth = robot.with_values(th)
    nxt = propose_next_pose(model, st, "A", n_candidates=100, rng=5, refine=False)
    run = active_calibration(truth, model, st, Q0, target=0.0, strategy="plan", plan=nxt.readings[None],
                             max_measurements=1, rng=6)
    assert run.covariance.shape == (model.p, model.p)
    assert np.trace(run.covariance) == pytest.approx(nxt.value_after, rel=1e-8)


def test_active_loop_needs_fewer_measurements_than_random():
    robot, model = _setup()
    std0 = 1e-3
    st = CalibrationState.prior(model, std0)
    target = 0.08e-3  # 0.08 mm predicted RMS error at the test pose
    n_act, n_rand = [], []
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        th = robot.params.values.copy()
        th[robot.params.indices(model.free)] += rng.normal(0, std0, model.p)
        truth = robot.with_values(th)
        a = active_calibration(truth, model, st, Q0, target, "active", max_measurements=60, rng=seed,
                               n_candidates=200)
        r = active_calibration(truth, model, st, Q0, target, "random", max_measurements=60, rng=seed)
        n_act.append(a.n_reached if a.n_reached is not None else 61)
        n_rand.append(r.n_reached if r.n_reached is not None else 61)
        assert a.n_reached is not None
        # the filter's error at the test pose is consistent with its prediction (3-D Gaussian, 3.5σ band)
        assert a.true_error[-1] < 3.5 * a.predicted[-1]
    assert np.mean(n_act) < np.mean(n_rand)


def test_cli_design_and_next_pose(tmp_path):
    from typer.testing import CliRunner

    from estcal.cli.main import app

    runner = CliRunner()
    out = tmp_path / "d.json"
    res = runner.invoke(app, ["design", "--robot", "planar2", "--n", "3", "--criterion", "test-pose",
                              "--free", "a_1,a_2,offset_1,offset_2", "--test-pose", "-45,20", "--noise-pos-mm", "1",
                              "--n-candidates", "300", "--random-plans", "200", "--json", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads(out.read_text())
    assert d["plan"]["m"] == 3 and d["baseline"]["n_plans"] == 200 and d["beats_random"]
    assert set(d["criteria"]["param_std"]) == {"a_1", "a_2", "offset_1", "offset_2"}
    # at least as good as Klimchik's (0, ±q2) optimum for the 4 parameters, 2σ²/m cos²q20/(1−sin q20),
    # and not better than the lengths-only bound σ²/m cos²q20/(1−sin q20) (more unknowns, more variance)
    bound = np.sqrt(1 / 3 * np.cos(20 * DEG) ** 2 / (1 - np.sin(20 * DEG)))
    assert bound * (1 - 1e-9) <= d["rho0_mm"][0] <= np.sqrt(2) * bound * (1 + 1e-6)
    state = tmp_path / "s.json"
    state.write_text(json.dumps({"parameters": ["a_1", "a_2"], "estimate": [1.0, 0.8],
                                 "covariance": [[1e-6, 0], [0, 1e-6]]}))
    out2 = tmp_path / "n.json"
    res = runner.invoke(app, ["next-pose", "--robot", "planar2", "--state", str(state), "--test-pose", "-45,20",
                              "--n-candidates", "200", "--json", str(out2)])
    assert res.exit_code == 0, res.output
    n = json.loads(out2.read_text())
    assert n["criterion"] == "test-pose" and 0 < n["next"]["reduction"] < 1
    res = runner.invoke(app, ["next-pose", "--robot", "planar2", "--state", str(tmp_path / "missing.json")])
    assert res.exit_code != 0
