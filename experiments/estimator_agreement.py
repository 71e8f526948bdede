"""Agreement and coverage of the estimators on one simulated PUMA 560 problem.

Setting: PUMA 560 (``puma560()``), 100 random poses, full pose (location
method: position + orientation), Gaussian noise σp = 0.1 mm, σr = 0.1 mrad,
known; the identifiable free set (30 parameters) chosen by the rank test; true
deviations 1 mm / 1 mrad on the free parameters.

1. **Agreement** on one dataset: LM (the lead's ``calibrate_lsq``), gtsam
   batch LM, iSAM2, the EKF after all rows (Q = 0, prior std 0.1), the UKF and
   the MCMC posterior mean; for each, max |θ̂ − θ̂_LM|/σ_LM and max |σ/σ_LM − 1|.
2. **Monte Carlo**: the same poses and truth, new noise in each of ``--sims``
   simulations; the spread (std) of each estimator's estimates against its
   reported std; and **coverage** of the 95 % intervals (θ̂ ± 1.96 σ for LM,
   gtsam, Kalman; the 2.5–97.5 % posterior quantiles for MCMC) pooled over
   parameters, with the binomial 99 % tolerance band, plus the coverage of the
   joint 95 % ellipsoid (one Bernoulli per simulation, exact binomial).
3. **Misspecification**: 10 % outliers (100 σ) → plain LM vs gtsam Huber /
   Cauchy (RMS error / σ); an unmodelled 0.2 % gear-ratio error → innovation tests.

Usage: ``python experiments/estimator_agreement.py [--quick] [--sims N] [--mcmc-sims N] [--skip-mcmc] [--json PATH]``

JSON keys: ``agreement`` ({method: {max_dz, max_std_ratio_dev, time_s}}),
``monte_carlo`` ({method: {coverage, coverage_band, joint_coverage, joint_band,
spread_over_std_median, n}}), ``outliers`` ({method: rms_error_over_std}),
``unmodelled`` ({fires, failed, nis_per_row}), ``settings``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.estimate.factorgraph import calibrate_gtsam, calibrate_isam2  # noqa: E402
from estcal.estimate.kalman import calibrate_kalman  # noqa: E402
from estcal.estimate.lsq import calibrate_lsq  # noqa: E402
from estcal.estimate.mcmc import calibrate_mcmc  # noqa: E402
from estcal.estimate.testproblems import simulated_problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402

SIG = 1e-4


def _band(n, p=0.95, conf=0.99):
    lo, hi = stats.binom.ppf([(1 - conf) / 2, 1 - (1 - conf) / 2], n, p)
    return [float(lo / n), float(hi / n)]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--sims", type=int, default=None, help="Monte-Carlo simulations (LM, gtsam, Kalman)")
    ap.add_argument("--mcmc-sims", type=int, default=None, help="simulations with MCMC coverage")
    ap.add_argument("--poses", type=int, default=100)
    ap.add_argument("--skip-mcmc", action="store_true", help="leave MCMC out (fast smoke test)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    sims = a.sims or (6 if a.quick else 200)
    msims = a.mcmc_sims if a.mcmc_sims is not None else (0 if a.quick else 20)
    ess = 150 if a.quick else 1000
    base = simulated_problem("puma560", n_poses=a.poses, seed=100, sigma_p=SIG, sigma_r=SIG)
    free, truth = base.free, base.truth
    readings = base.problem.terms[0].data.readings
    print(f"PUMA 560, {a.poses} poses, location method, σ = {SIG:g} m / rad (known), {len(free)} free parameters")

    # ---- 1. agreement on one dataset
    lm = calibrate_lsq(base.problem)
    runs = {"gtsam": lambda p: calibrate_gtsam(p), "isam2": lambda p: calibrate_isam2(p),
            "kalman": lambda p: calibrate_kalman(p), "ukf": lambda p: calibrate_kalman(p, filter="ukf"),
            "mcmc": lambda p: calibrate_mcmc(p, target_ess=ess, seed=1)}
    if a.skip_mcmc:
        runs.pop("mcmc")
        msims = 0
    agreement = {"lm": {"max_dz": 0.0, "max_std_ratio_dev": 0.0, "time_s": lm.extra["time_s"]}}
    print(f"{'method':<8} {'max|Δ|/σ_LM':>12} {'max|σ/σ_LM−1|':>14} {'time s':>8}")
    for name, f in runs.items():
        t = time.perf_counter()
        r = f(base.problem)
        dt = time.perf_counter() - t
        agreement[name] = {"max_dz": float(np.max(np.abs((r.estimate - lm.estimate) / lm.std))),
                           "max_std_ratio_dev": float(np.max(np.abs(r.std / lm.std - 1))), "time_s": dt}
        if name == "mcmc":
            agreement[name].update(min_ess=r.extra["min_ess"], acceptance=r.extra["acceptance_fraction"],
                                   mc_error_bound=float(3 / np.sqrt(r.extra["min_ess"])))
        print(f"{name:<8} {agreement[name]['max_dz']:>12.4f} {agreement[name]['max_std_ratio_dev']:>14.4f} {dt:>8.2f}")

    # ---- 2. Monte Carlo spread and coverage
    z95 = stats.norm.ppf(0.975)
    chi95 = stats.chi2.ppf(0.95, len(free))
    mc = {}
    est = {m: [] for m in ("lm", "gtsam", "kalman", "mcmc")}
    for m in est:
        mc[m] = {"covered": 0, "n": 0, "joint": 0, "n_sims": 0, "std": []}
    for s in range(sims):
        sim = simulated_problem("puma560", readings=readings, seed=1000 + s, free=free, truth=truth,
                                sigma_p=SIG, sigma_r=SIG)
        tf = sim.truth_free
        results = {"lm": calibrate_lsq(sim.problem), "gtsam": calibrate_gtsam(sim.problem),
                   "kalman": calibrate_kalman(sim.problem)}
        if s < msims:
            results["mcmc"] = calibrate_mcmc(sim.problem, target_ess=ess, seed=s)
        for m, r in results.items():
            if m == "mcmc":
                ci = np.array([r.extra["credible_intervals"][n] for n in r.names])
                cov_ok = (ci[:, 0] <= tf) & (tf <= ci[:, 1])
            else:
                cov_ok = np.abs(r.estimate - tf) <= z95 * r.std
            d = r.estimate - tf
            mc[m]["covered"] += int(cov_ok.sum())
            mc[m]["n"] += cov_ok.size
            mc[m]["joint"] += int(d @ np.linalg.solve(r.covariance, d) <= chi95)
            mc[m]["n_sims"] += 1
            mc[m]["std"].append(r.std)
            est[m].append(r.estimate)
    out_mc = {}
    print(f"\nMonte Carlo ({sims} simulations; MCMC {msims}): 95 % coverage (99 % binomial band), joint ellipsoid, "
          f"spread/σ")
    for m, d in mc.items():
        if d["n_sims"] < 2:
            continue
        E = np.array(est[m])
        spread = E.std(0, ddof=1) / np.mean(d["std"], 0)
        out_mc[m] = {"coverage": d["covered"] / d["n"], "coverage_band_independent": _band(d["n"]),
                     "joint_coverage": d["joint"] / d["n_sims"], "joint_band": _band(d["n_sims"]),
                     "spread_over_std_median": float(np.median(spread)),
                     "spread_over_std_range": [float(spread.min()), float(spread.max())], "n": d["n_sims"]}
        o = out_mc[m]
        print(f"  {m:<7} coverage {o['coverage']:.3f} [{o['coverage_band_independent'][0]:.3f}, "
              f"{o['coverage_band_independent'][1]:.3f}]  joint {o['joint_coverage']:.3f} "
              f"[{o['joint_band'][0]:.2f}, {o['joint_band'][1]:.2f}]  spread/σ median "
              f"{o['spread_over_std_median']:.3f} (range {o['spread_over_std_range'][0]:.2f}–"
              f"{o['spread_over_std_range'][1]:.2f})")
    # ---- 3. misspecification
    out = simulated_problem("puma560", readings=readings, seed=7, free=free, truth=truth, sigma_p=SIG, sigma_r=SIG,
                            outliers=0.1, outlier_scale=100.0)
    rms = lambda r: float(np.sqrt(np.mean(((r.estimate - out.truth_free) / lm.std) ** 2)))  # noqa: E731
    outliers = {"lm": rms(calibrate_lsq(out.problem)), "gtsam": rms(calibrate_gtsam(out.problem)),
                "gtsam-huber": rms(calibrate_gtsam(out.problem, robust="huber")),
                "gtsam-cauchy": rms(calibrate_gtsam(out.problem, robust="cauchy"))}
    print("\n10 % outliers (100 σ): RMS (estimate − truth)/σ: " + ", ".join(f"{k} {v:.2f}" for k, v in outliers.items()))
    t2 = truth.copy()
    t2[base.problem.params.index("gain_2")] *= 1.002
    um = simulated_problem("puma560", readings=readings, seed=8, free=free, truth=t2, sigma_p=SIG, sigma_r=SIG)
    inn = calibrate_kalman(um.problem).extra["innovation"]
    unmodelled = {"fires": inn["fires"], "failed": inn["failed"], "nis_per_row": inn["nis_mean_per_row"]}
    print(f"unmodelled 0.2 % gear ratio on joint 2: innovation tests fire = {inn['fires']} ({inn['failed']}), "
          f"NIS/row {inn['nis_mean_per_row']:.2f}")
    res = {"settings": {"poses": a.poses, "sigma": SIG, "n_free": len(free), "sims": sims, "mcmc_sims": msims,
                        "target_ess": ess},
           "agreement": agreement, "monte_carlo": out_mc, "outliers": outliers, "unmodelled": unmodelled}
    if a.json:
        write_json(a.json, res)
    return res


if __name__ == "__main__":
    main()
