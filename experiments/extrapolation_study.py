"""Where the error at new postures comes from: the TIAGo MAP model's extrapolation, joint by joint.

On the shared TIAGo sessions, with posture-disjoint halves (the splits of ``experiments/real_robots.py``),
the MAP prior model as ``estcal diagnose --geometric prior`` fits it (``estcal.discrepancy.prior_model``:
the full geometric set, joint compliance, backlash and link tilt, one prior width per parameter by the
evidence; docs/real-data.md, "A prior instead of a level") scores ~1.8 mm at new postures inside the
training joint ranges and 3.4–4.8 mm outside them. This study asks which joints' extrapolation carries that
error and whether a physically motivated model extrapolates better. Every model is fitted on half A of the
postures (both sessions' rows), one measuring frame, and scored once on half B.

1. **Attribution** (``attribution``). For each new posture p and joint j, the extrapolation distance
   ``d_pj = max(0, q_pj − max_A q_j, min_A q_j − q_pj) / (max_A q_j − min_A q_j)`` (in units of the
   training range). Per joint: the RMSE of the new postures that extrapolate along j (at all / along j
   only). A non-negative regression of each posture's RMS error on its distances, pooled over the seeds,
   ``e_p = a + Σ_j b_j d_pj`` (a first-order model: a misfit grows linearly with how far the joint goes
   beyond what was fitted), gives each joint's counterfactual: the RMSE of the new postures with
   ``b_j d_pj`` removed — the error joint j's extrapolation carries. Standard errors by bootstrap over
   postures. Descriptive: it reads the validation errors, and decides nothing.
2. **Leave one joint range out** (``joint_ranges``): the causal check, free of the collinearity of the
   regression. For joint j and each end of its range, the ``n_out`` postures with the most extreme
   readings on j are held out and the model is fitted on all the other postures: those held-out postures
   extrapolate along j (and, where they are extreme on other joints too, that is reported). Against it,
   the same number of postures inside every range held out at random (``n_control`` draws).
3. **Candidates** (``candidates``), each scored on the same halves: the RMSE of all new points, inside /
   outside the training ranges, and the bootstrap standard error over postures. The choice among them is
   made on half A only — posture-grouped CV on the training rows (``k`` folds, the same folds for every
   candidate), the one-standard-error rule with the candidates ordered by their number of parameters
   (:func:`estcal.discrepancy.prediction.choose_level`) — and the chosen one is scored on half B.
   (a) geometry under the prior restricted to the joint offsets; (a') the placement (axis and carried
   link) parameters dropped on the joints the target postures extrapolate along — decided from the
   targets' joint readings only, never their measurements (as ``estcal.discrepancy.budget.predicted_at``);
   (b) the other per-joint effects of the library under the prior (each parameter with its own width, as the
   model's): ``encoder_gain``, ``gear_harmonic``;
   (c) compliance with the hand's mass scaled (the arm_7 link and gripper, ×0.5 / ×2); (d) a stiffening
   gearbox, the cubic term of the compliance (:class:`StiffeningCompliance`). A common scale of
   all link masses is not a candidate: the torque, hence the compliance column ``c_j τ_j``, is linear in
   the masses, so one scale is absorbed exactly by every ``c_j``; only the *shape* of the torques across
   postures (the hand against the links) can change the fit.
4. **Training postures that span the ranges** (``span``): halves of the same 62 postures in which half A
   must hold, for every joint, the postures of its smallest and largest reading (the rest drawn at
   random): the new postures then all lie inside the training ranges — what the MAP model scores when the
   calibration postures span the joint ranges the robot will be used in. The same with the extremes of
   one group of joints only (:data:`SPAN_GROUPS`), and, for each, the model fitted without the forced
   extremes and scored on the same new postures: what training on them buys (forcing them into half A
   also takes them out of the scored half, which alone lowers its RMSE).
5. **Simulation** (``simulation``): the same halves on data simulated from the MAP model of all rows with
   noise at the repeatability floor — the extrapolation error of a model that is right.

``python experiments/extrapolation_study.py [--seeds 0,1,2] [--k 5] [--json out.json]`` (≈ 3 min on
2 busy cores; ``--parts attribution,joint_ranges,candidates,span,simulation`` selects parts); skips when the shared
data are absent.
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

from estcal.base.blas import single_thread_blas  # noqa: E402
from estcal.discrepancy.prior_model import EFFECTS, WIDTHS, prior_model, width_groups  # noqa: E402
from estcal.discrepancy.stages import FittedStage, measured_points  # noqa: E402
from estcal.effects.library import JointCompliance  # noqa: E402
from estcal.estimate.regularize import fit_group_prior  # noqa: E402
from estcal.validation import extrapolation_distance as extrapolation  # noqa: E402
from estcal.validation import grouped_folds, inside_ranges, posture_groups  # noqa: E402
from real_robots import NOISE, _boot_se, _halves, _rmse, finish, load_tiago, start  # noqa: E402

PLACEMENT = ("tx", "ty", "tz", "rx", "ry", "rz")


# ------------------------------------------------------------------ distances and errors
def posture_errors(err, groups):
    """``(postures, mean squared point-error norm per posture (m²), points per posture)`` of errors (N, k, 3)."""
    sq = np.sum(np.asarray(err) ** 2, -1)
    u = np.unique(groups)
    return u, np.array([sq[groups == p].mean() for p in u]), np.array([sq[groups == p].size for p in u])


# ------------------------------------------------------------------ the model and its variants
def hand_scaled(robot, scale: float):
    """``robot`` with the mass of its last link (TIAGo: arm_7 link, the wrist sensor and the gripper) × ``scale``."""
    from estcal.kinematics.chain import SerialRobot
    import dataclasses

    last = max(i for i, lk in enumerate(robot.links) if lk.joint is not None)
    links = [dataclasses.replace(lk, mass=lk.mass * scale) if i == last else lk for i, lk in enumerate(robot.links)]
    return SerialRobot(robot.name, links, robot.params.copy(), robot.joint_names, robot.joint_types, robot.limits,
                       robot.offset_idx, robot.gain_idx, robot.marker_idx, robot.gravity, robot.payload_mass,
                       robot.payload_com, robot.coupling, robot.convention, list(robot.effects), robot.meta)


def _placement_of(robot, joints):
    """The placement parameters of the axis of each joint in ``joints`` and of the link it carries (the next
    joint's placement): the geometric terms whose effect turns with that joint."""
    names = list(robot.joint_names)
    out = set()
    for j in joints:
        i = names.index(j)
        for jj in names[i:i + 2]:
            out.update(f"{a}_{jj}" for a in PLACEMENT)
    return out


def variant_fit(noise, effects=EFFECTS, geometry="full", drop_joints=(), hand=1.0, extra=(), stiffening=False):
    """The MAP prior model (``estcal.discrepancy.prior_model``) with a variation, as ``fit(robot, data) ->
    FittedStage``: ``effects`` under the prior; ``geometry="offsets"`` keeps only the joint offsets of the
    geometric set; ``drop_joints``: their placement parameters removed (:func:`_placement_of`); ``hand``: the
    last link's mass scaled (:func:`hand_scaled`); ``extra``: ``[(effect, options)]`` added on every joint the
    effect accepts, under the prior with the others (a width per parameter, as the model's); ``stiffening``:
    the cubic compliance term :class:`StiffeningCompliance` on the loaded joints (:func:`with_stiffening`)."""
    from estcal.effects import make_effect

    def fit(robot, data):
        rb = hand_scaled(robot, hand) if hand != 1.0 else robot
        for e, opts in extra:  # effects outside prior_model's own screening, added on every joint they accept
            rb = rb.add_effect(make_effect(e, rb, **opts))
        if stiffening:
            rb = with_stiffening(rb, data)
        problem, free, pen = prior_model(rb, data, noise, effects)
        kinds = dict(zip(problem.robot.params.names, problem.robot.params.kinds))
        drop = _placement_of(problem.robot, drop_joints)
        if geometry == "offsets":
            drop |= {n for n in pen if kinds[n] == "geometric"}
        free = [n for n in free if n not in drop]
        pen = [n for n in pen if n not in drop]
        gp = fit_group_prior(problem, free, pen, width_groups(pen, WIDTHS))
        fit.last = gp
        return FittedStage(problem.robot, gp.result.theta, free, gp.result)

    fit.last = None
    return fit


class StiffeningCompliance(JointCompliance):
    """The cubic term of a load-dependent joint stiffness: ``δq_j = c3_j · τ_j³ / τ_ref,j²``.

    A gearbox's torsional stiffness is not constant: a harmonic drive is softer at low load and stiffens with
    it (Tuttle & Seering 1996, *IEEE Trans. Robot. Autom.* 12(3):368), so the deflection is not linear in the
    gravity torque τ_j (:class:`estcal.effects.library.JointCompliance`) but has odd higher orders; the cubic
    one is the first. ``τ_ref,j`` (N·m; N for a prismatic joint) is the largest |τ_j| of the training rows, so
    ``c3_j`` (``compliance3_<joint>``) is, like ``c_j``, in rad/(N·m): the cubic term's deflection at the
    largest training load is ``c3_j τ_ref,j``. Beyond the training loads it grows as τ³: what extrapolates
    is exactly this term, which a posture-grouped CV on the training rows weighs."""

    name = "joint_compliance_cubic"
    prefixes = ("compliance3",)

    def __init__(self, robot, joints=None, tau_ref=None):
        super().__init__(robot, joints)
        self.tau_ref = np.asarray(tau_ref if tau_ref is not None else np.ones(len(self.joints)), float)

    def options(self):
        return {"tau_ref": self.tau_ref.tolist()}

    def features(self, robot, readings, q, theta, context):
        tau = super().features(robot, readings, q, theta, context)
        return tau ** 3 / self.tau_ref ** 2


def with_stiffening(robot, data):
    """``robot`` with :class:`StiffeningCompliance` on every joint whose gravity load varies over ``data``'s
    rows (a vertical axis or the lift's constant weight gives an offset, not a term)."""
    tau = robot.gravity_torques(data.readings, context=data.context)
    big = np.abs(tau).max()
    joints = [j for i, j in enumerate(robot.joint_names) if np.ptp(tau[:, i]) > 1e-6 * big]
    ref = [float(np.abs(tau[:, robot.joint_names.index(j)]).max()) for j in joints]
    return robot.add_effect(StiffeningCompliance(robot, joints, tau_ref=ref))


#: the candidates, ordered by their number of parameters (the one-standard-error rule prefers the first)
CANDIDATES = {
    "offsets + effects": dict(geometry="offsets"),
    "no placement on extrapolated joints": dict(drop_joints="targets"),
    "MAP (compliance + backlash + tilt)": dict(),
    "hand mass x0.5": dict(hand=0.5),
    "hand mass x2": dict(hand=2.0),
    "+ encoder_gain": dict(extra=[("encoder_gain", {})]),
    "+ stiffening compliance (cubic)": dict(stiffening=True),
    "+ gear_harmonic (1st order)": dict(extra=[("gear_harmonic", {"orders": [1]})]),
}
BASE = "MAP (compliance + backlash + tilt)"


def _fit_for(spec, noise, train_readings, target_readings):
    kw = dict(spec)
    if kw.get("drop_joints") == "targets":
        d = extrapolation(train_readings, target_readings)
        kw["drop_joints"] = [j for j, out in zip(JOINTS, (d > 0).any(0)) if out]
    return variant_fit(noise, **kw), kw.get("drop_joints", ())


# ------------------------------------------------------------------ 1. attribution
def _nnls_fit(E, D, P):
    """Non-negative ``E ≈ a + D b`` (a, b ≥ 0), each posture weighted by its number of points P (scipy's NNLS,
    Lawson & Hanson 1974) → (a, b)."""
    from scipy.optimize import nnls

    w = np.sqrt(P)
    x, _ = nnls(np.column_stack([np.ones(len(E)), D]) * w[:, None], E * w)
    return x[0], x[1:]


def _counterfactual(E, D, P, b):
    """RMSE (mm) over the points of postures with RMS errors E (mm) and P points: as measured, with each joint's
    ``b_j d_pj`` removed, and with all removed (clipped at 0)."""
    rm = lambda e: float(np.sqrt(np.sum(np.clip(e, 0, None) ** 2 * P) / P.sum()))  # noqa: E731
    return rm(E), [rm(E - b[j] * D[:, j]) for j in range(D.shape[1])], rm(E - D @ b)


def attribution(rows, n_boot=400, seed=0):
    """Per-joint figures from the pooled new postures of every split (``rows``: dicts with ``d`` (n,), ``mse``
    (m²), ``n_points``)."""
    D = np.array([r["d"] for r in rows])
    E = np.sqrt(np.array([r["mse"] for r in rows])) * 1e3
    P = np.array([r["n_points"] for r in rows])

    def rmse(mask):
        return float(np.sqrt(np.sum((E[mask] ** 2) * P[mask]) / P[mask].sum())) if mask.any() else float("nan")

    out = {"n_postures": len(rows), "joints": {}}
    a, b = _nnls_fit(E, D, P)
    tot, each, none = _counterfactual(E, D, P, b)
    rng = np.random.default_rng(seed)
    boot = []
    for _ in range(n_boot):
        i = rng.integers(0, len(E), len(E))
        _, bb = _nnls_fit(E[i], D[i], P[i])
        t_, e_, n_ = _counterfactual(E[i], D[i], P[i], bb)
        boot.append([bb, np.array(t_) - np.array(e_), t_ - n_])
    bse = np.std([x[0] for x in boot], 0, ddof=1)
    dse = np.std([x[1] for x in boot], 0, ddof=1)
    out.update(intercept_mm=float(a), rmse_mm=tot, rmse_if_none_extrapolated_mm=none,
               gain_if_none_extrapolated_mm=tot - none,
               gain_if_none_se_mm=float(np.std([x[2] for x in boot], ddof=1)),
               inside_mm=rmse((D == 0).all(1)), outside_mm=rmse((D > 0).any(1)),
               n_outside=int((D > 0).any(1).sum()))
    for j, name in enumerate(JOINTS):
        out_j, only = D[:, j] > 0, (D[:, j] > 0) & ((D > 0).sum(1) == 1)
        out["joints"][name] = {
            "n_outside": int(out_j.sum()), "rmse_outside_mm": rmse(out_j), "max_distance": float(D[:, j].max()),
            "n_only": int(only.sum()), "rmse_only_mm": rmse(only),
            "slope_mm_per_range": float(b[j]), "slope_se": float(bse[j]),
            "rmse_without_mm": each[j], "gain_mm": tot - each[j], "gain_se_mm": float(dse[j])}
    return out


def split_rows(robot, data, seeds, noise):
    """The MAP model on every half (seeds): per new posture its extrapolation distances and mean squared error;
    and the split's scores (all, inside, outside, bootstrap se)."""
    g = posture_groups(data.readings, robot.joint_types)
    rows, splits = [], []
    for seed in seeds:
        tr = _halves(g, seed)
        T, V = data.subset(tr), data.subset(~tr)
        fs = variant_fit(noise)(robot, T)
        e = measured_points(V) - fs.predict(V)
        gv = g[~tr]
        u, mse, npt = posture_errors(e, gv)
        first = np.array([np.flatnonzero(gv == p)[0] for p in u])
        d = extrapolation(T.readings, V.readings[first])
        rows += [{"seed": seed, "posture": int(p), "d": d[i].tolist(), "mse": float(mse[i]), "n_points": int(npt[i])}
                 for i, p in enumerate(u)]
        splits.append({"seed": seed, **_scores(e, T.readings, V.readings, gv)})
    return rows, splits


def _scores(e, train_readings, readings, groups):
    inside = inside_ranges(train_readings, readings)
    en = np.linalg.norm(e, axis=-1)
    return {"new_mm": _rmse(e), "se_mm": _boot_se(en, groups), "inside_mm": _rmse(e[inside]),
            "outside_mm": _rmse(e[~inside]), "fraction_outside": float(1 - inside.mean())}


# ------------------------------------------------------------------ 2. leave one joint range out
def _only_along(Q, j, ranked, n_out, max_left=8):
    """``(held, left)``: up to ``n_out`` postures (rows of ``Q``) taken in the order ``ranked`` (most extreme on
    joint j first) such that, once they are held out, every one of them lies inside the training postures'
    range on every joint but j — an extrapolation along j alone. A posture as extreme on another joint cannot
    be held out (it would extrapolate there too) nor trained on (it would cover j's range): it is ``left`` out
    of both (at most ``max_left``; fewer than ``n_out`` postures are held out when that is reached)."""
    others = np.arange(Q.shape[1]) != j
    pick, left = [], []
    for c in ranked:
        trial = pick + [int(c)]
        rest = np.setdiff1d(np.arange(len(Q)), trial + left)
        if inside_ranges(Q[rest][:, others], Q[trial][:, others]).all():
            pick = trial
        else:
            left.append(int(c))
        if len(pick) == n_out or len(left) == max_left:
            break
    return np.array(pick, int), np.array(left, int)


def joint_ranges(robot, data, noise, n_out=5, n_control=4, seed=0):
    """Hold out the ``n_out`` postures at each end of every joint's range; fit on the rest; score them."""
    g = posture_groups(data.readings, robot.joint_types)
    u, first = np.unique(g, return_index=True)
    Q = data.readings[first]
    fit = variant_fit(noise)

    def held(out_postures, left=()):
        m = np.isin(g, out_postures)
        T, V = data.subset(~m & ~np.isin(g, left)), data.subset(m)
        fs = fit(robot, T)
        e = measured_points(V) - fs.predict(V)
        d = extrapolation(T.readings, Q[np.isin(u, out_postures)])
        return e, d, g[m]

    res = {"n_out": n_out, "joints": {}}
    for j, name in enumerate(JOINTS):
        order = np.argsort(Q[:, j], kind="stable")
        for side, ranked in (("low", order), ("high", order[::-1])):
            pick, left = _only_along(Q, j, ranked, n_out)
            if not len(pick):  # every extreme posture on j is as extreme on another joint
                res["joints"].setdefault(name, {})[side] = None
                continue
            e, d, gm = held(u[pick], u[left])
            res["joints"].setdefault(name, {})[side] = {
                "rmse_mm": _rmse(e), "se_mm": _boot_se(np.linalg.norm(e, axis=-1), gm),
                "distance_mean": float(d[:, j].mean()), "distance_max": float(d[:, j].max()),
                "n_held_out": len(pick), "n_outside_on_j": int((d[:, j] > 0).sum()), "n_left_out": len(left),
                "n_outside_elsewhere": int(((np.delete(d, j, 1) > 0).any(1)).sum())}
    # control: postures inside every range of the others, held out at random
    rng = np.random.default_rng(seed)
    ctrl = []
    for _ in range(n_control):
        cand = rng.permutation(len(u))
        pick = []
        for c in cand:
            rest = np.setdiff1d(np.arange(len(u)), pick + [c])
            if inside_ranges(Q[rest], Q[[c] + pick]).all():
                pick.append(c)
            if len(pick) == n_out:
                break
        e, _, gm = held(u[pick])
        ctrl.append(_rmse(e))
    res["control_mm"] = ctrl
    res["control_mean_mm"] = float(np.mean(ctrl))
    return res


# ------------------------------------------------------------------ 3. candidates
def candidates(robot, data, seeds, noise, k=4):
    """Every candidate on every half: its scores at new postures and its posture-grouped CV on half A; the
    choice among them by the one-standard-error rule on half A, scored on half B."""
    from estcal.discrepancy.prediction import choose_level

    g = posture_groups(data.readings, robot.joint_types)
    out = []
    for seed in seeds:
        tr = _halves(g, seed)
        T, V = data.subset(tr), data.subset(~tr)
        gT = posture_groups(T.readings, robot.joint_types)
        folds = grouped_folds(gT, k, 0)
        meas_T, meas_V = measured_points(T), measured_points(V)
        res, sq = {}, {}
        for name, spec in CANDIDATES.items():
            t0 = time.time()
            fit, dropped = _fit_for(spec, noise, T.readings, V.readings)
            fs = fit(robot, T)
            e = meas_V - fs.predict(V)
            s = np.zeros(meas_T.shape[:2])
            for test in folds:
                trn = np.setdiff1d(np.arange(T.n), test)
                f_fit, _ = _fit_for(spec, noise, T.readings[trn], T.readings[test])
                f_fs = f_fit(robot, T.subset(trn))
                s[test] = np.sum((meas_T[test] - f_fs.predict(T.subset(test))) ** 2, -1)
            sq[name] = s
            res[name] = {**_scores(e, T.readings, V.readings, g[~tr]), "n_parameters": len(fs.free),
                         "dropped_joints": list(dropped), "time_s": time.time() - t0}
        chosen, cv = choose_level(robot, T, noise, gT, k, 0, levels=(), extra=sq)
        for name in res:
            res[name].update(cv_mm=cv[name]["cv_mm"], cv_se_mm=cv[name]["se_mm"])
        out.append({"seed": seed, "models": res, "chosen": chosen, "chosen_new_mm": res[chosen]["new_mm"]})
    return out


# ------------------------------------------------------------------ 4. spanning halves
def _extremes(Q, joints=None) -> set:
    """The rows of ``Q`` that hold the smallest or largest reading of a joint (of the columns ``joints``)."""
    cols = Q if joints is None else Q[:, list(joints)]
    return set(np.argmin(cols, 0).tolist()) | set(np.argmax(cols, 0).tolist())


def spanning_half(Q, seed, joints=None):
    """Mask of half the postures (rows of ``Q``) that holds, for every joint (or the columns ``joints``), its
    smallest and largest reading; the rest drawn at random."""
    must = _extremes(Q, joints)
    rest = np.random.default_rng(seed).permutation([i for i in range(len(Q)) if i not in must])
    pick = list(must) + rest[: max(0, len(Q) // 2 - len(must))].tolist()
    return np.isin(np.arange(len(Q)), pick)


#: joint groups whose extremes the partly spanning halves force into training (by attribution: the upper arm,
#: the wrist, and the joints that carry nothing)
SPAN_GROUPS = {"upper arm (arm_2, arm_3)": ("arm_2_joint", "arm_3_joint"),
               "wrist (arm_6, arm_7)": ("arm_6_joint", "arm_7_joint"),
               "torso lift, arm_1": ("torso_lift_joint", "arm_1_joint")}


def span(robot, data, seeds, noise):
    """The MAP model on halves whose half A holds the extremes of every joint (``"all"``) or of one group of
    :data:`SPAN_GROUPS` only — does covering those joints' ranges remove the error their extrapolation
    carries?"""
    g = posture_groups(data.readings, robot.joint_types)
    u, first = np.unique(g, return_index=True)
    Q = data.readings[first]
    out = {}
    for label, joints in [("all", None)] + list(SPAN_GROUPS.items()):
        cols = None if joints is None else [JOINTS.index(j) for j in joints]
        out[label] = []
        for seed in seeds:
            half = spanning_half(Q, seed, cols)
            tr = np.isin(g, u[half])
            T, V = data.subset(tr), data.subset(~tr)
            fs = variant_fit(noise)(robot, T)
            e = measured_points(V) - fs.predict(V)
            row = {"seed": seed, "n_train_postures": int(half.sum()), **_scores(e, T.readings, V.readings, g[~tr])}
            # the same new postures, the forced extremes not trained on: what training on them bought (removing
            # them from the scored half lowers its RMSE by itself)
            cut = half.copy()
            cut[list(_extremes(Q, cols))] = False
            fs2 = variant_fit(noise)(robot, data.subset(np.isin(g, u[cut])))
            row["without_extremes_mm"] = _rmse(measured_points(V) - fs2.predict(V))
            out[label].append(row)
    return out


# ------------------------------------------------------------------ 5. simulation: a model that is right
def simulate(robot, data, seeds, noise, n_draws=2, seed=0):
    """The same halves on simulated TIAGo data whose truth is in the model class: the MAP model fitted on all 99
    rows is the true robot, every measured point is its prediction plus Gaussian noise at the repeatability
    floor of the real data (``repeatability_floor`` after per-session registration, split equally over the
    three axes). Scored against the noise-free points: the error the fit itself makes at new postures,
    inside / outside the training ranges, for random and for spanning halves."""
    from estcal.validation import repeatability_floor

    g = posture_groups(data.readings, robot.joint_types)
    floor = repeatability_floor(measured_points(data), g, data.columns["session"])["registered_mm"] * 1e-3
    fit = variant_fit(noise)
    clean = fit(robot, data).predict(data)
    u, first = np.unique(g, return_index=True)
    rng = np.random.default_rng(seed)
    out = {"floor_mm": floor * 1e3, "n_draws": n_draws, "splits": []}
    for draw in range(n_draws):
        sim = data.subset(slice(None))
        sim.points = clean + rng.normal(0.0, floor / np.sqrt(3), clean.shape)
        for s_ in seeds:
            for kind, tr in (("random", _halves(g, s_)), ("span", np.isin(g, u[spanning_half(data.readings[first], s_)]))):
                T, V = sim.subset(tr), sim.subset(~tr)
                fs = fit(robot, T)
                e = clean[~tr] - fs.predict(V)
                out["splits"].append({"draw": draw, "seed": s_, "halves": kind,
                                      **_scores(e, T.readings, V.readings, g[~tr])})
    for kind in ("random", "span"):
        rs = [r for r in out["splits"] if r["halves"] == kind]
        out[kind] = {k: _mean(rs, k) for k in ("new_mm", "inside_mm", "outside_mm", "fraction_outside")}
    return out


# ------------------------------------------------------------------ printing
def _split_line(s) -> str:
    return (f"   seed {s['seed']}: {s['new_mm']:.2f} ± {s['se_mm']:.2f} mm (inside {s['inside_mm']:.2f}, outside "
            f"{s['outside_mm']:.2f}; {s['fraction_outside']:.0%} of the new rows outside)")


def _mean(rows, key) -> float:
    v = [r[key] for r in rows if r[key] is not None and np.isfinite(r[key])]
    return float(np.mean(v)) if v else float("nan")


def _print_attribution(splits, att):
    print("\n== MAP model at new postures (halves of real_robots.py, one frame)")
    for s in splits:
        print(_split_line(s))
    print(f"\n== Attribution: {att['n_postures']} new postures of the {len(splits)} halves, {att['n_outside']} outside; "
          f"RMSE {att['rmse_mm']:.2f} mm (inside {att['inside_mm']:.2f}, outside {att['outside_mm']:.2f})")
    print(f"   regression e_p = a + Σ b_j d_pj (NNLS): a = {att['intercept_mm']:.2f} mm; with no joint extrapolated "
          f"{att['rmse_if_none_extrapolated_mm']:.2f} mm (−{att['gain_if_none_extrapolated_mm']:.2f} ± "
          f"{att['gain_if_none_se_mm']:.2f})")
    print(f"   {'joint':<17} {'outside':>7} {'RMSE out':>9} {'max d':>6} {'only':>5} {'RMSE only':>10} "
          f"{'b mm/range':>12} {'RMSE without':>13} {'carried':>14}")
    for name, r in att["joints"].items():
        print(f"   {name:<17} {r['n_outside']:>7} {r['rmse_outside_mm']:>9.2f} {r['max_distance']:>6.3f} "
              f"{r['n_only']:>5} {r['rmse_only_mm']:>10.2f} {r['slope_mm_per_range']:>6.1f} ± {r['slope_se']:<4.1f} "
              f"{r['rmse_without_mm']:>13.2f} {r['gain_mm']:>7.2f} ± {r['gain_se_mm']:.2f}")


def _print_ranges(jr):
    print(f"\n== Leave one joint range out: the {jr['n_out']} postures at each end of a joint's range held out, "
          f"fitted on the other postures (mm; d in units of the training range)")
    print(f"   control ({len(jr['control_mm'])} draws of {jr['n_out']} postures inside every range): "
          f"{jr['control_mean_mm']:.2f} mm (" + ", ".join(f"{c:.2f}" for c in jr["control_mm"]) + ")")
    for name, sides in jr["joints"].items():
        print(f"   {name:<17} " + "; ".join(
            f"{side} —" if r is None else
            f"{side} {r['rmse_mm']:.2f} ± {r['se_mm']:.2f} ({r['n_held_out']} held out, d mean {r['distance_mean']:.2f}, "
            f"max {r['distance_max']:.2f}; {r['n_outside_elsewhere']} out elsewhere, {r['n_left_out']} left out)"
            for side, r in sides.items()))


def _print_candidates(cands):
    print("\n== Candidates at new postures (mm ± bootstrap se; inside / outside the training ranges) and their "
          "posture-grouped CV on half A")
    for c in cands:
        print(f"   seed {c['seed']}:")
        for name, r in c["models"].items():
            extra = f" [{', '.join(r['dropped_joints'])}]" if r["dropped_joints"] else ""
            print(f"     {name:<38} {r['n_parameters']:>3} p  new {r['new_mm']:.2f} ± {r['se_mm']:.2f} "
                  f"({r['inside_mm']:.2f} / {r['outside_mm']:.2f})  CV {r['cv_mm']:.2f} ± {r['cv_se_mm']:.2f}{extra}")
        print(f"     chosen on half A: {c['chosen']} -> {c['chosen_new_mm']:.2f} mm at new postures")
    names = list(cands[0]["models"])
    print("   mean over seeds: " + "; ".join(
        f"{n} {np.mean([c['models'][n]['new_mm'] for c in cands]):.2f}" for n in names)
        + f"; chosen {np.mean([c['chosen_new_mm'] for c in cands]):.2f}")


def _print_span(sp, splits):
    print("\n== Halves whose training half holds the extremes of every joint (all) or of some joints (MAP model)")
    for s in sp["all"]:
        print(_split_line(s))
    print(f"   random halves: {_mean(splits, 'new_mm'):.2f} mm (inside {_mean(splits, 'inside_mm'):.2f}, "
          f"outside {_mean(splits, 'outside_mm'):.2f}; {_mean(splits, 'fraction_outside'):.0%} outside)")
    for label, rows in sp.items():
        print(f"   extremes of {label:<26}: {_mean(rows, 'new_mm'):.2f} mm (inside {_mean(rows, 'inside_mm'):.2f}, "
              f"outside {_mean(rows, 'outside_mm'):.2f}; {_mean(rows, 'fraction_outside'):.0%} outside; seeds "
              + " / ".join(f"{r['new_mm']:.2f}" for r in rows) + f"); not trained on them "
              f"{_mean(rows, 'without_extremes_mm'):.2f} (" + " / ".join(f"{r['without_extremes_mm']:.2f}" for r in rows)
              + ")")


def _print_sim(sim):
    print(f"\n== Simulation: the MAP model of all rows as the truth, noise at the repeatability floor "
          f"({sim['floor_mm']:.2f} mm), {sim['n_draws']} draws; error against the noise-free points (mm)")
    for kind in ("random", "span"):
        r = sim[kind]
        print(f"   {kind:<6} halves: new {r['new_mm']:.2f} (inside {r['inside_mm']:.2f}, outside {r['outside_mm']:.2f}; "
              f"{r['fraction_outside']:.0%} outside)")


JOINTS: list = []


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--k", type=int, default=5, help="posture-grouped folds of the candidates' CV on half A")
    ap.add_argument("--parts", default="attribution,joint_ranges,candidates,span,simulation")
    args = start(ap, argv)
    if args is None:
        return {"skipped": True}
    seeds = [int(s) for s in args.seeds.split(",")]
    parts = args.parts.split(",")
    # the evidence search of every fit is tall-and-thin linear algebra: threaded BLAS only spins on it (30-50x
    # slower on a busy 2-core machine, measured), as estcal's commands know (estcal.base.blas)
    with single_thread_blas():
        return _run(args, seeds, parts)


def _run(args, seeds, parts) -> dict:
    robot, data = load_tiago()
    JOINTS[:] = list(robot.joint_names)
    out = {"protocol": __doc__, "seeds": seeds, "joints": JOINTS}
    t0 = time.time()
    if "attribution" in parts or "span" in parts:
        rows, splits = split_rows(robot, data, seeds, NOISE)
        out["splits"], out["postures"] = splits, rows
    if "attribution" in parts:
        out["attribution"] = attribution(rows)
        _print_attribution(splits, out["attribution"])
    if "joint_ranges" in parts:
        out["joint_ranges"] = joint_ranges(robot, data, NOISE)
        _print_ranges(out["joint_ranges"])
    if "candidates" in parts:
        out["candidates"] = candidates(robot, data, seeds, NOISE, args.k)
        _print_candidates(out["candidates"])
    if "span" in parts:
        out["span"] = span(robot, data, seeds, NOISE)
        _print_span(out["span"], splits)
    if "simulation" in parts:
        out["simulation"] = simulate(robot, data, seeds, NOISE)
        _print_sim(out["simulation"])
    return finish(out, t0, args.json)


if __name__ == "__main__":
    main()
