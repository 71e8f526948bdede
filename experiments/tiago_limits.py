"""What limits the TIAGo posture- and session-disjoint figure (``tiago_disjoint.py``) — two measurements on the
development halvings (seeds 0–5, both directions), no choice of the model made on them.

1. **Where the error is.** Each halving's validation file is scored three ways by the same diagnosis (a validation
   file never decides anything): all its new-posture rows; only those whose every joint reading lies inside the
   range the training rows span (interpolation); only the others (extrapolation). Each of the two partial files
   keeps the rows at seen postures, which register its measuring frame as in the whole file.
2. **What the protocol allows when the model class is right.** Both sessions are simulated at their real joint
   readings (and time, load columns) from the model the default diagnosis fits on both sessions together, with
   Gaussian noise — the error that model found (each posture's marker body moved rigidly by its own draw of
   the fitted rigid error per posture, plus the within-posture σ: ``simulate_like``'s default), independent
   noise of the same size as that model's residual (each session at its own frame), the between-session
   repeatability of a point (0.44 mm per point once the 37 postures the sessions share are registered by one
   rigid motion and arm_5's moved zero — the two-session diagnosis's floor; 0.96 with the rigid motion
   alone —, i.e. 0.44/√3 mm per coordinate), and 0.1 mm — and the same halvings are scored with the default
   diagnosis: the figure the protocol gives when the data hold nothing the model class cannot represent.

3. **What moved between the sessions, without a model.** The 37 postures both sessions measured (the same
   joint readings within 0.4 mrad): one rigid motion (Kabsch, scipy's ``Rotation.align_vectors``) registers
   11-26's points onto 11-30's over all of them; then, per posture, the rotation that still separates the two
   measurements of the hand (its four points) — a change of the measuring frame would leave none, a moved
   joint zero leaves one that turns with the posture; beside it, the joint zeros the diagnosis of both
   sessions registers for 11-26 (docs/discrepancy.md, "Sessions, postures and time"); and what that model leaves:
   its residual at the shared postures in both sessions (does the same posture keep the same error?) and,
   at 11-26's other postures, what the three nearest 11-30 postures' residual predicts of it (is it a smooth
   function of the joint angles?).

``--json PATH`` writes every figure; ``--noise-seeds`` the simulation draws (default 11, 21, 31).
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from estcal.base.jsonio import write_json  # noqa: E402

import tiago_disjoint as td  # noqa: E402

#: the between-session repeatability of a point, mm (the 37 shared postures, registered by one rigid motion and
#: arm_5's moved zero: the two-session diagnosis's repeatability floor; per session)
REPEATABILITY_MM = 0.44


def where_the_error_is(robot, sessions, seeds) -> list[dict]:
    """Per halving: the RMSE at all new postures, inside the training ranges, beyond them (mm), their counts, and
    the share of the squared error beyond."""
    from estcal.validation import inside_ranges, seen_postures
    from estcal.workflows.diagnose import diagnose

    rows = []
    for s, tr, T, V in td.halvings(robot, sessions, seeds):
        seen = seen_postures(T.readings, V.readings, robot.joint_types)
        inside = inside_ranges(T.readings, V.readings) & ~seen
        beyond = ~inside & ~seen
        parts = [V, V.subset(np.flatnonzero(seen | inside)), V.subset(np.flatnonzero(seen | beyond))]
        res = diagnose(robot, T, validate=parts, budget=False)
        v = res.accuracy["validation"]
        n_in, n_out = int(inside.sum()), int(beyond.sum())
        sq_out = v[2]["rmse_mm"] ** 2 * n_out if n_out else 0.0
        rows.append({"seed": s, "train": tr, "n_train": T.n, "new_mm": v[0]["rmse_mm"], "n_new": v[0]["n_new"],
                     "inside_mm": v[1]["rmse_mm"] if n_in else None, "n_inside": n_in,
                     "beyond_mm": v[2]["rmse_mm"] if n_out else None, "n_beyond": n_out,
                     "beyond_share_of_sq": sq_out / (v[0]["rmse_mm"] ** 2 * v[0]["n_new"]),
                     # a load-side backlash is a candidate only where the joint's gravity torque changes sign
                     # (a backlash by approach wherever the joint moved)
                     "backlash_candidates": sorted(j for c in res.terms["candidates"] if c["effect"] == "backlash"
                                                   and c["options"].get("by") == "load" for j in c["joints"])})
        r = rows[-1]
        print(f"seed {s} train {tr} ({T.n} rows): new postures {r['new_mm']:.2f} mm ({r['n_new']} rows); inside the "
              f"training ranges {_f(r['inside_mm'])} ({n_in}), beyond {_f(r['beyond_mm'])} ({n_out}: "
              f"{100 * r['beyond_share_of_sq']:.0f} % of the squared error); backlash-by-load candidates "
              f"{', '.join(j.replace('_joint', '') for j in r['backlash_candidates']) or 'none'}", flush=True)
    return rows


def _f(x):
    return "—" if x is None else f"{x:.2f} mm"


def simulated(robot, sessions, seeds, noise_seeds) -> dict:
    """The halvings' mean on data simulated from the two-session model (module docstring, 2.)."""
    from estcal.discrepancy.feedback import simulate_like
    from estcal.workflows.diagnose import diagnose

    ref = diagnose(robot, [sessions["11-30"], sessions["11-26"]], budget=False)
    resid_mm = float(ref.model["residual"]["rmse_mm"])
    out = {"reference_named": [c.label for c in ref.causes], "reference_residual_mm": resid_mm, "runs": []}
    print(f"reference: the default diagnosis of both sessions — residual {resid_mm:.2f} mm per point; named "
          f"{', '.join(out['reference_named']) or 'nothing'}")
    iid = resid_mm * 1e-3 / np.sqrt(3.0)
    for label, sigma in (("its rigid error per posture", None), ("its residual, independent", iid),
                         ("repeatability", REPEATABILITY_MM * 1e-3 / np.sqrt(3.0)), ("0.1 mm", 1e-4)):
        for ns in noise_seeds:
            sims = {k: simulate_like(ref, sessions[k], seed=ns + i, noise=sigma)
                    for i, k in enumerate(("11-30", "11-26"))}
            r = [diagnose(robot, T, validate=[V], budget=False).accuracy["validation"][0]["rmse_mm"]
                 for _, _, T, V in td.halvings(robot, sims, seeds)]
            out["runs"].append({"noise": label, "sigma_m": sigma, "noise_seed": ns, "new_mm": r,
                                "mean_mm": float(np.mean(r))})
            print(f"simulated, noise {label}, draw {ns}: mean {np.mean(r):.2f} mm (trained on 11-30 "
                  f"{np.mean(r[0::2]):.2f}, on 11-26 {np.mean(r[1::2]):.2f})", flush=True)
    return out


def between_sessions(robot, sessions) -> dict:
    """Part 3 of the module docstring: the hand's rotation between the sessions at their shared postures (mrad:
    its mean vector and the RMS of its change about that mean, in the measuring frame), the points' RMS
    difference after the one registration (mm), and the two-session diagnosis's joint zeros of 11-26."""
    from scipy.spatial.transform import Rotation

    from estcal.validation import posture_groups
    from estcal.workflows.diagnose import diagnose

    a, b = sessions["11-30"], sessions["11-26"]
    g = posture_groups(np.vstack([a.readings, b.readings]), robot.joint_types)
    shared = np.intersect1d(g[: a.n], g[a.n:])
    ia = np.array([np.flatnonzero(g[: a.n] == p)[0] for p in shared])
    ib = np.array([np.flatnonzero(g[a.n:] == p)[0] for p in shared])
    pa, pb = np.asarray(a.points)[ia], np.asarray(b.points)[ib]  # (P, 4, 3)
    ca, cb = pa.reshape(-1, 3).mean(0), pb.reshape(-1, 3).mean(0)
    rot, _ = Rotation.align_vectors((pa.reshape(-1, 3) - ca), (pb.reshape(-1, 3) - cb))
    pb = rot.apply((pb - cb).reshape(-1, 3)).reshape(pb.shape) + ca
    turn = np.array([Rotation.align_vectors(x - x.mean(0), y - y.mean(0))[0].as_rotvec()
                     for x, y in zip(pb, pa)]) * 1e3  # the hand of 11-26 onto 11-30's, per posture
    both = diagnose(robot, [a, b], budget=False)
    zeros = next(iter(both.model["session_frames"].values())).get("zeros", {})
    ra, rb = _residual(both, a, {}), _residual(both, b, zeros)  # (n, 4, 3) m, each session at its frame and zeros
    rms = lambda e: float(np.sqrt(np.mean(np.sum(e ** 2, axis=-1))) * 1e3)  # noqa: E731
    new = np.setdiff1d(np.arange(b.n), ib)
    # the three 11-30 postures nearest in joint space (readings standardised by 11-26's spread) predict 11-26's
    # residual at its 25 new postures: a smooth error in the joint angles would be predicted
    q_sd = np.where(b.readings.std(0) > 0, b.readings.std(0), 1.0)
    dist = np.linalg.norm((b.readings[new, None, :] - a.readings[None, :, :]) / q_sd, axis=-1)
    near = np.argsort(dist, axis=1)[:, :3]
    residual = {"shared_correlation": float(np.corrcoef(ra[ia].ravel(), rb[ib].ravel())[0, 1]),
                "shared_mean_mm": rms((ra[ia] + rb[ib]) / 2), "shared_half_difference_mm": rms((ra[ia] - rb[ib]) / 2),
                "new_mm": rms(rb[new]), "new_minus_nearest_mm": rms(rb[new] - ra[near].mean(axis=1))}
    out = {"postures": int(len(shared)),
           "max_reading_difference_mrad": float(np.abs(a.readings[ia] - b.readings[ib]).max() * 1e3),
           "points_rms_mm": float(np.sqrt(np.mean(np.sum((pb - pa) ** 2, axis=-1))) * 1e3),
           "hand_turn_mean_mrad": turn.mean(0).tolist(),
           "hand_turn_spread_mrad": float(np.sqrt(np.mean(np.sum((turn - turn.mean(0)) ** 2, axis=1)))),
           "two_session_zeros_11_26": zeros, "two_session_residual": residual}
    moved = ", ".join(f"{j} {v[0]:+.1f} ± {v[1]:.1f} {v[2]}" for j, v in zeros.items() if abs(v[0]) > 3 * v[1])
    print(f"between the sessions, {out['postures']} shared postures (readings within "
          f"{out['max_reading_difference_mrad']:.2f} mrad): after one rigid registration the points differ by "
          f"{out['points_rms_mm']:.2f} mm RMS; the hand turns by {np.linalg.norm(turn.mean(0)):.1f} mrad on average "
          f"and by {out['hand_turn_spread_mrad']:.1f} mrad RMS about that, posture to posture; the two sessions "
          f"diagnosed together move 11-26's zeros: {moved or 'none'}")
    print(f"that model's residual at the shared postures: correlation {residual['shared_correlation']:.2f} between the "
          f"sessions, {residual['shared_mean_mm']:.2f} mm RMS in common and {residual['shared_half_difference_mm']:.2f} "
          f"apart; at 11-26's {len(new)} other postures {residual['new_mm']:.2f} mm, "
          f"{residual['new_minus_nearest_mm']:.2f} once the three nearest 11-30 postures' residual is subtracted")
    return out


def _residual(res, data, zeros):
    """(n, k, 3) measured minus predicted points (m) of ``data`` with the diagnosis's model, its joint zeros moved by
    ``zeros`` ({joint: [value (mrad or mm), std, unit]}) and its frame registered by one rigid motion."""
    from scipy.spatial.transform import Rotation

    from estcal.discrepancy.zeros import zero_parameters

    model = res.robot
    theta = model.params.values.copy()
    param = dict(zero_parameters(model))
    for j, v in zeros.items():
        theta[model.params.index(param[j])] += v[0] * 1e-3
    d = res.prepare(data)
    meas = np.asarray(data.points)
    pred = model.kinematics(d.readings, theta, context=d.context, jacobian=False).points[:, : meas.shape[1]]
    cp, cm = pred.reshape(-1, 3).mean(0), meas.reshape(-1, 3).mean(0)
    rot, _ = Rotation.align_vectors(meas.reshape(-1, 3) - cm, pred.reshape(-1, 3) - cp)
    return meas - (rot.apply(pred.reshape(-1, 3) - cp).reshape(pred.shape) + cm)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise-seeds", default="11,21,31")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    from estcal.base.blas import single_thread_blas

    warnings.filterwarnings("ignore")
    if td.missing():
        print(td.missing())
        return {"skipped": True}
    robot, sessions = td.load()
    t0 = time.process_time()
    with single_thread_blas():  # as the diagnosis runs anyway: the simulation's own arrays too
        out = {"seeds": list(td.DEVELOPMENT), "where": where_the_error_is(robot, sessions, td.DEVELOPMENT)}
        w = out["where"]
        ins = [r["inside_mm"] for r in w if r["inside_mm"] is not None]
        out["inside_mean_mm"], out["new_mean_mm"] = float(np.mean(ins)), float(np.mean([r["new_mm"] for r in w]))
        print(f"mean at new postures {out['new_mean_mm']:.2f} mm; inside the training ranges {out['inside_mean_mm']:.2f} "
              f"mm (range {min(ins):.2f}–{max(ins):.2f})")
        out["simulated"] = simulated(robot, sessions, td.DEVELOPMENT, [int(x) for x in args.noise_seeds.split(",")])
        out["between_sessions"] = between_sessions(robot, sessions)
    out["cpu_s"] = time.process_time() - t0
    if args.json:
        write_json(args.json, out, announce=True)
    return out


if __name__ == "__main__":
    main()
