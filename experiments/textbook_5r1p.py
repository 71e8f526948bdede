"""The textbook's 5R1P simulation study (Mooring–Roth–Driels §4.6, Driels & Pathre; digest §5.2, Tables 4.2–4.7).

Set-up as in the book (documented choices where it is silent):

* robot :func:`estcal.kinematics.robot_5r1p` (Table 4.1, inches → m), world = frame 0
  (no base parameters), measured point = origin of frame 6 (position only);
* the **21 identified parameters**: standard DH ``alpha_1..5`` (α6 is not observable
  with position only and stays fixed), ``a_1, a_2, a_4, a_5, a_6`` (l3 = 0 forced by the
  prismatic joint), ``d_1, d_2, d_3, d_5, d_6`` (r4 = 0 forced; ``d_3`` is the prismatic
  joint's offset) and ``theta_1..6`` (joint offsets; θ3 is the prismatic link's constant);
* truth = nominal + initial errors of 5° on every angle and 0.5 in on every length,
  random signs (the book's default "initial errors 5° and 0.5 in"), except that the
  tool lengths a_6, d_6 err by at most 20 % of the tool distance (else the short tools
  of Table 4.2 would vanish); the fit starts from the nominal model;
* noise uniform with half-widths ε_m/2 on each measured coordinate (in) and ε_e/2 on
  each joint reading (deg, in for the prismatic joint); defaults 0.001 / 0.001;
  values stored with 4 decimals (in / deg) — the book's "4 stored digits";
* defaults: l6 = r6 = 10 in, strategy S4 (:mod:`estcal.simulate.strategies`),
  m = 36 poses, joint range N;
* δrms = RMS of the parameter errors after calibration, angles (deg) / lengths (in),
  and κ = κ(JᵀJ) = cond(J)² of the unscaled Jacobian (inches, degrees) at the
  true parameters, as the book defines κ (4.174, see the digest's errata). Each cell is
  the RMS over ``reps`` repetitions (independent truth, poses and noise; κ: median),
  with the delta-method standard error of the RMS, se = sd(δ²)/(2·RMS·√reps).
  Table 4.6 uses ``reps46`` repetitions (default 200): its S3-vs-S4 separation at
  m = 36 is ~20 % of δrms, which 10 repetitions cannot resolve.

Strategies S1–S4 (:mod:`estcal.simulate.strategies`): S1 all joints stepped together,
S2 one joint at a time, S3 one joint held at home while the others step together
(S2's complement), S4 independent uniform draws. The book ranks S4 > S3 > S2 ≫ S1.

Tables: 4.2 (tool distance), 4.5 (noise), 4.6 (strategy × m), 4.7 (joint range ×
strategy, l6 = r6 = 5 in). For each, the book's and our values side by side and
whether the orderings match (Kendall's τ between the two sequences, per table, in
``kendall_tau``; "match" = same ranking of the book's clearly separated cases, listed
in ``checks``).

``--json PATH`` keys: ``config``, ``tables`` ({table: [{case, ours: {angle, length,
kappa, failures, reps, angle_se, length_se}, book: {angle, length, kappa}}]}),
``checks`` ({name: bool}), ``kendall_tau`` ({table: {angle, length, kappa}}, null
where fewer than 3 book values), ``separation_46`` ({"S4<S3", "S3<S2", "S2<S1":
z = angle difference / its standard error at m = 36}).
``--quick``: 3 repetitions (100 for Table 4.6) and fewer cases.
"""
from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.estimate import calibrate_lsq  # noqa: E402
from estcal.io.dataset import dataset_from_arrays  # noqa: E402
from estcal.kinematics import robot_5r1p  # noqa: E402
from estcal.methods import NoiseModel, Problem  # noqa: E402
from estcal.simulate.strategies import generate_poses  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

IN = 0.0254
DEG = np.pi / 180
FREE = (["alpha_1", "alpha_2", "alpha_3", "alpha_4", "alpha_5"] + ["a_1", "a_2", "a_4", "a_5", "a_6"]
        + ["d_1", "d_2", "d_3", "d_5", "d_6"] + [f"theta_{j}" for j in range(1, 7)])
ANGLES = [n for n in FREE if n.startswith(("alpha", "theta"))]
RANGES = {  # theta1 (deg), theta2 (deg), r3 (in); wrist full range
    "N": ((0, 300), (-120, 120), (12, 48)), "F": ((0, 360), (-180, 180), (12, 48)),
    "H": ((0, 180), (-90, 90), (30, 48)), "Q": ((0, 90), (-45, 45), (39, 48)), "E": ((0, 45), (-22, 22), (44, 48))}
BOOK = {
    "4.2": {10: (0.00078, 0.00017, 260), 5: (0.0016, 0.00020, 252), 1: (0.0083, 0.00021, 373),
            0.5: (0.017, 0.00022, 480), 0.1: (0.049, 0.00028, 1848)},
    "4.5": {(0, 0): (0.00007, 0.00002, None), (0, 0.001): (0.0004, 0.0002, None),
            (0.0001, 0.001): (0.0004, 0.0002, None), (0.001, 0.001): (0.0008, 0.0002, None),
            (0.01, 0.001): (0.006, 0.001, None)},
    "4.6": {("S1", 7): (0.032, 0.013, 23020), ("S1", 36): (0.0078, 0.0037, 20024), ("S1", 90): (0.0044, 0.0020, 21664),
            ("S1", 180): (0.0047, 0.0025, 22307), ("S1", 360): (0.0054, 0.0019, 22650),
            ("S2", 36): (0.0018, 0.00028, 1203), ("S2", 90): (0.0010, 0.00026, 1138),
            ("S2", 180): (0.0012, 0.00019, 1119), ("S2", 360): (0.00045, 0.00013, 1110),
            ("S3", 36): (0.0013, 0.00048, 364), ("S3", 90): (0.00065, 0.00021, 396),
            ("S3", 180): (0.00089, 0.00010, 420), ("S3", 360): (0.00032, 0.000090, 434),
            ("S4", 12): (0.0021, 0.00029, 539), ("S4", 36): (0.00078, 0.00017, 260), ("S4", 90): (0.00079, 0.00011, 209),
            ("S4", 180): (0.00042, 0.00011, 204), ("S4", 360): (0.00030, 0.00010, 189)},
    "4.7": {("S1", "F"): (0.015, 0.0033, 16375), ("S1", "H"): (0.030, 0.016, 47802), ("S1", "Q"): (0.196, 0.089, 303101),
            ("S1", "E"): (None, None, 1e6),
            ("S2", "F"): (0.0032, 0.00044, 1260), ("S2", "H"): (0.0024, 0.00045, 1393), ("S2", "Q"): (0.0037, 0.0011, 3330),
            ("S2", "E"): (0.010, 0.0027, 9260),
            ("S3", "F"): (0.0011, 0.00019, 282), ("S3", "H"): (0.0020, 0.00069, 909), ("S3", "Q"): (0.0010, 0.00041, 2579),
            ("S3", "E"): (0.0067, 0.0023, 6640),
            ("S4", "F"): (0.0013, 0.00020, 239), ("S4", "H"): (0.0016, 0.00076, 501), ("S4", "Q"): (0.0024, 0.0017, 1696),
            ("S4", "E"): (0.0069, 0.0041, 4804)},
}


def make_robot(tool_in=10.0, rng_name="N"):
    robot = robot_5r1p(tool_in)
    lim = np.array(robot.limits, float).copy()
    t1, t2, r3 = RANGES[rng_name]
    lim[0] = np.array(t1) * DEG
    lim[1] = np.array(t2) * DEG
    lim[2] = np.array(r3) * IN
    rob = robot.copy()
    rob.limits = lim
    return rob


def one_run(robot, rng, m=36, strategy="S4", eps_m=0.001, eps_e=0.001, digits=4):
    """One calibration: returns (δrms angle deg, δrms length in, κ, ok)."""
    pv = robot.params
    idx = pv.indices(FREE)
    truth = pv.values.copy()
    is_ang = np.array([n in ANGLES for n in FREE])
    signs = rng.choice([-1.0, 1.0], len(FREE))
    mag = np.where(is_ang, 5 * DEG, 0.5 * IN)
    # the tool lengths keep their intended size: a 0.5 in error on a 0.1–0.5 in tool would
    # make the truth's tool vanish (θ6 unobservable), which is not what Table 4.2 studies
    tool = abs(pv["a_6"])
    for k, n in enumerate(FREE):
        if n in ("a_6", "d_6"):
            mag[k] = min(mag[k], 0.2 * tool)
    truth[idx] += signs * mag
    q = generate_poses(robot, m, strategy, rng)
    p = robot.kinematics(q, truth, jacobian=False).p
    # measurement: uniform ±ε_m/2 (in) per coordinate, stored with `digits` decimals (in)
    meas_in = p / IN + rng.uniform(-eps_m / 2, eps_m / 2, p.shape)
    prism = np.array([t == "prismatic" for t in robot.joint_types])
    q_units = np.where(prism, q / IN, q / DEG)  # in / deg
    read_units = q_units + rng.uniform(-eps_e / 2, eps_e / 2, q.shape)
    if digits is not None:
        meas_in = np.round(meas_in, digits)
        read_units = np.round(read_units, digits)
    readings = np.where(prism, read_units * IN, read_units * DEG)
    ds = dataset_from_arrays(robot.joint_names, readings, points=meas_in * IN)
    sig = max(eps_m / 2 / np.sqrt(3), 1e-6) * IN
    prob = Problem(robot, [("position", ds, NoiseModel(position=sig))])
    try:
        res = calibrate_lsq(prob, "lm", free=FREE, max_iter=100, check=False)
    except (np.linalg.LinAlgError, ValueError):
        return np.nan, np.nan, np.inf, False
    est = dict(zip(res.names, res.estimate))
    err = np.array([est[n] - truth[pv.index(n)] for n in FREE])
    ang = np.sqrt(np.mean((err[is_ang] / DEG) ** 2))
    length = np.sqrt(np.mean((err[~is_ang] / IN) ** 2))
    # κ(JᵀJ) of the unscaled Jacobian in the book's units (rows in inches, columns per inch / per
    # degree), at the true parameters: a property of the poses, not of where a fit ended
    rows = prob.evaluate(truth)
    J = rows.H[:, idx] / IN
    J[:, ~is_ang] *= IN  # length columns: d(in)/d(in)
    J[:, is_ang] *= DEG  # angle columns: d(in)/d(deg)
    s = np.linalg.svd(J, compute_uv=False)
    kappa = float((s[0] / s[-1]) ** 2) if s[-1] > 0 else np.inf
    ok = bool(res.converged and np.isfinite(ang) and ang < 5.0)
    return float(ang), float(length), kappa, ok


def cell(reps, seed, key, **kw):
    tool = kw.pop("tool", 10.0)
    rname = kw.pop("range", "N")
    robot = make_robot(tool, rname)
    a, l_, k, nf = [], [], [], 0
    for r in range(reps):
        rng = np.random.default_rng([seed, zlib.crc32(str(key).encode()), r])  # deterministic per cell
        ang, length, kappa, ok = one_run(robot, rng, **kw)
        if ok:
            a.append(ang)
            l_.append(length)
        else:
            nf += 1
        k.append(kappa)
    def rms(v):
        return float(np.sqrt(np.mean(np.square(v)))) if v else None

    def se(v):  # delta method: RMS = sqrt(mean δ²), se(mean δ²) = sd(δ²)/√n
        if len(v) < 2:
            return None
        r = rms(v)
        return float(np.std(np.square(v), ddof=1) / np.sqrt(len(v)) / (2 * r)) if r > 0 else 0.0

    return {"angle": rms(a), "length": rms(l_), "kappa": float(np.median(k)), "failures": nf, "reps": reps,
            "angle_se": se(a), "length_se": se(l_)}


def _tau(book, ours):
    pairs = [(b, o) for b, o in zip(book, ours) if b is not None and o is not None]
    if len(pairs) < 3:
        return None
    return float(stats.kendalltau([p[0] for p in pairs], [p[1] for p in pairs]).statistic)


def run(reps=10, seed=0, quick=False, reps46=200):
    tables = {}
    # Table 4.2: tool distance
    tools = [10, 5, 1, 0.5, 0.1] if not quick else [10, 1, 0.1]
    tables["4.2"] = [{"case": {"tool_in": t}, "ours": cell(reps, seed, ("4.2", t), tool=t),
                      "book": dict(zip(("angle", "length", "kappa"), BOOK["4.2"][t]))} for t in tools]
    # Table 4.5: noise
    noises = list(BOOK["4.5"]) if not quick else [(0, 0), (0.001, 0.001), (0.01, 0.001)]
    tables["4.5"] = [{"case": {"eps_m_half": em, "eps_e_half": ee},
                      "ours": cell(reps, seed, ("4.5", em, ee), eps_m=2 * em, eps_e=2 * ee),
                      "book": dict(zip(("angle", "length", "kappa"), BOOK["4.5"][(em, ee)]))} for em, ee in noises]
    # Table 4.6: strategy x m
    cases = list(BOOK["4.6"]) if not quick else [("S1", 36), ("S2", 36), ("S3", 36), ("S4", 36)]
    tables["4.6"] = [{"case": {"strategy": s, "m": m}, "ours": cell(reps46, seed, ("4.6", s, m), strategy=s, m=m),
                      "book": dict(zip(("angle", "length", "kappa"), BOOK["4.6"][(s, m)]))} for s, m in cases]
    # Table 4.7: joint range x strategy (m = 36, l6 = r6 = 5)
    cases = list(BOOK["4.7"]) if not quick else [("S4", "F"), ("S4", "Q"), ("S4", "E")]
    tables["4.7"] = [{"case": {"strategy": s, "range": rg},
                      "ours": cell(reps, seed, ("4.7", s, rg), strategy=s, range=rg, tool=5.0),
                      "book": dict(zip(("angle", "length", "kappa"), BOOK["4.7"][(s, rg)]))} for s, rg in cases]
    checks = ordering_checks(tables)
    config = {"reps": reps, "reps46": reps46, "seed": seed, "quick": quick, "free": FREE, "default": {
        "tool_in": 10, "strategy": "S4", "m": 36, "range": "N", "eps_m": 0.001, "eps_e": 0.001, "digits": 4,
        "initial_errors": "5 deg / 0.5 in, random signs"}}
    return {"config": config, "tables": tables, "checks": checks, "kendall_tau": kendall_taus(tables),
            "separation_46": separation_46(tables)}


def _by_strategy(rows):
    by_s = {}
    for r in rows:
        by_s.setdefault(r["case"]["strategy"], {})[r["case"]["m"]] = r["ours"]
    return by_s


def separation_46(tables):
    """z = (δrms angle of the worse − of the better strategy) / its standard error, m = 36, book order."""
    by_s = _by_strategy(tables["4.6"])
    out = {}
    for better, worse in (("S4", "S3"), ("S3", "S2"), ("S2", "S1")):
        b, w = by_s.get(better, {}).get(36), by_s.get(worse, {}).get(36)
        if b and w and None not in (b["angle"], w["angle"], b["angle_se"], w["angle_se"]):
            den = np.hypot(b["angle_se"], w["angle_se"])
            out[f"{better}<{worse}"] = float((w["angle"] - b["angle"]) / den) if den > 0 else None
    return out


def kendall_taus(tables):
    return {name: {q: _tau([r["book"][q] for r in rows], [r["ours"][q] for r in rows])
                   for q in ("angle", "length", "kappa")} for name, rows in tables.items()}


def ordering_checks(tables):
    """Orderings the book establishes clearly, evaluated on our numbers."""
    chk = {}
    t42 = tables["4.2"]
    ang = [r["ours"]["angle"] for r in t42]
    kap = [r["ours"]["kappa"] for r in t42]
    chk["4.2 angle error grows as the tool distance shrinks"] = bool(all(np.diff(ang) > 0))
    chk["4.2 kappa largest for the shortest tool"] = bool(kap[-1] == max(kap))
    t45 = tables["4.5"]
    a45 = [r["ours"]["angle"] for r in t45]
    chk["4.5 noise-free best, largest measurement noise worst (angle)"] = bool(a45[0] == min(a45) and a45[-1] == max(a45))
    by_s = _by_strategy(tables["4.6"])
    if all(s in by_s and 36 in by_s[s] for s in ("S1", "S2", "S3", "S4")):
        k36 = [by_s[s][36]["kappa"] for s in ("S4", "S3", "S2", "S1")]
        chk["4.6 kappa at m=36: S4 < S3 < S2, S1 > 5 S2 (book S4 > S3 > S2 >> S1)"] = bool(
            k36[0] < k36[1] < k36[2] and k36[3] > 5 * k36[2])
        a36 = [by_s[s][36]["angle"] or np.inf for s in ("S4", "S3", "S2", "S1")]
        chk["4.6 angle error at m=36: S4 < S3 < S2 < S1 (book ranking)"] = bool(np.all(np.diff(a36) > 0))
        z = separation_46(tables).get("S4<S3")
        chk["4.6 S4 < S3 angle at m=36 resolved (> 2 standard errors)"] = bool(z is not None and z > 2)
    if "S4" in by_s and len(by_s["S4"]) > 2:
        ms = sorted(by_s["S4"])
        a = [by_s["S4"][m]["angle"] for m in ms]
        chk["4.6 S4 angle error falls from m=12 to m=360"] = bool(a[0] > a[-1])
        k4 = [by_s["S4"][m]["kappa"] for m in ms]
        chk["4.6 S4 kappa falls from m=12 to m=360 (book 539 -> 189)"] = bool(k4[-1] < k4[0])
    if "S3" in by_s and len(by_s["S3"]) > 2:
        k3 = [by_s["S3"][m]["kappa"] for m in sorted(by_s["S3"])]
        chk["4.6 S3 kappa does not fall from m=36 to m=360 (book 364 -> 434)"] = bool(k3[-1] >= k3[0])
    t47 = tables["4.7"]
    for s in ("S2", "S3", "S4"):
        rows = [r for r in t47 if r["case"]["strategy"] == s]
        if len(rows) >= 3:
            k = [r["ours"]["kappa"] for r in rows]  # F, H, Q, E
            chk[f"4.7 {s}: kappa grows as the joint range shrinks (F < E)"] = bool(k[0] < k[-1])
            a = [r["ours"]["angle"] or np.inf for r in rows]
            chk[f"4.7 {s}: angle error worst at the smallest range E"] = bool(a[-1] == max(a))
    for name, tau in kendall_taus(tables).items():
        chk[f"{name} Kendall tau (book vs ours) of the angle error > 0"] = (
            None if tau["angle"] is None else bool(tau["angle"] > 0))
    return chk


def _f(v, nd=5):
    return f"{v:.{nd}f}" if isinstance(v, (int, float)) and v is not None and np.isfinite(v) else "—"


def _k(v):
    return f"{v:.0f}" if v is not None and np.isfinite(v) else "inf"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--reps", type=int, default=10, help="repetitions per cell, Tables 4.2, 4.5, 4.7")
    ap.add_argument("--reps46", type=int, default=200, help="repetitions per cell, Table 4.6 (quick: 100)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    out = run(3 if a.quick else a.reps, a.seed, a.quick, 100 if a.quick else a.reps46)
    print(f"5R1P study (Driels & Pathre; textbook Tables 4.2-4.7): {len(FREE)} parameters, "
          f"{out['config']['reps']} repetitions per cell ({out['config']['reps46']} in Table 4.6); "
          f"δrms angle (deg) / length (in), κ = cond(J)²")
    for name, rows in out["tables"].items():
        print(f"\nTable {name}")
        print(f"  {'case':<34} {'ours angle (±se) / length':>34} {'κ':>9} {'fail':>4} | "
              f"{'book angle/length':>20} {'κ':>7}")
        for r in rows:
            o, b = r["ours"], r["book"]
            case = ", ".join(f"{k}={v}" for k, v in r["case"].items())
            print(f"  {case:<34} {_f(o['angle']):>10} (±{_f(o['angle_se'])}) / {_f(o['length'], 6):>9} "
                  f"{_k(o['kappa']):>9} "
                  f"{o['failures']:>4} | {_f(b['angle']):>9} / {_f(b['length'], 6):>8} {_k(b['kappa']) if b['kappa'] else '—':>7}")
    print("\nKendall τ, book vs ours: " + "; ".join(
        f"{name}: " + ", ".join(f"{q} {_f(v, 2) if v is not None else '—'}" for q, v in t.items())
        for name, t in out["kendall_tau"].items()))
    print("Table 4.6, m = 36, angle-error separation in standard errors (book order): " + ", ".join(
        f"{k} z = {_f(v, 1)}" for k, v in out["separation_46"].items()))
    print("\nordering checks:")
    for k, v in out["checks"].items():
        print(f"  [{'ok' if v else ('--' if v is None else 'NO')}] {k}")
    if a.json:
        write_json(a.json, out, announce=True)
    return out


if __name__ == "__main__":
    main()
