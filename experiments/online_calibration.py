"""Online incremental calibration of a PUMA 560, stopping when more data would not help.

Measurements (tool pose, Gaussian noise) arrive one at a time. Before any
measurement, the covariance recursion for the planned pose stream (it does not
depend on the data: :mod:`estcal.estimate.riccati`) predicts P_k; with
repeatability modelled as process noise Q > 0 the covariance has a floor P∞
(periodic Riccati solution of the pose cycle), and the stopping rule 4.114
‖P_k − P∞‖₂ ≤ δ ‖P∞‖₂ gives the index M after which more data no longer help.
The filter (filterpy EKF) then runs on the stream, printing the estimate and
its uncertainty as it goes, and stops at M. As a check the script continues to
the end of the pool and reports how little the error improved after M.

Usage::

    python experiments/online_calibration.py [--quick] [--json PATH] [--delta 0.1] [--q 1e-5]

JSON keys: ``n_free``, ``planned_stop`` (M), ``pool`` (poses available),
``q`` (process-noise std per pose, m/rad), ``floor_std_max`` (max √diag P∞),
``at_stop`` / ``at_end`` ({``rms_error_over_std`` (RMS of (estimate−truth)/std),
``max_std``}), ``trace`` (list of {row, trace_P, predicted_trace_P, max_std}).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.estimate._common import GroupedProblem  # noqa: E402
from estcal.estimate.kalman import ParameterFilter, process_noise  # noqa: E402
from estcal.estimate.riccati import (covariance_sequence, periodic_steady_state, planned_jacobians,  # noqa: E402
                                     stopping_index_sequence)
from estcal.estimate.testproblems import simulated_problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small pool (smoke test)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--delta", type=float, default=0.1, help="stop when ‖P_k − P∞‖ ≤ δ ‖P∞‖")
    ap.add_argument("--q", type=float, default=1e-5, help="process-noise std per pose (repeatability), SI")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    pool = 150 if a.quick else 600
    cycle = 40
    # a planned cycle of `cycle` poses, measured repeatedly (the stream)
    base = simulated_problem("puma560", n_poses=cycle, seed=a.seed, sigma_p=1e-4, sigma_r=1e-4)
    readings = np.tile(base.problem.terms[0].data.readings, (pool // cycle + 1, 1))[:pool]
    sim = simulated_problem("puma560", readings=readings, seed=a.seed + 1, free=base.free, truth=base.truth,
                            sigma_p=1e-4, sigma_r=1e-4)
    names = sim.free
    p = len(names)
    Q = process_noise(names, a.q)
    P0 = np.eye(p) * 0.1 ** 2
    # ---- offline: planned covariance, floor and stopping index (no measurement used)
    t0 = time.perf_counter()
    H, s, _ = planned_jacobians(sim.problem.robot, readings, "location", free=names, sigma_p=1e-4, sigma_r=1e-4)
    Ps = covariance_sequence(list(H), list(s), P0, Q)
    P_inf, cycles = periodic_steady_state(list(H[:cycle]), list(s[:cycle]), Q, P0=Ps[cycle - 1])
    # P_k fluctuates within a cycle; P∞ is the end-of-cycle floor, so rule 4.114 is applied at cycle ends
    Mc = stopping_index_sequence(Ps[cycle - 1::cycle], P_inf, a.delta * np.linalg.norm(P_inf, 2))
    M = Mc * cycle if Mc > 0 else -1
    plan_s = time.perf_counter() - t0
    print(f"plan: {p} free parameters, pool {pool} poses (cycle of {cycle}), q = {a.q:g} per pose")
    print(f"  floor P∞: max std {np.sqrt(np.diag(P_inf)).max():.3g} (periodic Riccati, {cycles} cycles); "
          f"stopping index (4.114, δ = {a.delta}) M = {M}  [{plan_s:.2f} s]")
    # ---- online: the filter on the stream
    gp = GroupedProblem(sim.problem)
    flt = ParameterFilter(sim.problem.params.values, sim.problem.params.free_indices, P0, Q, names=names)
    truth = sim.truth_free
    trace, at_stop = [], None

    def score():
        x, sd = flt.x, flt.std
        return {"rms_error_over_std": float(np.sqrt(np.mean(((x - truth) / sd) ** 2))), "max_std": float(sd.max()),
                "max_abs_error": float(np.abs(x - truth).max())}

    for k in range(pool):
        flt.step(gp.subproblem([k]))
        if (k + 1) % (cycle // 2) == 0 or k + 1 == M:
            tr = float(np.trace(flt.P))
            trace.append({"row": k + 1, "trace_P": tr, "predicted_trace_P": float(np.trace(Ps[k])),
                          "max_std": float(flt.std.max())})
            print(f"  row {k + 1:4d}: trace P {tr:.3e} (predicted {np.trace(Ps[k]):.3e}), max std "
                  f"{flt.std.max():.3g}, NIS/row {flt.monitor.running(p // 6 + 1)['nis_per_row']:.2f}")
        if k + 1 == M:
            at_stop = score()
            print(f"STOP at row {M}: predicted covariance within δ of its floor — "
                  f"RMS error/std {at_stop['rms_error_over_std']:.2f}, max std {at_stop['max_std']:.3g}")
    at_end = score()
    if at_stop is None:
        print(f"the planned stop M = {M} is beyond the pool of {pool}: all measurements were used")
    else:
        print(f"(continuing to {pool}: max std {at_end['max_std']:.3g} vs {at_stop['max_std']:.3g} at the "
              f"stop — the extra {pool - M} measurements bought "
              f"{100 * (1 - at_end['max_std'] / at_stop['max_std']):.1f} % in std)")
    out = {"n_free": p, "planned_stop": M, "pool": pool, "q": a.q, "floor_std_max": float(np.sqrt(np.diag(P_inf)).max()),
           "at_stop": at_stop, "at_end": at_end, "trace": trace, "plan_time_s": plan_s}
    if a.json:
        write_json(a.json, out)
    return out


if __name__ == "__main__":
    main()
