"""Benchmark: compensation of N pose targets at once (vectorised Levenberg–Marquardt).

PUMA 560 with masses and a 2 kg payload; the model is the nominal robot + 1 mm / 1 mrad
random geometric errors + j2/j3 compliance; N well-conditioned targets planned on the
nominal model (as in experiments/compensation.py). Measures, median of the repeats:

* ``solve_ms``      — :func:`estcal.compensation.compensate` without covariance;
* ``with_std_ms``   — with the covariance propagation (30 free parameters);
* ``rows_per_s``    — N / solve time; ``iterations_max`` / ``iterations_median``;
* ``max_error_mm``  — largest residual of the reached rows (a sanity check).

Usage::

    python benchmarks/bench_compensate.py [--targets 2000] [--repeats 5] [--quick] [--json PATH]

Not a timed test: numbers depend on the machine (``load_average_1min`` recorded).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))


def main(argv=None) -> dict:
    import compensation as exp  # experiments/compensation.py: nominal robot and target planning

    from estcal.compensation import compensate
    from estcal.effects import make_effect
    from estcal.base.jsonio import write_json
    from estcal.kinematics.transforms import matrix_to_quat

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", type=int, default=None, help="pose targets (default 2000, quick 200)")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats (default 5, quick 2)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    n = a.targets or (200 if a.quick else 2000)
    reps = a.repeats or (2 if a.quick else 5)

    nominal = exp.nominal_robot()
    model = nominal.add_effect(make_effect("joint_compliance", nominal, joints=["j2", "j3"]))
    rng = np.random.default_rng(0)
    geo = [i for i, k in enumerate(model.params.kinds) if k in ("geometric", "offset", "base", "tool")]
    model.params.values[geo] += rng.normal(0, 1e-3, len(geo))
    model.params["compliance_j2"], model.params["compliance_j3"] = exp.COMPLIANCE.values()
    names = [model.params.names[i] for i in geo[:30]]
    cov = (names, np.diag(np.full(len(names), 1e-4)) ** 2)
    q0, p, R = exp.plan_targets(nominal, n, 7)
    T = np.c_[p, matrix_to_quat(R)]

    def timed(**kw):
        ts, res = [], None
        for _ in range(reps):
            t = time.perf_counter()
            res = compensate(model, T, q0, **kw)
            ts.append(time.perf_counter() - t)
        return float(np.median(ts)) * 1e3, res

    solve_ms, res = timed(covariance=None)
    std_ms, _ = timed(covariance=cov)
    out = {"n_targets": int(len(T)), "repeats": reps, "solve_ms": solve_ms, "with_std_ms": std_ms,
           "rows_per_s": len(T) / solve_ms * 1e3, "iterations_max": int(res.iterations.max()),
           "iterations_median": float(np.median(res.iterations)), "reachable": int(res.reachable.sum()),
           "max_error_mm": float(res.error_mm[res.reachable].max()),
           "load_average_1min": os.getloadavg()[0]}
    print(f"{out['n_targets']} pose targets: solve {solve_ms:.1f} ms ({out['rows_per_s']:.0f} rows/s), "
          f"with std {std_ms:.1f} ms; iterations median {out['iterations_median']:.0f}, max "
          f"{out['iterations_max']}; {out['reachable']} reached, max residual {out['max_error_mm']:.2g} mm "
          f"(load {out['load_average_1min']:.1f})")
    if a.json:
        write_json(a.json, out)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
