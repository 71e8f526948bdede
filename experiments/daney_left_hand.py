"""Reproduce Daney (1998): constrained-leg calibration of the INRIA "Left Hand".

Protocol (``shared/reference/daney.md`` §5): leg k = 3; uniform noise of
amplitude err_p (cm) on each platform position component, err_a (degrees) on
each ZYX Euler angle and err_l (cm) on the leg reading; ``n_sets``
independent random constrained pose sets per pose count; N = 4..50 (Type I,
method 3.2), N1 = 4..30 (Type II, b_k), N2 = 5..30 (Type III, a_k, with b_k
from a Type II set of N1 = 7 poses, i.e. the two steps chained).

Error factor = mean over the sets of ‖estimate − truth‖ (cm) divided by the
noise amplitude err (cm); err_p = err_l = err cm and err_a = err degrees
(numerically equal, as the paper mixes cm and degrees).

For every N the sets are the first N poses of sets generated with the
largest N (common random numbers across N, independent across sets).

Baseline: unconstrained inverse-kinematics calibration of the same leg
(Gauss–Newton iterated to convergence, batched over the sets; Model 36 = a_k, b_k with Δρ_k
known, N ≥ 7, and Model 42 = a_k, b_k, Δρ_k, N ≥ 8) on N random workspace poses with the
same noise; the sets where it does not converge are refitted with the shared LM.

Usage::

    python experiments/daney_left_hand.py              # full protocol (1000 sets)
    python experiments/daney_left_hand.py --quick      # smoke test (<20 s)
    python experiments/daney_left_hand.py --json out.json --png docs/parallel_daney_factors.png --docs

``--json PATH`` keys (errors for err_p = 0.01 cm, err_a = 0.01°, err_l = 0.01 cm):

* ``config``: robot, leg, workspace (cm, deg), noise, n_sets, conventions;
* ``method_3_2``: ``N``, ``factor_base``, ``factor_platform``, ``median_condition``;
* ``method_3_3``: ``N1``, ``factor_b``, ``N2``, ``factor_a`` (b from N1 = 7),
  ``N1_for_a``, ``factor_a_N1_N2_7``, ``factor_offset_single_pose``;
* ``b_examples``: for err = 0.01 and 0.001: ``b_cm`` of the first set and
  ``mean_error_cm`` (N1 = 7);
* ``ik_unconstrained``: ``N``, ``model36`` {``factor_base``, ``factor_platform``, ``refitted``,
  ``left_out``}, ``model42`` {``N``, ``factor_a``, ``factor_b``, ``factor_offset``, ``refitted``, ``left_out``};
* ``noise_sources``: factors at N = 7 with only one noise source active;
* ``workspace_sensitivity``: factors at N = 7 for other workspace choices;
* ``direction_cap_sweep``: ``cap_deg``, ``factor_a`` (N1 = N2 = 7) when the
  Type III directions fill a cap of that half-angle (no workspace limits).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from estcal.parallel.daney import (  # noqa: E402
    add_uniform_noise,
    batched_lstsq,
    generate_random_poses,
    generate_type1,
    generate_type2,
    generate_type3,
    solve_offset,
    solve_type1,
    solve_type2,
    solve_type3,
)
from estcal.parallel.data import GoughData  # noqa: E402
from estcal.parallel.gough import GoughPlatform, Workspace, left_hand  # noqa: E402
from estcal.workflows.gough import calibrate_gough  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

CM = 0.01
K = 2  # leg 3, 0-based


def workspaces() -> dict[str, dict]:
    """Workspace variants (cm, deg). 'default' is the one of ``left_hand()``."""
    return {
        "default": dict(pmin=[-4, -4, 16], pmax=[4, 4, 26], angle=20, legs=[16, 26]),
        "narrow": dict(pmin=[-2, -2, 19], pmax=[2, 2, 23], angle=10, legs=[16, 26]),
        "wide": dict(pmin=[-8, -8, 14], pmax=[8, 8, 32], angle=35, legs=[15.25, 35]),
    }


def make_robot(ws: dict) -> GoughPlatform:
    r = left_hand()
    r.workspace = Workspace(np.array(ws["pmin"], float) * CM, np.array(ws["pmax"], float) * CM,
                            np.radians(ws["angle"]))
    r.length_limits = np.tile(np.array(ws["legs"], float) * CM, (6, 1))
    return r


def _leg_len(robot, T):
    P, R = T[..., :3, 3], T[..., :3, :3]
    return np.linalg.norm(P + R @ robot.b[K] - robot.a[K], axis=-1)


def _noisy(rng, T, L, err_p, err_a, err_l):
    """Uniform noise; lengths in m, err_* in m / rad / m."""
    return add_uniform_noise(T, rng, err_p, err_a), L + rng.uniform(-err_l, err_l, L.shape)


def _mean_err_cm(x, truth):
    return float(np.nanmean(np.linalg.norm(x - truth, axis=-1)) / CM)


def ik_leg_gn(robot, T, rho, model: int, max_iter: int = 100, tol: float = 1e-12):
    """Batched Gauss–Newton for one leg's IK residuals ρ_i − (‖P_i + R_i b − a‖ − Δρ).

    T (S, N, 4, 4), rho (S, N). Starts at the true values and iterates every set until its step
    is below ``tol`` (m) — the least-squares solution, as the shared estimators give it
    (tests/test_parallel_daney.py compares with ``calibrate_gough``) — or ``max_iter``. Returns
    a, b, Δρ (NaN for the sets that did not converge: a near-singular set with N = 7 or 8 poses
    can make plain Gauss–Newton diverge) and the converged mask (S,).
    """
    S = T.shape[0]
    p = 7 if model == 42 else 6
    x = np.tile(np.r_[robot.a[K], robot.b[K], robot.drho[K]][:p], (S, 1))
    P, R = T[..., :3, 3], T[..., :3, :3]
    done = np.zeros(S, bool)
    for _ in range(max_iter):
        a, b = x[:, None, :3], x[:, 3:6]
        d = x[:, 6:7] if model == 42 else robot.drho[K]
        v = P + np.einsum("snij,sj->sni", R, b) - a
        L = np.linalg.norm(v, axis=-1)
        u = v / L[..., None]
        r = rho - (L - d)
        Jr = np.concatenate([u, -np.einsum("sni,snij->snj", u, R)], axis=-1)  # ∂r/∂(a, b)
        if model == 42:
            Jr = np.concatenate([Jr, np.ones(r.shape + (1,))], axis=-1)
        dx, _ = batched_lstsq(Jr, -r)
        dx[done] = 0.0
        x = x + dx
        done |= np.max(np.abs(dx), axis=1) < tol  # NaN steps (rank-deficient sets) never converge
        if done.all():
            break
    x[~done] = np.nan
    return x[:, :3], x[:, 3:6], (x[:, 6] if model == 42 else None), done


def method_3_2(robot, rng, n_sets, Ns, err_p, err_a, err_l):
    T = generate_type1(robot, K, n_sets, max(Ns), rng)
    Tn, Ln = _noisy(rng, T, _leg_len(robot, T), err_p, err_a, err_l)
    fb, fp, cond = [], [], []
    for N in Ns:
        b, a, c = solve_type1(Tn[:, :N, :3, 3], Tn[:, :N, :3, :3], Ln[:, :N])
        fb.append(_mean_err_cm(a, robot.a[K]))
        fp.append(_mean_err_cm(b, robot.b[K]))
        cond.append(float(np.median(c)))
    return fb, fp, cond


def method_3_3(robot, rng, n_sets, N1s, N2s, err_p, err_a, err_l, N1_for_a=7):
    T2 = generate_type2(robot, K, n_sets, max(max(N1s), N1_for_a), rng)
    T2n = add_uniform_noise(T2, rng, err_p, err_a)
    eb, b7 = [], None
    for N1 in N1s:
        b, _ = solve_type2(T2n[:, :N1, :3, 3], T2n[:, :N1, :3, :3])
        eb.append(_mean_err_cm(b, robot.b[K]))
    b7, _ = solve_type2(T2n[:, :N1_for_a, :3, 3], T2n[:, :N1_for_a, :3, :3])
    T3 = generate_type3(robot, K, n_sets, max(N2s), rng)
    T3n, rho3 = _noisy(rng, T3, _leg_len(robot, T3) - robot.drho[K], err_p, err_a, err_l)
    ea, a_by_N2 = [], {}
    for N2 in N2s:
        a, _ = solve_type3(T3n[:, :N2, :3, 3], T3n[:, :N2, :3, :3], b7)
        ea.append(_mean_err_cm(a, robot.a[K]))
        a_by_N2[N2] = a
    # offset (19) from one further noisy pose per set, with the estimated a (N2 = 7) and b
    a7 = a_by_N2.get(7, a_by_N2[N2s[0]])
    Tq = generate_random_poses(robot, n_sets, rng)[:, None]
    Tqn, rq = _noisy(rng, Tq, _leg_len(robot, Tq) - robot.drho[K], err_p, err_a, err_l)
    d = solve_offset(Tqn[..., :3, 3], Tqn[..., :3, :3], rq, a7, b7)
    e_off = float(np.mean(np.abs(d - robot.drho[K])) / CM)
    return eb, ea, b7, e_off


def ik_leg_fit(robot, T, rho, model: int):
    """One leg's IK least-squares fit on every set: batched Gauss–Newton (:func:`ik_leg_gn`), and the
    shared LM (:func:`estcal.workflows.gough.calibrate_gough`, leg K free) on each set where it did
    not converge. Returns a, b, Δρ (NaN where no estimator converged on all the leg's parameters),
    the number of sets refitted and the number left out."""
    a, b, d, ok = ik_leg_gn(robot, T, rho, model)
    redo = np.flatnonzero(~ok)
    free = [f"a{K + 1}_*", f"b{K + 1}_*"] + ([f"drho_{K + 1}"] if model == 42 else [])
    left_out = 0
    for s in redo:
        readings = robot.leg_lengths(T[s])
        readings[:, K] = rho[s]  # the other legs' rows do not involve leg K's parameters
        try:
            res = calibrate_gough(robot, GoughData(T[s], readings), model=model, free=free, max_iter=1000)
        except ValueError:  # InputError / NumericalRefusal: the set cannot determine the leg
            left_out += 1
            continue
        if not res.converged or len(res.names) != len(res.requested):
            left_out += 1  # not converged, or a parameter not identifiable (kept at its true value)
            continue
        th = res.theta.reshape(6, 7)[K]
        a[s], b[s] = th[:3], th[3:6]
        if model == 42:
            d[s] = th[6]
    return a, b, d, len(redo), left_out


def ik_baseline(robot, rng, n_sets, Ns, err_p, err_a, err_l):
    Nmax = max(Ns)
    T = generate_random_poses(robot, n_sets * Nmax, rng).reshape(n_sets, Nmax, 4, 4)
    Tn, rho = _noisy(rng, T, _leg_len(robot, T) - robot.drho[K], err_p, err_a, err_l)
    out = {"N": list(Ns), "model36": {"factor_base": [], "factor_platform": [], "refitted": [], "left_out": []},
           "model42": {"N": [n for n in Ns if n >= 8], "factor_a": [], "factor_b": [], "factor_offset": [],
                       "refitted": [], "left_out": []}}
    for N in Ns:
        a, b, _, nr, nl = ik_leg_fit(robot, Tn[:, :N], rho[:, :N], 36)
        m = out["model36"]
        m["factor_base"].append(_mean_err_cm(a, robot.a[K]))
        m["factor_platform"].append(_mean_err_cm(b, robot.b[K]))
        m["refitted"].append(nr)
        m["left_out"].append(nl)
        if N >= 8:  # Model 42 needs 7 poses; with N = 7 the system is square and the fit exact
            a, b, d, nr, nl = ik_leg_fit(robot, Tn[:, :N], rho[:, :N], 42)
            m = out["model42"]
            m["factor_a"].append(_mean_err_cm(a, robot.a[K]))
            m["factor_b"].append(_mean_err_cm(b, robot.b[K]))
            m["factor_offset"].append(float(np.nanmean(np.abs(d - robot.drho[K])) / CM))
            m["refitted"].append(nr)
            m["left_out"].append(nl)
    return out


def direction_cap_sweep(rng, n_sets, caps_deg, err_p, err_a, err_l, N1=7, N2=7):
    """Method 3.3 a_k/b_k factors when leg k's Type III directions fill a cap of
    half-angle ``cap`` about the base normal, without position or leg-length
    limits (Euler bound kept at the default ±20°): isolates the effect of the
    direction spread on the sphere fit (17)."""
    ws = dict(pmin=[-1e3, -1e3, -1e3], pmax=[1e3, 1e3, 1e3], angle=20, legs=[0.1, 1e3])
    rob = make_robot(ws)
    T2 = generate_type2(rob, K, n_sets, N1, rng)
    b, _ = solve_type2(*_pr(add_uniform_noise(T2, rng, err_p, err_a)))
    out = {"cap_deg": list(caps_deg), "factor_a": [], "factor_b": _mean_err_cm(b, rob.b[K])}
    for cap in caps_deg:
        T3 = generate_type3(rob, K, n_sets, N2, rng, max_tilt=np.radians(cap))
        a, _ = solve_type3(*_pr(add_uniform_noise(T3, rng, err_p, err_a)), b)
        out["factor_a"].append(_mean_err_cm(a, rob.a[K]))
    return out


def _pr(T):
    return T[..., :3, 3], T[..., :3, :3]


def _div(xs, err_cm):
    return [x / err_cm for x in xs]


def run(n_sets: int, Ns, N1s, N2s, Ns_ik, seed: int = 0, sensitivity: bool = True) -> dict:
    err_cm = 0.01
    e = (err_cm * CM, np.radians(err_cm), err_cm * CM)
    robot = make_robot(workspaces()["default"])
    rng = np.random.default_rng(seed)
    out: dict = {"config": {
        "robot": "left_hand (Daney 1998)", "leg": K + 1, "n_sets": n_sets,
        "workspace_cm_deg": workspaces()["default"],
        "noise": {"err_p_cm": err_cm, "err_a_deg": err_cm, "err_l_cm": err_cm, "distribution": "uniform"},
        "euler_convention": "ZYX: R = Rz(psi) Ry(theta) Rx(phi)",
        "factor": "mean ||estimate - truth|| (cm) / err (cm); err_a in degrees numerically equal to err",
        "seed": seed}}
    fb, fp, cond = method_3_2(robot, rng, n_sets, Ns, *e)
    out["method_3_2"] = {"N": list(Ns), "factor_base": _div(fb, err_cm), "factor_platform": _div(fp, err_cm),
                         "median_condition": cond}
    eb, ea, _, e_off = method_3_3(robot, rng, n_sets, N1s, N2s, *e)
    fa = _div(ea, err_cm)
    out["method_3_3"] = {"N1": list(N1s), "factor_b": _div(eb, err_cm), "N2": list(N2s), "factor_a": fa,
                         "N1_for_a": 7, "factor_a_N1_N2_7": fa[list(N2s).index(7)] if 7 in N2s else None,
                         "factor_offset_single_pose": e_off / err_cm}
    out["b_examples"] = {}
    for amp in (0.01, 0.001):
        r2 = np.random.default_rng(seed + 1)
        T2 = generate_type2(robot, K, n_sets, 7, r2)
        T2n = add_uniform_noise(T2, r2, amp * CM, np.radians(amp))
        b, _ = solve_type2(T2n[..., :3, 3], T2n[..., :3, :3])
        out["b_examples"][str(amp)] = {"b_cm": (b[0] / CM).tolist(), "mean_error_cm": _mean_err_cm(b, robot.b[K]),
                                       "factor": _mean_err_cm(b, robot.b[K]) / amp, "true_b_cm": (robot.b[K] / CM).tolist()}
    ik = ik_baseline(robot, rng, n_sets, Ns_ik, *e)
    for key in ("factor_base", "factor_platform"):
        ik["model36"][key] = _div(ik["model36"][key], err_cm)
    for key in ("factor_a", "factor_b", "factor_offset"):
        ik["model42"][key] = _div(ik["model42"][key], err_cm)
    out["ik_unconstrained"] = ik
    # separate noise sources at N = 7
    src = {}
    for name, ee in (("position", (e[0], 0, 0)), ("orientation", (0, e[1], 0)), ("length", (0, 0, e[2]))):
        r3 = np.random.default_rng(seed + 2)
        fb7, fp7, _ = method_3_2(robot, r3, n_sets, [7], *ee)
        eb7, ea7, _, _ = method_3_3(robot, r3, n_sets, [7], [7], *ee)
        src[name] = {"3.2_base": fb7[0] / err_cm, "3.2_platform": fp7[0] / err_cm,
                     "3.3_a": ea7[0] / err_cm, "3.3_b": eb7[0] / err_cm}
    out["noise_sources"] = src
    cap = direction_cap_sweep(np.random.default_rng(seed + 4), n_sets, [15, 25, 35, 45, 60, 75, 90], *e)
    cap["factor_a"] = _div(cap["factor_a"], err_cm)
    cap["factor_b"] = cap["factor_b"] / err_cm
    out["direction_cap_sweep"] = cap
    if sensitivity:
        sens = {}
        for name, ws in workspaces().items():
            rob = make_robot(ws)
            r4 = np.random.default_rng(seed + 3)
            fb7, fp7, _ = method_3_2(rob, r4, n_sets, [7], *e)
            eb7, ea7, _, _ = method_3_3(rob, r4, n_sets, [7], [7], *e)
            ikw = ik_baseline(rob, r4, n_sets, [7, 14], *e)
            sens[name] = {"workspace_cm_deg": ws, "3.2_base": fb7[0] / err_cm, "3.2_platform": fp7[0] / err_cm,
                          "3.3_a": ea7[0] / err_cm, "3.3_b": eb7[0] / err_cm,
                          "ik36_N7_base": ikw["model36"]["factor_base"][0] / err_cm,
                          "ik36_N7_platform": ikw["model36"]["factor_platform"][0] / err_cm,
                          "ik42_N14_a": ikw["model42"]["factor_a"][0] / err_cm,
                          "ik42_N14_b": ikw["model42"]["factor_b"][0] / err_cm}
        out["workspace_sensitivity"] = sens
    return out


def _at(xs, Ns, n):
    return xs[list(Ns).index(n)] if n in Ns else float("nan")


def report(out: dict) -> str:
    m2, m3, ik = out["method_3_2"], out["method_3_3"], out["ik_unconstrained"]
    L = []
    L.append(f"Daney (1998) on the Left Hand, leg {out['config']['leg']}, {out['config']['n_sets']} pose sets per N, "
             f"uniform noise 0.01 cm / 0.01 deg / 0.01 cm. Factor = mean error (cm) / 0.01.")
    L.append("")
    L.append("| quantity | paper | this run |")
    L.append("|---|---|---|")
    L.append(f"| 3.2 base point a_k, N = 7 | ≈ 13 | {_at(m2['factor_base'], m2['N'], 7):.2f} |")
    L.append(f"| 3.2 platform point b_k, N = 7 | ≈ 1.4 | {_at(m2['factor_platform'], m2['N'], 7):.2f} |")
    L.append(f"| 3.3 b_k, N1 = 7 | ≈ 1.2 (from the two b_k values) | {_at(m3['factor_b'], m3['N1'], 7):.2f} |")
    fa7 = m3["factor_a_N1_N2_7"]
    L.append(f"| 3.3 a_k, N1 = N2 = 7 | ≈ 2.8 | {fa7 if fa7 is None else f'{fa7:.2f}'} |")
    L.append(f"| 3.3 Δρ_k (one pose, eq. 19) | ≈ largest noise | {m3['factor_offset_single_pose']:.2f} |")
    L.append(f"| IK (unconstrained) Model 36, N = 7: a_k / b_k | — | "
             f"{_at(ik['model36']['factor_base'], ik['N'], 7):.2f} / {_at(ik['model36']['factor_platform'], ik['N'], 7):.2f} |")
    L.append(f"| IK (unconstrained) Model 42, N = 14: a_k / b_k / Δρ_k | — | "
             f"{_at(ik['model42']['factor_a'], ik['model42']['N'], 14):.2f} / "
             f"{_at(ik['model42']['factor_b'], ik['model42']['N'], 14):.2f} / "
             f"{_at(ik['model42']['factor_offset'], ik['model42']['N'], 14):.2f} |")
    L.append("")
    L.append("b_k from N1 = 7 Type II poses (first set; true b_3 = [7.822, -1.052, 0] cm):")
    L.append("")
    L.append("| err | paper b_k (cm) | this run b_k (cm) | mean ‖b − b_true‖ (cm) |")
    L.append("|---|---|---|---|")
    paper = {"0.01": "[7.8291, −1.05809, 0.007995]", "0.001": "[7.82149, −1.052215, 0.0011]"}
    for amp, v in out["b_examples"].items():
        b = ", ".join(f"{x:.6g}" for x in v["b_cm"])
        L.append(f"| {amp} cm / {amp}° | {paper[amp]} | [{b}] | {v['mean_error_cm']:.3g} |")
    L.append("")
    L.append("Factor curves (method 3.2 over N; method 3.3: b over N1, a over N2 with b from N1 = 7; "
             "IK = unconstrained inverse-kinematics calibration of the same leg on N random poses):")
    L.append("")
    L.append("| N | 3.2 a_k | 3.2 b_k | 3.3 b_k (N1=N) | 3.3 a_k (N2=N) | IK36 a_k | IK36 b_k | IK42 a_k | IK42 b_k |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    allN = sorted(set(m2["N"]) | set(m3["N1"]) | set(m3["N2"]))
    show = [n for n in allN if n <= 10 or n % 5 == 0]

    def f(xs, Ns, n):
        return f"{xs[list(Ns).index(n)]:.2f}" if n in Ns else ""

    for n in show:
        L.append(f"| {n} | {f(m2['factor_base'], m2['N'], n)} | {f(m2['factor_platform'], m2['N'], n)} | "
                 f"{f(m3['factor_b'], m3['N1'], n)} | {f(m3['factor_a'], m3['N2'], n)} | "
                 f"{f(ik['model36']['factor_base'], ik['N'], n)} | {f(ik['model36']['factor_platform'], ik['N'], n)} | "
                 f"{f(ik['model42']['factor_a'], ik['model42']['N'], n)} | {f(ik['model42']['factor_b'], ik['model42']['N'], n)} |")
    nc = [f"Model {m} N = {n}: {r} ({o} left out)" for m, Ns_m in (("36", ik["N"]), ("42", ik["model42"]["N"]))
          for n, r, o in zip(Ns_m, ik[f"model{m}"]["refitted"], ik[f"model{m}"]["left_out"]) if r]
    L.append("")
    L.append("IK baseline: batched Gauss–Newton from the true values, iterated until the step is below 1e-12 m; "
             "the sets where it does not get there in 100 iterations (near-singular sets with few poses) are "
             "refitted one by one with the shared LM (estcal.workflows.gough.calibrate_gough); a set left out "
             "is one where no estimator converged on all the leg's parameters — "
             + ("; ".join(nc) if nc else "none") + f" of {out['config']['n_sets']} sets.")
    L.append("")
    L.append("Separate noise sources at N = 7 (factor still divided by 0.01):")
    L.append("")
    L.append("| noise only on | 3.2 a_k | 3.2 b_k | 3.3 a_k | 3.3 b_k |")
    L.append("|---|---|---|---|---|")
    for name, v in out["noise_sources"].items():
        L.append(f"| {name} | {v['3.2_base']:.2f} | {v['3.2_platform']:.2f} | {v['3.3_a']:.2f} | {v['3.3_b']:.2f} |")
    if "direction_cap_sweep" in out:
        cap = out["direction_cap_sweep"]
        L.append("")
        L.append("Method 3.3, N1 = N2 = 7, Type III leg directions uniform in a cap of half-angle c about the "
                 f"base normal, no position/leg limits (3.3.1 b_k factor {cap['factor_b']:.2f}):")
        L.append("")
        L.append("| c (deg) | " + " | ".join(str(c) for c in cap["cap_deg"]) + " |")
        L.append("|---|" + "---|" * len(cap["cap_deg"]))
        L.append("| 3.3 a_k factor | " + " | ".join(f"{x:.2f}" for x in cap["factor_a"]) + " |")
    if "workspace_sensitivity" in out:
        L.append("")
        L.append("Workspace sensitivity at N = 7 (N1 = N2 = 7; IK42 at N = 14):")
        L.append("")
        L.append("| workspace | box x,y / z (cm) | Euler bound | leg length (cm) | 3.2 a_k | 3.2 b_k | 3.3 a_k | 3.3 b_k | IK36 a_k | IK36 b_k | IK42 a_k | IK42 b_k |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for name, v in out["workspace_sensitivity"].items():
            ws = v["workspace_cm_deg"]
            L.append(f"| {name} | ±{ws['pmax'][0]} / {ws['pmin'][2]}–{ws['pmax'][2]} | ±{ws['angle']}° | "
                     f"{ws['legs'][0]}–{ws['legs'][1]} | {v['3.2_base']:.2f} | {v['3.2_platform']:.2f} | "
                     f"{v['3.3_a']:.2f} | {v['3.3_b']:.2f} | {v['ik36_N7_base']:.2f} | {v['ik36_N7_platform']:.2f} | "
                     f"{v['ik42_N14_a']:.2f} | {v['ik42_N14_b']:.2f} |")
    return "\n".join(L)


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m2, m3, ik = out["method_3_2"], out["method_3_3"], out["ik_unconstrained"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    ax[0].semilogy(m2["N"], m2["factor_base"], "C0-", label="3.2 base point $a_k$")
    ax[0].semilogy(m2["N"], m2["factor_platform"], "C1-", label="3.2 platform point $b_k$")
    ax[0].semilogy(ik["N"], ik["model36"]["factor_base"], "C0--", label="IK Model 36 $a_k$")
    ax[0].semilogy(ik["N"], ik["model36"]["factor_platform"], "C1--", label="IK Model 36 $b_k$")
    ax[0].axhline(13, color="C0", lw=0.6, ls=":")
    ax[0].axhline(1.4, color="C1", lw=0.6, ls=":")
    ax[0].set_xlabel("number of poses N (Type I)")
    ax[0].set_ylabel("output / input error factor")
    ax[0].set_title("Method 3.2 (fixed direction)")
    ax[0].legend(fontsize=8)
    ax[1].semilogy(m3["N1"], m3["factor_b"], "C1-", label="3.3.1 $b_k$ vs $N_1$")
    ax[1].semilogy(np.array(m3["N2"]) + m3["N1_for_a"], m3["factor_a"], "C0-",
                   label="3.3.2 $a_k$ vs $N_1 + N_2$ ($N_1$ = 7)")
    ax[1].semilogy(ik["model42"]["N"], ik["model42"]["factor_a"], "C0--", label="IK Model 42 $a_k$ vs N")
    ax[1].semilogy(ik["model42"]["N"], ik["model42"]["factor_b"], "C1--", label="IK Model 42 $b_k$ vs N")
    ax[1].axhline(2.8, color="C0", lw=0.6, ls=":")
    ax[1].set_xlabel("number of measured poses ($N_1$, $N_1 + N_2$ or N)")
    ax[1].set_title("Method 3.3 (Type II then III)")
    ax[1].legend(fontsize=8)
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"Left Hand, leg 3, uniform noise 0.01 cm / 0.01°, {out['config']['n_sets']} sets per N "
                 "(dotted: paper's factors)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def update_docs(text: str, doc: Path) -> None:
    begin, end = "<!-- BEGIN daney_left_hand.py output -->", "<!-- END daney_left_hand.py output -->"
    s = doc.read_text()
    if begin not in s or end not in s:
        raise SystemExit(f"{doc}: markers {begin!r} / {end!r} not found")
    i, j = s.index(begin) + len(begin), s.index(end)
    doc.write_text(s[:i] + "\n" + text + "\n" + s[j:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="50 sets and a few N (smoke test)")
    ap.add_argument("--sets", type=int, default=None, help="pose sets per N (default 1000, quick 50)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    ap.add_argument("--png", type=Path, default=None, help="write the factor curves (PNG)")
    ap.add_argument("--docs", action="store_true", help="refresh the results section of docs/parallel.md")
    args = ap.parse_args(argv)
    t0 = time.time()
    if args.quick:
        n_sets = args.sets or 50
        Ns, N1s, N2s, Nik = [4, 7, 12], [4, 7, 12], [5, 7, 12], [7, 14]
    else:
        n_sets = args.sets or 1000
        Ns, N1s, N2s, Nik = list(range(4, 51)), list(range(4, 31)), list(range(5, 31)), list(range(7, 51))
    out = run(n_sets, Ns, N1s, N2s, Nik, args.seed, sensitivity=True)
    out["config"]["runtime_s"] = round(time.time() - t0, 1)
    text = report(out)
    print(text)
    print(f"\n(run time {out['config']['runtime_s']} s)")
    if args.json:
        write_json(args.json, out)
    if args.png:
        args.png.parent.mkdir(parents=True, exist_ok=True)
        plot(out, args.png)
    if args.docs:
        cmd = "python experiments/daney_left_hand.py" + (" --quick" if args.quick else "") + \
              (f" --sets {args.sets}" if args.sets else "") + " --png docs/parallel_daney_factors.png --docs"
        update_docs(f"_Generated by `{cmd}` (seed {args.seed}, {out['config']['runtime_s']} s)._\n\n" + text,
                    ROOT / "docs" / "parallel.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
