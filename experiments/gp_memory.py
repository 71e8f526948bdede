"""How much L-BFGS-B memory the joint-space GP's hyperparameter fit should keep: likelihood evaluations
and the optimum reached, scipy's default (10 correction pairs) against more.

The fit (:func:`estcal.discrepancy.residual.fit_joint_gp`) optimises 2·(active joints) + 1 log
hyperparameters — 17 on TIAGo — with L-BFGS-B (Byrd, Lu, Nocedal & Zhu 1995), whose limited-memory
Hessian keeps ``maxcor`` pairs of (step, gradient change). With fewer pairs than dimensions the
approximation forgets curvature it has seen, and on a likelihood this cheap in dimensions and this
expensive per evaluation (a Cholesky and an inverse of 444 × 444 on a TIAGo session, ~4 ms), memory is
free and evaluations are not. Nocedal & Wright (2006, §7.2) note that 3–20 pairs usually suffice; here
the question is measured.

For every joint GP fit ``estcal diagnose``'s error budget makes on the published data (the all-rows fit
and the five posture-grouped folds that start from it; :func:`gp_restarts.captured_fits`), and the
simulated two-optima cases of ``experiments/gp_restarts.py``, the first L-BFGS-B run is repeated with
``maxcor`` = 10, 20 and 30 from the same start, same bounds and tolerance: likelihood evaluations and
the final negative log marginal likelihood (nats; lower is better).

Usage::

    python experiments/gp_memory.py [--cases tiago,talos,ur10,sim] [--maxcor 10,20,30] [--json out.json]

Figures and the decision: docs/benchmarks.md, "Everyday commands".
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

from gp_restarts import DATA, _cases, captured_fits, simulated_cases  # noqa: E402


def runs(fit, maxcors, maxiter=200):
    """``{maxcor: (evaluations, final nll)}`` of the first run of one fit."""
    from scipy.optimize import minimize

    from estcal.base.blas import single_thread_blas
    from estcal.discrepancy.residual import NLL_FTOL

    out = {}
    with single_thread_blas():
        for mc in maxcors:
            r = minimize(fit.nll, fit.x0, jac=True, method="L-BFGS-B", bounds=fit.bounds,
                         options={"maxiter": maxiter, "ftol": NLL_FTOL, "maxcor": mc})
            out[mc] = (int(r.nfev), float(r.fun), bool(r.success))
    return out


def real_fits(groups):
    from estcal.discrepancy.residual import joint_gp_fit_problem

    cases = _cases()
    for group in groups:
        for label, files, options in cases.get(group, []):
            if not all(f.exists() for f in files):
                print(f"{label}: data not found, skipped")
                continue
            for i, (args, kwargs) in enumerate(captured_fits(files, options)):
                readings, H, residuals, _, joint_of, joint_names = args[:6]
                yield (label, "all rows" if kwargs.get("start") is None else f"fold {i}",
                       joint_gp_fit_problem(readings, H, residuals, joint_of, joint_names, kwargs.get("start")))


def simulated_fits(seeds=2, wobbles=(0.1, 0.25), snrs=(0.7, 2.0)):
    """The two-optima simulation of experiments/gp_restarts.py (TIAGo 11-30 design, a short-scale wobble of
    arm_6_joint's placement)."""
    from estcal.discrepancy.residual import joint_gp_fit_problem

    if not (DATA / "tiago" / "qualisys_2021-11-30_static_postures.csv").exists():
        print("TIAGo data not found: simulated cases skipped")
        return
    for label, _, (Q, H, R, _names, jo, joint_names) in simulated_cases(seeds, wobbles, snrs):
        yield label, "all rows", joint_gp_fit_problem(Q, H, R, jo, joint_names)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="tiago,talos,ur10,sim")
    ap.add_argument("--maxcor", default="10,20,30")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    wanted = a.cases.split(",")
    mcs = [int(v) for v in a.maxcor.split(",")]
    rows = []
    fits = list(real_fits([g for g in ("tiago", "talos", "ur10") if g in wanted]))
    fits += list(simulated_fits()) if "sim" in wanted else []
    for label, which, fit in fits:
        r = runs(fit, mcs)
        rows.append({"case": label, "fit": which, "coordinates": int(fit.Y.size), "dimension": len(fit.x0),
                     "runs": {str(k): {"evaluations": v[0], "nll": v[1], "converged": v[2]} for k, v in r.items()}})
        print(f"{label:34s} {which:8s} M={fit.Y.size:5d} " + "  ".join(
            f"m={k}: {v[0]:3d} ev {v[1] - r[mcs[0]][1]:+8.3f}" for k, v in r.items()), flush=True)
    tot = {mc: sum(r["runs"][str(mc)]["evaluations"] for r in rows) for mc in mcs}
    # evaluations weighted by their cost (∝ M³: the factorisations dominate)
    cost = {mc: sum(r["runs"][str(mc)]["evaluations"] * (r["coordinates"] / 444) ** 3 for r in rows) for mc in mcs}
    worse = {mc: sum(r["runs"][str(mc)]["nll"] > r["runs"][str(mcs[0])]["nll"] + 0.5 for r in rows) for mc in mcs}
    better = {mc: sum(r["runs"][str(mc)]["nll"] < r["runs"][str(mcs[0])]["nll"] - 0.5 for r in rows) for mc in mcs}
    summary = {"fits": len(rows), "evaluations": tot, "cost_in_444_coordinate_evaluations": cost,
               "worse_by_half_a_nat_than_default": worse, "better_by_half_a_nat_than_default": better}
    print(json.dumps(summary, indent=1))
    if a.json:
        a.json.write_text(json.dumps({"summary": summary, "fits": rows}, indent=1))


if __name__ == "__main__":
    main()
