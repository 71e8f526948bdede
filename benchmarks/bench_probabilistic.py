"""Speed of the probabilistic and recursive estimators (printed, not timed tests).

1. Kalman updates per second, ~40-parameter state, 3-D and 6-D measurements:
   (a) filterpy's ``ExtendedKalmanFilter.update`` alone (H and residual given);
   (b) the same update written as plain numpy (Joseph form, ``solve`` instead of
       ``inv``, no ``deepcopy``/posterior copies) — to show filterpy's per-update overhead;
   (c) a full EKF step of :class:`~estcal.estimate.kalman.ParameterFilter` on a PUMA 560
       pose (kinematics + Jacobian of one pose through ``Problem.evaluate`` + update);
   (d) batch-linearised: Jacobians of 100 poses in one vectorised call, then 100
       filterpy updates (what a high-rate logger would do between re-linearisations).
2. gtsam batch: one CustomFactor per pose vs several poses per factor (Python-callback cost).
   iSAM2: time per new measurement (``update`` with one factor) vs a gtsam batch LM re-solve
   of all measurements so far, at several sizes.
3. MCMC: wall time for the ESS of every parameter of the PUMA problem (100 poses, location,
   30 identifiable parameters) to reach 1,000, with the default (Laplace-MH + DE) moves and
   with emcee's DE moves.

Usage: ``python benchmarks/bench_probabilistic.py [--quick] [--only-isam2] [--json PATH]``
JSON keys: ``kalman`` ({filterpy_3d, filterpy_6d, numpy_3d, numpy_6d, ekf_step_pose,
batch_linearised}: updates/s), ``gtsam`` (list of {poses, poses_per_factor,
solve_plus_marginals_s, python_callback_s, callbacks}), ``isam2`` (list of {k, p, customfactor, linear: {wall_ms, cpu_ms, wall_ms_mean, cpu_ms_mean,
loadavg, relinearisations, max_diff_batch_sigma}, isam2_update_ms, batch_resolve_ms}),
``mcmc`` ({moves: {wall_s, min_ess, tau_max, steps, evaluations}}), ``machine`` (nproc, load).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from estcal.base.jsonio import write_json

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _rate(fn, n):
    fn()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - t)


def bench_kalman(quick):
    from filterpy.kalman import ExtendedKalmanFilter

    rng = np.random.default_rng(0)
    p = 40
    out = {}
    n = 500 if quick else 5000
    for m in (3, 6):
        H = rng.standard_normal((m, p))
        R = np.eye(m) * 1e-8
        f = ExtendedKalmanFilter(dim_x=p, dim_z=m)
        f.x = np.zeros(p)
        f.P = np.eye(p) * 1e-2
        e = rng.standard_normal(m) * 1e-4

        def step_filterpy():
            f.predict()
            f.update(np.zeros(m), lambda x: H, lambda x: -e, R=R)

        out[f"filterpy_{m}d"] = _rate(step_filterpy, n)
        state = {"x": np.zeros(p), "P": np.eye(p) * 1e-2}
        Q = np.zeros((p, p))

        def step_numpy():
            P = state["P"] + Q
            PHt = P @ H.T
            S = H @ PHt + R
            K = np.linalg.solve(S, PHt.T).T
            state["x"] = state["x"] + K @ e
            IKH = np.eye(p) - K @ H
            state["P"] = IKH @ P @ IKH.T + K @ R @ K.T

        out[f"numpy_{m}d"] = _rate(step_numpy, n)
    # full EKF step on PUMA poses (~40 parameters: geometry, base, tool, offsets; the prior keeps
    # the unidentifiable directions at their prior)
    from estcal.estimate._common import GroupedProblem
    from estcal.estimate.kalman import ParameterFilter
    from estcal.estimate.testproblems import simulated_problem

    sim = simulated_problem("puma560", n_poses=100, seed=0, free=["base_*", "d_*", "a_*", "alpha_*", "beta_2",
                                                                  "theta_*", "tool_*"])
    prob = sim.problem
    gp = GroupedProblem(prob)
    subs = [gp.subproblem([k]) for k in range(len(gp))]
    pv = prob.params
    flt = ParameterFilter(pv.values, pv.free_indices, np.eye(pv.free.sum()) * 1e-2)
    out["state_dim_pose_steps"] = int(pv.free.sum())
    k = {"i": 0}

    def ekf_step():
        flt.step(subs[k["i"] % len(subs)])
        k["i"] += 1

    out["ekf_step_pose"] = _rate(ekf_step, 100 if quick else 400)
    # batch-linearised: one vectorised Jacobian evaluation for 100 poses, then 100 updates
    f = ExtendedKalmanFilter(dim_x=int(pv.free.sum()), dim_z=6)
    f.x = pv.values[pv.free].copy()
    f.P = np.eye(f.x.size) * 1e-2
    fidx = pv.free_indices

    def batch():
        rows = prob.evaluate()
        Hs = rows.H[:, fidx].reshape(100, 6, -1)
        es = rows.e.reshape(100, 6)
        R = np.diag(rows.sigma[:6] ** 2)
        for i in range(100):
            f.update(np.zeros(6), lambda x, H=Hs[i]: H, lambda x, e=es[i]: -e, R=R)

    out["batch_linearised"] = 100 * _rate(batch, 3 if quick else 10)
    return out


def bench_isam2(quick):
    """iSAM2 per added pose at k poses: one CustomFactor per pose (gtsam relinearises every
    factor's Python callback: ``linear=False``, the previous default) vs linear factors held
    in one ``LinearContainerFactor`` (the default, :func:`~estcal.estimate.factorgraph._isam2_linear`).
    Per update: median of the last 10 updates (the cost at k) and mean over the stream
    (relinearisations amortised), wall and CPU time, the 1-min load average beside each."""
    from estcal.estimate.factorgraph import calibrate_gtsam, calibrate_isam2
    from estcal.estimate.testproblems import simulated_problem

    rows = []
    for n in ((30, 60) if quick else (50, 100, 200, 400)):
        sim = simulated_problem("puma560", n_poses=n, seed=1)
        row = {"k": n, "p": len(sim.free)}
        for label, lin in (("customfactor", False), ("linear", True)):
            r = calibrate_isam2(sim.problem, free=sim.free, linear=lin)
            w, c = np.asarray(r.extra["update_time_s"]), np.asarray(r.extra["update_cpu_s"])
            row[label] = {"wall_ms": float(np.median(w[-10:]) * 1e3), "cpu_ms": float(np.median(c[-10:]) * 1e3),
                          "wall_ms_mean": float(w.mean() * 1e3), "cpu_ms_mean": float(c.mean() * 1e3),
                          "loadavg": os.getloadavg()[0], "estimate": r.estimate, "std": r.std,
                          "relinearisations": r.extra.get("n_relinearisations")}
        b = calibrate_gtsam(sim.problem, free=sim.free, use_prior=True)  # the same default prior as iSAM2
        for label in ("customfactor", "linear"):
            d = row[label]
            d["max_diff_batch_sigma"] = float(np.max(np.abs(d.pop("estimate") - b.estimate) / b.std))
            d.pop("std")
        t = time.perf_counter()
        calibrate_gtsam(sim.problem, free=sim.free, marginals=False, check=False)
        row["batch_resolve_ms"] = (time.perf_counter() - t) * 1e3
        row["isam2_update_ms"] = row["linear"]["wall_ms"]
        rows.append(row)
    return rows


def bench_gtsam_vs_lm(quick, repeat=3):
    """gtsam batch (a Gaussian factor graph per LM step, the default) vs estcal's LM vs the
    nonlinear CustomFactor graph, PUMA 560 full-pose data, the same identifiable free set.
    Best of ``repeat`` wall times and the CPU time of that run; ratio to LM."""
    from estcal.estimate import calibrate_lsq
    from estcal.estimate.factorgraph import calibrate_gtsam
    from estcal.estimate.testproblems import simulated_problem

    rows = []
    for n in ((50, 500) if quick else (50, 5000)):
        sim = simulated_problem("puma560", n_poses=n, seed=1)
        calibrate_gtsam(sim.problem)  # warm-up (imports, caches)
        runs = {"lm": lambda: calibrate_lsq(sim.problem),
                "gtsam (Gaussian graph per step)": lambda: calibrate_gtsam(sim.problem),
                "gtsam (CustomFactor graph)": lambda: calibrate_gtsam(sim.problem, linear=False,
                                                                       poses_per_factor=1 if n <= 100 else n)}
        res = {}
        for name, f in runs.items():
            best = None
            for _ in range(repeat if n <= 500 else 3):
                t, c = time.perf_counter(), time.process_time()
                r = f()
                w, cp = time.perf_counter() - t, time.process_time() - c
                if best is None or w < best[0]:
                    best = (w, cp, r)
            res[name] = best
        ref = res["lm"][2]
        for name, (w, cp, r) in res.items():
            rows.append({"poses": n, "solver": name, "wall_ms": w * 1e3, "cpu_ms": cp * 1e3,
                         "ratio_to_lm_wall": w / res["lm"][0], "ratio_to_lm_cpu": cp / max(res["lm"][1], 1e-9),
                         "max_diff_sigma": float(np.max(np.abs(r.estimate - ref.estimate) / ref.std)),
                         "iterations": r.n_iterations})
    return rows


def bench_gtsam(quick):
    """Batch solve with one CustomFactor per pose vs grouped factors: the Python-callback cost."""
    from estcal.estimate.factorgraph import calibrate_gtsam
    from estcal.estimate.testproblems import simulated_problem

    rows = []
    for n in ((100,) if quick else (100, 400)):
        sim = simulated_problem("puma560", n_poses=n, seed=3)
        calibrate_gtsam(sim.problem)  # warm-up (imports, caches)
        for ppf in (1, 10, n):
            r = calibrate_gtsam(sim.problem, poses_per_factor=ppf, linear=False)
            e = r.extra
            rows.append({"poses": n, "poses_per_factor": ppf, "solve_plus_marginals_s": e["solve_time_s"]
                         + e["marginals_time_s"], "python_callback_s": e["python_factor_time_s"],
                         "callbacks": e["python_factor_calls"], "kinematics_evaluations": e["kinematics_evaluations"]})
    return rows


def bench_mcmc(quick):
    from estcal.estimate.mcmc import sample_posterior
    from estcal.estimate.testproblems import simulated_problem

    sim = simulated_problem("puma560", n_poses=100, seed=2)
    out = {}
    for moves in (("laplace",) if quick else ("laplace", "de")):
        target = 200 if quick else 1000
        s = sample_posterior(sim.problem, target_ess=target, max_steps=1000 if quick else 20000, moves=moves)
        out[moves] = {"target_ess": target, "wall_s": s.wall_time_s, "min_ess": float(s.ess.min()),
                      "tau_max": float(s.tau.max()), "steps": s.n_steps, "walkers": s.n_walkers,
                      "evaluations": s.n_evaluations, "converged": s.converged,
                      "acceptance": s.acceptance_fraction, "n_parameters": len(s.names)}
    return out


def _print_isam2(rows):
    print("iSAM2 per added pose (PUMA 560, full pose, median of the last 10 updates; mean over the stream):")
    for r in rows:
        cf, li = r["customfactor"], r["linear"]
        print(f"  k = {r['k']:4d} ({r['p']} params): CustomFactor {cf['wall_ms']:6.2f} ms wall {cf['cpu_ms']:6.2f} ms CPU "
              f"(load {cf['loadavg']:.1f}) | linear containers {li['wall_ms']:6.2f} ms wall {li['cpu_ms']:6.2f} ms CPU "
              f"(load {li['loadavg']:.1f}), mean {li['wall_ms_mean']:.2f} / {li['cpu_ms_mean']:.2f} ms, "
              f"{li['relinearisations']} relinearisations | ×{cf['cpu_ms'] / li['cpu_ms']:.1f} CPU | "
              f"end vs batch {li['max_diff_batch_sigma']:.1e} σ | batch re-solve {r['batch_resolve_ms']:.1f} ms")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--only-isam2", action="store_true", help="run only the iSAM2 section")
    a = ap.parse_args(argv)
    res = {"machine": {"nproc": os.cpu_count(), "loadavg": list(os.getloadavg())}}
    if a.only_isam2:
        res["isam2"] = _print_isam2(bench_isam2(a.quick))
        if a.json:
            write_json(a.json, res)
        return res
    k = bench_kalman(a.quick)
    res["kalman"] = k
    print("Kalman updates/s (40-parameter state):")
    print(f"  filterpy EKF update      3-D {k['filterpy_3d']:8.0f}/s   6-D {k['filterpy_6d']:8.0f}/s")
    print(f"  plain numpy update       3-D {k['numpy_3d']:8.0f}/s   6-D {k['numpy_6d']:8.0f}/s   "
          f"(filterpy overhead ×{k['numpy_6d'] / k['filterpy_6d']:.1f})")
    print(f"  EKF step incl. one-pose kinematics ({k['state_dim_pose_steps']} params, 6-D): "
          f"{k['ekf_step_pose']:8.0f}/s")
    print(f"  batch-linearised (100 poses per Jacobian call) + filterpy updates: {k['batch_linearised']:8.0f}/s")
    gl = bench_gtsam_vs_lm(a.quick)
    res["gtsam_vs_lm"] = gl
    print("gtsam batch vs estcal LM (PUMA 560, pose data, identifiable set):")
    for r in gl:
        print(f"  {r['poses']:5d} poses  {r['solver']:<32} {r['wall_ms']:9.1f} ms wall {r['cpu_ms']:9.1f} ms CPU  "
              f"×{r['ratio_to_lm_wall']:.2f} wall ×{r['ratio_to_lm_cpu']:.2f} CPU of LM  "
              f"{r['iterations']} it, max |Δ| {r['max_diff_sigma']:.1e} σ")
    g = bench_gtsam(a.quick)
    res["gtsam"] = g
    print("gtsam batch LM + marginals: one CustomFactor per pose vs grouped:")
    for r in g:
        print(f"  {r['poses']:4d} poses, {r['poses_per_factor']:4d} poses/factor: {r['solve_plus_marginals_s'] * 1e3:7.1f} ms, "
              f"Python callbacks {r['python_callback_s'] * 1e3:7.1f} ms in {r['callbacks']} calls "
              f"({r['kinematics_evaluations']} vectorised kinematics evaluations)")
    res["isam2"] = _print_isam2(bench_isam2(a.quick))
    m = bench_mcmc(a.quick)
    res["mcmc"] = m
    print("MCMC to ESS target, all parameters of the PUMA problem:")
    for moves, r in m.items():
        print(f"  {moves:<8} {r['n_parameters']} params, ESS ≥ {r['target_ess']}: {r['wall_s']:.1f} s "
              f"(min ESS {r['min_ess']:.0f}, τ max {r['tau_max']:.1f}, {r['steps']} steps × {r['walkers']} walkers, "
              f"converged {r['converged']})")
    print(f"(load average {res['machine']['loadavg'][0]:.1f} on {res['machine']['nproc']} cores)")
    if a.json:
        write_json(a.json, res)
    return res


if __name__ == "__main__":
    main()
