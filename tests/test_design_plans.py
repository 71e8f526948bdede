"""Plan optimisation: optimised plans beat random ones; predicted accuracy matches Monte Carlo."""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from estcal.design import criteria as cr
from estcal.design.criteria import criterion_value, larger_is_better
from estcal.design.model import DesignModel, identifiable_subset
from estcal.design.plans import (evaluate_plan, fedorov_exchange, greedy, load_candidates, detmax,
                                 optimise_continuous, optimise_discrete, random_baseline, replicate)
from estcal.kinematics.robots import planar2, puma560, stanford

DEG = np.pi / 180
Q_TEST = {"puma560": np.array([[10, -60, 120, 0, 30, 0]]) * DEG,
          "stanford": np.array([[10, -30, 0, 20, 30, 0]]) * DEG + np.array([[0, 0, 0.6, 0, 0, 0]])}
_MODELS = {}


def _model(name):
    if name not in _MODELS:
        robot = {"puma560": puma560, "stanford": stanford}[name]()
        _MODELS[name] = DesignModel(robot, "position", identifiable_subset(robot, "position"), sigma=1e-4)
    return _MODELS[name]


@pytest.mark.parametrize("robot", ["puma560", "stanford"])
@pytest.mark.parametrize("criterion", ["D", "A", "O1", "test-pose", "E"])
def test_optimised_plan_beats_best_of_1000_random(robot, criterion):
    model = _model(robot)
    m = 12  # 36 position rows for 25 parameters
    q0 = Q_TEST[robot]
    plan = optimise_discrete(model, m, criterion, n_candidates=400, restarts=1, rng=1, q_test=q0)
    base = random_baseline(model, m, criterion, n_plans=1000, rng=2, q_test=q0)
    if larger_is_better(criterion):
        assert plan.value > base.max
    else:
        assert plan.value < base.min
    # the reported value is the criterion of the returned readings
    J0 = model.position_jacobian(q0)
    assert plan.value == pytest.approx(float(criterion_value(criterion, model.information(plan.readings), m, J0)))


def test_cond_criterion_beats_random_puma():
    model = _model("puma560")
    plan = optimise_discrete(model, 12, "cond", n_candidates=200, restarts=1, rng=3)
    base = random_baseline(model, 12, "cond", n_plans=1000, rng=4)
    assert plan.value < base.min


def test_greedy_fedorov_detmax_improve_in_order():
    model = _model("puma560")
    cand = model.random_readings(300, 5)
    g = greedy(model, cand, 10, "D")
    f = fedorov_exchange(model, cand, 10, "D", start=g.info["candidate_indices"])
    d = detmax(model, cand, 10, "D", start=g.info["candidate_indices"], max_excursion=2)
    assert f.value <= g.value * (1 + 1e-12) and d.value <= g.value * (1 + 1e-12)
    # an exchange optimum: no single swap improves it
    M = model.information(f.readings)
    F = model.pose_information(cand)
    from estcal.design.criteria import d_criterion
    best_swap = min(d_criterion(M - F[i] + F).min() for i in f.info["candidate_indices"])
    assert best_swap >= f.value * (1 - 1e-9)


def test_replication_divides_rho0_squared():
    model = _model("puma560")
    q0 = Q_TEST["puma560"]
    plan = optimise_discrete(model, 9, "test-pose", n_candidates=300, restarts=1, rng=6, q_test=q0)
    for k in (2, 4):
        rep = replicate(plan, k, model, q_test=q0)
        assert rep.m == 9 * k
        assert rep.value == pytest.approx(plan.value / k, rel=1e-9)


def test_random_baseline_vectorised_equals_loop():
    model = _model("stanford")
    q0 = Q_TEST["stanford"]
    b = random_baseline(model, 10, "test-pose", n_plans=50, rng=11, q_test=q0, keep_values=True, chunk=7)
    # regenerate the same plans in the same order
    rng = np.random.default_rng(11)
    J0 = model.position_jacobian(q0)
    vals = []
    done = 0
    while done < 50:
        nb = min(7, 50 - done)
        Q = model.random_readings(nb * 10, rng).reshape(nb, 10, -1)
        vals += [float(cr.test_pose_criterion(model.information(Q[i]), J0)) for i in range(nb)]
        done += nb
    np.testing.assert_allclose(b.values, vals, rtol=1e-10)
    assert b.min == pytest.approx(min(vals)) and b.mean == pytest.approx(np.mean(vals))
    assert b.percentiles[50] == pytest.approx(np.median(vals))


def test_continuous_optimisation_within_limits_and_executor():
    model = DesignModel(planar2(), "position", ["a_1", "a_2", "offset_1", "offset_2"], sigma=1e-3)
    q0 = np.array([[-45 * DEG, 20 * DEG]])
    with ThreadPoolExecutor(2) as ex:
        plan = optimise_continuous(model, 3, "test-pose", n_starts=4, rng=0, q_test=q0, scheduler=ex)
    lim = model.robot.limits
    assert np.all(plan.readings >= lim[:, 0] - 1e-12) and np.all(plan.readings <= lim[:, 1] + 1e-12)
    # Klimchik eq. (20) doubled (lengths and offsets contribute equally): 2σ²/m cos²q20/(1−|sin q20|)
    closed = 2 * 1e-6 / 3 * np.cos(20 * DEG) ** 2 / (1 - np.sin(20 * DEG))
    assert plan.value <= closed * (1 + 1e-4)


def test_continuous_with_constraint_callback():
    model = DesignModel(planar2(), "position", ["a_1", "a_2"], sigma=1e-3)
    q0 = np.array([[-45 * DEG, 20 * DEG]])
    plan = optimise_continuous(model, 2, "test-pose", n_starts=2, rng=1, q_test=q0, scheduler="serial",
                               constraint=_q2_positive_cap)
    assert plan.info["feasible"]
    assert np.all(plan.readings[:, 1] >= -1e-6) and np.all(plan.readings[:, 1] <= 1.0 + 1e-6)


def _q2_positive_cap(Q):
    """Feasible when 0 ≤ q2 ≤ 1 rad (module level: picklable)."""
    Q = np.atleast_2d(Q)
    return np.stack([Q[:, 1], 1.0 - Q[:, 1]], -1)


def test_monte_carlo_matches_predicted_test_pose_error():
    """ρ0 of an optimised plan vs the Monte-Carlo error of weighted LS calibrations with it (linearised)."""
    model = _model("puma560")
    q0 = Q_TEST["puma560"]
    plan = optimise_discrete(model, 12, "test-pose", n_candidates=300, restarts=1, rng=21, q_test=q0)
    rho_pred = np.sqrt(plan.value)
    J = model.jacobian(plan.readings).reshape(-1, model.p)
    J0 = model.position_jacobian(q0)[0]
    sigma = model.sigma
    rng = np.random.default_rng(22)
    reps = 4000
    true_dtheta = rng.normal(0, 1e-3, (reps, model.p))
    y = true_dtheta @ J.T + rng.normal(0, sigma, (reps, J.shape[0]))
    est = np.linalg.lstsq(J, y.T, rcond=None)[0].T  # equal weights: W = I/σ²
    err2 = np.sum(((est - true_dtheta) @ J0.T) ** 2, axis=1)
    mc = np.sqrt(err2.mean())
    se_rel = err2.std() / err2.mean() / np.sqrt(reps) / 2  # relative s.e. of sqrt(mean)
    assert se_rel < 0.02
    assert abs(mc / rho_pred - 1) < 0.10
    assert abs(mc / rho_pred - 1) < 4 * se_rel  # and statistically consistent


def test_load_candidates(tmp_path):
    robot = planar2()
    f = tmp_path / "c.csv"
    f.write_text("q2,q1\n10,20\n-30,40\n")
    Q = load_candidates(f, robot, degrees=True)
    np.testing.assert_allclose(Q, np.radians([[20, 10], [40, -30]]))
    g = tmp_path / "bad.csv"
    g.write_text("0.1,0.2\n0.3,7.0\n")
    with pytest.raises(ValueError, match=r"bad\.csv, line 2: joint 'q2'"):
        load_candidates(g, robot)


def test_plan_report_serialises():
    import json

    model = _model("stanford")
    plan = optimise_discrete(model, 10, "D", n_candidates=100, restarts=1, rng=0)
    rep = evaluate_plan(model, plan.readings, q_test=Q_TEST["stanford"])
    json.dumps(plan.to_dict())
    json.dumps(rep.to_dict())
    assert "plan" in str(plan) and set(rep.param_std) == set(model.free)


def test_baseline_percentiles_of_singular_plans_are_infinite_without_warnings():
    """The random-plan baseline's percentiles equal numpy's linear ones; where both neighbours are a singular
    plan's infinite criterion the percentile is infinite (numpy gives NaN with a RuntimeWarning)."""
    import warnings

    from estcal.design.plans import _percentile

    rng = np.random.default_rng(3)
    for _ in range(100):
        v = rng.normal(size=int(rng.integers(1, 40)))
        p = float(rng.uniform(0, 100))
        assert np.isclose(_percentile(v, p), np.percentile(v, p))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _percentile([1.0, np.inf, np.inf], 90) == np.inf
        assert _percentile([1.0, 2.0, np.inf], 25) == 1.5
