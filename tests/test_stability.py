"""Causes that survive a new split (estcal.discrepancy.stability, inside estcal.diagnose): named on all
rows and in most posture-grouped folds (the count is reported); a time drift never explains an offset
between sessions."""
import json

import numpy as np

from estcal.discrepancy import diagnose
from estcal.discrepancy.hidden import simulate_hidden
from estcal.io.robotfile import load_robot

SIGMA = 5e-5


def test_a_real_cause_is_named_in_every_fold_and_kept_and_the_output_says_so():
    sim, _ = simulate_hidden(load_robot("puma560_masses"), [("joint_compliance", ["j3"], 10)], SIGMA, n_poses=45,
                             measure="points", seed=2)
    res = diagnose(sim.nominal_robot, sim.dataset, k_folds=3, noise=SIGMA, families=False, max_effects=1)
    assert res.named == [("joint_compliance", ("j3",))]
    assert res.stability["kept"] == ["joint_compliance(j3)"] and res.stability["folds_naming"]["joint_compliance(j3)"] == 3
    c = json.loads(json.dumps(res.to_dict()))["causes"][0]
    assert (c["folds_naming"], c["k_folds"]) == (3, 3)
    assert "named in 3 of 3 posture-grouped folds" in str(res)


def test_the_linearised_selection_names_what_the_selection_names():
    # the fold selections are linear algebra on the all-rows screening's columns: on all rows they
    # must name what the nonlinear forward selection names (here a compliance and nothing else)
    from estcal.discrepancy.stability import linear_selection
    from estcal.validation import grouped_folds, posture_groups

    sim, _ = simulate_hidden(load_robot("puma560_masses"), [("joint_compliance", ["j3"], 10)], SIGMA, n_poses=45,
                             measure="points", seed=2)
    res = diagnose(sim.nominal_robot, sim.dataset, k_folds=3, noise=SIGMA, families=False, max_effects=2)
    d = sim.dataset
    folds = grouped_folds(posture_groups(d.readings), 3, 0)
    sel = res.selector(np.arange(d.n), res.geometric_free)
    assert [e[:2] for e in sel] == [("joint_compliance", ["j3"])]
    assert res.named == [("joint_compliance", ("j3",))]
    assert res.stability["kept"] == ["joint_compliance(j3)"]
    assert folds and callable(linear_selection)


def test_repeated_postures_stay_in_one_fold_and_clean_data_keep_nothing():
    sim, _ = simulate_hidden(load_robot("puma560_masses"), [], SIGMA, n_poses=30, measure="points", seed=4)
    d = sim.dataset
    both = d.subset(np.r_[np.arange(d.n), np.arange(d.n)])  # every posture measured twice
    both.points = both.points + SIGMA * np.random.default_rng(0).standard_normal(both.points.shape)
    res = diagnose(sim.nominal_robot, both, k_folds=3, noise=SIGMA, families=False, max_effects=1)
    assert res.causes == [] and (res.stability is None or res.stability["kept"] == [])


def _two_sessions(drift: bool):
    """Session 1: 40 postures over 20 min; session 2: 14 of them over 2 min, with joint 2 re-homed by 1 mrad
    (an offset between sessions); ``drift``: both sessions also drift on joint 2 (within each session)."""
    hidden = [("drift", ["j2"], 8.0)] if drift else []
    sim, _ = simulate_hidden(load_robot("puma560_masses"), hidden, SIGMA, n_poses=40, measure="points", seed=3,
                             dt=30.0)
    a = sim.dataset
    idx = np.arange(0, 40, 3)
    b = a.subset(idx)
    b.readings = b.readings - np.r_[0, 1e-3, 0, 0, 0, 0]  # the readings of a re-homed joint 2
    b.context["t"] = np.arange(len(idx)) * 10.0
    truth = sim.true_robot
    pts = truth.kinematics(b.readings + np.r_[0, 1e-3, 0, 0, 0, 0], context=b.context, jacobian=False).points
    b.points = pts[:, :a.n_points] + SIGMA * np.random.default_rng(1).standard_normal(b.points.shape)
    return sim.nominal_robot, [a, b]


def test_time_drift_never_explains_an_offset_between_sessions():
    # with time from each session's start, a drift of joint 2 explained 46 % of the re-homing offset of
    # the short second session and was named; time from each session's mean leaves it nothing to explain
    robot, sessions = _two_sessions(drift=False)
    res = diagnose(robot, sessions, noise=SIGMA, candidates=["drift"], max_effects=2)
    assert res.causes == [], res.verdict
    assert all(e.get("explained_excess_fraction", 0) < 0.05 for e in res.steps[0]["table"] if "delta_bic" in e)
    # a drift within the sessions is still found, beside the same offset
    robot, sessions = _two_sessions(drift=True)
    res = diagnose(robot, sessions, noise=SIGMA, candidates=["drift"], max_effects=2)
    assert res.named == [("drift", ("j2",))] and res.causes[0].folds_naming == res.causes[0].k_folds


def test_diagnose_cross_validates_by_posture():
    # every posture measured twice: a row-wise split holds out rows whose twin is in training
    from estcal.discrepancy import cross_validate, diagnose
    from estcal.discrepancy.geometric import fit_geometric
    from estcal.methods import NoiseModel

    sim, _ = simulate_hidden(load_robot("puma560_masses"), [], SIGMA, n_poses=15, measure="points", seed=6)
    d = sim.dataset
    both = d.subset(np.r_[np.arange(d.n), np.arange(d.n)])
    both.points = both.points + SIGMA * np.random.default_rng(1).standard_normal(both.points.shape)
    res = diagnose(sim.nominal_robot, both, noise=SIGMA, k_folds=5, max_effects=0)
    pb, r, free, _ = fit_geometric(sim.nominal_robot, both, NoiseModel(position=SIGMA, known=True))
    perm = np.random.default_rng(0).permutation(both.n)
    row_wise = cross_validate(pb, r.theta, free, [np.sort(f) for f in np.array_split(perm, 5)])[0]
    grouped = res.rmse_mm["geometric"]["cv"]
    assert grouped > 1.2 * row_wise > 1.1 * res.rmse_mm["geometric"]["train"]


def test_diagnose_reports_the_budget_in_json_text_and_report(tmp_path):
    from estcal.discrepancy import diagnose
    from estcal.report.diagnose import diagnose_report

    sim, _ = simulate_hidden(load_robot("puma560_masses"), [("joint_compliance", ["j3"], 10)], SIGMA, n_poses=30,
                             measure="points", seed=2)
    res = diagnose(sim.nominal_robot, sim.dataset, noise=SIGMA, k_folds=3, max_effects=1, families=False,
                   budget=True)
    diagnose_report(tmp_path, res)  # the analysis writes no file: the report does
    b = res.to_dict()["budget"]
    keys = ("nominal_mm", "geometric_mm", "named_mm", "structured_unnamed_mm", "unstructured_mm",
            "repeatability_mm", "predicted_validation_mm")
    assert all(k in b for k in keys)
    assert b["named_mm"] < b["geometric_mm"] < b["nominal_mm"]  # the named compliance lowers the grouped CV
    assert b["effects"] == [{"effect": "joint_compliance", "joints": ["j3"]}]
    assert "predicted at new postures" in str(res)
    assert (tmp_path / "budget.png").stat().st_size > 1000 and "budget.png" in res.report_files


def test_diagnose_predicts_the_validation_error_at_its_postures_before_scoring_it():
    # a --validate file: its RMSE, the prediction at its postures (from its readings) and the coverage of
    # the 95 % region, in the budget and in the text
    sim, _ = simulate_hidden(load_robot("puma560_masses"), [("joint_compliance", ["j3"], 10)], SIGMA, n_poses=40,
                             measure="points", seed=2)
    train, valid = sim.dataset.subset(np.arange(30)), sim.dataset.subset(np.arange(30, 40))
    res = diagnose(sim.nominal_robot, train, validate=[valid], noise=SIGMA, k_folds=3, max_effects=1,
                   families=False, budget=True)
    v = res.to_dict()["budget"]["validation"][0]
    assert v["n_points"] == valid.n * valid.points.shape[1] and 0.7 <= v["coverage"] <= 1
    assert 0.5 * v["rmse_mm"] <= v["predicted_mm"] <= 2 * v["rmse_mm"], v
    assert "predicted at its postures" in str(res)
