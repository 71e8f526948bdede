"""Active (covariance-driven) calibration vs random poses vs a fixed optimal plan.

Set-up: PUMA 560 (textbook Table 6.1 model), position measurements of the tool
origin (σ = 0.05 mm per coordinate), the 25 identifiable parameters (offsets
first), prior N(nominal, diag(1 mm², 1 mrad²)); each seed draws a "true" robot
from the prior. Three test poses (the stopping rule uses their mean ρ0²). At
every step a pose is chosen, measured on the true robot (simulated noise) and
the estimate updated by the extended Kalman filter of
:mod:`estcal.estimate.kalman` (filterpy EKF, linearised at the current
estimate):

* ``active`` — :func:`estcal.design.sequential.propose_next_pose`: the pose
  (of 500 random candidates per step) minimising the test-pose criterion of
  the predicted covariance C⁺ = C − C Hᵀ(H C Hᵀ + R)⁻¹ H C;
* ``random`` — uniform within the joint limits;
* ``plan`` — a fixed plan of ``--max`` poses optimised offline for the same
  criterion and prior (Fedorov exchange from 2000 candidates), measured in
  greedy order (each prefix is a good plan too).

Reported: predicted ρ0 and the true RMS position error at the test poses
against the number of measurements (mean over seeds), and the number of
measurements needed to reach the target predicted ρ0 (``--target`` mm).
Note: with a linearised model C⁺ does not depend on the measured values, so the
active loop is the greedy sequential design; re-linearisation at the current
estimate is what makes it adaptive.

Run: ``python experiments/active_calibration.py [--quick] [--json PATH] [--png PATH] [--seeds N]``

JSON keys: ``n`` (0…max), ``curves`` {strategy: {predicted_mm, true_error_mm}} (mean over seeds),
``n_reached`` {strategy: [per seed]}, ``n_reached_mean`` {strategy}, ``target_mm``, ``settings``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.design.model import DesignModel, identifiable_subset  # noqa: E402
from estcal.design.plans import greedy, optimise_discrete  # noqa: E402
from estcal.design.sequential import CalibrationState, active_calibration  # noqa: E402
from estcal.kinematics.robots import puma560  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

DEG = np.pi / 180
Q_TEST = np.array([[10, -60, 120, 0, 30, 0], [-40, -90, 150, 20, -40, 10], [60, -30, 60, -30, 60, 0]]) * DEG


def prior_std(names):
    """1 mm for lengths, 1 mrad for angles: numerically the same 1e-3 in SI units."""
    return np.full(len(names), 1e-3)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--png", type=Path, default=None, help="plot (default: next to --json, or none)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None, help="seeds (default 10, quick 2)")
    ap.add_argument("--max", type=int, default=None, help="measurements per run (default 60, quick 20)")
    ap.add_argument("--target", type=float, default=0.05, help="target predicted ρ0 (mm)")
    ap.add_argument("--sigma", type=float, default=0.05, help="measurement noise per coordinate (mm)")
    args = ap.parse_args(argv)
    seeds = args.seeds or (2 if args.quick else 10)
    n_max = args.max or (20 if args.quick else 60)
    n_cand = 150 if args.quick else 500
    target = args.target * 1e-3
    t0 = time.time()
    robot = puma560()
    free = identifiable_subset(robot, "position")
    std0 = prior_std(free)
    model = DesignModel(robot, "position", free, sigma=args.sigma * 1e-3)
    st0 = CalibrationState.prior(model, std0)
    # fixed optimal plan, designed offline with the same prior; measured in greedy order
    pm = model.with_prior(st0.covariance)
    J0 = pm.position_jacobian(Q_TEST)
    opt = optimise_discrete(pm, n_max, "test-pose", n_candidates=600 if args.quick else 2000,
                            restarts=1 if args.quick else 2, rng=0, J_test=J0)
    plan = greedy(pm, opt.readings, n_max, "test-pose", J_test=J0, allow_repeats=False).readings
    curves = {s: {"pred": [], "err": []} for s in ("active", "random", "plan")}
    reached = {s: [] for s in curves}
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        th = robot.params.values.copy()
        th[robot.params.indices(free)] += rng.normal(0, 1, len(free)) * std0
        truth = robot.with_values(th)
        for s in curves:
            run = active_calibration(truth, model, st0, Q_TEST, target, s, max_measurements=n_max,
                                     rng=seed, n_candidates=n_cand, plan=plan, run_to_max=True)
            curves[s]["pred"].append(run.predicted)
            curves[s]["err"].append(run.true_error)
            reached[s].append(run.n_reached if run.n_reached is not None else np.nan)
        print(f"seed {seed}: n to reach {args.target} mm — " +
              ", ".join(f"{s} {reached[s][-1]}" for s in curves))
    n = np.arange(n_max + 1)
    out = {s: {"predicted_mm": (np.mean(c["pred"], 0) * 1e3).tolist(),
               "true_error_mm": (np.sqrt(np.mean(np.square(c["err"]), 0)) * 1e3).tolist()}
           for s, c in curves.items()}
    mean_reached = {s: (float(np.nanmean(v)) if np.any(np.isfinite(v)) else None) for s, v in reached.items()}
    never = {s: int(np.sum(~np.isfinite(v))) for s, v in reached.items()}
    print(f"\nmeasurements to reach predicted ρ0 ≤ {args.target} mm (mean over {seeds} seeds; "
          f"runs that never reached it within {n_max} are left out and counted):")
    for s in curves:
        print(f"  {s:>6}: {mean_reached[s]}  (not reached: {never[s]})")
    print("\n  n   " + "  ".join(f"{s:>18}" for s in curves) + "   (predicted / true RMS error, mm)")
    for k in sorted(set([1, 3, 5, 9, 12, 15, 20, 30, 40, 60]) & set(n.tolist())):
        print(f"{k:>3}   " + "  ".join(f"{out[s]['predicted_mm'][k]:>8.4f} / {out[s]['true_error_mm'][k]:<8.4f}"
                                       for s in curves))
    png = args.png or (args.json.with_suffix(".png") if args.json else None)
    if png is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4.5))
        for s, col in zip(curves, ("C0", "C1", "C2")):
            ax.semilogy(n[1:], out[s]["predicted_mm"][1:], color=col, label=f"{s}: predicted ρ0")
            ax.semilogy(n[1:], out[s]["true_error_mm"][1:], color=col, ls="--", label=f"{s}: true RMS error")
        ax.axhline(args.target, color="k", lw=0.8, ls=":", label="target")
        ax.set_xlabel("number of measurements")
        ax.set_ylabel("position error at the test poses (mm)")
        ax.set_title(f"PUMA 560, σ = {args.sigma} mm, mean over {seeds} seeds")
        ax.legend(fontsize=8)
        fig.tight_layout()
        png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(png, dpi=120)
        print(f"wrote {png}")
    res = {"n": n.tolist(), "curves": out, "n_reached": {s: [None if not np.isfinite(v) else int(v) for v in r]
                                                         for s, r in reached.items()},
           "n_reached_mean": mean_reached, "not_reached": never, "target_mm": args.target,
           "settings": {"robot": "puma560", "method": "position", "sigma_mm": args.sigma, "free": free,
                        "prior_std": std0.tolist(), "seeds": seeds, "max": n_max, "candidates": n_cand,
                        "test_poses_deg": np.degrees(Q_TEST).tolist(), "quick": args.quick},
           "runtime_s": time.time() - t0}
    if args.json:
        write_json(args.json, res, announce=True)
    return res


if __name__ == "__main__":
    main()
