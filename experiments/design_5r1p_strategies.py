"""Textbook 5R1P study (Mooring–Roth–Driels §4.6, Tables 4.6–4.7): condition number by strategy and range.

Robot: ``robot_5r1p()`` (Table 4.1; l6 = r6 = 10 in for Table 4.6, 5 in for
Table 4.7), position-only measurement, the book's 21 parameters: θ, d, a, α of
every link (θ3 constant and d3 the offset of the prismatic joint) minus l3 = a_3
and r4 = d_4 (dependent through the prismatic joint) and α6 (not seen by a
point), no base frame. Strategies come from :mod:`estcal.simulate.strategies`
(S1 all joints together, S2 one joint at a time, S3 one joint held at home
while the others step together — S2's complement — and S4 uniform random;
S1–S3 are deterministic).

κ is the book's quantity ``κ(JᵀJ) = (s_max/s_min)²`` (digest §5.1: the book's
"κ(J)" of (4.174)), computed in the book's units (inches for lengths, radians
for angles: position rows in inches, angle columns in in/rad). The random
strategy S4 reports the median over ``--seeds`` draws. The book's
simulated δrms also depends on encoder noise, rounding and the nonlinear
solver; we add the *predicted* δrms from the covariance σ²(JᵀJ)⁻¹ with the
book's measurement noise only (uniform, half-width 0.001 in → σ = 0.001/√3 in),
RMS over the angle parameters (deg) and the length parameters (in). As the
digest warns, absolute κ values depend on undocumented details — compare
orderings. (No unit choice we tried — in/rad, in/deg, ft/rad, mm/rad, unit
columns — reproduces the printed κ; ft/rad comes closest for S4.)

Run: ``python experiments/design_5r1p_strategies.py [--quick] [--json PATH] [--seeds N]``

JSON keys: ``parameters`` (the 21 names), ``table46`` {S: {m: {kappa, book_kappa,
drms_angle_deg, drms_length_in, book_drms}}}, ``table47`` {S: {range: {...}}},
``kappa_colnorm`` is κ(JᵀJ) with unit-norm columns (unit free). ``optimised`` {m: kappa of a D-optimal plan from 2000 candidates (range N)},
``ranking_46`` / ``ranking_47`` (strategies by median κ, best first), ``kendall_tau``
({"4.6", "4.7"}: Kendall τ between the book's and our κ over the cells the book
prints), ``settings``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import kendalltau

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.design.criteria import cond_JtJ, covariance  # noqa: E402
from estcal.design.model import DesignModel  # noqa: E402
from estcal.design.plans import optimise_discrete  # noqa: E402
from estcal.kinematics.robots import INCH, robot_5r1p  # noqa: E402
from estcal.simulate.strategies import generate_poses  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

DEG = np.pi / 180
PARAMS = ["theta_1", "d_1", "a_1", "alpha_1", "theta_2", "d_2", "a_2", "alpha_2", "theta_3", "d_3", "alpha_3",
          "theta_4", "a_4", "alpha_4", "theta_5", "d_5", "a_5", "alpha_5", "theta_6", "d_6", "a_6"]
ANGLE = np.array([p.startswith(("theta", "alpha")) for p in PARAMS])
SIGMA_IN = 0.001 / np.sqrt(3)
BOOK46 = {"S1": {7: (23020, "0.032/0.013"), 36: (20024, "0.0078/0.0037"), 90: (21664, "0.0044/0.0020"),
                 180: (22307, "0.0047/0.0025"), 360: (22650, "0.0054/0.0019")},
          "S2": {36: (1203, "0.0018/0.00028"), 90: (1138, "0.0010/0.00026"), 180: (1119, "0.0012/0.00019"),
                 360: (1110, "0.00045/0.00013")},
          "S3": {36: (364, "0.0013/0.00048"), 90: (396, "0.00065/0.00021"), 180: (420, "0.00089/0.00010"),
                 360: (434, "0.00032/0.000090")},
          "S4": {12: (539, "0.0021/0.00029"), 36: (260, "0.00078/0.00017"), 90: (209, "0.00079/0.00011"),
                 180: (204, "0.00042/0.00011"), 360: (189, "0.00030/0.00010")}}
RANGES = {"N": (0, 300, 120, 12, 48), "F": (0, 360, 180, 12, 48), "H": (0, 180, 90, 30, 48),
          "Q": (0, 90, 45, 39, 48), "E": (0, 45, 22, 44, 48)}
BOOK47 = {"S1": {"F": (16375, "0.015/0.0033"), "H": (47802, "0.030/0.016"), "Q": (303101, "0.196/0.089"),
                 "E": (1e6, "diverged")},
          "S2": {"F": (1260, "0.0032/0.00044"), "H": (1393, "0.0024/0.00045"), "Q": (3330, "0.0037/0.0011"),
                 "E": (9260, "0.010/0.0027")},
          "S3": {"F": (282, "0.0011/0.00019"), "H": (909, "0.0020/0.00069"), "Q": (2579, "0.0010/0.00041"),
                 "E": (6640, "0.0067/0.0023")},
          "S4": {"F": (239, "0.0013/0.00020"), "H": (501, "0.0016/0.00076"), "Q": (1696, "0.0024/0.0017"),
                 "E": (4804, "0.0069/0.0041")}}


def with_range(robot, key):
    lo1, hi1, t2, r_lo, r_hi = RANGES[key]
    r = robot.copy()
    lim = r.limits.copy()
    lim[0] = [lo1 * DEG, hi1 * DEG]
    lim[1] = [-t2 * DEG, t2 * DEG]
    lim[2] = [r_lo * INCH, r_hi * INCH]
    r.limits = lim
    return r


def metrics(model, Q):
    """κ(JᵀJ) and predicted δrms in the book's units (in, rad → deg)."""
    J = model.jacobian(Q).reshape(-1, model.p) / INCH  # position rows in inches
    J[:, ~ANGLE] *= INCH  # length columns per inch (in/in)
    M = J.T @ J / SIGMA_IN ** 2
    kap = float(cond_JtJ(M))
    Jn = J / np.linalg.norm(J, axis=0)  # unit-free variant: columns scaled to unit norm
    kap_n = float(cond_JtJ(Jn.T @ Jn))
    try:
        std = np.sqrt(np.diag(covariance(M)))
        da = float(np.sqrt(np.mean(std[ANGLE] ** 2)) / DEG)
        dl = float(np.sqrt(np.mean(std[~ANGLE] ** 2)))
    except np.linalg.LinAlgError:
        da = dl = float("inf")
    return kap, da, dl, kap_n


def cell(robot, strategy, m, seeds, tool):
    model = DesignModel(robot, "position", PARAMS, sigma=1.0)
    n_draw = seeds if strategy == "S4" else 1  # S1-S3 are deterministic
    vals = [metrics(model, generate_poses(robot, m, strategy, rng=s)) for s in range(n_draw)]
    k, a, l_, kn = (float(np.median([v[i] for v in vals])) for i in range(4))
    return {"kappa": k, "kappa_colnorm": kn, "drms_angle_deg": a, "drms_length_in": l_, "n_draws": n_draw,
            "tool_in": tool}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None, help="random draws per S4 cell (default 50, quick 5)")
    args = ap.parse_args(argv)
    seeds = args.seeds or (5 if args.quick else 50)
    t0 = time.time()
    r10 = robot_5r1p(10.0)
    r5 = robot_5r1p(5.0)
    model = DesignModel(r10, "position", PARAMS, sigma=1.0)
    J = model.jacobian(r10.random_readings(100, 0)).reshape(-1, model.p)
    rank = int(np.linalg.matrix_rank(J / np.linalg.norm(J, axis=0)))
    print(f"5R1P, {len(PARAMS)} parameters, position-only rank {rank} (book: 21)")

    t46 = {}
    ms = (12, 36, 90) if args.quick else (7, 12, 36, 90, 180, 360)
    print("\nTable 4.6 (range N, l6 = r6 = 10 in): κ(JᵀJ) ours [book]; predicted δrms deg/in [book simulated]")
    for s in ("S1", "S2", "S3", "S4"):
        t46[s] = {}
        for m in ms:
            if s != "S4" and m == 12 or (s != "S1" and m == 7):
                continue
            c = cell(r10, s, m, seeds, 10.0)
            bk = BOOK46[s].get(m)
            c["book_kappa"], c["book_drms"] = (bk if bk else (None, None))
            t46[s][str(m)] = c
            print(f"  {s} m={m:>3}: κ {c['kappa']:>12.4g} [{bk[0] if bk else '-':>6}] (unit-norm columns "
                  f"{c['kappa_colnorm']:>9.4g})  δrms "
                  f"{c['drms_angle_deg']:.2g}/{c['drms_length_in']:.2g} [{bk[1] if bk else '-'}]")
    t47 = {}
    print("\nTable 4.7 (m = 36, l6 = r6 = 5 in): κ(JᵀJ) ours [book] by joint range")
    for s in ("S1", "S2", "S3", "S4"):
        t47[s] = {}
        row = []
        for key in RANGES:
            c = cell(with_range(r5, key), s, 36, seeds, 5.0)
            bk = BOOK47[s].get(key)
            c["book_kappa"], c["book_drms"] = (bk if bk else (None, None))
            t47[s][key] = c
            row.append(f"{key}: {c['kappa']:.3g} [{bk[0] if bk else '-'}]")
        print(f"  {s}: " + "; ".join(row))

    opt = {}
    for m in ((36,) if args.quick else (12, 36, 90)):
        plan = optimise_discrete(model, m, "D", n_candidates=500 if args.quick else 2000,
                                 restarts=1 if args.quick else 3, rng=m)
        opt[str(m)] = {"kappa": metrics(model, plan.readings)[0]}
    print("\nD-optimal plans (Fedorov exchange, range N, l6 = r6 = 10 in): " +
          ", ".join(f"m={k}: κ {v['kappa']:.4g}" for k, v in opt.items()))

    def ranking(table, key):
        return sorted(table, key=lambda s: table[s][key]["kappa"]) if all(key in table[s] for s in table) else []

    r46 = ranking(t46, "36")
    r47 = {key: ranking(t47, key) for key in RANGES}
    print(f"\nranking by κ at m = 36 (best first): {r46} (book: S4 > S3 > S2 >> S1; its κ: S4 260, S3 364, "
          f"S2 1203, S1 20024)")
    print("κ grows as the range shrinks (N → E) for every strategy: " + ", ".join(
        f"{s}: {all(np.diff([t47[s][k]['kappa'] for k in 'NHQE']) > 0)}" for s in t47))

    def tau(table):
        pairs = [(c["book_kappa"], c["kappa"]) for row in table.values() for c in row.values()
                 if c["book_kappa"] is not None]
        return float(kendalltau(*zip(*pairs)).statistic) if len(pairs) >= 3 else None

    taus = {"4.6": tau(t46), "4.7": tau(t47)}
    print("Kendall τ, book κ vs ours: " + ", ".join(
        f"Table {k}: {v:.2f}" if v is not None else f"Table {k}: —" for k, v in taus.items()))
    res = {"parameters": PARAMS, "rank": rank, "table46": t46, "table47": t47, "optimised": opt,
           "ranking_46": r46, "ranking_47": r47, "kendall_tau": taus,
           "settings": {"seeds": seeds, "sigma_in": SIGMA_IN, "units": "inches, radians (kappa); deg, in (drms)",
                        "quick": args.quick}, "runtime_s": time.time() - t0}
    if args.json:
        write_json(args.json, res, announce=True)
    return res


if __name__ == "__main__":
    main()
