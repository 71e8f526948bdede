"""Compensation on a simulated robot: nominal vs geometric vs extended (compliance) model.

Setting
-------
* Nominal model: the PUMA 560 of Table 6.1 with the packaged link masses
  (``puma560_masses``) and a 2 kg payload at 0.1 m on the tool axis.
* True robot (:func:`estcal.simulate.simulate`): nominal + random geometric
  errors (σ = 1 mm / 1 mrad on every length, angle and offset) + joint
  compliance on j2 and j3 (2e-5 and 3e-5 rad/(N·m)).
* Calibration data: ``--poses`` full poses (strategy S4) measured with CMM
  noise 0.05 mm / 0.5 mrad.
* Models: **geometric** — ``run_calibration`` at level ``full`` (the
  identifiable set by QR); **extended** — the effects that
  :func:`estcal.discrepancy.diagnose.diagnose` names on the same data, added to
  the nominal model and calibrated together with the geometric set. Both are
  saved with their ``calibration:`` block (free names + covariance).
* Held-out targets: ``--targets`` new postures (uniform within the limits
  shrunk by 10 %, a seed not used for calibration), kept only away from
  singularities (smallest singular value of the weighted pose Jacobian
  ≥ 0.03, as a real program is planned), *planned on the nominal model*: the
  target is the nominal forward kinematics of the nominal command.
* Execution: each model's commands (nominal = the planned command itself;
  geometric / extended = :func:`estcal.compensation.compensate` from the saved
  file) are sent to the true robot (noise-free forward kinematics, effects
  included) with the file's payload, and again with a 5 kg payload (a
  ``payload`` column in the targets: only the extended model can use it).

Reported per model, pooled over ``--reps`` independent true robots (seed,
seed + 1, …; each with its own calibration data, models and targets):
position error of the reached pose (RMSE, max, mm), orientation error (RMSE,
max, mrad), the RMS of the predicted std (``predicted_std_mm``) to compare with
the reached RMSE, and the rows a model could not reach within tolerance. The
statistics use the rows both compensating models reached (unreachable rows are
counted, never averaged in).

Run: ``python experiments/compensation.py [--quick] [--json PATH] [--out DIR] [--reps R]``
(``--out`` writes the first repetition's saved models, true robot and targets
CSV, used in docs/compensation.md).

JSON keys: ``settings``, ``diagnosis`` (named causes, per repetition),
``calibration`` (per repetition: {geometric, extended}: n_parameters,
train_rmse_mm, sigma0, effects), ``results`` ({payload label: {nominal,
geometric, extended: {rmse_mm, max_mm, rmse_mrad, max_mrad, unreachable, n_rows,
predicted_std_rms_mm}}}), ``noise_floor_mm``, ``seconds``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

COMPLIANCE = {"compliance_j2": 2e-5, "compliance_j3": 3e-5}  # rad/(N·m)
NOISE_POS, NOISE_ROT = 5e-5, 5e-4  # CMM, m / rad


def nominal_robot():
    from estcal.io.robotfile import load_robot, robot_from_dict, robot_to_dict

    d = robot_to_dict(load_robot("puma560_masses"))
    d["payload"] = {"mass": 2.0, "com": [0.0, 0.0, 0.1]}
    return robot_from_dict(d, "puma560_masses+payload")


def plan_targets(nominal, n, seed):
    """Well-conditioned nominal commands and the poses the nominal model reaches with them."""
    from estcal.compensation.solve import task_residual

    r = nominal.random_readings(4 * n, np.random.default_rng(seed), margin=0.1)
    kin = nominal.kinematics(r, jacobian=False)
    _, J = task_residual(nominal, r, nominal.params.values, {}, kin.p, kin.R, 0.1)
    keep = np.flatnonzero(np.linalg.svd(J, compute_uv=False)[:, -1] >= 0.03)[:n]
    return r[keep], kin.p[keep], kin.R[keep]


def with_covariance(res, base):
    robot = res.robot(base)
    robot.meta["calibration"] = {"method": res.method, "free": list(res.names),
                                 "covariance": np.asarray(res.covariance).tolist()}
    return robot


def errors(true, cmd, p, R, context):
    from estcal.kinematics.transforms import so3_log

    k = true.kinematics(cmd, context=context, jacobian=False)
    dp = np.linalg.norm(k.p - p, axis=1) * 1e3
    dr = np.linalg.norm(so3_log(R @ np.swapaxes(k.R, 1, 2)), axis=1) * 1e3
    return dp, dr


def run(n_poses: int, n_targets: int, seed: int, out: Path | None) -> dict:
    from estcal.compensation import compensate
    from estcal.discrepancy.diagnose import diagnose
    from estcal.effects import make_effect
    from estcal.workflows.calibrate import run_calibration
    from estcal.io.robotfile import save_robot
    from estcal.kinematics.transforms import matrix_to_quat
    from estcal.methods import NoiseModel
    from estcal.simulate import simulate

    nominal = nominal_robot()
    sim = simulate(nominal, n_poses, measure="pose", errors="random",
                   effects=[{"effect": "joint_compliance", "joints": ["j2", "j3"], "params": COMPLIANCE}],
                   noise={"position": NOISE_POS, "orientation": NOISE_ROT}, seed=seed)
    true, ds = sim.true_robot, sim.dataset
    noise = NoiseModel(position=NOISE_POS, orientation=NOISE_ROT)

    res_g, sel, _ = run_calibration(nominal, ds, noise=noise)
    geo = with_covariance(res_g, nominal)

    dg = diagnose(nominal, ds, noise=NoiseModel(position=NOISE_POS, orientation=NOISE_ROT, known=True))
    ext = nominal
    for name, joints in dg.named:
        ext = ext.add_effect(make_effect(name, ext, joints=list(joints)))
    eff_names = [n for e in ext.effects for n in e.param_names]
    res_e, _, _ = run_calibration(ext, ds, free=list(res_g.names) + eff_names, noise=noise)
    extm = with_covariance(res_e, ext)

    cmd0, p, R = plan_targets(nominal, n_targets, seed + 1000)
    rows = {}
    for label, ctx in (("file payload 2 kg", {}), ("payload 5 kg", {"payload": np.full(len(p), 5.0)})):
        for name, model in (("nominal", None), ("geometric", geo), ("extended", extm)):
            if model is None:
                cmd, ok, std = cmd0, np.ones(len(p), bool), np.full(len(p), np.nan)
            else:
                c = compensate(model, np.c_[p, matrix_to_quat(R)], cmd0, context=ctx)
                cmd, ok, std = c.readings, c.reachable, c.std_mm
            dp, dr = errors(true, cmd, p, R, ctx)
            rows[(label, name)] = {"pos_mm": dp, "rot_mrad": dr, "reachable": ok, "std_mm": std}
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        save_robot(geo, out / "geometric.yaml")
        save_robot(extm, out / "extended.yaml")
        save_robot(true, out / "true.yaml")
        q = matrix_to_quat(R)
        header = list(nominal.joint_names) + ["x", "y", "z", "qw", "qx", "qy", "qz"]
        M = np.c_[cmd0, p, q]
        np.savetxt(out / "targets.csv", M, delimiter=",", header=",".join(header), comments="", fmt="%.17g")

    return {
        "settings": {"robot": nominal.name, "poses": n_poses, "targets": len(p), "seed": seed,
                     "compliance": COMPLIANCE, "noise_mm_mrad": [NOISE_POS * 1e3, NOISE_ROT * 1e3],
                     "true_errors": len(sim.truth["errors"])},
        "diagnosis": [{"effect": e, "joints": list(j)} for e, j in dg.named],
        "calibration": {
            "geometric": {"n_parameters": len(res_g.names), "train_rmse_mm": res_g.to_dict()["rmse_mm"]["train"],
                          "sigma0": res_g.sigma0},
            "extended": {"n_parameters": len(res_e.names), "train_rmse_mm": res_e.to_dict()["rmse_mm"]["train"],
                         "sigma0": res_e.sigma0,
                         "effects": {n: [float(v), float(s)] for n, v, s in zip(res_e.names, res_e.estimate,
                                                                               res_e.std) if n in eff_names}}},
        "rows": rows,
    }


def summarise(reps: list[dict]) -> dict:
    """Pool the held-out rows of every repetition. Statistics use the rows that both compensating
    models reached within tolerance (the others are counted, never averaged in silently)."""
    out = {}
    for key in reps[0]["rows"]:
        label, name = key
        common = [r["rows"][(label, "geometric")]["reachable"] & r["rows"][(label, "extended")]["reachable"]
                  for r in reps]
        dp = np.concatenate([r["rows"][key]["pos_mm"][m] for r, m in zip(reps, common)])
        dr = np.concatenate([r["rows"][key]["rot_mrad"][m] for r, m in zip(reps, common)])
        sd = np.concatenate([r["rows"][key]["std_mm"][m] for r, m in zip(reps, common)])
        unreach = sum(int((~r["rows"][key]["reachable"]).sum()) for r in reps)
        out.setdefault(label, {})[name] = {
            "rmse_mm": float(np.sqrt(np.mean(dp ** 2))), "max_mm": float(dp.max()),
            "rmse_mrad": float(np.sqrt(np.mean(dr ** 2))), "max_mrad": float(dr.max()),
            "unreachable": unreach, "n_rows": int(dp.size),
            "predicted_std_rms_mm": None if np.isnan(sd).all() else float(np.sqrt(np.mean(sd ** 2)))}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="40 calibration poses, 50 targets, 2 repetitions")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None, help="write the first repetition's saved models, true "
                                                           "robot and targets.csv here")
    ap.add_argument("--poses", type=int, default=None, help="calibration poses (default 60, quick 40)")
    ap.add_argument("--targets", type=int, default=None, help="held-out targets per repetition (default 200, "
                                                              "quick 50)")
    ap.add_argument("--reps", type=int, default=None, help="independent true robots + calibrations "
                                                           "(default 5, quick 2)")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    t0 = time.time()
    n_poses = a.poses or (40 if a.quick else 60)
    n_targets = a.targets or (50 if a.quick else 200)
    reps = [run(n_poses, n_targets, a.seed + k, a.out if k == 0 else None)
            for k in range(a.reps or (2 if a.quick else 5))]
    out = {"settings": {**reps[0]["settings"], "repetitions": len(reps), "seeds": [r["settings"]["seed"]
                                                                                  for r in reps]},
           "diagnosis": [r["diagnosis"] for r in reps],
           "calibration": [r["calibration"] for r in reps],
           "results": summarise(reps),
           "noise_floor_mm": float(np.sqrt(3) * NOISE_POS * 1e3)}
    out["seconds"] = round(time.time() - t0, 1)
    for k, (dg, cal) in enumerate(zip(out["diagnosis"], out["calibration"])):
        print(f"rep {k}: diagnose names {', '.join(d['effect'] + ':' + ','.join(d['joints']) for d in dg)}; "
              f"geometric {cal['geometric']['n_parameters']} parameters (σ0 = {cal['geometric']['sigma0']:.2f}), "
              f"extended {cal['extended']['n_parameters']} (σ0 = {cal['extended']['sigma0']:.2f}): "
              + ", ".join(f"{n} = {v[0]:.3g} ± {v[1]:.2g}" for n, v in cal["extended"]["effects"].items()))
    first = next(iter(out["results"].values()))["extended"]
    print(f"{len(reps)} × {n_targets} held-out pose targets planned on the nominal model, executed on the true "
          f"robot; statistics over the {first['n_rows']} rows both models reached "
          f"(noise floor √3·σ = {out['noise_floor_mm']:.3f} mm)")
    print(f"{'payload':<18}{'commands':<11}{'RMSE mm':>9}{'max mm':>9}{'RMSE mrad':>11}{'max mrad':>10}"
          f"{'pred. std mm':>14}{'unreach.':>10}")
    for lab, rows in out["results"].items():
        for name, r in rows.items():
            ps = "—" if r["predicted_std_rms_mm"] is None else f"{r['predicted_std_rms_mm']:.4f}"
            print(f"{lab:<18}{name:<11}{r['rmse_mm']:>9.4f}{r['max_mm']:>9.4f}{r['rmse_mrad']:>11.4f}"
                  f"{r['max_mrad']:>10.4f}{ps:>14}{r['unreachable']:>10}")
    print(f"({out['seconds']} s)")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
