"""Saved models (docs/robot-file.md, "Saved models"): `--save-model` writes the identified robot,
`--robot M.yaml` reloads it, and `estcal fk` with it reproduces the fit's predictions.

The predictions the fk output is compared with are computed independently of the saved file:
from the nominal robot and the fitted parameter values of the run's JSON (calibrate), or by
the diagnosis feedback path from its fit JSON (diagnose). Provenance hashes are checked
against hashlib on the files themselves.
"""
from __future__ import annotations

import hashlib
import json
from datetime import datetime, timezone

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.io import load_dataset, write_dataset
from estcal.io.robotfile import calibration_covariance, load_robot
from estcal.kinematics.transforms import matrix_to_quat
from estcal.simulate import simulate

RUN = CliRunner()

# A TIAGo-like chain: prismatic torso, four revolute joints with inertials, and a fixed tool
# origin at pitch -90° (the gimbal lock of rpy that TIAGo's own tool frame has).
TIAGO_LIKE = """<?xml version="1.0"?>
<robot name="tiago_like">
  <link name="base_footprint"/>
  <link name="torso"><inertial><origin xyz="0 0 0.1"/><mass value="8.0"/>
    <inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial></link>
  <link name="arm_1"><inertial><origin xyz="0.05 0 0"/><mass value="1.5"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="arm_2"><inertial><origin xyz="0.1 0 0"/><mass value="1.2"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="arm_3"><inertial><origin xyz="0 0 0.1"/><mass value="1.0"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="arm_4"><inertial><origin xyz="0.05 0 0"/><mass value="0.8"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="tool"/>
  <joint name="torso_lift_joint" type="prismatic"><parent link="base_footprint"/><child link="torso"/>
    <origin xyz="-0.062 0 0.8885" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.35" effort="100" velocity="1"/></joint>
  <joint name="arm_1_joint" type="revolute"><parent link="torso"/><child link="arm_1"/>
    <origin xyz="0.155 0.014 -0.151" rpy="0 0 -1.57079632679"/><axis xyz="0 0 1"/>
    <limit lower="0.07" upper="2.68" effort="40" velocity="2"/></joint>
  <joint name="arm_2_joint" type="revolute"><parent link="arm_1"/><child link="arm_2"/>
    <origin xyz="0.125 0.0195 -0.031" rpy="-1.57079632679 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-1.5" upper="1.02" effort="40" velocity="2"/></joint>
  <joint name="arm_3_joint" type="revolute"><parent link="arm_2"/><child link="arm_3"/>
    <origin xyz="0.0895 0 -0.0015" rpy="-1.57079632679 0 1.57079632679"/><axis xyz="0 0 1"/>
    <limit lower="-3.4" upper="1.5" effort="20" velocity="2"/></joint>
  <joint name="arm_4_joint" type="revolute"><parent link="arm_3"/><child link="arm_4"/>
    <origin xyz="-0.02 -0.027 -0.222" rpy="-1.57079632679 -1.57079632679 0"/><axis xyz="0 0 1"/>
    <limit lower="-0.3" upper="2.3" effort="20" velocity="2"/></joint>
  <joint name="tool_joint" type="fixed"><parent link="arm_4"/><child link="tool"/>
    <origin xyz="0.1 0 0" rpy="-1.57079632679 -1.57079632679 0"/></joint>
</robot>
"""


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _fk(tmp_path, data, model, *extra):
    out = tmp_path / f"fk_{model.stem}_{data.stem}.csv"
    r = RUN.invoke(app, ["fk", str(data), "--robot", str(model), "-o", str(out), *extra])
    assert r.exit_code == 0, r.output
    a = np.loadtxt(out, delimiter=",", skiprows=1, ndmin=2)
    header = out.read_text().splitlines()[0].split(",")
    return {c: a[:, i] for i, c in enumerate(header)}


def _at_json_estimate(robot, fit: dict):
    """``robot`` with the parameter values of a calibrate JSON (``theta``), matched by name."""
    th = fit["theta"]
    vals = np.array([th.get(n, v) for n, v in zip(robot.params.names, robot.params.values)])
    assert sum(n in th for n in robot.params.names) == robot.n_params
    return robot.with_values(vals)


def _check_block(block, files_roles, fit):
    assert block["estcal_version"]
    date = datetime.fromisoformat(block["date"])
    assert date.utcoffset().total_seconds() == 0
    assert abs((datetime.now(timezone.utc) - date).total_seconds()) < 600
    assert [(d["file"], d["role"]) for d in block["data"]] == [(str(p), r) for p, r in files_roles]
    for d, (p, _) in zip(block["data"], files_roles):
        assert d["sha256"] == _sha(p)
        assert d["n_poses"] == len(p.read_text().strip().splitlines()) - 1
    assert block["free"] == list(fit["parameters"])
    np.testing.assert_array_equal(np.array(block["covariance"]), np.array(fit["covariance"]))
    assert block["sigma0"] == pytest.approx(fit["sigma0"], rel=1e-12)


@pytest.fixture(scope="module")
def puma_pose(tmp_path_factory):
    d = tmp_path_factory.mktemp("puma")
    kw = dict(measure="pose", noise={"position": 5e-5, "orientation": 5e-4})
    tr = simulate("puma560", n_poses=40, seed=1, errors="random", **kw)
    va = simulate("puma560", n_poses=15, seed=2, errors=tr.truth["errors"], **kw)
    return write_dataset(d / "train.csv", tr.dataset), write_dataset(d / "valid.csv", va.dataset)


@pytest.mark.parametrize("estimator", ["lm", "gtsam", "kalman"])
def test_calibrate_saved_model_reproduces_the_fit_through_fk(puma_pose, tmp_path, estimator):
    train, valid = puma_pose
    model, js = tmp_path / "M.yaml", tmp_path / "fit.json"
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--estimator", estimator,
                         "--validate", str(valid), "--noise-pos-mm", "0.05", "--noise-rot-mrad", "0.5",
                         "--json", str(js), "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    fit = json.loads(js.read_text())
    ref = _at_json_estimate(load_robot("puma560"), fit)
    for data in (train, valid):
        ds = load_dataset(data, ref)
        kin = ref.kinematics(ds.readings, jacobian=False)
        out = _fk(tmp_path, data, model)
        p = np.column_stack([out["x"], out["y"], out["z"]])
        assert np.abs(p - kin.p).max() < 1e-12
        quat = np.column_stack([out[c] for c in ("qw", "qx", "qy", "qz")])
        assert np.abs(quat - matrix_to_quat(kin.R)).max() < 1e-12  # orientation too (rad-level 1e-12)
    block = yaml.safe_load(model.read_text())["calibration"]
    _check_block(block, [(train, "train"), (valid, "validation")], fit)
    assert block["estimator"] == estimator and block["noise"]["position"] == 5e-5
    assert block["noise"]["orientation"] == 5e-4 and block["level"] == "full"
    assert block["rmse_mm"]["train"]["after"] == pytest.approx(fit["rmse_mm"]["train"], rel=1e-12)
    assert block["rmse_mm"]["validation"][0]["after"] == pytest.approx(fit["rmse_mm"]["validation"][0], rel=1e-12)
    names, C = calibration_covariance(load_robot(model))
    assert names == list(fit["parameters"]) and C.shape == (len(names), len(names))
    if estimator != "lm":
        return
    # the saved model is accepted wherever a robot is: calibrating it again on the same data moves nothing
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", str(model), "--json", str(tmp_path / "again.json")])
    assert r.exit_code == 0, r.output
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["rmse_mm"]["train"] == pytest.approx(fit["rmse_mm"]["train"], rel=0.02)


def test_tiago_like_marker_model_round_trip(tmp_path):
    """Three unknown markers on a URDF chain (TIAGo-like): the saved model holds the located
    markers and the URDF placement errors; fk --markers reproduces every point to 1e-12 m."""
    urdf = tmp_path / "tiago_like.urdf"
    urdf.write_text(TIAGO_LIKE)
    truth_markers = np.array([[0.02, 0.03, 0.05], [-0.03, 0.02, 0.06], [0.01, -0.04, 0.04]])
    sim = simulate(str(urdf), n_poses=30, measure="points", markers=truth_markers, seed=3,
                   noise={"position": 1e-4}, errors=None)
    data = write_dataset(tmp_path / "mocap.csv", sim.dataset)
    model, js = tmp_path / "tiago_model.yaml", tmp_path / "fit.json"
    r = RUN.invoke(app, ["calibrate", str(data), "--robot", str(urdf), "--level", "joint_offset",
                         "--json", str(js), "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    fit = json.loads(js.read_text())
    ref = _at_json_estimate(load_robot(urdf, n_markers=3), fit)
    ds = load_dataset(data, ref, points=3)
    kin = ref.kinematics(ds.readings, jacobian=False)
    out = _fk(tmp_path, data, model, "--markers")
    for k in range(3):
        got = np.column_stack([out[f"x{k + 1}"], out[f"y{k + 1}"], out[f"z{k + 1}"]])
        assert np.abs(got - kin.points[:, k]).max() < 1e-12
    saved = load_robot(model)
    assert saved.n_markers == 3 and saved.convention == "urdf"
    _check_block(yaml.safe_load(model.read_text())["calibration"], [(data, "train")], fit)


def test_diagnosed_model_with_effects_reads_its_columns_in_fk(tmp_path):
    """A diagnosed model with a backlash by approach direction and a drift in time: fk takes the
    approach_<joint> and t columns from its input, with t measured from the file's first row as
    in the diagnosis; its points equal the fit JSON's identified robot (feedback path)."""
    from estcal.discrepancy.feedback import simulate_like

    sigma = 5e-5
    robot = load_robot("puma560_masses")
    t = 5000.0 + 30.0 * np.arange(40)  # absolute clock: only the session time makes t0 = 0 right
    sim = simulate(robot, n_poses=40, measure="position", seed=5, noise={"position": sigma},
                   effects=[{"effect": "backlash", "joints": ["j2"], "params": {"backlash_j2": 2e-3}},
                            {"effect": "drift", "joints": ["j3"], "options": {"t0": 5000.0},
                             "params": {"drift_j3": 4e-6}}],
                   t=t, record_approach=True)
    data = write_dataset(tmp_path / "data.csv", sim.dataset)
    model, js = tmp_path / "diag.yaml", tmp_path / "fit.json"
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", "puma560_masses", "--noise-pos-mm", str(sigma * 1e3),
                         "--effects", "backlash,drift", "--folds", "3", "--json", str(js),
                         "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    fit = json.loads(js.read_text())
    named = {c["effect"] for c in fit["causes"]}
    assert named == {"backlash", "drift"}, fit["verdict"]
    saved = load_robot(model)
    assert {e.name for e in saved.effects} == named
    block = saved.meta["calibration"]
    assert block["data_preparation"]["session_time"] is True
    assert {c["effect"] for c in block["causes"]} == named
    assert block["data"] == [{"file": str(data), "sha256": _sha(data), "n_poses": 40, "role": "train"}]
    names, C = calibration_covariance(saved)
    assert set(fit["model"]["free"]) == set(names) and np.all(np.diag(C) > 0)
    out = _fk(tmp_path, data, model)
    got = np.column_stack([out["x"], out["y"], out["z"]])
    ref = simulate_like(js, load_dataset(data, load_robot("puma560_masses")), noise=0.0).points[:, 0]
    assert np.abs(got - ref).max() < 1e-12
    # the effects matter at this scale, so the check above is not vacuous
    plain = load_robot(model)
    plain.effects.clear()
    assert np.abs(plain.kinematics(load_dataset(data, plain).readings, jacobian=False).p - ref).max() > 1e-5


def test_fit_json_is_self_contained(tmp_path, monkeypatch):
    """`simulate --from-fit` of a URDF robot's diagnosis works with the URDF gone and
    ESTCAL_SHARED pointing to an empty folder: the fit carries its nominal robot."""
    urdf = tmp_path / "tiago_like.urdf"
    urdf.write_text(TIAGO_LIKE)
    sim = simulate(str(urdf), n_poses=25, measure="points", markers=np.array([[0.02, 0.03, 0.05],
                                                                              [-0.03, 0.02, 0.06]]),
                   seed=4, noise={"position": 1e-4})
    data = write_dataset(tmp_path / "mocap.csv", sim.dataset)
    js = tmp_path / "fit.json"
    r = RUN.invoke(app, ["diagnose", str(data), "--robot", str(urdf), "--noise-pos-mm", "0.1",
                         "--effects", "joint_compliance", "--folds", "3", "--json", str(js)])
    assert r.exit_code == 0, r.output
    urdf.unlink()
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("ESTCAL_SHARED", str(empty))
    r = RUN.invoke(app, ["simulate", "--from-fit", str(js), "--n", "5", "-o", str(tmp_path / "s.csv"),
                         "--truth", str(tmp_path / "truth.json")])
    assert r.exit_code == 0, r.output
    fit = json.loads(js.read_text())
    truth = json.loads((tmp_path / "truth.json").read_text())
    for n, v in fit["model"]["theta"].items():
        if n in truth["parameters"]:
            assert truth["parameters"][n] == pytest.approx(v, abs=1e-15)


def test_unknown_estimator_option_names_the_estimator_and_keys(puma_pose):
    train, _ = puma_pose
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--option", "nosuch=1"])
    assert r.exit_code == 2
    assert "estimator 'lm' has no option 'nosuch'" in r.output and "max_iter" in r.output
    assert "Traceback" not in r.output
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--estimator", "kalman",
                         "--option", "passes=2", "--option", "qq=1"])
    assert r.exit_code == 2 and "'kalman' has no option 'qq'" in r.output and "(did you mean 'q'?)" in r.output
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--estimator", "kalman", "--option", "q=abc"])
    assert r.exit_code == 2 and "option 'q': expected a number" in r.output
    # a valid option is accepted (3 iterations do not converge: a numerical refusal, exit 3, unless allowed)
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--option", "max_iter=3"])
    assert r.exit_code == 3 and "did not converge" in r.output, r.output
    r = RUN.invoke(app, ["calibrate", str(train), "--robot", "puma560", "--option", "max_iter=3",
                         "--allow-ill-conditioned"])
    assert r.exit_code == 0, r.output
    r = RUN.invoke(app, ["estimators", "kalman"])
    assert r.exit_code == 0 and "passes=" in r.output and "q=0.0" in r.output


def test_lumped_mass_model_keeps_the_tool_link_mass(tmp_path):
    """A diagnosis of a robot without masses uses 1 kg at the end of every moving link, the tool
    link included; the saved file keeps that mass (``tool: {mass, com}``), so gravity torques —
    and the compliance deflections they drive — are those of the fit (hand sum: the tool's 1 kg
    alone changes the joint-1..6 torques)."""
    from estcal.discrepancy.geometric import gravity_ready
    from estcal.io.robotfile import save_robot

    lumped, was_lumped = gravity_ready(load_robot("puma560"))
    assert was_lumped and lumped.links[-1].mass == 1.0
    back = load_robot(save_robot(lumped, tmp_path / "lumped.yaml"))
    q = np.random.default_rng(0).uniform(-1, 1, (20, 6))
    np.testing.assert_allclose(back.gravity_torques(q), lumped.gravity_torques(q), rtol=0, atol=1e-12)
    no_tool = load_robot(tmp_path / "lumped.yaml")
    no_tool.links[-1] = no_tool.links[-1].__class__(**{**no_tool.links[-1].__dict__, "mass": 0.0})
    assert np.abs(no_tool.gravity_torques(q) - lumped.gravity_torques(q)).max() > 0.1


def test_method_unknowns_are_kept_apart_from_the_robot_covariance(tmp_path):
    """Plane-unknown data estimate the plane too: the block's free/covariance hold the robot's
    parameters (their marginal: the matching sub-matrix of the full covariance), the plane is
    listed under method_unknowns, and calibration_covariance works on the reloaded file."""
    from estcal.estimate import calibrate_lsq
    from estcal.io.dataset import dataset_from_arrays
    from estcal.methods import NoiseModel, Problem, get_method

    robot = load_robot("puma560")
    q = simulate(robot, n_poses=40, measure="position", seed=2).dataset.readings
    ds = dataset_from_arrays(robot.joint_names, q)  # encoders only: the poses touch one unknown plane
    problem = Problem(robot, [(get_method("plane-unknown"), ds, NoiseModel(scalar=1e-5))])
    kinds = dict(zip(problem.params.names, problem.params.kinds))
    plane = [n for n in problem.params.names if kinds[n] == "other"]
    assert plane  # the plane's parameters are unknowns of the method
    res = calibrate_lsq(problem, "lm", free=["offset_2", "offset_3"] + plane, check=False)
    back = load_robot(res.save_model(tmp_path / "plane.yaml"))
    names, C = calibration_covariance(back)
    idx = [res.names.index(n) for n in ("offset_2", "offset_3")]
    assert names == ["offset_2", "offset_3"]
    np.testing.assert_array_equal(C, res.covariance[np.ix_(idx, idx)])
    assert set(back.meta["calibration"]["method_unknowns"]) == set(plane)


def test_recalibrating_a_saved_model_reuses_its_free_set(tmp_path):
    """The structural selection belongs to the design geometry: at a calibrated one it admits
    near-dependent parameters (condition ~1e5, refused). A recalibration of a saved model at the
    same level and measurement fits the saved set, well conditioned, to the same residuals."""
    from estcal.estimate.levels import select_free
    from estcal.methods import Problem
    from estcal.estimate.checks import COND_MAX

    tr = simulate("puma560", n_poses=60, seed=0, errors="random", noise={"position": 5e-5})
    data = write_dataset(tmp_path / "d.csv", tr.dataset)
    model, js1, js2 = tmp_path / "m.yaml", tmp_path / "a.json", tmp_path / "b.json"
    r = RUN.invoke(app, ["calibrate", str(data), "-r", "puma560", "--json", str(js1), "--save-model", str(model)])
    assert r.exit_code == 0, r.output
    saved = yaml.safe_load(model.read_text())["calibration"]["free"]
    r = RUN.invoke(app, ["calibrate", str(data), "-r", str(model), "--json", str(js2)])
    assert r.exit_code == 0, r.output
    assert "the saved model's free set" in " ".join(r.output.split())
    a, b = json.loads(js1.read_text()), json.loads(js2.read_text())
    assert list(b["parameters"]) == saved
    assert b["reliability"]["condition_number"] < COND_MAX
    assert b["rmse_mm"]["train"] == pytest.approx(a["rmse_mm"]["train"], rel=1e-6)
    # why: the structural selection redone at the calibrated point is ill-conditioned
    rob = load_robot(str(model))
    ds = load_dataset(data, rob)
    sel = select_free(Problem(rob, [(None, ds, None)]), "full", "structural")
    assert set(sel.identifiable) != set(saved) and sel.condition_number > COND_MAX


def test_identifiability_of_a_saved_model_is_that_of_its_design(tmp_path):
    """`identifiable` and the online default free set analyse a saved model at its design geometry:
    the same identifiable set as the nominal robot (at the calibrated geometry the QR would keep
    near-dependent parameters: |R_jj| ~ 1e-10, condition ~1e16)."""
    from estcal.identify import identify
    from estcal.io.savedmodel import design_values

    tr = simulate("puma560", n_poses=60, seed=0, errors="random", noise={"position": 5e-5})
    data = write_dataset(tmp_path / "d.csv", tr.dataset)
    model = tmp_path / "m.yaml"
    assert RUN.invoke(app, ["calibrate", str(data), "-r", "puma560", "--save-model", str(model)]).exit_code == 0
    saved, nominal = load_robot(str(model)), load_robot("puma560")
    dv = design_values(saved)
    kinds = dict(zip(saved.params.names, saved.params.kinds))
    joint_model = [i for i, n in enumerate(saved.params.names) if kinds[n] != "marker"]
    np.testing.assert_array_equal(dv[joint_model], nominal.params.values[joint_model])
    a = identify(saved, "position", n_poses=60, seed=3)
    b = identify(nominal, "position", n_poses=60, seed=3)
    assert a.identifiable == b.identifiable and a.condition_number == pytest.approx(b.condition_number, rel=1e-9)
    bare = saved.copy(saved.params)
    bare.meta = {}
    calibrated = identify(bare, "position", n_poses=60, seed=3)  # what the calibrated geometry alone gives
    assert calibrated.condition_number > 1e6
    r = RUN.invoke(app, ["online", str(data), "-r", str(model)])
    assert r.exit_code == 0, r.output
    assert f"{len(b.identifiable)} free parameters" in " ".join(r.output.split())
    from estcal.design.model import identifiable_subset

    assert identifiable_subset(saved, "position") == identifiable_subset(nominal, "position")  # design's set


def test_saved_model_finds_its_design_robot_from_another_folder(tmp_path, monkeypatch):
    """The design robot is recorded as an absolute path: design_values works from any folder."""
    from estcal.io.robotfile import save_robot
    from estcal.io.savedmodel import design_values

    work = tmp_path / "work"
    work.mkdir()
    save_robot(load_robot("puma560"), work / "base.yaml")
    tr = simulate("puma560", n_poses=30, seed=2, errors="random", noise={"position": 5e-5})
    write_dataset(work / "d.csv", tr.dataset)
    monkeypatch.chdir(work)
    r = RUN.invoke(app, ["calibrate", "d.csv", "-r", "base.yaml", "--level", "joint_offset", "--save-model", "m.yaml"])
    assert r.exit_code == 0, r.output
    block = yaml.safe_load((work / "m.yaml").read_text())["calibration"]
    assert block["robot"] == str((work / "base.yaml").resolve())
    monkeypatch.chdir(tmp_path)
    saved = load_robot(str(work / "m.yaml"))
    dv = design_values(saved)
    assert dv is not None
    np.testing.assert_array_equal(dv, load_robot("puma560").params.values)  # no markers: all design values
