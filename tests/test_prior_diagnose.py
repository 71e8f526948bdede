"""``estcal diagnose --geometric prior`` (estcal.discrepancy.prior_model; docs/real-data.md, "A prior instead of
a level"): the command's model against a direct ``fit_group_prior`` of the same model built here by hand; the
error budget's nested CV refitting the model and its widths on every fold's training rows only; the saved
model through ``compensate`` and ``export``; bad input."""
from __future__ import annotations

import csv
import json
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.base.errors import EstcalWarning
from estcal.cli.main import app
from estcal.discrepancy.geometric import fit_geometric, geometric_candidates, gravity_ready, weighted_system
from estcal.estimate.regularize import fit_group_prior, prior_groups
from estcal.identify.select import select_identifiable
from estcal.io import load_dataset, write_dataset
from estcal.io.robotfile import load_robot
from estcal.methods import NoiseModel, Problem
from estcal.simulate import simulate

RUN = CliRunner()
SIGMA = 1e-4  # simulated position noise (m)


def _simulated(n=30, seed=3):
    """PUMA 560 with link masses, geometric errors and the compliance of joints 2 and 3 (0.1 mm noise)."""
    return simulate("puma560_masses", n_poses=n, measure="position", seed=seed, noise={"position": SIGMA},
                    errors="random", effects=[{"effect": "joint_compliance", "joints": ["j2", "j3"],
                                               "params": {"compliance_j2": 2e-5, "compliance_j3": 3e-5}}])


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("prior")
    sim = _simulated()
    data = write_dataset(tmp / "sim.csv", sim.dataset)
    js, model = tmp / "fit.json", tmp / "model.yaml"
    # the evidence alone, the criterion _direct fits (the default, evidence+cv, is checked against it below)
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--geometric", "prior", "--folds", "3",
                         "--prior-criterion", "evidence", "--no-budget", "--json", str(js), "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    return tmp, data, json.loads(js.read_text()), model, r.output


def _direct(data_path, per_parameter=True, criterion="evidence"):
    """The prior model assembled here from its definition (docs/real-data.md): the registration fit (the
    identifiable base and tool parameters), the compliance of every joint with a gravity torque and the backlash
    of every joint whose torque changes sign, the identifiable geometric set, then fit_group_prior."""
    robot = load_robot("puma560_masses")
    ds = load_dataset(data_path, robot)
    noise = NoiseModel(known=False)
    kinds = dict(zip(robot.params.names, robot.params.kinds))
    problem, res, reg, _ = fit_geometric(robot, ds, noise, free=[n for n in robot.params.names
                                                                 if kinds[n] in ("base", "tool")])
    rb, _ = gravity_ready(problem.robot, res.theta, robot.params.values)  # gravity in the measuring frame
    tau = rb.gravity_torques(ds.readings, context=ds.context)
    big = np.abs(tau).max()
    from estcal.effects import make_effect

    for effect, keep in (("joint_compliance", lambda t: np.abs(t).max() > 1e-9 * big),
                         ("backlash", lambda t: np.abs(t).max() > 1e-9 * big and (t > 0).any() and (t < 0).any())):
        for j, name in enumerate(rb.joint_names):
            if keep(tau[:, j]):
                rb = rb.add_effect(make_effect(effect, rb, joints=[name]))
    kin = rb.rigid_kinematics(ds.readings)  # link tilt: every joint with a gravity moment across its axis
    M = rb.gravity_moments(ds.readings, context=ds.context, kin=kin)
    across = np.linalg.norm(M - np.sum(M * kin.joint_axis, -1, keepdims=True) * kin.joint_axis, axis=-1)
    for j, name in enumerate(rb.joint_names):
        if np.abs(across[:, j]).max() > 1e-9 * across.max():
            rb = rb.add_effect(make_effect("link_tilt", rb, joints=[name]))
    problem = Problem(rb, [(None, ds, noise)])
    cands = geometric_candidates(rb)
    _, A, _ = weighted_system(problem, rb.params.values, cands)
    geo = select_identifiable(A, names=cands).identifiable
    eff = [n for n, k in zip(rb.params.names, rb.params.kinds) if k == "effect"]
    penalised = [n for n in geo + eff if n not in reg]  # the registration stays free
    groups = {n: n for n in penalised} if per_parameter else None
    return problem, fit_group_prior(problem, reg + penalised, penalised, groups, criterion=criterion), eff


def test_default_criterion_is_evidence_and_cv(case, tmp_path):
    """Without --prior-criterion the widths are the evidence's times one multiplier chosen by leave-one-posture-out
    CV (evidence+cv): the command's model is the direct fit with that criterion, its multiplier and CV curve
    reported."""
    _, data, _, _, _ = case
    js = tmp_path / "cv.json"
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--geometric", "prior", "--folds", "3",
                         "--no-budget", "--json", str(js)])
    assert r.exit_code == 0, r.output
    fit = json.loads(js.read_text())
    problem, gp, _ = _direct(data, criterion="evidence+cv")
    assert fit["prior"]["criterion"] == "evidence+cv" == gp.criterion
    names = problem.robot.params.names
    got = np.array([fit["model"]["theta"][n] for n in gp.result.names])
    want = gp.result.theta[[names.index(n) for n in gp.result.names]]
    assert np.all(np.abs(got - want) <= 1e-6 * gp.result.std + 1e-12)
    assert "widths (evidence+cv): " in r.output


def test_command_model_is_a_direct_group_prior_fit(case):
    tmp, data, fit, _, out = case
    problem, gp, eff = _direct(data)
    prior = fit["prior"]
    assert fit["causes"] == [] and fit["model"]["geometric_level"] == "prior"
    assert sorted(n for n in fit["model"]["theta"] if n.split("_")[0] in ("compliance", "backlash", "tilt")) \
        == sorted(eff)
    assert any(n.startswith("tilt_") for n in eff)
    assert {g: w["width"] for g, w in prior["widths"].items()} == pytest.approx(gp.widths, rel=1e-6)
    assert prior["sigma0"] == pytest.approx(gp.sigma0, rel=1e-6)
    assert prior["effective_parameters"] == pytest.approx(gp.result.extra["prior"]["effective_parameters"], rel=1e-6)
    names = problem.robot.params.names
    got = np.array([fit["model"]["theta"][n] for n in gp.result.names])
    want = gp.result.theta[[names.index(n) for n in gp.result.names]]
    assert np.all(np.abs(got - want) <= 1e-6 * gp.result.std + 1e-12)
    # the training RMSE of the report is the direct model's
    e = problem.evaluate(gp.result.theta, jacobian=False).e.reshape(-1, 3)
    rmse = np.sqrt(np.mean(np.sum(e ** 2, axis=1))) * 1e3
    assert prior["train_rmse_mm"] == pytest.approx(rmse, rel=1e-9)
    assert fit["rmse_mm"]["extended"]["train"] == pytest.approx(rmse, rel=1e-9)
    # the text summarises the widths per kind with their units, σ0 and the effective number of parameters
    assert "one width per parameter" in out and "widths (evidence): " in out and "length ×" in out
    assert " mm" in out and "mrad/(N·m)" in out and "tilt ×" in out
    assert f"{prior['effective_parameters']:.1f} effective" in out and "σ0" in out


def test_saved_model_compensates_and_exports(case):
    """The saved robot carries every effect term at the MAP estimate: compensate drives it onto targets it
    can reach, export writes the URDF and names the effects it drops."""
    tmp, data, fit, model, _ = case
    saved = load_robot(model)
    assert {e.name for e in saved.effects} == {"joint_compliance", "backlash", "link_tilt"}
    for n, v in fit["model"]["theta"].items():
        assert saved.params[n] == pytest.approx(v, abs=1e-12)
    assert saved.meta["calibration"]["prior"]["widths"].keys() == fit["prior"]["widths"].keys()
    q = np.random.default_rng(7).uniform(-0.6, 0.6, (5, saved.n_joints)) + np.array([0, -0.4, 0.4, 0, 0.5, 0])
    p = saved.kinematics(q, jacobian=False).p
    targets = tmp / "targets.csv"
    with targets.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["label", *saved.joint_names, "x", "y", "z"])
        for i in range(len(q)):  # the start readings a little off the solution
            w.writerow([f"pt{i}", *[repr(float(v) + 0.01) for v in q[i]], *[repr(float(v)) for v in p[i]]])
    out = tmp / "commands.csv"
    r = RUN.invoke(app, ["compensate", str(targets), "--robot", str(model), "-o", str(out)])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(out.open()))
    qc = np.array([[float(row[j]) for j in saved.joint_names] for row in rows])
    assert np.abs(saved.kinematics(qc, jacobian=False).p - p).max() < 1e-8
    # without its effects the model would miss the targets: the check above is not vacuous
    plain = load_robot(model)
    plain.effects.clear()
    assert np.abs(plain.kinematics(qc, jacobian=False).p - p).max() > 1e-5
    r = RUN.invoke(app, ["export", "--robot", str(model), "--urdf", str(tmp / "prior.urdf")])
    assert r.exit_code == 0, r.output
    assert (tmp / "prior.urdf").exists() and "effect" in r.output


def test_budget_refits_the_model_and_its_widths_on_each_folds_training_rows():
    """error_budget with Procedure(fit=…): every outer fold calls the fit on exactly its training rows (no
    held-out row), its widths differ from fold to fold and from the all-rows widths, and the nested figure is
    the CV recomputed here fold by fold."""
    from estcal.discrepancy.budget import error_budget
    from estcal.discrepancy.prediction import Procedure
    from estcal.discrepancy.prior_model import prior_fit
    from estcal.discrepancy.stages import measured_points
    from estcal.validation import grouped_folds, posture_groups

    robot = load_robot("puma560_masses")
    ds = _simulated(24, seed=5).dataset
    noise = NoiseModel(known=False)
    seen, inner = [], prior_fit(noise)

    def spy(rb, d):
        seen.append(d.readings.copy())
        return inner(rb, d)

    b = error_budget(robot, ds, noise, level="full", procedure=Procedure(fit=spy, label="prior", k_inner=3),
                     k_folds=3, spaces=())
    folds = grouped_folds(posture_groups(ds.readings, robot.joint_types), 3, 0)
    assert len(seen) == 1 + len(folds) and np.array_equal(seen[0], ds.readings)  # the final fit, then the folds
    for test, rows in zip(folds, seen[1:]):
        train = np.setdiff1d(np.arange(ds.n), test)
        assert np.array_equal(rows, ds.readings[train])
        assert not (rows[:, None, :] == ds.readings[test][None]).all(-1).any()  # no held-out row in the fit
    d = b.to_dict()
    assert d["model"] == "prior" and d["recommended"] == "prior"
    widths = [dec["fit"]["widths_si"] for dec in d["decisions"]]
    all_rows = b.extra["fitted"].result.extra["fold_decision"]["widths_si"]
    # a width the evidence switches off sits at the search's lower bound (1e-8) in several fits alike; every
    # other differs from fold to fold and from the all-rows width
    live = [g for g in all_rows if min([all_rows[g]] + [w[g] for w in widths]) > 1.01e-8]
    assert len(live) >= len(all_rows) // 2
    for g in live:
        per_fold = [w[g] for w in widths]
        assert len(set(per_fold)) == len(folds) and all_rows[g] not in per_fold, g
    # the nested figure, recomputed: the model refitted on each fold's training rows, scored at its held-out rows
    meas = measured_points(ds)
    sq = np.zeros(meas.shape[:2])
    for test in folds:
        fs = prior_fit(noise)(robot, ds.subset(np.setdiff1d(np.arange(ds.n), test)))
        sq[test] = np.sum((meas[test] - fs.predict(ds.subset(test))) ** 2, axis=-1)
    assert b.predicted_validation_mm == pytest.approx(np.sqrt(sq.mean()) * 1e3, rel=1e-9)
    assert b.named_mm == pytest.approx(b.predicted_validation_mm, rel=1e-12)


def test_effects_refused_and_no_excitable_effect_falls_back_with_a_note(case, tmp_path):
    tmp, data, *_ = case
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--geometric", "prior",
                         "--effects", "backlash", "--no-budget"])
    assert r.exit_code == 2 and "--effects" in r.output and "--geometric prior" in r.output
    # an arm without gravity (a robot file with gravity [0, 0, 0]): no torque, no compliance or backlash to excite
    from estcal.io.robotfile import save_robot
    from estcal.workflows.diagnose import diagnose

    space = load_robot("puma560_masses")
    space.gravity[:] = 0.0
    save_robot(space, tmp_path / "space.yaml")
    sim = simulate(str(tmp_path / "space.yaml"), n_poses=20, measure="position", seed=1, noise={"position": SIGMA},
                   errors="random")
    flat = write_dataset(tmp_path / "space.csv", sim.dataset)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = diagnose(tmp_path / "space.yaml", flat, geometric="prior", k_folds=3)
    assert any(issubclass(w.category, EstcalWarning) and "excite no" in str(w.message) for w in caught)
    assert res.prior["effects"] == [] and "geometry alone" in res.prior["note"] and not res.robot.effects
    assert "note: the data excite no" in str(res)


def test_one_width_per_parameter_by_default_one_per_group_when_asked(case):
    """The default fit has a width per parameter, each reported with its kind and the kind's unit;
    ``--prior-widths group`` gives the one-width-per-kind fit of fit_group_prior's own groups; without
    --geometric prior the option is refused."""
    tmp, data, fit, _, _ = case
    prior = fit["prior"]
    problem, _, _ = _direct(data)
    pen = list(prior["widths"])
    kinds = prior_groups(problem.robot, pen)
    assert prior["widths_per"] == "parameter"
    assert all(w["kind"] == kinds[g] and w["n_parameters"] == 1 for g, w in prior["widths"].items())
    assert {w["display_unit"] for g, w in prior["widths"].items() if kinds[g] == "length"} == {"mm"}
    js = tmp / "group.json"
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--geometric", "prior", "--folds", "3",
                         "--no-budget", "--prior-widths", "group", "--prior-criterion", "evidence", "--json", str(js)])
    assert r.exit_code == 0, r.output
    grouped = json.loads(js.read_text())["prior"]
    _, gp, _ = _direct(data, per_parameter=False)
    assert grouped["widths_per"] == "group"
    assert {g: w["width"] for g, w in grouped["widths"].items()} == pytest.approx(gp.widths, rel=1e-6)
    assert "one width per group" in r.output and "widths (evidence): length" in r.output
    bad = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--prior-widths", "parameter"])
    assert bad.exit_code == 2 and "--geometric prior" in bad.output
