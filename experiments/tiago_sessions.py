"""TIAGo over sessions (real data, ../shared/data/tiago): repeatability as process noise.

Protocol — written before any score was computed; every decision uses the
training sessions only (the two files of ``../shared/data/tiago``, 2021-11-30
and 2021-11-26); files given with ``--validate`` are scored once, at the end,
with the final model and never inform a choice.

1. Robot: the TIAGo URDF chain (torso lift + 7 arm joints) with the URDF link
   masses carried by each joint (:func:`estcal.discrepancy.masses.with_urdf_masses`)
   and the four points of the tracked hand body as unknown markers.
2. Approach columns are derived per session from the posture order (each
   session starts with no approach), time runs from each session's first pose.
3. Causes: :func:`estcal.discrepancy.diagnose` on the stacked training sessions
   (its default model: geometry and effects under relevance priors, causes named by
   evidence, folds and cross-validation); its model (the effects it keeps at their
   estimates, effect parameters free) is the model of the next steps.
4. Free set: the identifiable joint-offset level (base, markers, joint offsets)
   plus the named effects' parameters, by QR on the stacked training sessions; the
   load terms the diagnosis keeps without naming them stay at its estimate.
5. Varying parameters: forward selection among the free joint offsets and base
   parameters by the REML likelihood-ratio test (½χ²₀ + ½χ²₁, Bonferroni α = 1 %)
   on the training sessions (:func:`estcal.sessions.choose_vary`). Every
   candidate's variance component (REML, alone) is reported with its standard
   error in mrad / mm.
6. Leave-one-session-out, both ways: steps 3–4 on one session only (its own
   diagnosis, free set and fit) and the other session scored. A one-session fit
   has no between-session information, so its prediction carries only θ's
   covariance (Q = 0): its coverage is reported as is. The coverage with the
   repeatability Q of step 8 is also reported, flagged *in-sample* (Q saw both
   sessions). With two sessions that is all the data can say: Q cannot be
   chosen by leave-one-session-out (one training session has no between-session
   variance), so step 5 uses the likelihood-ratio test, and the ``--validate``
   sessions are the independent check.
7. Re-measuring k poses of a held-out session (k = 0…10): error on the rest of
   that session, poses chosen by the covariance rule or at random.
8. Final model: steps 3–5 on both sessions; each ``--validate`` file is scored
   with ``bl_mm`` (RMSE of the first marker, BL, as FIGAROH reports),
   ``all_points_mm`` and ``coverage95`` (95 % prediction ellipsoids of the BL point,
   θ covariance + Q).

``--json PATH`` keys: ``protocol``, ``decisions``, ``levels`` (one-session fits
scored on the other session, per level), ``causes``, ``free``, ``vary``,
``variance_components``, ``loso``, ``recalibration``, ``validation``
({file name: {bl_mm, all_points_mm, coverage95}}), ``figaroh``.
``--quick`` uses 5-fold CV in the diagnosis and k ≤ 5.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from estcal.discrepancy import diagnose  # noqa: E402
from estcal.io.prepare import derive_approach  # noqa: E402
from estcal.discrepancy.masses import with_urdf_masses  # noqa: E402
from estcal.estimate.levels import select_free  # noqa: E402
from estcal.io import load_dataset  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402
from estcal.kinematics.robots import shared_dir, tiago  # noqa: E402
from estcal.methods import NoiseModel, Problem  # noqa: E402
from estcal.sessions import choose_vary, fit_sessions, predict_session, recalibration_curve  # noqa: E402
from estcal.sessions.data import stack_sessions  # noqa: E402

FILES = ["qualisys_2021-11-30_static_postures.csv", "qualisys_2021-11-26_static_postures.csv"]
FIGAROH = {"full_params_11_26_mm": 3.07, "note": "FIGAROH full_params, trained on 11-30, BL point RMSE on 11-26"}
NOISE = NoiseModel(position=2e-4, orientation=2e-4, known=False)


def _session(path, robot):
    d = derive_approach(load_dataset(path, robot))
    if "t" in d.context:
        d.columns["t_abs"] = d.context["t"].copy()
        d.context["t"] = d.context["t"] - d.context["t"].min()
    return d


def _prepared(res, d):
    """A session prepared for the extended robot (effect columns into the context)."""
    from estcal.io.prepare import with_effect_context

    return with_effect_context(res.robot, d)


def _free(robot, sessions, level="joint_offset", effects=None):
    """The identifiable parameters of ``level`` and the effect parameters ``effects`` (None: every effect
    parameter of ``robot``). The diagnosis's model keeps further load terms under relevance priors; fitted
    without their priors on one session they are not determined, so only the named causes' parameters are
    freed and the other kept terms stay at the diagnosis's estimate."""
    is_effect = np.array([k == "effect" for k in robot.params.kinds])
    # the level's identifiable set of the geometry alone (the effects at zero): a kept load term at its estimate
    # would make a parameter it nearly regroups with (arm_7's offset with the markers) formally identifiable,
    # and the unpenalised fit would wander along that direction (26 rad on 11-30)
    geometric = robot.with_values(np.where(is_effect, 0.0, robot.params.values))
    prob = Problem(geometric, [(None, d, NOISE) for d in sessions], NOISE)
    sel = select_free(prob, level)
    effect = [n for n, e in zip(robot.params.names, is_effect) if e and (effects is None or n in effects)]
    # start: the level's own registration fit for a geometric robot, the diagnosis's estimate for its model
    start = robot.params.values.copy() if is_effect.any() else sel.theta
    return sel.identifiable + [n for n in effect if n not in sel.identifiable], start


def _score(fit, d) -> dict:
    full = predict_session(fit, d)  # every marker; BL = the first (FIGAROH's point)
    return {"bl_mm": full["rmse_mm_per_point"][0], "all_points_mm": full["rmse_mm"],
            "coverage95": full["coverage_per_point"][0], "coverage95_all_points": full["coverage"],
            "predicted_std_bl_mm": full["predicted_std_mm"][0], "n_poses": d.n, "band_bl": _band(d.n)}


def _band(n):
    from estcal.sessions import coverage_band

    return coverage_band(n)


def model_on(sessions, names, quick: bool, log) -> dict:
    """Steps 3–5 on ``sessions``: diagnosis, free set, varying parameters, fit."""
    stacked = stack_sessions(sessions, names)
    k = 5 if quick else min(stacked.n, 10)
    res = diagnose(ROBOT, stacked, k_folds=k, noise=None, robot_spec="tiago", budget=False)
    log(f"  diagnosis on {' + '.join(names)}: {res.named or 'no cause'} "
        f"(effect terms kept: {', '.join(res.terms['kept']) or 'none'})")
    prepared = [_prepared(res, d) for d in sessions]
    free, _ = _free(res.robot, prepared, effects={n for c in res.causes for n in c.parameters})
    # start from the diagnosis' estimate (effects included)
    cand = [n for n in free if n.startswith("offset_") or n.startswith("base_")]
    choice = choose_vary(res.robot, prepared, free, candidates=cand, noise=NOISE, theta=res.robot.params.values)
    fit = choice["fit"]
    comps = []
    for c in (cand if len(sessions) > 1 else []):
        f1 = fit_sessions(res.robot, prepared, free, [c], noise=NOISE, theta=fit.theta)
        comps.append(f1.variance_components()[0])
    return {"diagnosis": res, "prepared": prepared, "free": free, "choice": choice, "fit": fit,
            "components": comps, "robot": res.robot}


ROBOT = None


def main(argv=None) -> dict:
    global ROBOT
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="folder with the TIAGo files (default ../shared/data/tiago)")
    ap.add_argument("--validate", type=Path, nargs="*", default=[], help="extra sessions, scored only")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    folder = args.data or (shared_dir() / "data" / "tiago")
    if not (folder / FILES[0]).exists():
        print(f"TIAGo data not found at {folder} (../shared/data/tiago next to the repository)")
        return {"skipped": True}
    t0 = time.time()
    log = print
    ROBOT = with_urdf_masses(tiago(n_markers=4))
    sessions = [_session(folder / f, ROBOT) for f in FILES]
    names = [f.split("_")[1] for f in FILES]
    out: dict = {"protocol": __doc__.split("Protocol —")[1].split("``--json")[0].strip(), "decisions": [],
                 "figaroh": FIGAROH, "sessions": {n: d.n for n, d in zip(names, sessions)}}

    # levels: one-session geometric fits scored on the other session (both ways)
    log("== one-session fits scored on the other session (no repeatability model)")
    levels = {}
    for level in ("registration", "joint_offset", "full"):
        levels[level] = {}
        for a, b in ((0, 1), (1, 0)):
            free, th = _free(ROBOT, [sessions[a]], level)
            f = fit_sessions(ROBOT, [sessions[a]], free, [], noise=NOISE, theta=th)
            s = _score(f, sessions[b])
            levels[level][f"{names[a]}->{names[b]}"] = {"n_parameters": len(free), **s}
            log(f"  {level:<13} {names[a]} -> {names[b]}: {len(free):3d} parameters, BL {s['bl_mm']:.3f} mm, "
                f"all points {s['all_points_mm']:.3f} mm, coverage95 (BL) {s['coverage95']:.2f}")
    out["levels"] = levels

    # final model on both training sessions
    log("\n== repeatability model on both sessions")
    final = model_on(sessions, names, args.quick, log)
    fit = final["fit"]
    out["causes"] = [c.to_dict() for c in final["diagnosis"].causes]
    out["free"] = final["free"]
    out["vary"] = final["choice"]["vary"]
    out["vary_selection"] = [{"accepted": s["accepted"], "alpha_per_test": s["alpha_per_test"],
                              "table": [{k: v for k, v in e.items() if k != "std"} for e in s["table"][:8]]}
                             for s in final["choice"]["steps"]]
    out["variance_components"] = final["components"]
    out["decisions"].append(f"causes {final['diagnosis'].named} by the diagnosis on both training sessions")
    out["decisions"].append(f"varying parameters {out['vary'] or 'none'} by REML LR (α = 1 %, Bonferroni)")
    log(f"  free: {len(final['free'])} parameters; varying between sessions: {out['vary'] or 'none'}")
    for v in final["components"]:
        log(f"    {v['parameter']:<22} between-session std {v['std']:.3f} ± {v['std_err']:.3f} {v['unit']}")

    # leave-one-session-out both ways: diagnosis, free set and fit on one session only
    log("\n== leave one session out (causes, free set and fit from the training session only)")
    loso, recal = {}, {}
    ks = range(0, 6 if args.quick else 11)
    for a, b in ((0, 1), (1, 0)):
        one = model_on([sessions[a]], [names[a]], args.quick, log)
        prep_b = _prepared(one["diagnosis"], sessions[b])
        f0 = one["fit"]  # one session: no between-session information, Q = 0
        s0 = _score(f0, prep_b)
        key = f"{names[a]}->{names[b]}"
        loso[key] = {"causes": one["diagnosis"].named, "n_parameters": len(one["free"]), "without_Q": s0}
        msg = (f"  {key}: BL {s0['bl_mm']:.3f} mm, all points {s0['all_points_mm']:.3f} mm; coverage95 (BL) "
               f"{s0['coverage95']:.2f} (band {s0['band_bl'][0]:.2f}–{s0['band_bl'][1]:.2f})")
        vq = [n for n in fit.vary if n in f0.names]
        if vq:
            # the same one-session θ with the final model's repeatability Q (in-sample: Q saw both sessions)
            f0.vary = vq
            f0.q = np.array([fit.q[fit.vary.index(n)] for n in vq])
            sq = _score(f0, prep_b)
            loso[key]["with_Q_in_sample"] = sq
            msg += f"; {sq['coverage95']:.2f} with the final Q (in-sample)"
            rc = recalibration_curve(f0, prep_b, ks)
            rr = recalibration_curve(f0, prep_b, ks, rule="random", n_random=10)
            recal[key] = {"covariance": rc, "random": rr, "note": "prior covariance uses the final (in-sample) Q"}
            msg += ("\n    re-measured k = " + ", ".join(f"{k}: {v:.2f}" for k, v in zip(rc["k"], rc["rmse_mm"]))
                    + " mm (covariance rule); random: " + ", ".join(f"{v:.2f}" for v in rr["rmse_mm"]))
        log(msg)
    out["loso"], out["recalibration"] = loso, recal

    # independent sessions
    out["validation"] = {}
    for path in args.validate:
        d = _prepared(final["diagnosis"], _session(path, ROBOT))
        s = _score(fit, d)
        out["validation"][path.name] = s
        log(f"  validate {path.name}: BL {s['bl_mm']:.3f} mm, all points {s['all_points_mm']:.3f} mm, "
            f"coverage95 {s['coverage95']:.2f}")
    out["final_model"] = fit.to_dict()
    out["time_s"] = time.time() - t0
    log(f"\n{out['time_s']:.0f} s")
    if args.json:
        write_json(args.json, out)
        log(f"wrote {args.json}")
    return out


if __name__ == "__main__":
    main()
