"""A prior instead of a level: MAP calibration with one nominal-centred prior width per parameter (or per group).

The recommended procedure of ``experiments/real_robots.py`` chooses a discrete geometric level
(joint_offset / aic / full) and names effects one by one; on half the TIAGo postures both choices are
unstable (docs/real-data.md). Here nothing is chosen discretely: the model is the one ``estcal diagnose
--geometric prior`` fits (:mod:`estcal.discrepancy.prior_model`) — the ``full`` structurally identifiable
geometric set **plus** the per-joint candidates the diagnosis screens for the gravity load along each
joint's axis (``joint_compliance``, ``backlash``) and across it (``link_tilt``, docs/effects.md), wherever
the data can excite them; every such parameter has a Gaussian prior centred on its nominal value. By
default every parameter has its own width (automatic relevance determination: MacKay 1994, Tipping 2001 —
the evidence switches off, one by one, the terms the data do not support); ``--widths group`` gives one
width per group of like parameters (lengths, angles, joint offsets, each kind of effect;
:func:`estcal.estimate.regularize.prior_groups`), the former default. The widths maximise the evidence of
the training rows (type-II maximum likelihood, :func:`estcal.estimate.regularize.fit_group_prior`, searched
by L-BFGS-B with the evidence's gradient in closed form, :func:`estcal.estimate.regularize.log_evidence_grad`);
``--criterion evidence+cv`` adds a common multiplier chosen by leave-one-posture-out CV; ``--effects``
changes the effect kinds (empty: the prior on the geometry alone).

Protocol per split — every decision on the training rows only, the validation rows scored once:

1. registration (base frame, markers / unknown tool) by Kabsch and least squares;
2. the penalised set: the structurally identifiable geometric candidates and the effect candidates;
3. widths by the evidence, MAP fit (alternating, :func:`fit_group_prior`); with
   ``per_session``, a rigid registration of every further session by alternation (Kabsch);
4. nested prediction: 5 posture-grouped outer folds of the training rows, each running 1–3 on its own
   training part (widths included) and predicting its held-out postures — ``predicted_validation_mm``; the
   line ``E|e|² = a + b·v`` of the held-out errors against their leverage (maximum likelihood) and the
   conformal 95 % region — the error budget's own (:mod:`estcal.discrepancy.budget`,
   :mod:`estcal.discrepancy.prediction`) — applied at the validation postures from their readings;
5. the validation rows at new postures: RMSE of the point-error norms (inside / outside the
   training joint ranges) and the coverage of the 95 % region.

Splits: TIAGo (both sessions, postures halved with ``--seeds``, default 0, 1, 2 — the halves of
``experiments/real_robots.py``; one frame and per-session registration, ``--frames``), UR10 (first 16 /
last 7), TALOS session 02-10 alone (halves, the same seeds). Unless ``--no-baselines``, on the same splits
and with no selection: ``joint_offset`` and ``full`` least squares, the prior on the geometry alone, the
same model class without a prior (refused where least squares cannot determine it), and the prior model as
one more candidate of the level choice (posture-grouped CV, one-standard-error rule). ``--robots recommended``:
the command recommended for new postures (``--geometric prior --residual-model gp-joints --folds 10`` on both
TIAGo sessions: ``evidence+cv`` widths, each further session registered, the joint-space residual GP) through the
error budget it runs, scored at the new postures of the same halvings (``--gp-spaces``, ``--rec-folds``). ``--robots ablation``:
the prior model's effect terms without any prior, with the joint_offset and aic levels (TIAGo, one frame).

``python experiments/prior_study.py [--robots tiago,ur10,talos_session,recommended,ablation] [--seeds 0,1,2]
[--widths parameter|group] [--criterion evidence|evidence+cv] [--json out.json]`` (≈ 2 min on 2 busy
cores for the default robots; skips when the shared data are absent).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

# the model (its terms, free and penalised sets, the per-session alternation) lives in the package: the one
# definition `estcal diagnose --geometric prior` runs
from estcal.discrepancy.prior_model import (EFFECTS, WIDTH_CHOICES, WIDTHS, fit_prior, prior_fit,  # noqa: E402
                                             prior_model)
from estcal.discrepancy.stages import FittedStage, fit_stage_sessions, measured_points, point_covariance  # noqa: E402
from estcal.validation import extrapolation_distance, grouped_folds, inside_ranges, posture_groups  # noqa: E402
from real_robots import _rmse, finish, start  # noqa: E402


def _plain(robot, data, noise, level, per_session=None):
    return fit_stage_sessions(robot, data, noise, "geometric", level, per_session=per_session)


def study(robot, train, valid, noise, *, k=5, per_session=None, criterion="evidence", label="", effects=EFFECTS,
          compare_levels=True, widths=WIDTHS, baselines=True):
    """Steps 1–5 of the module docstring on one split; a JSON-ready dict."""
    # the budget's region (one definition: maximum-likelihood variance model, the slope's bound beyond the
    # farthest held-out leverage, the conformal threshold), from this procedure's nested held-out errors
    from estcal.discrepancy.budget import _region
    from estcal.discrepancy.prediction import beyond_leverage, predicted_rmse_at, region_coverage
    from estcal.validation import seen_postures

    t0 = time.time()
    fs, gp = fit_prior(robot, train, noise, criterion, per_session, effects, widths=widths)
    t_fit = time.time() - t0
    g = posture_groups(train.readings, robot.joint_types)
    meas = measured_points(train)
    held, S = np.zeros_like(meas), np.zeros(meas.shape + (3,))
    fold_widths, cv_reach = [], 0.0
    for test in grouped_folds(g, k, 0):
        tr = np.setdiff1d(np.arange(train.n), test)
        cv_reach = max(cv_reach, float(extrapolation_distance(train.readings[tr], train.readings[test]).max()))
        dtr, dte = train.subset(tr), train.subset(test)
        f_fs, f_gp = fit_prior(robot, dtr, noise, criterion, per_session, effects, widths=widths)
        held[test] = meas[test] - f_fs.predict(dte)
        S[test] = point_covariance(f_fs, dte) * len(tr)
        fold_widths.append(f_gp.to_dict()["widths"])
    region = _region(held, S)
    levels = _as_candidate(robot, train, noise, g, k, per_session, held) if compare_levels else None
    seen = seen_postures(train.readings, valid.readings, robot.joint_types)
    new = valid.subset(~seen)
    inside = inside_ranges(train.readings, new.readings)
    e = measured_points(new) - fs.predict(new)
    Sv = point_covariance(fs, new) * train.n
    reach = extrapolation_distance(train.readings, new.readings).max(1)
    out = {"label": label, "per_session": per_session, "criterion": criterion, "n_train_rows": train.n,
           "n_new_rows": int(new.n), "prior": gp.to_dict(), "fold_widths": fold_widths,
           "n_parameters": len(gp.result.names), "effective_parameters": gp.result.extra["prior"]["effective_parameters"],
           "new_mm": _rmse(e), "new_inside_mm": _rmse(e[inside]), "new_outside_mm": _rmse(e[~inside]),
           "fraction_outside": float(1 - inside.mean()), "predicted_validation_mm": _rmse(held),
           "predicted_at_new_mm": predicted_rmse_at(region["variance_model"]["a_mm2"] * 1e-6,
                                                    region["variance_model"]["b"], Sv) * 1e3,
           "coverage95_new": region_coverage(region, e, Sv), "beyond_cv_leverage": beyond_leverage(region, Sv),
           "region": region, "fit_s": t_fit, "levels": levels,
           # how far the new rows extrapolate (in joint ranges) against the farthest a nested-CV held-out row went
           # (estcal.discrepancy.budget.reach_at): past it the prediction is calibrated on nothing
           "reach_max": float(reach.max()) if reach.size else 0.0, "cv_reach_max": cv_reach,
           "beyond_cv_reach": float(np.mean(reach > cv_reach + 1e-9)) if reach.size else 0.0}
    out["ratio_nested"] = out["predicted_validation_mm"] / out["new_mm"]
    out["ratio_at"] = out["predicted_at_new_mm"] / out["new_mm"]
    out["time_s"] = time.time() - t0
    if not baselines:
        return out
    # baselines on the same split, no selection
    for level in ("joint_offset", "full"):
        b = _plain(robot, train, noise, level, per_session)
        out[f"{level}_new_mm"] = _rmse(measured_points(new) - b.predict(new))
    geo_fs, _ = fit_prior(robot, train, noise, criterion, per_session, effects=())
    out["prior_geometric_only_new_mm"] = _rmse(measured_points(new) - geo_fs.predict(new))
    free_fs, _ = _free_fit(robot, train, noise, effects)
    out["free_new_mm"] = _rmse(measured_points(new) - free_fs.predict(new)) if free_fs is not None else None
    out["time_s"] = time.time() - t0
    return out


def _as_candidate(robot, train, noise, g, k, per_session, held):
    """The prior model as one more candidate of the level choice (:func:`estcal.discrepancy.prediction.choose_level`:
    posture-grouped CV on the training rows, the same folds, the one-standard-error rule with the prior model
    ranked first, as ``estcal diagnose --geometric auto`` ranks it) → ``{candidate: {cv_mm, se_mm}, "chosen": …,
    "chosen_ranked_last": the choice with the prior model as the most complex candidate, the former rule}``."""
    from estcal.discrepancy.prediction import choose_level, one_se_choice

    last, out = choose_level(robot, train, noise, g, k, 0, per_session, extra={"prior": np.sum(held ** 2, axis=-1)})
    out = {"prior": out.pop("prior"), **out}
    out["chosen"], out["chosen_ranked_last"] = one_se_choice(out), last
    return out


def _free_fit(robot, data, noise, effects):
    """The prior model's parameter set fitted without a prior, one frame (None when the data cannot determine it)."""
    from estcal.estimate import calibrate_lsq

    problem, free, pen = prior_model(robot, data, noise, effects)
    try:
        res = calibrate_lsq(problem, "lm", free=free, check=True, max_iter=60)
    except Exception:  # unidentifiable without the prior: that is the point of the prior
        return None, None
    return FittedStage(problem.robot, res.theta, free, res), res


def _print(r):
    w = ", ".join(f"{g} {v * 1e3:.3g}" for g, v in r["prior"]["widths"].items())
    free = "—" if r.get("free_new_mm") is None else f"{r['free_new_mm']:.2f}"
    print(f"-- {r['label']}: widths (mm, mrad, mrad/N·m…) {w}; σ0 {r['prior']['sigma0']:.2f}; "
          f"{r['n_parameters']} parameters, {r['effective_parameters']:.1f} effective")
    print(f"   MAP at new postures {r['new_mm']:.2f} mm (inside {r['new_inside_mm']:.2f}, outside "
          f"{r['new_outside_mm']:.2f}, {r['fraction_outside']:.0%} outside); nested CV {r['predicted_validation_mm']:.2f} "
          f"(ratio {r['ratio_nested']:.2f}); at the new postures {r['predicted_at_new_mm']:.2f} (ratio "
          f"{r['ratio_at']:.2f}); coverage {r['coverage95_new']:.2f}; reach {r['reach_max']:.2f} ranges (CV "
          f"{r['cv_reach_max']:.2f}; {r['beyond_cv_reach']:.0%} of the new rows beyond it)")
    if r["levels"]:
        lv = r["levels"]
        print("   as a candidate of the level choice (grouped CV mm ± se): " + ", ".join(
            f"{c} {lv[c]['cv_mm']:.2f} ± {lv[c]['se_mm']:.2f}" for c in lv if not c.startswith("chosen"))
              + f" -> {lv['chosen']} (ranked last: {lv['chosen_ranked_last']})")
    if "full_new_mm" not in r:
        return
    print(f"   baselines at new postures: joint_offset {r['joint_offset_new_mm']:.2f}, full {r['full_new_mm']:.2f}, "
          f"the prior on the geometry only {r['prior_geometric_only_new_mm']:.2f}, the same model without prior {free}"
          f"  ({r['time_s']:.0f} s)")


def run_tiago(seeds, frames=(None, "registration"), **kw):
    from real_robots import NOISE, _halves, load_tiago

    robot, data = load_tiago()
    g = posture_groups(data.readings, robot.joint_types)
    out = []
    for seed in seeds:
        tr = _halves(g, seed)
        for per in frames:
            r = study(robot, data.subset(tr), data.subset(~tr), NOISE, per_session=per, **kw,
                      label=f"TIAGo seed {seed}" + (", per-session registration" if per else ", one frame"))
            r["seed"] = seed
            _print(r)
            out.append(r)
    return out


def _tiago_halvings(seeds):
    """``(robot, [(seed, half A, half B)])``: both TIAGo sessions, the postures halved with each seed (the halves of
    ``experiments/real_robots.py``)."""
    from real_robots import _halves, load_tiago

    robot, data = load_tiago()
    g = posture_groups(data.readings, robot.joint_types)
    return robot, [(s, data.subset(_halves(g, s)), data.subset(~_halves(g, s))) for s in seeds]


def run_recommended(seeds, spaces=("joints",), k=10, **_):
    """TIAGo, both sessions: the command recommended for new postures, ``estcal diagnose S1 S2 --geometric prior
    --residual-model gp-joints --folds 10`` — the prior model with ``evidence+cv`` widths, each further session's
    registration and the joint-space residual GP, ten posture-grouped folds — through the error budget it runs (:func:`estcal.discrepancy.budget.error_budget`: the nested
    CV refits the model, its widths, the registration and the GP in every outer fold), scored at the new postures
    of half B (their RMSE, the region's coverage, the prediction from their readings)."""
    from real_robots import NOISE

    from estcal.discrepancy.budget import error_budget, region_at
    from estcal.discrepancy.prediction import Procedure
    from estcal.discrepancy.prior_model import CRITERION
    from estcal.validation import seen_postures

    robot, halvings = _tiago_halvings(seeds)
    out = []
    for seed, T, V in halvings:
        t0 = time.time()
        proc = Procedure(level="full", fit=prior_fit(NOISE, CRITERION), gp="always", label="prior", k_inner=k)
        b = error_budget(robot, T, NOISE, level="full", procedure=proc, per_session="registration", spaces=spaces,
                         k_folds=k)
        new = V.subset(~seen_postures(T.readings, V.readings, robot.joint_types))
        r = region_at(b, new)
        res = {"seed": seed, "new_mm": r["rmse_mm"], "predicted_validation_mm": b.predicted_validation_mm,
               "predicted_at_new_mm": r["predicted_mm"], "coverage95_new": r["coverage"],
               "ratio_nested": b.predicted_validation_mm / r["rmse_mm"], "ratio_at": r["predicted_mm"] / r["rmse_mm"],
               "gp_space": b.extra["gp_space"], "fold_gp": [d["gp"] for d in b.extra["decisions"]],
               "reach_max": r["reach_max"], "beyond_cv_reach": r["beyond_cv_reach"], "time_s": time.time() - t0}
        print(f"-- TIAGo seed {seed}, the recommended command: at new postures {res['new_mm']:.2f} mm; nested CV "
              f"{res['predicted_validation_mm']:.2f} (ratio {res['ratio_nested']:.2f}); at the new postures "
              f"{res['predicted_at_new_mm']:.2f} (ratio {res['ratio_at']:.2f}); coverage {res['coverage95_new']:.2f}; "
              f"GP {res['gp_space']} (folds {res['fold_gp']})  ({res['time_s']:.0f} s)", flush=True)
        out.append(res)
    print(f"   mean at new postures {np.mean([r['new_mm'] for r in out]):.2f} mm, nested CV "
          f"{np.mean([r['predicted_validation_mm'] for r in out]):.2f}")
    return out


def run_ur10(**kw):
    from real_robots import NOISE, load_ur10

    robot, data = load_ur10()
    n = np.arange(data.n)
    r = study(robot, data.subset(n < 16), data.subset(n >= 16), NOISE, **kw,
              label="UR10 first 16 / last 7")
    _print(r)
    return [r]


def run_talos_session(seeds, session=1, **kw):
    from real_robots import NOISE, _halves, gross_errors, load_talos

    from estcal.sessions.data import split_sessions

    robot, data = load_talos()
    part = split_sessions(data.subset(~gross_errors(robot, data)))[session]
    g = posture_groups(part.readings, robot.joint_types)
    out = []
    for seed in seeds:
        tr = _halves(g, seed)
        r = study(robot, part.subset(tr), part.subset(~tr), NOISE, **kw,
                  label=f"TALOS session {session} seed {seed}")
        r["seed"] = seed
        _print(r)
        out.append(r)
    return out


def run_ablation(seeds, effects=EFFECTS, **_):
    """TIAGo, one frame: the prior model's effects with the joint-offset level and no prior (least squares) — is it
    the prior, or the effects, that helps?"""
    from real_robots import NOISE

    from estcal.discrepancy.diagnose import default_candidates
    from estcal.discrepancy.geometric import gravity_ready

    robot, halvings = _tiago_halvings(seeds)
    out = []
    for seed, T, V in halvings:
        rb, _ = gravity_ready(robot)
        eff = [(c.effect, list(c.joints), dict(c.options)) for c in default_candidates(rb, T, effects=list(effects),
                                                                                      families=False)]
        r = {"seed": seed, "effects": [[e[0], e[1]] for e in eff]}
        for level in ("joint_offset", "aic"):
            fs = fit_stage_sessions(robot, T, NOISE, "named", level, eff)
            r[f"{level}_effects_new_mm"] = _rmse(measured_points(V) - fs.predict(V))
        print(f"-- TIAGo seed {seed}, one frame, {len(eff)} effect terms without prior: joint_offset + effects "
              f"{r['joint_offset_effects_new_mm']:.2f} mm, aic + effects {r['aic_effects_new_mm']:.2f} mm at new postures")
        out.append(r)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", default="tiago,ur10,talos_session")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--criterion", default="evidence", choices=("evidence", "evidence+cv"))
    ap.add_argument("--k", type=int, default=5)
    ap.add_argument("--effects", default=",".join(EFFECTS),
                    help="effect kinds of the prior model (comma-separated registry names; empty: geometry only)")
    ap.add_argument("--frames", default="one,per-session", help="TIAGo: one frame, per-session registration or both")
    ap.add_argument("--widths", default=WIDTHS, choices=WIDTH_CHOICES,
                    help="one prior width per group of like parameters, or one per parameter (ARD)")
    ap.add_argument("--gp-spaces", default="joints",
                    help="--robots recommended: the residual GP's spaces (joints,cartesian: the better by inner CV)")
    ap.add_argument("--rec-folds", type=int, default=10, help="--robots recommended: posture-grouped folds")
    ap.add_argument("--no-baselines", action="store_true",
                    help="skip the baselines (levels, the geometric prior, no prior) and the level-choice comparison")
    args = start(ap, argv)
    if args is None:
        return {"skipped": True}
    seeds = [int(s) for s in args.seeds.split(",")]
    robots = args.robots.split(",")
    kw = {"criterion": args.criterion, "k": args.k, "effects": tuple(e for e in args.effects.split(",") if e),
          "widths": args.widths}
    if args.no_baselines:
        kw.update(baselines=False, compare_levels=False)
    out = {"protocol": __doc__, "criterion": args.criterion, "effects": list(kw["effects"]), "widths": args.widths}
    t0 = time.time()
    if "tiago" in robots:
        frames = [{"one": None, "per-session": "registration"}[f] for f in args.frames.split(",")]
        out["tiago"] = run_tiago(seeds, frames, **kw)
    if "recommended" in robots:
        out["recommended"] = run_recommended(seeds, spaces=tuple(args.gp_spaces.split(",")), k=args.rec_folds)
    if "ablation" in robots:
        out["ablation"] = run_ablation(seeds, **kw)
    if "ur10" in robots:
        out["ur10"] = run_ur10(**kw)
    if "talos_session" in robots:
        out["talos_session"] = run_talos_session(seeds, **kw)
    return finish(out, t0, args.json)


if __name__ == "__main__":
    main()
