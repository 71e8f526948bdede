"""Compensation (estcal.compensation, `estcal compensate`): independent checks of the solve,
the limits, the effects, the covariance propagation and the command-line contract."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from estcal.cli.main import app
from estcal.compensation import compensate
from estcal.compensation.solve import task_residual
from estcal.effects import make_effect
from estcal.io.robotfile import load_robot, robot_from_dict, robot_to_dict, save_robot
from estcal.kinematics.transforms import matrix_to_quat, so3_log

runner = CliRunner()


def true_puma(seed=0, markers=0, payload=2.0):
    """PUMA 560 with masses, a payload and random geometric errors (1 mm / 1 mrad) — a 'calibrated model'."""
    d = robot_to_dict(load_robot("puma560_masses"))
    d["payload"] = {"mass": payload, "com": [0.0, 0.0, 0.1]}
    if markers:
        d["markers"] = [[0.05, 0.0, 0.1]]
    robot = robot_from_dict(d, "test_puma")
    rng = np.random.default_rng(seed)
    geo = [i for i, k in enumerate(robot.params.kinds) if k in ("geometric", "offset", "base", "tool")]
    robot.params.values[geo] += rng.normal(0, 1e-3, len(geo))
    return robot


def planned(robot_nominal, n, seed=1, margin=0.15):
    """Nominal program: readings and the targets the nominal model reaches with them."""
    r0 = robot_nominal.random_readings(n, np.random.default_rng(seed), margin=margin)
    kin = robot_nominal.kinematics(r0, jacobian=False)
    return r0, kin


def well_conditioned(robot, r0, kin, floor=0.02):
    """Rows away from the PUMA's elbow/shoulder/wrist singularities (smallest singular value of the
    weighted pose Jacobian wrt the readings above ``floor``) — what a real program plans."""
    _, J = task_residual(robot, r0, robot.params.values, {}, kin.p, kin.R, 0.1)
    return np.linalg.svd(J, compute_uv=False)[:, -1] > floor


def test_position_and_pose_targets_reached_to_1e9_m_by_independent_fk():
    nominal = load_robot("puma560_masses")
    model = true_puma()
    r0, kin = planned(nominal, 80)
    keep = well_conditioned(nominal, r0, kin)
    r0, p, R = r0[keep], kin.p[keep], kin.R[keep]
    assert len(r0) > 30
    res = compensate(model, p, r0, covariance=None)
    assert res.reachable.all()
    k = model.kinematics(res.readings, jacobian=False)  # independent check: the chain's own FK
    assert np.abs(k.p - p).max() < 1e-9
    # the nominal commands miss by millimetres: the solve did something
    assert np.linalg.norm(model.kinematics(r0, jacobian=False).p - p, axis=1).max() > 1e-3
    res = compensate(model, np.c_[p, matrix_to_quat(R)], r0, covariance=None)
    assert res.reachable.all() and res.rot_error_mrad is not None
    k = model.kinematics(res.readings, jacobian=False)
    assert np.abs(k.p - p).max() < 1e-9
    assert np.linalg.norm(so3_log(R @ np.swapaxes(k.R, 1, 2)), axis=1).max() < 1e-9
    lo, hi = model.limits.T
    assert np.all((res.readings >= lo) & (res.readings <= hi))


@pytest.mark.parametrize("effect,kw,values", [
    ("joint_compliance", dict(joints=["j2", "j3"]), 3e-4),       # 100 N·m -> 30 mrad: strong on purpose
    ("backlash", dict(joints=["j1", "j2", "j3"]), 5e-3),
    ("gear_harmonic", dict(joints=["j1", "j2"], orders=[1, 2], gear_ratio=20.0), 2e-3),
    ("thermal_expansion", dict(), 2.3e-5),
])
def test_effects_compensated_under_the_same_model(effect, kw, values):
    nominal = load_robot("puma560_masses")
    base = true_puma(markers=1 if effect == "thermal_expansion" else 0)
    model = base.add_effect(make_effect(effect, base, **kw))
    for n in model.effects[0].param_names:
        model.params[n] = values
    r0, kin = planned(nominal, 40, seed=4)
    keep = well_conditioned(nominal, r0, kin)
    r0, p = r0[keep], kin.p[keep]
    rng = np.random.default_rng(5)
    ctx = {"payload": rng.uniform(0, 5, len(r0)), "temperature": rng.uniform(25, 45, len(r0))}
    ctx.update({f"approach_{j}": rng.choice([-1.0, 1.0], len(r0)) for j in ("j1", "j2")})  # j3: gravity side
    res = compensate(model, p, r0, context=ctx, covariance=None)
    assert res.reachable.all()
    k = model.kinematics(res.readings, context=ctx, jacobian=False)
    reached = k.points[:, 0] if model.n_markers else k.p
    assert np.abs(reached - p).max() < 1e-9
    # the effect matters: the geometric model's commands miss under the effect model
    geo = compensate(base, p, r0, covariance=None)
    kg = model.kinematics(geo.readings, context=ctx, jacobian=False)
    miss = np.linalg.norm((kg.points[:, 0] if model.n_markers else kg.p) - p, axis=1)
    assert miss.max() > 1e-4


def test_limits_respected_and_unreachable_rows_flagged_not_clipped():
    model = true_puma()
    nominal = load_robot("puma560_masses")
    r0, kin = planned(nominal, 30, seed=7)
    keep = well_conditioned(nominal, r0, kin)
    r0, p = r0[keep][:10], kin.p[keep][:10]
    # a joint limit just at the nominal command of row 0, on the side the compensation needs
    free = compensate(model, p, r0, covariance=None)
    j = int(np.argmax(np.abs(free.readings[0] - r0[0])[:3]))
    lim = model.limits.copy()
    if free.readings[0, j] > r0[0, j]:
        lim[j, 1] = r0[0, j]
    else:
        lim[j, 0] = r0[0, j]
    other = np.ones(len(r0), bool)
    other[0] = False
    inside = np.all((free.readings[other] >= lim[:, 0]) & (free.readings[other] <= lim[:, 1]), axis=1)
    d = robot_to_dict(model)
    d["joints"][j]["limits"] = lim[j].tolist()
    limited = robot_from_dict(d, "limited")
    res = compensate(limited, p, r0, covariance=None)
    assert np.all((res.readings >= lim[:, 0]) & (res.readings <= lim[:, 1]))
    assert not res.reachable[0] and res.at_limit[0, j] and res.error_mm[0] > 1e-3
    assert res.unreachable_lines[0] == 2  # CSV line of row 0
    # rows whose solution lies inside the new limits are still solved exactly
    assert res.reachable[1:][inside].all()


def test_predicted_std_matches_monte_carlo_over_theta():
    """θ ~ N(θ̂, C) with C from a real calibration; the fixed commands reach x(r*, θ): RMS error vs column."""
    from estcal.workflows.calibrate import run_calibration
    from estcal.methods import NoiseModel
    from estcal.simulate import simulate

    nominal = load_robot("puma560")
    sim = simulate(nominal, 25, measure="pose", errors="random", noise={"position": 5e-5, "orientation": 5e-4},
                   seed=11)
    res, _, _ = run_calibration(nominal, sim.dataset, noise=NoiseModel(position=5e-5, orientation=5e-4,
                                                                        known=True))
    model = res.robot(nominal)
    model.meta["calibration"] = {"free": list(res.names), "covariance": np.asarray(res.covariance).tolist()}
    r0, kin = planned(nominal, 12, seed=3)
    keep = well_conditioned(nominal, r0, kin)
    r0, p, R = r0[keep], kin.p[keep], kin.R[keep]
    out = compensate(model, np.c_[p, matrix_to_quat(R)], r0)
    assert out.reachable.all() and out.std_mm is not None and out.rot_std_mrad is not None
    rng = np.random.default_rng(0)
    idx = model.params.indices(res.names)
    S = 1000  # relative sampling error of an RMS over 1000 draws: ≲ 2.5 %
    draws = rng.multivariate_normal(np.zeros(len(idx)), np.asarray(res.covariance), S)
    err2 = np.zeros(len(p))
    rot2 = np.zeros(len(p))
    for s in range(S):
        th = model.params.values.copy()
        th[idx] += draws[s]
        k = model.kinematics(out.readings, th, jacobian=False)
        err2 += np.sum((k.p - p) ** 2, axis=1)
        rot2 += np.sum(so3_log(R @ np.swapaxes(k.R, 1, 2)) ** 2, axis=1)
    mc = np.sqrt(err2 / S) * 1e3
    mc_rot = np.sqrt(rot2 / S) * 1e3
    assert np.all(np.abs(out.std_mm / mc - 1) < 0.10), np.c_[out.std_mm, mc]
    assert np.all(np.abs(out.rot_std_mrad / mc_rot - 1) < 0.10)


def test_joint_std_is_the_implicit_derivative_of_the_solution():
    """dr*/dθ from the implicit function theorem against re-solving at θ ± ε (square pose task)."""
    nominal = load_robot("puma560_masses")
    model = true_puma()
    r0, kin = planned(nominal, 10, seed=9)
    keep = well_conditioned(nominal, r0, kin)
    r0, tgt = r0[keep][:4], np.c_[kin.p[keep][:4], matrix_to_quat(kin.R[keep][:4])]
    names = ["a_2", "d_3", "offset_3", "alpha_2"]
    sd = np.array([2e-4, 3e-4, 1e-4, 5e-4])
    out = compensate(model, tgt, r0, covariance=(names, np.diag(sd ** 2)))
    D = np.zeros((len(r0), 6, len(names)))
    for k, n in enumerate(names):
        pr = []
        for sgn in (1, -1):
            m = model.copy()
            m.params[n] = model.params[n] + sgn * 1e-6
            pr.append(compensate(m, tgt, out.readings, covariance=None).readings)
        D[:, :, k] = (pr[0] - pr[1]) / 2e-6
    fd_std = np.sqrt(np.einsum("njk,k->nj", D ** 2, sd ** 2))
    assert np.allclose(out.joint_std, fd_std, rtol=1e-3, atol=1e-9)


# ------------------------------------------------------------------ command line
def write_targets(path, robot, r0, p, quat=None, extra=None):
    xyz = ["x", "y", "z"] if np.shape(p)[1] else []
    cols = ["label"] + list(robot.joint_names) + xyz + (["qw", "qx", "qy", "qz"] if quat is not None
                                                                    else []) + list(extra or {})
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for i in range(len(r0)):
            row = [f"pt{i}"] + [repr(float(v)) for v in r0[i]] + [repr(float(v)) for v in p[i]]
            if quat is not None:
                row += [repr(float(v)) for v in quat[i]]
            row += [repr(float(v[i])) for v in (extra or {}).values()]
            w.writerow(row)


@pytest.fixture
def cli_case(tmp_path):
    nominal = load_robot("puma560_masses")
    model = true_puma()
    model = model.add_effect(make_effect("backlash", model, joints=["j2"]))
    model.params["backlash_j2"] = 1e-3
    free = ["a_2", "d_3", "backlash_j2"]
    model.meta["calibration"] = {"free": free, "covariance": np.diag([1e-4, 1e-4, 1e-4]) ** 2}
    save_robot(model, tmp_path / "model.yaml")
    r0, kin = planned(nominal, 12, seed=2)
    keep = well_conditioned(nominal, r0, kin)
    r0, p, R = r0[keep][:6], kin.p[keep][:6].copy(), kin.R[keep][:6]
    # 1 m further from the shoulder than the arm reaches (≈ 0.86 m): outside the workspace (CSV line 5)
    o2 = nominal.kinematics(r0[3:4], jacobian=False).joint_origin[0, 1]
    p[3] += (p[3] - o2) / np.linalg.norm(p[3] - o2)
    appr = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    write_targets(tmp_path / "targets.csv", nominal, r0, p, matrix_to_quat(R), {"approach_j2": appr})
    return tmp_path, model, r0, p, R, appr


def test_cli_writes_commands_flags_unreachable_line_and_keeps_other_columns(cli_case):
    tmp, model, r0, p, R, appr = cli_case
    out, rep = tmp / "cmd.csv", tmp / "rep.json"
    before = (tmp / "targets.csv").read_text()
    r = runner.invoke(app, ["compensate", str(tmp / "targets.csv"), "--robot", str(tmp / "model.yaml"),
                            "-o", str(out), "--json", str(rep)])
    assert r.exit_code == 3, r.output
    assert "line" in r.output and "5" in r.output.split("lines")[-1]
    assert (tmp / "targets.csv").read_text() == before
    rows = list(csv.DictReader(out.open()))
    assert [row["label"] for row in rows] == [f"pt{i}" for i in range(6)]
    assert [row["reachable"] for row in rows] == ["1", "1", "1", "0", "1", "1"]
    assert {"predicted_error_mm", "predicted_std_mm", "predicted_rot_error_mrad"} <= set(rows[0])
    rep_d = json.loads(rep.read_text())
    assert rep_d["unreachable_lines"] == [5]
    rb = load_robot(tmp / "model.yaml")
    q = np.array([[float(row[j]) for j in rb.joint_names] for row in rows])
    ok = np.array([row["reachable"] == "1" for row in rows])
    k = rb.kinematics(q[ok], context={"approach_j2": appr[ok]}, jacobian=False)
    assert np.abs(k.p - p[ok]).max() < 1e-9
    assert np.all(np.array([float(row["predicted_std_mm"]) for row in rows]) > 0)
    r2 = runner.invoke(app, ["compensate", str(tmp / "targets.csv"), "--robot", str(tmp / "model.yaml"),
                             "-o", str(tmp / "cmd2.csv"), "--allow-unreachable"])
    assert r2.exit_code == 0 and "5" in r2.output


def test_cli_errors_exit_2_and_no_covariance_column(cli_case, tmp_path):
    tmp, model, r0, p, R, appr = cli_case
    t = str(tmp / "targets.csv")
    r = runner.invoke(app, ["compensate", t, "--robot", str(tmp / "model.yaml"), "-o", t])
    assert r.exit_code == 2 and "input" in r.output
    nominal = load_robot("puma560_masses")
    write_targets(tmp / "nox.csv", nominal, r0, np.zeros((len(r0), 0)))
    r = runner.invoke(app, ["compensate", str(tmp / "nox.csv"), "--robot", str(tmp / "model.yaml"), "-o",
                            str(tmp / "o.csv")])
    assert r.exit_code == 2 and "x,y,z" in r.output
    write_targets(tmp / "bad.csv", nominal, r0, p, extra={"approach_j9": appr})
    r = runner.invoke(app, ["compensate", str(tmp / "bad.csv"), "--robot", str(tmp / "model.yaml"), "-o",
                            str(tmp / "o.csv")])
    assert r.exit_code == 2 and "j9" in r.output
    text = (tmp / "targets.csv").read_text().replace("j3,", "jx,", 1)
    (tmp / "nojoint.csv").write_text(text)
    r = runner.invoke(app, ["compensate", str(tmp / "nojoint.csv"), "--robot", str(tmp / "model.yaml"), "-o",
                            str(tmp / "o.csv")])
    assert r.exit_code == 2 and "j3" in r.output
    assert not (tmp / "o.csv").exists()
    # a model without a calibration block: no std column, said on the console
    plain = model.copy()
    plain.meta.pop("calibration")
    save_robot(plain, tmp / "plain.yaml")
    r = runner.invoke(app, ["compensate", t, "--robot", str(tmp / "plain.yaml"), "-o", str(tmp / "o.csv"),
                            "--allow-unreachable"])
    assert r.exit_code == 0 and "predicted_std_mm omitted" in r.output
    assert "predicted_std_mm" not in (tmp / "o.csv").read_text().splitlines()[0]


def test_experiment_quick_headline(tmp_path):
    """experiments/compensation.py (one repetition): held-out targets planned on the nominal model."""
    from conftest import load_experiment

    out = load_experiment("compensation").main(["--quick", "--reps", "1", "--poses", "30", "--targets", "20", "--json", str(tmp_path / "c.json")])
    assert json.loads((tmp_path / "c.json").read_text())["results"] == out["results"]
    assert out["diagnosis"][0] and all(d["effect"] == "joint_compliance" for d in out["diagnosis"][0])
    r = out["results"]["file payload 2 kg"]
    assert r["nominal"]["rmse_mm"] > 2.0                      # several mm without compensation
    assert r["extended"]["rmse_mm"] < out["noise_floor_mm"]   # at the measurement-noise floor
    assert r["geometric"]["rmse_mm"] > 5 * r["extended"]["rmse_mm"]  # compliance matters


def test_gains_coupling_and_prismatic_joint_inverted():
    """Readings, not joint values: gains ≠ 1, a wrist coupling (GECARO eq. 4) and the Stanford
    arm's prismatic joint; the compensated readings drive the chain onto the target."""
    d = robot_to_dict(load_robot("stanford"))
    n = len([j for j in d["joints"] if j["type"] != "fixed"])
    Cm = np.eye(n)
    Cm[5, 4] = 0.3  # motor 5 drags joint 6 (wrist coupling)
    d["coupling"] = {"joint": np.eye(n).tolist(), "motor": Cm.tolist()}
    nominal = robot_from_dict(d, "stanford_coupled")
    model = nominal.copy()
    rng = np.random.default_rng(3)
    model.params.values[model.gain_idx] = 1 + rng.normal(0, 0.01, n)
    model.params.values[model.offset_idx] += rng.normal(0, 2e-3, n)
    r0, kin = planned(nominal, 30, seed=5, margin=0.2)
    keep = well_conditioned(nominal, r0, kin, floor=0.01)
    r0, T = r0[keep], np.c_[kin.p[keep], matrix_to_quat(kin.R[keep])]
    assert len(r0) >= 10
    res = compensate(model, T, r0, covariance=None)
    assert res.reachable.all()
    k = model.kinematics(res.readings, jacobian=False)
    assert np.abs(k.p - T[:, :3]).max() < 1e-9
    assert np.abs(k.R - kin.R[keep]).max() < 1e-9
    assert np.abs(res.readings - r0)[:, 2].max() > 1e-4  # the prismatic reading moved (m)
    # the solver's reading Jacobian (J_q · C_j diag(K) C_m) against central differences, at the
    # solution (zero rotation residual: there the log map's own Jacobian is the identity)
    th = model.params.values
    r0 = res.readings
    e, J = task_residual(model, r0[:5], th, {}, T[:5, :3], kin.R[keep][:5], 0.1)
    Jfd = np.empty_like(J)
    for c in range(n):
        dr = np.zeros(n)
        dr[c] = 1e-6
        ep, _ = task_residual(model, r0[:5] + dr, th, {}, T[:5, :3], kin.R[keep][:5], 0.1)
        em, _ = task_residual(model, r0[:5] - dr, th, {}, T[:5, :3], kin.R[keep][:5], 0.1)
        Jfd[..., c] = -(ep - em) / 2e-6
    assert np.abs(J - Jfd).max() < 1e-7 * np.abs(J).max()


@pytest.mark.parametrize("effect,column,value", [("joint_compliance", "payload", 6.0),
                                                 ("thermal_expansion", "temperature", 45.0)])
def test_cli_context_columns_reach_the_effects(tmp_path, effect, column, value):
    """A `payload` / `temperature` column changes the commands, and the model with that context reaches
    the target (the thermal model has a marker: the target is marker 1)."""
    nominal = load_robot("puma560_masses")
    base = true_puma(markers=1 if effect == "thermal_expansion" else 0)
    model = base.add_effect(make_effect(effect, base))
    for n in model.effects[0].param_names:
        model.params[n] = 3e-4 if effect == "joint_compliance" else 2.3e-5
    save_robot(model, tmp_path / "m.yaml")
    r0, kin = planned(nominal, 20, seed=8)
    keep = well_conditioned(nominal, r0, kin)
    r0, p = r0[keep][:5], kin.p[keep][:5]
    ctx = {column: np.full(len(r0), value)}
    write_targets(tmp_path / "t.csv", nominal, r0, p, extra=ctx)
    write_targets(tmp_path / "t0.csv", nominal, r0, p)
    outs = []
    for t in ("t.csv", "t0.csv"):
        r = runner.invoke(app, ["compensate", str(tmp_path / t), "--robot", str(tmp_path / "m.yaml"), "-o",
                                str(tmp_path / f"c_{t}")])
        assert r.exit_code == 0, r.output
        rows = list(csv.DictReader((tmp_path / f"c_{t}").open()))
        outs.append(np.array([[float(row[j]) for j in model.joint_names] for row in rows]))
    k = model.kinematics(outs[0], context=ctx, jacobian=False)
    reached = k.points[:, 0] if model.n_markers else k.p
    assert np.abs(reached - p).max() < 1e-9
    assert np.abs(outs[0] - outs[1]).max() > 1e-5  # the column was used


@pytest.mark.parametrize("from_order", [True, False])
def test_backlash_by_approach_takes_the_program_order_when_the_model_was_diagnosed_so(tmp_path, from_order):
    """A model with a backlash by approach, diagnosed with directions from the acquisition order (its
    ``data_preparation``): targets without ``approach_<joint>`` columns get them from the rows' order — the
    program's order of motion — and the commands reach the targets under those directions, said in a note.
    Without that preparation the correction is 0 (either side as likely), said too."""
    from estcal.io.prepare import derive_approach
    from estcal.io.dataset import dataset_from_arrays

    nominal = load_robot("puma560_masses")
    base = true_puma()
    model = base.add_effect(make_effect("backlash", base, joints=["j2", "j3"], by="approach"))
    model.params["backlash_approach_j2"], model.params["backlash_approach_j3"] = 2e-3, 1e-3
    model.meta["calibration"] = {"data_preparation": {"approach_from_order": from_order}}
    save_robot(model, tmp_path / "m.yaml")
    r0, kin = planned(nominal, 20, seed=8)
    keep = well_conditioned(nominal, r0, kin)
    r0, p = r0[keep][:6], kin.p[keep][:6]
    write_targets(tmp_path / "t.csv", nominal, r0, p)
    r = runner.invoke(app, ["compensate", str(tmp_path / "t.csv"), "--robot", str(tmp_path / "m.yaml"), "-o",
                            str(tmp_path / "c.csv")])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "c.csv").open()))
    q = np.array([[float(row[j]) for j in model.joint_names] for row in rows])
    # the directions a user would write by hand: the sign of each joint's move from the previous target's command
    d = derive_approach(dataset_from_arrays(model.joint_names, r0, p=p, R=kin.R[keep][:6], path=None))
    ctx = {f"approach_{j}": d.columns[f"approach_{j}"] for j in ("j2", "j3")} if from_order else {}
    assert not from_order or np.count_nonzero(ctx["approach_j2"]) == 5  # the first row's is unknown
    reached = model.kinematics(q, context=ctx, jacobian=False).p
    assert np.abs(reached - p).max() < 1e-9
    note = ("directions from the rows' order, the program's order of motion" if from_order
            else "no approach_<joint> column, correction 0")
    assert f"backlash by approach of j2, j3: {note}" in " ".join(r.output.split())
