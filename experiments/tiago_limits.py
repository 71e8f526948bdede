"""What limits the TIAGo posture- and session-disjoint figure (``tiago_disjoint.py``) — two measurements on the
development halvings (seeds 0–5, both directions; ``--seeds`` other sets), no choice of the model made on them,
and two on the sessions.

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
   ``simulate_like`` draws both sessions at the first one's frame and joint zeros; two more noises start from
   the model's prediction at each session's own frame and zeros (the measured points minus its residual, so
   11-26's moved arm_5 zero is there to register): a Gaussian draw of the fitted rigid error per posture
   (``rigid-sessions``), and each posture's real rigid residual given to another posture of its session
   (``permuted``: the error's real sizes and shape, with no tie to the posture); and, to tell the real error's
   shape from its size and correlation, Gaussian draws of the covariance of those real rigid residuals in each
   session (``gaussian``) and of its diagonal alone (``gaussian-diag``); and the real residuals permuted by one
   permutation of the postures in both sessions (``permuted-shared``: the error still repeats between the
   sessions at a shared posture, as on the robot, but is no longer tied to its posture). A fitted residual is
   smaller than the error it stands for; ``permuted-inflated`` divides each component by the square root of the
   share of its variance a refit keeps, measured by refitting the two sessions simulated with known errors.

3. **What moved between the sessions, without a model.** The 37 postures both sessions measured (the same
   joint readings within 0.4 mrad): one rigid motion (Kabsch, scipy's ``Rotation.align_vectors``) registers
   11-26's points onto 11-30's over all of them; then, per posture, the rotation that still separates the two
   measurements of the hand (its four points) — a change of the measuring frame would leave none, a moved
   joint zero leaves one that turns with the posture; beside it, the joint zeros the diagnosis of both
   sessions registers for 11-26 (docs/discrepancy.md, "Sessions, postures and time"); and what that model leaves:
   its residual at the shared postures in both sessions (does the same posture keep the same error?) and,
   at 11-26's other postures, what the three nearest 11-30 postures' residual predicts of it (is it a smooth
   function of the joint angles?).
4. **What that residual is not a function of.** The same model's residual at every posture of both sessions, as the
   small rigid motion (rotation, translation) of the marker body that best explains its four points' residual, is
   screened against what the robot carries along its path — for every joint the move into the posture (signed and
   its size), the direction of the move before it, the previous posture's reading — and against the marker
   system's own jitter (``marker_std_mm``); and it is compared between postures near each other in the capture
   volume (the marker body's position and orientation), in joint space, and at random. Chance is measured, not
   assumed: the postures' residuals are permuted within each session (``--permutations``, seeded) and the same
   largest correlation, the same mean agreement of neighbours, recomputed. Beside them, a drift of one joint
   within each session (its column times the time), against the times permuted within the session.
5. **What the diagnosis of both whole sessions names when the truth is known** (not in the default ``--parts``):
   both sessions simulated as part 2's ``permuted-inflated`` (draw ``s``: seeds 2s and 2s + 1, ``--whole-seeds``,
   default 400–423) and diagnosed together, as a user diagnoses all their data: how often each cause of the truth,
   a term it holds unnamed, and a cause it does not hold are named.

``--json PATH`` writes every figure; ``--noise-seeds`` the simulation draws (default 11, 21, 31); ``--parts`` which
parts to run (default all).
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


#: part 2's simulated noises: ``--noises`` names and the table's labels. The first four draw from
#: ``simulate_like`` (both sessions at the first one's frame and joint zeros); the last two start from the
#: two-session model's prediction at each session's own frame and zeros (11-26's moved arm_5 zero included)
NOISES = {"rigid": "its rigid error per posture", "independent": "its residual, independent",
          "repeatability": "repeatability", "0.1": "0.1 mm",
          "rigid-sessions": "its rigid error per posture, each session at its frame and zeros",
          "permuted": "the real rigid error of another posture of the session, each at its frame and zeros",
          "gaussian": "Gaussian draws of the real rigid error's covariance in its session, each at its frame and zeros",
          "gaussian-diag": "the same with its diagonal only (no correlation)",
          "permuted-shared": "the real rigid error of another posture, the same permutation in both sessions",
          "permuted-inflated": "the real rigid error of another posture, each component divided by the square root "
                               "of the share of its variance a refit keeps"}


def simulated(robot, sessions, seeds, noise_seeds, kinds=tuple(NOISES), model=None) -> dict:
    """The halvings' mean on data simulated from the two-session model (module docstring, 2.), for the noise
    ``kinds`` (the table's rows, in its order); ``model``: :func:`two_session_model` (computed if not given)."""
    from estcal.discrepancy.feedback import simulate_like
    from estcal.workflows.diagnose import diagnose

    model = model or two_session_model(robot, sessions)
    ref = model["fit"]
    resid_mm = float(ref.model["residual"]["rmse_mm"])
    out = {"reference_named": [c.label for c in ref.causes], "reference_terms": _term_labels(ref),
           "reference_residual_mm": resid_mm, "runs": []}
    print(f"reference: the default diagnosis of both sessions — residual {resid_mm:.2f} mm per point; named "
          f"{', '.join(out['reference_named']) or 'nothing'}")
    iid = resid_mm * 1e-3 / np.sqrt(3.0)
    sigmas = {"rigid": None, "independent": iid, "repeatability": REPEATABILITY_MM * 1e-3 / np.sqrt(3.0), "0.1": 1e-4}
    psi, within = _random_effect(model)
    out["real_rigid_shape"] = shape = {k: rigid_shape(_rigid(model["residual"][k], np.asarray(sessions[k].points)))
                                       for k in ("11-30", "11-26")}
    print("the real rigid residual per posture: " + "; ".join(
        f"{k} components correlate by up to {v['max_abs_correlation']:.2f}, Mardia's kurtosis {v['mardia_kurtosis']:.1f} "
        f"(a Gaussian's {v['gaussian_kurtosis']:.0f}, 95 % of samples of {v['n']} within "
        f"{v['gaussian_range'][0]:.1f}–{v['gaussian_range'][1]:.1f})" for k, v in shape.items()))
    if "permuted-inflated" in kinds:
        out["residual_shrink"] = _shrink_of(robot, sessions, model)
        shrink = np.asarray(out["residual_shrink"]["variance_kept"])
        print("a refit on simulated errors keeps " + ", ".join(f"{100 * v:.0f} %" for v in shrink) + " of their variance "
              "(rotation x, y, z, translation x, y, z): the residuals permuted below are divided by its square root; "
              "those refits of both sessions, " + _named_line(out["residual_shrink"]["named"], out["reference_named"],
                                                              out["reference_terms"]).replace("halvings", "simulations"))
    for kind in kinds:
        for ns in noise_seeds:
            if kind == "permuted-inflated":
                sims = {k: _rebuilt(sessions[k], model, k, "permuted", psi, within, ns + i, scale=1 / np.sqrt(shrink))
                        for i, k in enumerate(("11-30", "11-26"))}
            elif kind == "permuted-shared":
                source = _shared_permutation(robot, sessions, ns)
                sims = {k: _rebuilt(sessions[k], model, k, "permuted", psi, within, ns + i, source[k])
                        for i, k in enumerate(("11-30", "11-26"))}
            elif kind in sigmas:
                sims = {k: simulate_like(ref, sessions[k], seed=ns + i, noise=sigmas[kind])
                        for i, k in enumerate(("11-30", "11-26"))}
            else:
                sims = {k: _rebuilt(sessions[k], model, k, kind, psi, within, ns + i)
                        for i, k in enumerate(("11-30", "11-26"))}
            fits = [diagnose(robot, T, validate=[V], budget=False) for _, _, T, V in td.halvings(robot, sims, seeds)]
            r = [f.accuracy["validation"][0]["rmse_mm"] for f in fits]
            named = [[c.label for c in f.causes] for f in fits]
            out["runs"].append({"noise": NOISES[kind], "kind": kind, "sigma_m": sigmas.get(kind), "noise_seed": ns,
                                "new_mm": r, "mean_mm": float(np.mean(r)), "named": named,
                                "causes": [[c.to_dict() for c in f.causes] for f in fits]})
            print(f"simulated, noise {NOISES[kind]}, draw {ns}: mean {np.mean(r):.2f} mm (trained on 11-30 "
                  f"{np.mean(r[0::2]):.2f}, on 11-26 {np.mean(r[1::2]):.2f}); "
                  f"{_named_line(named, out['reference_named'], out['reference_terms'])}", flush=True)
    return out


def whole_sessions(robot, sessions, model, draws) -> dict:
    """Part 5 of the module docstring: the causes the default diagnosis of both simulated sessions names, per draw."""
    from estcal.workflows.diagnose import diagnose

    ref = model["fit"]
    truth, terms = [c.label for c in ref.causes], _term_labels(ref)
    _, within = _random_effect(model)
    shrink = np.asarray(_shrink_of(robot, sessions, model)["variance_kept"])
    named = []
    for s in draws:
        sims = [_rebuilt(sessions[k], model, k, "permuted", None, within, 2 * s + i, scale=1 / np.sqrt(shrink))
                for i, k in enumerate(("11-30", "11-26"))]
        named.append([c.label for c in diagnose(robot, sims, budget=False).causes])
    line = _named_line(named, truth, terms).replace("halvings", "simulations")
    print(f"both whole sessions simulated from the two-session model and diagnosed together, {line}")
    return {"draws": list(draws), "named": named, "truth": truth, "terms": terms}


def _term_labels(fit) -> list[str]:
    """The labels (as a named cause prints them) of every effect term ``fit``'s model holds, named or not."""
    from estcal.discrepancy.feedback import load_fit
    from estcal.discrepancy.result import cause_label

    return [cause_label(e["effect"], e.get("joints") or [], e.get("options")) for e in load_fit(fit)["model"]["effects"]]


def _named_line(named, truth, terms) -> str:
    """Over the halvings of one draw: how often each cause the simulation's truth names is named; in how many a
    term the truth holds without naming it is named; in how many a cause it does not hold at all (the false
    causes; the whole lists are in the JSON)."""
    found = ", ".join(f"{t} {sum(t in x for x in named)}" for t in truth)
    kept = sum(any(c in terms and c not in truth for c in x) for x in named)
    false = [c for x in named for c in x if c not in terms]
    return (f"of its {len(named)} halvings named: {found}; a term it holds unnamed in {kept}; a cause it does not "
            f"hold in {sum(any(c not in terms for c in x) for x in named)}"
            + (f" ({', '.join(sorted(set(false)))})" if false else ""))


def rigid_shape(motion, draws: int = 2000, seed: int = 0) -> dict:
    """The shape of per-posture rigid residuals ``motion`` (n, p): their largest correlation between components
    and Mardia's multivariate kurtosis ``b₂ = mean((xᵢ − x̄)ᵀ S⁻¹ (xᵢ − x̄))²`` (S the covariance with divisor n;
    Mardia 1970, Biometrika 57:519), which is p(p + 2) for a Gaussian and larger for heavier tails; beside it the
    central 95 % of b₂ over ``draws`` Gaussian samples of the same size (seeded), since b₂ of a few tens of rows
    scatters (and is biased low) about p(p + 2)."""
    def b2(x):
        c = x - x.mean(axis=-2, keepdims=True)
        S = np.swapaxes(c, -1, -2) @ c / x.shape[-2]
        d2 = np.einsum("...ij,...jk,...ik->...i", c, np.linalg.inv(S), c)
        return np.mean(d2 ** 2, axis=-1)

    n, p = motion.shape
    c = motion - motion.mean(axis=0)
    corr = np.corrcoef(c.T)
    sims = b2(np.random.default_rng(seed).normal(size=(draws, n, p)))
    return {"n": int(n), "max_abs_correlation": float(np.max(np.abs(corr - np.eye(p)))),
            "mardia_kurtosis": float(b2(motion)), "gaussian_kurtosis": float(p * (p + 2)),
            "gaussian_range": np.quantile(sims, [0.025, 0.975]).tolist()}


def _shared_permutation(robot, sessions, seed) -> dict:
    """Per session, the row whose real residual each row takes (``permuted-shared``): one permutation of the
    postures, applied in both sessions — a posture both measured takes, in each, the residual of the same other
    posture (so the sessions' errors at a shared posture still repeat), the postures of one session alone are
    permuted among themselves."""
    from estcal.validation import posture_groups

    a, b = sessions["11-30"], sessions["11-26"]
    g = posture_groups(np.vstack([a.readings, b.readings]), robot.joint_types)
    ga, gb = g[: a.n], g[a.n:]
    rng = np.random.default_rng(seed)
    to = {}
    for group in (np.intersect1d(ga, gb), np.setdiff1d(ga, gb), np.setdiff1d(gb, ga)):
        to.update(zip(group.tolist(), rng.permutation(group).tolist()))
    row = lambda lab: {p: i for i, p in enumerate(lab.tolist())}  # noqa: E731 (one row per posture)
    ra, rb = row(ga), row(gb)
    if len(ra) != a.n or len(rb) != b.n:
        raise ValueError("permuted-shared needs one row per posture in each session")
    return {"11-30": np.array([ra[to[p]] for p in ga.tolist()]), "11-26": np.array([rb[to[p]] for p in gb.tolist()])}


def residual_shrink(robot, sessions, model, seeds=(1010, 1020, 1030, 1040, 1050, 1060)) -> dict:
    """How much smaller a fitted residual is than the error it stands for: both sessions simulated from
    ``model`` (:func:`two_session_model`) with Gaussian draws of its residuals' covariance (``gaussian``), the
    two-session diagnosis refitted on them, and the variance of its rigid residual per posture divided by that of
    the errors drawn, per component (rotation x, y, z, translation x, y, z), averaged over the ``seeds`` (and the
    causes each refit names, ``named``). Reusing
    real residuals as errors (``permuted``) understates their size by this share (the fit's own degrees of freedom,
    Laird & Ware 1982's REML argument)."""
    _, within = _random_effect(model)
    ratios, named = [], []
    for ns in seeds:
        sims = {k: _rebuilt(sessions[k], model, k, "gaussian", None, within, ns + i) for i, k in enumerate(sessions)}
        refit = two_session_model(robot, sims)
        named.append([c.label for c in refit["fit"].causes])
        drawn, kept = [], []
        for k, sim in sims.items():
            pts = np.asarray(sim.points)
            e = _rigid(pts - (np.asarray(sessions[k].points) - model["residual"][k]), pts)
            r = _rigid(refit["residual"][k], pts)
            drawn.append(e - e.mean(axis=0))
            kept.append(r - r.mean(axis=0))
        ratios.append(np.sum(np.vstack(kept) ** 2, axis=0) / np.sum(np.vstack(drawn) ** 2, axis=0))
    R = np.array(ratios)
    return {"variance_kept": R.mean(axis=0).tolist(), "per_seed": R.tolist(), "seeds": list(seeds), "named": named}


def _shrink_of(robot, sessions, model) -> dict:
    """:func:`residual_shrink` of ``model`` (:func:`two_session_model`), measured once per model: parts 2 and 5 both
    use it, and it costs six two-session diagnoses."""
    if "shrink" not in model:
        model["shrink"] = residual_shrink(robot, sessions, model)
    return model["shrink"]


def _random_effect(model) -> tuple:
    """``(Ψ (6,) (m², rad²), within-posture σ (m))`` of the two-session model's random effect."""
    from estcal.discrepancy.feedback import load_fit

    re_ = load_fit(model["fit"])["random_effect"]
    return np.asarray(re_["psi_si"], float), float(re_["sigma_mm"]) * 1e-3


def _rebuilt(data, model, label, kind, psi, within, seed, source=None, scale=1.0):
    """``data`` with its points replaced by the two-session model's prediction at the session's own frame and
    joint zeros (the measured points minus that model's residual), each posture's body moved rigidly by a
    Gaussian draw of the fitted Ψ (``rigid-sessions``), by the real rigid residual of another posture of the
    session, centred and permuted (``permuted``; ``source``: the row each row takes it from, else a random
    permutation; ``scale``: each component of the residual multiplied by it), or by a Gaussian draw of those
    residuals' covariance in the session (``gaussian``; ``gaussian-diag``: its diagonal), plus ``within`` (m) on
    every coordinate."""
    rng = np.random.default_rng(seed)
    meas = np.asarray(data.points)
    pred = meas - model["residual"][label]
    if kind == "rigid-sessions":
        motion = rng.normal(0.0, 1.0, (data.n, 6)) * np.sqrt(np.r_[psi[3:], psi[:3]])  # (δφ, δt)
    else:
        real = _rigid(model["residual"][label], meas) * 1e-3
        real = (real - real.mean(axis=0)) * scale
        if kind == "permuted":
            motion = real[rng.permutation(data.n) if source is None else source]
        else:  # the real error's covariance (its size and correlation), a Gaussian shape
            cov = real.T @ real / data.n
            if kind == "gaussian-diag":
                cov = np.diag(np.diag(cov))
            motion = rng.multivariate_normal(np.zeros(6), cov, size=data.n, method="eigh")
    arm = pred - pred.mean(axis=1, keepdims=True)
    out = data.subset(slice(None))
    out.points = pred + motion[:, None, 3:] + np.cross(motion[:, None, :3], arm) + rng.normal(0, within, pred.shape)
    return out


def two_session_model(robot, sessions) -> dict:
    """The default diagnosis of both sessions together: ``zeros`` (11-26's registered joint zeros), each session's
    residual ``(n, 4, 3)`` (m) at its own frame and zeros and its points' derivatives in the joint readings
    (:func:`_residual`)."""
    from estcal.workflows.diagnose import diagnose

    a, b = sessions["11-30"], sessions["11-26"]
    both = diagnose(robot, [a, b], budget=False)
    zeros = next(iter(both.model["session_frames"].values())).get("zeros", {})
    (ra, ja), (rb, jb) = _residual(both, a, {}, True), _residual(both, b, zeros, True)
    return {"fit": both, "zeros": zeros, "residual": {"11-30": ra, "11-26": rb},
            "joint_columns": {"11-30": ja, "11-26": jb}}


def between_sessions(robot, sessions, model) -> dict:
    """Part 3 of the module docstring: the hand's rotation between the sessions at their shared postures (mrad:
    its mean vector and the RMS of its change about that mean, in the measuring frame), the points' RMS
    difference after the one registration (mm), and the two-session diagnosis's joint zeros of 11-26
    (``model``: :func:`two_session_model`)."""
    from scipy.spatial.transform import Rotation

    from estcal.validation import posture_groups

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
    zeros = model["zeros"]
    ra, rb = model["residual"]["11-30"], model["residual"]["11-26"]  # (n, 4, 3) m, each at its frame and zeros
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


def _rigid(resid, points) -> np.ndarray:
    """(n, 6) the small rigid motion of each posture's marker body that best explains its points' residual
    (least squares ``r_i ≈ t + ω × (x_i − c)``): rotation ω (mrad), translation t (mm), measuring frame."""
    from estcal.kinematics.transforms import skew

    x = points - points.mean(axis=1, keepdims=True)
    # ω × x = −[x]× ω: the rotation's columns of the design, then the translation's
    design = np.concatenate([-skew(x), np.broadcast_to(np.eye(3), x.shape + (3,))], axis=-1).reshape(len(x), -1, 6)
    sol = np.stack([np.linalg.lstsq(A, r.ravel(), rcond=None)[0] for A, r in zip(design, resid)])
    return sol * 1e3


def _path_features(data) -> dict:
    """What the robot carries along its path into each posture, per joint: the move into it (signed, and its
    size), the direction of the move before, the previous posture's reading; and the marker system's jitter."""
    q = data.readings
    dq = np.diff(q, axis=0, prepend=q[:1])
    feats = {}
    for j, nm in enumerate(data.joint_names):
        feats[f"{nm} move"] = dq[:, j]
        feats[f"{nm} move size"] = np.abs(dq[:, j])
        feats[f"{nm} move before"] = np.sign(np.r_[0.0, dq[:-1, j]])
        feats[f"{nm} previous reading"] = np.r_[q[0, j], q[:-1, j]]
    feats["marker jitter"] = np.asarray(data.columns["marker_std_mm"], float)
    return feats


def _standardise(x, groups):
    """Columns centred and scaled within each session (the sessions' own offsets are not a feature)."""
    x = np.array(x, float)
    for g in np.unique(groups):
        m = groups == g
        x[m] -= x[m].mean(axis=0)
    sd = np.sqrt((x ** 2).mean(axis=0))
    return x / np.where(sd > 0, sd, 1.0)


#: part 4's power: path errors of these sizes (mrad; mm for a prismatic joint) are added to find the least one found
AMPLITUDES = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def _joint_screen(sessions, model, feats, perms, grp) -> dict:
    """The path features (``feats``: :func:`_path_features` of every session) as a hysteresis would act: joint j's
    angle error ``c · f_ij`` for one feature of joint j (standardised within each session), i.e. the regressor ``f_ij ∂x/∂q_j`` on all points of posture i; the share
    of the squared residual its least-squares ``c`` explains, the largest over joints and features, against the
    same largest share with the features permuted within each session (the residuals and columns stay paired).
    The screen's power: the least of :data:`AMPLITUDES` × "the move before" (±1), added to each joint in turn,
    that the same screen finds at p ≤ 0.05."""
    labels = list(sessions)
    pairs = [(j, n) for j in model["joint_columns"][labels[0]] for n in feats[labels[0]] if n.startswith(j + " ")]
    R = np.concatenate([model["residual"][lab][1:].reshape(sessions[lab].n - 1, -1) for lab in labels])
    raw = np.column_stack([np.concatenate([feats[lab][n][1:] for lab in labels]) for _, n in pairs])
    F = _standardise(raw, grp)
    J = np.stack([np.concatenate([model["joint_columns"][lab][j][1:].reshape(sessions[lab].n - 1, -1)
                                  for lab in labels]) for j, _ in pairs], axis=-1)  # (rows, 12, pairs)
    JJ = np.einsum("rcp,rcp->rp", J, J)

    def screen(res):
        JR, RR = np.einsum("rcp,rc->rp", J, res), float(np.sum(res ** 2))
        share = [(np.sum(F[p] * JR, axis=0) ** 2 / np.sum(F[p] ** 2 * JJ, axis=0)) / RR for p in perms]
        top = np.array([x.max() for x in share])
        return top, int(np.argmax(share[0]))

    top, best = screen(R)
    found = {}  # the least of AMPLITUDES (mrad, or mm for a prismatic joint) the screen finds at p ≤ 0.05
    for c, (j, n) in enumerate(pairs):
        if n.endswith(" move before"):
            found[j] = next((a for a in AMPLITUDES
                             if _p_value(screen(R + a * 1e-3 * raw[:, c, None] * J[:, :, c])[0]) <= 0.05), None)
    return {"pairs": len(pairs), "largest_share": float(top[0]), "feature": pairs[best][1],
            "chance_median_share": float(np.median(top[1:])), "p_value": _p_value(top), "found_from": found}


def _p_value(stat) -> float:
    """Permutation p-value of ``stat[0]`` against ``stat[1:]``, counting the observed one (Phipson & Smyth 2010,
    *Stat. Appl. Genet. Mol. Biol.* 9:39): never 0."""
    return float((np.sum(stat[1:] >= stat[0]) + 1) / len(stat))


def not_a_function_of(sessions, model, permutations: int, seed: int) -> dict:
    """Part 4 of the module docstring. Rows after each session's first (a move into them exists): the largest
    squared correlation between a path feature and a component of the rigid residual, against the same largest
    value with the residuals permuted within each session; the mean agreement ``r_i·r_j / mean |r|²`` of the
    point residuals of the nearest 5 % of pairs of postures (capture volume, joint space), against permutation.
    Pairs at one posture measured in both sessions are left out (they agree: part 3)."""
    from scipy.spatial.transform import Rotation

    feats = {label: _path_features(d) for label, d in sessions.items()}
    names, Y, F, R, pos, rot, q, grp = [], [], [], [], [], [], [], []
    for k, (label, d) in enumerate(sessions.items()):
        r = model["residual"][label][1:]
        pts = np.asarray(d.points)[1:]
        names = list(feats[label])
        F.append(np.column_stack([v[1:] for v in feats[label].values()]))
        Y.append(_rigid(r, pts))
        R.append(r.reshape(len(r), -1) * 1e3)
        pos.append(pts.mean(axis=1))
        rot.append(np.array([Rotation.align_vectors(p - p.mean(0), pts[0] - pts[0].mean(0))[0].as_matrix()
                             for p in pts]))  # each body's orientation, relative to the session's first
        q.append(d.readings[1:])
        grp.append(np.full(len(r), k))
    grp = np.concatenate(grp)
    F, Y, R = _standardise(np.vstack(F), grp), _standardise(np.vstack(Y), grp), np.vstack(R)
    for g in np.unique(grp):  # each session's mean residual is its frame's business
        R[grp == g] -= R[grp == g].mean(axis=0)
    rng = np.random.default_rng(seed)
    perms = [np.arange(len(grp))] + [np.concatenate([rng.permutation(np.flatnonzero(grp == g)) for g in np.unique(grp)])
                                     for _ in range(permutations)]
    corr = lambda y: (F.T @ y / len(y)) ** 2  # noqa: E731
    top = np.array([corr(Y[p]).max() for p in perms])
    c0 = corr(Y)
    best = np.unravel_index(np.argmax(c0), c0.shape)
    comp = ["rx", "ry", "rz", "tx", "ty", "tz"]
    out = {"rows": int(len(grp)), "features": len(names), "screen": {
        "largest_r2": float(top[0]), "feature": names[best[0]], "component": comp[best[1]],
        "chance_median_r2": float(np.median(top[1:])), "p_value": _p_value(top)}}
    pos, q = np.vstack(pos), np.vstack(q)
    rot = np.concatenate(rot)
    iu = np.triu_indices(len(grp), 1)
    q_sd = np.where(q.std(0) > 0, q.std(0), 1.0)
    d_q = np.linalg.norm((q[:, None] - q[None]) / q_sd, axis=-1)[iu]
    d_pos = np.linalg.norm(pos[:, None] - pos[None], axis=-1)[iu]
    rel = np.einsum("iab,jac->ijbc", rot, rot)
    d_rot = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1))[iu]
    keep = d_q > 1e-2  # a posture measured in both sessions is part 3's business
    near = {"capture volume": d_pos / np.median(d_pos) + d_rot / np.median(d_rot), "joint space": d_q}
    scale = np.mean(np.sum(R ** 2, axis=1))
    out["neighbours"] = {}
    for label, dist in near.items():
        pairs = np.argsort(np.where(keep, dist, np.inf))[: int(0.05 * keep.sum())]
        i, j = iu[0][pairs], iu[1][pairs]
        agree = np.array([np.mean(np.sum(R[p][i] * R[p][j], axis=1)) / scale for p in perms])
        out["neighbours"][label] = {"pairs": int(len(pairs)), "agreement": float(agree[0]),
                                    "chance_95": float(np.quantile(agree[1:], 0.95)),
                                    "p_value": _p_value(agree)}
    out["joint_screen"] = _joint_screen(sessions, model, feats, perms, grp)
    out["drift_screen"] = _drift_screen(sessions, model, perms, grp)
    sc = out["screen"]
    print(f"the two-session model's residual at {out['rows']} postures (each session's first left out): the best of "
          f"{out['features']} path features ({sc['feature']}, {sc['component']}) explains r² = {sc['largest_r2']:.2f} "
          f"of a component, chance's best {sc['chance_median_r2']:.2f} (median; p = {sc['p_value']:.3f})")
    js = out["joint_screen"]
    print(f"  as a joint's angle error proportional to one of its own path features: the best of {js['pairs']} "
          f"({js['feature']}) explains {js['largest_share']:.3f} of the squared residual, chance's best "
          f"{js['chance_median_share']:.3f} (median; p = {js['p_value']:.3f}); added, one is found from "
          + ", ".join(f"{j} {a:g}" if a else f"{j} > {AMPLITUDES[-1]:g}" for j, a in js["found_from"].items())
          + " mrad (mm for a prismatic joint)")
    for label, v in out["neighbours"].items():
        print(f"  the nearest 5 % of pairs in {label} ({v['pairs']}): agreement {v['agreement']:+.2f} of the mean "
              f"squared residual (chance's 95 % point {v['chance_95']:+.2f}; p = {v['p_value']:.4f})")
    print("  as a drift of one joint within its session (its column times the time): " + "; ".join(
        f"{k} best {v['joint']} {100 * v['share']:.1f} % of the squared residual ({v['slope_mrad_per_s']:+.4f} mrad/s; "
        f"p = {v['p_value']:.3f})" for k, v in out["drift_screen"].items()))
    return out


def _drift_screen(sessions, model, perms, grp) -> dict:
    """A drift of one joint within a session, as the diagnosis's drift term acts: joint j's angle error ``c · t``
    (``t`` the middle of the posture's averaging window, centred in the session), i.e. the regressor
    ``t ∂x/∂q_j`` on all points of the posture. Per session: the share of its squared residual the
    least-squares ``c`` explains, the largest over joints, and its p-value against the same largest share with
    the times permuted within the session (``perms``, ``grp``: :func:`not_a_function_of`'s rows, each session's
    first left out)."""
    T = np.concatenate([((np.asarray(d.columns["t_start_robot"], float) + np.asarray(d.columns["t_end_robot"], float))
                         / 2)[1:] for d in sessions.values()])
    out = {}
    for k, label in enumerate(sessions):
        rows = np.flatnonzero(grp == k)
        R = model["residual"][label][1:].reshape(len(rows), -1)
        joints = list(model["joint_columns"][label])
        J = np.stack([model["joint_columns"][label][j][1:].reshape(len(rows), -1) for j in joints])  # (joints, n, 12)
        a, b = np.einsum("jnc,nc->jn", J, R), np.einsum("jnc,jnc->jn", J, J)
        t = np.stack([T[p[rows]] for p in perms])  # (perms, n): the observed times first
        t = t - t.mean(axis=1, keepdims=True)
        share = (t @ a.T) ** 2 / (t ** 2 @ b.T) / float(np.sum(R ** 2))  # (perms, joints)
        best = int(np.argmax(share[0]))
        out[label] = {"joint": joints[best], "share": float(share[0, best]),
                      "slope_mrad_per_s": float(t[0] @ a[best] / (t[0] ** 2 @ b[best]) * 1e3),
                      "p_value": _p_value(share.max(axis=1))}
    return out


def _residual(res, data, zeros, joint_columns: bool = False):
    """(n, k, 3) measured minus predicted points (m) of ``data`` with the diagnosis's model, its joint zeros moved by
    ``zeros`` ({joint: [value (mrad or mm), std, unit]}) and its frame registered by one rigid motion; with
    ``joint_columns`` also ``{joint: (n, k, 3)}``, the points' derivative in its reading (m/rad or m/m),
    turned by the same registration."""
    from scipy.spatial.transform import Rotation

    from estcal.discrepancy.zeros import zero_parameters

    model = res.robot
    theta = model.params.values.copy()
    param = dict(zero_parameters(model))
    for j, v in zeros.items():
        theta[model.params.index(param[j])] += v[0] * 1e-3
    d = res.prepare(data)
    meas = np.asarray(data.points)
    kin = model.kinematics(d.readings, theta, context=d.context, jacobian=joint_columns)
    pred = kin.points[:, : meas.shape[1]]
    cp, cm = pred.reshape(-1, 3).mean(0), meas.reshape(-1, 3).mean(0)
    rot, _ = Rotation.align_vectors(meas.reshape(-1, 3) - cm, pred.reshape(-1, 3) - cp)
    resid = meas - (rot.apply(pred.reshape(-1, 3) - cp).reshape(pred.shape) + cm)
    if not joint_columns:
        return resid
    cols = {j: rot.apply(kin.J_points[:, : meas.shape[1], :, model.params.index(n)].reshape(-1, 3)).reshape(pred.shape)
            for j, n in param.items()}
    return resid, cols


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise-seeds", default="11,21,31")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--parts", default="1,2,3,4", help="which parts of the module docstring to run (1–5)")
    ap.add_argument("--whole-seeds", default="400-423", help="part 5's draws: first-last")
    ap.add_argument("--seeds", type=td.seed_set, default="development", help="the halvings of parts 1 and 2: a "
                    "set's name as tiago_disjoint.py's --seeds (development, confirmation…, all) or a list")
    ap.add_argument("--noises", default="rigid,independent,repeatability,0.1,rigid-sessions,permuted",
                    help="part 2's simulated noises")
    ap.add_argument("--permutations", type=int, default=2000, help="part 4's permutations of the residuals")
    ap.add_argument("--permutation-seed", type=int, default=4)
    args = ap.parse_args(argv)
    parts = {int(x) for x in args.parts.split(",") if x.strip().isdigit()}
    if not parts or parts - {1, 2, 3, 4, 5} or set(args.noises.split(",")) - set(NOISES):
        ap.error(f"--parts takes some of 1,2,3,4,5 and --noises some of {','.join(NOISES)}")
    from estcal.base.blas import single_thread_blas

    warnings.filterwarnings("ignore")
    if td.missing():
        print(td.missing())
        return {"skipped": True}
    robot, sessions = td.load()
    t0 = time.process_time()
    with single_thread_blas():  # as the diagnosis runs anyway: the simulation's own arrays too
        seeds = args.seeds
        out = {"seeds": list(seeds)}
        if 1 in parts:
            out["where"] = w = where_the_error_is(robot, sessions, seeds)
            ins = [r["inside_mm"] for r in w if r["inside_mm"] is not None]
            out["inside_mean_mm"], out["new_mean_mm"] = float(np.mean(ins)), float(np.mean([r["new_mm"] for r in w]))
            print(f"mean at new postures {out['new_mean_mm']:.2f} mm; inside the training ranges "
                  f"{out['inside_mean_mm']:.2f} mm (range {min(ins):.2f}–{max(ins):.2f})")
        if parts & {2, 3, 4, 5}:
            model = two_session_model(robot, sessions)
        if 2 in parts:
            out["simulated"] = simulated(robot, sessions, seeds, [int(x) for x in args.noise_seeds.split(",")],
                                         args.noises.split(","), model)
        if 3 in parts:
            out["between_sessions"] = between_sessions(robot, sessions, model)
        if 4 in parts:
            out["not_a_function_of"] = not_a_function_of(sessions, model, args.permutations, args.permutation_seed)
        if 5 in parts:
            first, last = (int(x) for x in args.whole_seeds.split("-"))
            out["whole_sessions"] = whole_sessions(robot, sessions, model, range(first, last + 1))
    out["cpu_s"] = time.process_time() - t0
    if args.json:
        write_json(args.json, out, announce=True)
    return out


if __name__ == "__main__":
    main()
