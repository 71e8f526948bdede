"""Klimchik-style test-pose design for a 6R KR-270-class industrial robot (cf. Klimchik 2012 Table 2, Fig. 5).

Robot (documented assumption — Klimchik gives the KR-270 model only as a
figure): a standard-DH 6R arm with KUKA KR 270 R2700-class public dimensions,
d1 = 0.675 m (floor to A2), a1 = 0.350 m (A1–A2 offset), a2 = 1.150 m
(upper arm), a3 = 0.041 m (forearm offset), d4 = −1.200 m (forearm),
d6 = −0.215 m (flange); reach to the wrist centre 0.35 + 1.15 + 1.20 = 2.70 m,
the nominal 2700 mm. Joint ranges are the datasheet's (A1 ±185°, A2 −140…−5°,
A3 −120…168°, A4 ±350°, A5 ±125°, A6 ±350°) applied to our DH joint variables;
our DH zero need not be KUKA's mechanical zero, so the workspace is KR-270-like,
not exact. Workspace limit: tool centre point above z = 0.3 m (``ToolBox``).

Measurement (Klimchik A1–A3): a laser tracker measures the positions of three
targets on the tool (σ = 0.03 mm per coordinate), at (0.15, 0, 0),
(−0.075, ±0.13, 0) m in a tool frame 0.25 m beyond the flange; the targets,
base and tool frames are known (registered). Three points of one rigid body
carry at most 6 independent equations per configuration, so an m = 3 plan
identifies at most 18 parameters; following Klimchik ("mainly link-length
deviations and joint offsets") the identified parameters are the identifiable
subset of the DH lengths a_j, d_j and the joint offsets (QR with priorities
offsets > lengths). Of these 17 are identifiable with many configurations, but
the stacked rank grows 6, 11, 14, 17 with 1…4 configurations, so m = 3 needs
a 14-parameter set: we keep the 14 chosen by the same QR on a 3-configuration
plan and fix the other 3 (Klimchik likewise removes three, d0, d5, Δq6). The test pose q0 (not given in the paper) is
(15°, −70°, 40°, 30°, 50°, 20°); ρ0 is the RMS position error of the tool
centre point there after calibration.

Plans: optimised m = 3, 4, 12 (Fedorov exchange over 3000 feasible random
candidates, then continuous multi-start SLSQP over all joint values with the
workspace constraint, one start from the exchange optimum and the others the
best of 2000 random feasible plans, run in parallel processes; ``--quick``
uses the exchange only), the 3×4 and 4×3 replicated plans, and 20,000 random plans per
size (vectorised: one kinematics call and one batched eigen-decomposition per
chunk) — the random 3×4 / 4×3 baselines replicate random 3- / 4-pose plans.
Each optimised plan is checked by Monte-Carlo calibration (nonlinear LM with
``calibrate_lsq`` on simulated tracker data, true parameters drawn around the
nominal: 0.5 mm / 0.5 mrad).

Run: ``python experiments/kr270_design.py [--quick] [--json PATH] [--random N] [--reps N]``

JSON keys: ``table2`` {"3", "4", "3x4", "4x3", "12": {random_max_um, random_min_um,
random_mean_um, random_median_um, proposed_um, random_n_singular}}, ``plans``
{size: readings in degrees}, ``monte_carlo`` {size: {rms_um, predicted_um, ratio,
rel_se}}, ``improvement_vs_random_mean_pct``, ``robot``, ``free`` (14 used), ``free_all`` (17),
``settings``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.design.model import DesignModel, ToolBox, identifiable_subset  # noqa: E402
from estcal.design.montecarlo import monte_carlo_test_pose_error  # noqa: E402
from estcal.design.plans import optimise_continuous, optimise_discrete, random_baseline, replicate  # noqa: E402
from estcal.kinematics.builder import build_robot  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

DEG = np.pi / 180
SIGMA = 0.03e-3
Q0 = np.array([[15, -70, 40, 30, 50, 20]]) * DEG
MARKERS = [[0.15, 0, 0], [-0.075, 0.13, 0], [-0.075, -0.13, 0]]


def kr270():
    """The documented KR-270-class robot (see module docstring)."""
    frames = [{"name": "a1", "d": 0.675, "a": 0.35, "alpha": -90 * DEG, "limits": [-185 * DEG, 185 * DEG]},
              {"name": "a2", "a": 1.15, "limits": [-140 * DEG, -5 * DEG]},
              {"name": "a3", "a": 0.041, "alpha": -90 * DEG, "limits": [-120 * DEG, 168 * DEG]},
              {"name": "a4", "d": -1.2, "alpha": 90 * DEG, "limits": [-350 * DEG, 350 * DEG]},
              {"name": "a5", "alpha": -90 * DEG, "limits": [-125 * DEG, 125 * DEG]},
              {"name": "a6", "d": -0.215, "limits": [-350 * DEG, 350 * DEG]}]
    return build_robot("kr270_class", frames, convention="dh", tool={"xyz": [0, 0, -0.25], "rpy": [0, 0, 0]},
                       markers=MARKERS, meta={"source": "KR 270 R2700-class public dimensions (assumed)"})


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--random", type=int, default=None, help="random plans per size (default 20000, quick 500)")
    ap.add_argument("--reps", type=int, default=None, help="Monte-Carlo calibrations per plan (default 300, quick 10)")
    ap.add_argument("--starts", type=int, default=None, help="multi-start runs per size (default 16, quick 2)")
    args = ap.parse_args(argv)
    n_random = args.random or (500 if args.quick else 20000)
    reps = args.reps or (10 if args.quick else 300)
    starts = args.starts or (2 if args.quick else 16)
    t0 = time.time()
    robot = kr270()
    # Klimchik: "mainly link-length deviations and joint offsets" — lengths a_j, d_j and offsets
    cands = [n for n, k in zip(robot.params.names, robot.params.kinds)
             if k == "offset" or (k == "geometric" and n.split("_")[0] in ("a", "d"))]
    robot = robot.copy(robot.params.with_free(cands))
    full = identifiable_subset(robot, "points")
    # identifiable with only 3 configurations (rank 6, 11, 14, 17 for 1…4 configurations)
    free = identifiable_subset(robot, "points", candidates=robot.random_readings(3, np.random.default_rng(5)))
    model = DesignModel(robot, "points", free, sigma=SIGMA)
    floor = ToolBox(robot, lower=(None, None, 0.3))
    print(f"{robot.name}: {len(full)} identifiable lengths/offsets; {len(free)} identifiable from 3 configurations, "
          f"used (dropped: {sorted(set(full) - set(free))}); points method, 3 targets, σ = 0.03 mm")
    print(f"test pose q0 = {np.degrees(Q0[0]).round(1).tolist()} deg, TCP at "
          f"{robot.kinematics(Q0, jacobian=False).p[0].round(3).tolist()} m")

    sizes = {"3": (3, 1), "4": (4, 1), "3x4": (3, 4), "4x3": (4, 3), "12": (12, 1)}
    opt = {}
    for m in (3, 4, 12):
        ts = time.time()
        disc = optimise_discrete(model, m, "test-pose", n_candidates=300 if args.quick else 3000,
                                 restarts=1 if args.quick else 4, rng=m, q_test=Q0, constraint=floor)
        opt[m] = disc
        if not args.quick:  # polish: continuous multi-start, one start from the discrete optimum
            cont = optimise_continuous(model, m, "test-pose", n_starts=starts, rng=m, q_test=Q0, constraint=floor,
                                       starts=[disc.readings], prescreen=2000, maxiter=400)
            if cont.info["feasible"] and cont.value < disc.value:
                opt[m] = cont
        print(f"optimised m = {m:>2}: ρ0 = {np.sqrt(opt[m].value) * 1e6:7.2f} µm ({opt[m].method}; discrete "
              f"{np.sqrt(disc.value) * 1e6:.2f} µm; {time.time() - ts:.0f} s)")
    plans = {"3": opt[3], "4": opt[4], "3x4": replicate(opt[3], 4, model, q_test=Q0),
             "4x3": replicate(opt[4], 3, model, q_test=Q0), "12": opt[12]}

    table = {}
    print(f"\nTable 2 analogue: ρ0 in µm (random: {n_random} plans within joint and workspace limits)")
    print(f"{'plan':>5} {'random max':>12} {'random min':>11} {'random mean':>12} {'random median':>13} "
          f"{'proposed':>9}")
    for key, (m, k) in sizes.items():
        b = random_baseline(model, m, "test-pose", n_plans=n_random, rng=1000 + m * 10 + k, q_test=Q0,
                            replicate=k, constraint=floor, keep_values=True)
        v = np.sqrt(b.values) * 1e6
        row = {"random_max_um": float(np.max(v)), "random_min_um": float(np.min(v)),
               "random_mean_um": float(np.mean(v[np.isfinite(v)])), "random_median_um": float(np.median(v)),
               "random_n_singular": b.n_singular, "proposed_um": float(np.sqrt(plans[key].value) * 1e6)}
        table[key] = row
        print(f"{key:>5} {row['random_max_um']:>12.4g} {row['random_min_um']:>11.4g} {row['random_mean_um']:>12.4g} "
              f"{row['random_median_um']:>13.4g} {row['proposed_um']:>9.4g}")

    mc = {}
    print(f"\nMonte-Carlo check ({reps} LM calibrations per plan, true errors 0.5 mm / 0.5 mrad):")
    for i, key in enumerate(sizes):
        r = monte_carlo_test_pose_error(model, plans[key].readings, Q0, n_reps=reps, rng=77 + i, param_std=5e-4)
        mc[key] = {"rms_um": r.rms * 1e6, "predicted_um": r.predicted * 1e6, "ratio": r.ratio, "rel_se": r.rel_se}
        print(f"  {key:>4}: MC {r.rms * 1e6:7.2f} µm vs predicted {r.predicted * 1e6:7.2f} µm "
              f"(ratio {r.ratio:.3f} ± {r.rel_se:.3f})")
    imp = {k: 100 * (1 - table[k]["proposed_um"] / table[k]["random_mean_um"]) for k in table}
    print("\nimprovement of the proposed plan over the random-plan mean: " +
          ", ".join(f"{k}: {v:.0f} %" for k, v in imp.items()))
    res = {"table2": table, "plans": {k: np.degrees(p.readings).tolist() for k, p in plans.items()},
           "monte_carlo": mc, "improvement_vs_random_mean_pct": imp,
           "robot": {"name": robot.name, "dh": "d1 0.675, a1 0.35, a2 1.15, a3 0.041, d4 -1.2, d6 -0.215 (m)",
                     "tool_z_m": -0.25, "markers_m": MARKERS}, "free": free, "free_all": full,
           "settings": {"sigma_m": SIGMA, "q0_deg": np.degrees(Q0[0]).tolist(), "random_plans": n_random,
                        "mc_reps": reps, "starts": starts, "workspace": "TCP z >= 0.3 m", "quick": args.quick},
           "runtime_s": time.time() - t0}
    if args.json:
        write_json(args.json, res, announce=True)
    return res


if __name__ == "__main__":
    main()
