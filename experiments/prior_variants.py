"""Variants of the prior model at new TIAGo postures: what else was tried to go below 2.5 mm, and what it gave.

The prior model (:mod:`estcal.discrepancy.prior_model`, ``estcal diagnose --geometric prior``) scores 2.66 mm at
new postures on the TIAGo halvings of seeds 0–2 and 2.65 on seeds 3–5 (docs/real-data.md, "A prior instead of a
level"). Each variant below changes one thing and is scored on the same six halvings (both sessions, one
measuring frame, train on half A, every row of half B; every decision on the training rows):

``default``      the model as shipped (the reference);
``joint-gp``     + the joint-space residual GP (:func:`estcal.discrepancy.residual.fit_residual_model`, ARD over
                 the joint angles) fitted on the training residuals, its mean added at the new postures;
``cartesian-gp`` the same over the measured position (a tracker error that varies across the volume);
``bagged``       the mean prediction of the five models of the nested CV's folds and the full model (bagging,
                 Breiman 1996: the average of an unstable procedure's refits on subsets);
``hyper-S``      one width per parameter under a log-normal hyperprior ``log τ_j ~ N(μ_kind, S²)`` with one free
                 ``μ`` per kind (angle, length, offset, compliance, backlash, tilt) — a compromise between one
                 width per parameter (S → ∞, the default) and one per kind (S → 0) against the evidence's
                 pruning of parameters a half of the postures cannot separate (seed 3: the arm_4 offset,
                 pruned, carries 2.8 mm of the error at the two postures beyond arm_2's range); S = 1, 2.3, 4.6
                 (a factor e, 10, 100 around the kind's width);
``offsets-free`` the joint offsets without a prior (least squares on them, as every level does);
``lift-tilt``    + a tilt of the torso's lift column that grows with its extension (a telescopic column's
                 bending compliance is proportional to its free length): ``δx = t_l · q_lift · M⊥ × (x − o)``;
``tilt-play``    + a tilt of fixed size along the moment across the torso, arm_1 and arm_2 axes (play in a
                 guide or bearing that the load takes up: ``δx = p_j · M⊥_j/|M⊥_j| × (x − o_j)``);
``drift``        + the library's joint drift with time (per session, from each session's mean time);
``payload-shape`` + a second joint compliance and link tilt per joint under the load of a unit mass at the
                 tool alone (a hand or marker body heavier or lighter than the URDF says changes the shape
                 of the loads with the posture, which one coefficient per joint on the URDF's loads cannot);
``stack``        the four small gains together: per-session registration, ``--criterion evidence+cv``, the
                 joint-space GP and the bagged mean (the study options of docs/real-data.md plus the two above);
                 ``stack-no-bag``, ``stack-no-gp``, ``stack-no-cv``, ``stack-one-frame``: the stack without one.

``python experiments/prior_variants.py [--seeds 0,1,2,3,4,5] [--variants default,joint-gp,…] [--json out.json]``
(≈ 4 min on 2 busy cores; skips when the shared data are absent). The variants that change the evidence search
or add an effect kind swap in a study-local function for the duration of the variant only; nothing here is
part of the package.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

import estcal.discrepancy.prior_model as pm  # noqa: E402
import estcal.estimate.regularize as reg  # noqa: E402
from estcal.discrepancy.residual import fit_residual_model, residual_correction  # noqa: E402
from estcal.discrepancy.stages import measured_points  # noqa: E402
from estcal.effects.base import register_effect  # noqa: E402
from estcal.effects.library import JointCompliance, LinkTilt, across_axis_moments  # noqa: E402
from estcal.methods import Problem  # noqa: E402
from estcal.validation import grouped_folds, posture_groups  # noqa: E402
from real_robots import NOISE, _halves, _rmse, finish, load_tiago, start  # noqa: E402

VARIANTS = ("default", "joint-gp", "cartesian-gp", "bagged", "hyper-1", "hyper-2.3", "hyper-4.6", "offsets-free",
            "lift-tilt", "tilt-play", "drift", "payload-shape", "stack", "stack-no-bag", "stack-no-gp",
            "stack-no-cv", "stack-one-frame")


class LiftTilt(LinkTilt):
    """The lift column's tilt growing with its extension: the moment across it times ``q_lift`` (m)."""

    name = "lift_tilt_study"
    prefixes = ("lifttilt",)

    def loads(self, robot, readings, theta, context):
        Mp, o = across_axis_moments(robot, readings, theta, context)
        q = readings[:, self.joint_index][:, :, None]
        return Mp[:, self.joint_index] * q, o[:, self.joint_index]


class TiltPlay(LinkTilt):
    """A tilt of fixed size along the moment across the axis (the unit moment: play taken up by the load)."""

    name = "tilt_play_study"
    prefixes = ("tiltplay",)

    def loads(self, robot, readings, theta, context):
        Mp, o = across_axis_moments(robot, readings, theta, context)
        Mp = Mp[:, self.joint_index]
        return Mp / np.maximum(np.linalg.norm(Mp, axis=-1, keepdims=True), 1e-9), o[:, self.joint_index]


def _unit_payload(context, n):
    """The context with a 1 kg payload at the tool and with none (the difference of their loads is the payload's)."""
    return dict(context or {}, payload=np.ones(n)), dict(context or {}, payload=np.zeros(n))


class PayloadCompliance(JointCompliance):
    """A joint compliance under the gravity torque of a unit mass at the tool alone."""

    name = "payload_compliance_study"
    prefixes = ("pcompliance",)

    def features(self, robot, readings, q, theta, context):
        one, none = _unit_payload(context, len(readings))
        tau = robot.gravity_torques(readings, theta, one) - robot.gravity_torques(readings, theta, none)
        return tau[:, None, self.joint_index]


class PayloadTilt(LinkTilt):
    """A link tilt under the moment of a unit mass at the tool alone."""

    name = "payload_tilt_study"
    prefixes = ("ptilt",)

    def loads(self, robot, readings, theta, context):
        one, none = _unit_payload(context, len(readings))
        M1, o = across_axis_moments(robot, readings, theta, one)
        M0, _ = across_axis_moments(robot, readings, theta, none)
        return (M1 - M0)[:, self.joint_index], o[:, self.joint_index]


@contextlib.contextmanager
def _swapped(module, name, value):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


def _with_extra_effects(make):
    """``prior_model`` with the effects ``make(robot)`` added to the robot and to the penalised set."""
    base = pm.prior_model

    def prior_model(robot, data, noise, effects=pm.EFFECTS):
        problem, free, pen = base(robot, data, noise, effects)
        rb = problem.robot
        for e in make(rb):
            rb = rb.add_effect(e)
        new = [n for n in rb.params.names if n not in set(problem.robot.params.names)]
        return Problem(rb, [(t.method, t.data, t.noise) for t in problem.terms]), free + new, pen + new

    return prior_model


def _offsets_free():
    base = pm.prior_model

    def prior_model(robot, data, noise, effects=pm.EFFECTS):
        problem, free, pen = base(robot, data, noise, effects)
        kinds = dict(zip(problem.robot.params.names, problem.robot.params.kinds))
        return problem, free, [n for n in pen if kinds[n] != "offset"]

    return prior_model


def _hyperprior(S: float):
    """``(fit_group_prior, evidence_widths)`` with the log-normal hyperprior of the module docstring: the kind of
    every width group is recorded by the first, read by the second (one fit at a time)."""
    kind = {}
    base_fit = reg.fit_group_prior

    def fit_group_prior(problem, free, penalised, groups=None, **kw):
        groups = groups if groups is not None else reg.prior_groups(problem.robot, list(penalised))
        per_kind = reg.prior_groups(problem.robot, list(groups))
        glist = list(dict.fromkeys(groups.values()))
        kinds = [per_kind[next(n for n, g in groups.items() if g == gg)] for gg in glist]
        names = list(dict.fromkeys(kinds))
        kind["of"], kind["n"] = np.array([names.index(k) for k in kinds]), len(names)
        return base_fit(problem, free, penalised, groups, **kw)

    def evidence_widths(A, y, group_of, n_groups, start=None, bounds=(1e-8, 10.0)):
        from scipy.optimize import minimize

        k, nk = kind["of"], kind["n"]
        r = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        s2_0 = max(float(r @ r) / max(len(y) - A.shape[1], 1), 1e-12 * max(float(y @ y), 1e-300))
        gram = reg._gram(A, y)

        def f(x):
            lt, ls2, mu = x[:n_groups], x[n_groups], x[n_groups + 1:]
            lp, g_tau, g_s2 = reg._log_evidence_grad(gram, group_of, lt, ls2)
            d = lt - mu[k]
            return (-(lp - 0.5 * float(d @ d) / S ** 2),
                    -np.concatenate([g_tau - d / S ** 2, [g_s2], np.bincount(k, weights=d, minlength=nk) / S ** 2]))

        lo, hi = np.log(bounds[0]), np.log(bounds[1])
        box = [(lo, hi)] * n_groups + [(np.log(s2_0) - 12, np.log(s2_0) + 12)] + [(lo, hi)] * nk
        best = None
        # the default search's two starts: 1e-3 (or the previous round's widths) and 1e-5
        for lt0 in (np.log(np.full(n_groups, 1e-3) if start is None else np.asarray(start, float)),
                    np.full(n_groups, np.log(1e-5))):
            x0 = np.concatenate([lt0, [np.log(s2_0)], [lt0[k == i].mean() for i in range(nk)]])
            with np.errstate(invalid="ignore", over="ignore"):
                o = minimize(f, x0, method="L-BFGS-B", jac=True, bounds=box)
            best = o if best is None or o.fun < best.fun else best
        return best.x[:n_groups], float(best.x[n_groups]), float(-best.fun)

    return fit_group_prior, evidence_widths


def _context(variant):
    """The swaps of ``variant`` (an ExitStack) and the effect kinds of the prior model."""
    stack = contextlib.ExitStack()
    effects = pm.EFFECTS
    if variant.startswith("hyper-"):
        fgp, ew = _hyperprior(float(variant.split("-")[1]))
        stack.enter_context(_swapped(pm, "fit_group_prior", fgp))
        stack.enter_context(_swapped(reg, "evidence_widths", ew))
    elif variant == "offsets-free":
        stack.enter_context(_swapped(pm, "prior_model", _offsets_free()))
    elif variant == "lift-tilt":
        stack.enter_context(_swapped(pm, "prior_model", _with_extra_effects(
            lambda rb: [LiftTilt(rb, ["torso_lift_joint"])])))
    elif variant == "tilt-play":
        stack.enter_context(_swapped(pm, "prior_model", _with_extra_effects(
            lambda rb: [TiltPlay(rb, ["torso_lift_joint", "arm_1_joint", "arm_2_joint"])])))
    elif variant == "payload-shape":
        def payload(rb):
            arm = [j for j in rb.joint_names if j.startswith("arm_")]
            return [PayloadCompliance(rb, arm[1:]), PayloadTilt(rb, arm)]

        stack.enter_context(_swapped(pm, "prior_model", _with_extra_effects(payload)))
    elif variant == "drift":
        effects = tuple(effects) + ("drift",)
    return stack, effects


def score(variant, robot, T, V, k=5):
    """RMSE (mm) of ``variant`` at the rows of ``V``, fitted on ``T``."""
    stack, effects = _context(variant)
    stacked = variant.startswith("stack")
    per = "registration" if stacked and variant != "stack-one-frame" else None
    crit = "evidence+cv" if stacked and variant != "stack-no-cv" else "evidence"
    use_gp = variant in ("joint-gp", "cartesian-gp") or (stacked and variant != "stack-no-gp")
    bag = variant == "bagged" or (stacked and variant != "stack-no-bag")
    with stack:
        def fit(rows):
            return pm.fit_prior(robot, rows, NOISE, crit, per, effects)[0]

        def predict(fs, rows):
            p = fs.predict(rows)
            if use_gp:
                space = "cartesian" if variant == "cartesian-gp" else "joints"
                R = fs.residual_common(rows_fit[0])
                gp = fit_residual_model(space, fs.robot, fs.theta, rows_fit[0].readings, R, rows_fit[0].context, 1)
                p = p + fs.rotate_to_session(rows, residual_correction(gp, fs.robot, fs.theta, rows.readings,
                                                                       rows.context))
            return p

        rows_fit = [T]
        fs = fit(T)
        pred = predict(fs, V)
        if bag:
            preds = [pred]
            for test in grouped_folds(posture_groups(T.readings, robot.joint_types), k, 0):
                rows_fit[0] = T.subset(np.setdiff1d(np.arange(T.n), test))
                preds.append(predict(fit(rows_fit[0]), V))
            pred = np.mean(preds, axis=0)
    return _rmse(measured_points(V) - pred)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2,3,4,5")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = start(ap, argv)
    if args is None:
        return {"skipped": True}
    for cls in (LiftTilt, TiltPlay, PayloadCompliance, PayloadTilt):
        register_effect(cls.name, cls, overwrite=True)  # so that the fitted robots can be copied and saved
    seeds = [int(s) for s in args.seeds.split(",")]
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {', '.join(VARIANTS)}")
    robot, data = load_tiago()
    g = posture_groups(data.readings, robot.joint_types)
    splits = {s: _halves(g, s) for s in seeds}
    out, t0 = {"protocol": __doc__, "seeds": seeds, "variants": {}}, time.time()
    print(f"TIAGo, both sessions, one frame; RMSE at new postures (mm), halvings of seeds {args.seeds}")
    for v in variants:
        tv = time.time()
        r = [score(v, robot, data.subset(splits[s]), data.subset(~splits[s])) for s in seeds]
        out["variants"][v] = {"new_mm": r, "mean_mm": float(np.mean(r)), "time_s": time.time() - tv}
        print(f"  {v:13s} " + " ".join(f"{x:5.2f}" for x in r) + f"   mean {np.mean(r):.3f}  ({time.time() - tv:.0f} s)",
              flush=True)
    return finish(out, t0, args.json)


if __name__ == "__main__":
    main()
