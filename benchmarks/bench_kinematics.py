"""Benchmark: vectorised forward kinematics + full identification Jacobian.

Measures, for a 6-joint robot (PUMA 560, Table 6.1 model: 54 parameters) and
N = 10,000 poses (issue 2 target: FK + Jacobian < 50 ms on this machine):

* ``fk_ms``            — FK only (``jacobian=False``), median of the repeats;
* ``fk_jac_ms``        — FK + analytic Jacobian of the tool pose (N, 6, P);
* ``poses_per_s``      — N / fk_jac time;
* ``fk_best_ms``, ``fk_jac_best_ms`` — fastest repeat (less sensitive to other load on the
  machine; ``load_average_1min`` is recorded with the result);
* ``fd_jac_ms``        — the same Jacobian by central finite differences (2P FK calls);
* ``fd_over_analytic`` — time ratio finite differences / analytic;
* ``max_abs_diff``     — max |analytic − finite difference| (a sanity check).

Usage::

    python benchmarks/bench_kinematics.py [--poses 10000] [--repeats 7] [--robot puma560]
                                          [--quick] [--json PATH]

``--json`` writes the keys above plus ``robot``, ``n_poses``, ``n_params``,
``repeats``, ``target_ms``, ``meets_target`` (median) and ``meets_target_best``. Not a timed test: numbers
depend on the machine.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from estcal.io.robotfile import load_robot  # noqa: E402
from estcal.kinematics.transforms import so3_log  # noqa: E402
from estcal.io.jsonio import write_json  # noqa: E402


def _times(fn, repeats: int) -> np.ndarray:
    fn()  # warm-up (allocations, imports)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return np.array(ts)


def fd_jacobian(robot, q, theta, eps=1e-6):
    P = robot.n_params
    J = np.empty((q.shape[0], 6, P))
    for i in range(P):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += eps
        tm[i] -= eps
        kp = robot.kinematics(q, tp, jacobian=False)
        km = robot.kinematics(q, tm, jacobian=False)
        J[:, :3, i] = (kp.p - km.p) / (2 * eps)
        J[:, 3:, i] = so3_log(kp.R @ np.swapaxes(km.R, 1, 2)) / (2 * eps)
    return J


def run(robot_name: str = "puma560", n_poses: int = 10_000, repeats: int = 7, fd_repeats: int = 1) -> dict:
    robot = load_robot(robot_name)
    rng = np.random.default_rng(0)
    q = robot.random_readings(n_poses, rng)
    theta = robot.params.values.copy()
    ts_fk = _times(lambda: robot.kinematics(q, theta, jacobian=False), repeats)
    ts_jac = _times(lambda: robot.kinematics(q, theta, jacobian=True), repeats)
    t_fk, t_jac = float(np.median(ts_fk)), float(np.median(ts_jac))
    t_fd = float(np.median(_times(lambda: fd_jacobian(robot, q, theta), fd_repeats)))
    Ja = robot.kinematics(q, theta).J
    Jf = fd_jacobian(robot, q, theta)
    return {
        "robot": robot.name, "n_poses": n_poses, "n_joints": robot.n_joints, "n_params": robot.n_params,
        "repeats": repeats, "fk_ms": t_fk * 1e3, "fk_jac_ms": t_jac * 1e3, "poses_per_s": n_poses / t_jac,
        "fk_jac_best_ms": float(ts_jac.min()) * 1e3, "fk_best_ms": float(ts_fk.min()) * 1e3,
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "fd_jac_ms": t_fd * 1e3, "fd_over_analytic": t_fd / t_jac,
        "max_abs_diff": float(np.abs(Ja - Jf).max()),
        "target_ms": 50.0, "meets_target": bool(t_jac * 1e3 < 50.0) if n_poses == 10_000 else None,
        "meets_target_best": bool(ts_jac.min() * 1e3 < 50.0) if n_poses == 10_000 else None,
        "python": platform.python_version(), "numpy": np.__version__, "machine": platform.machine(),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", default="puma560")
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="1,000 poses, 3 repeats")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.poses, a.repeats = min(a.poses, 1000), 3
    r = run(a.robot, a.poses, a.repeats)
    print(f"robot {r['robot']}: {r['n_joints']} joints, {r['n_params']} parameters, {r['n_poses']} poses "
          f"(median of {r['repeats']})")
    print(f"  (median; best of the repeats in brackets; 1-min load average {r['load_average_1min']})")
    print(f"  FK only                 {r['fk_ms']:9.2f} ms   [{r['fk_best_ms']:.2f}]")
    print(f"  FK + analytic Jacobian  {r['fk_jac_ms']:9.2f} ms   [{r['fk_jac_best_ms']:.2f}]   "
          f"{r['poses_per_s']:,.0f} poses/s"
          + (f"   target < 50 ms: median {'met' if r['meets_target'] else 'NOT met'}, best "
             f"{'met' if r['meets_target_best'] else 'NOT met'}" if r["meets_target"] is not None else ""))
    print(f"  finite-diff Jacobian    {r['fd_jac_ms']:9.2f} ms   ({r['fd_over_analytic']:.1f}x the analytic time)")
    print(f"  max |analytic - FD|     {r['max_abs_diff']:.2e}")
    if a.json:
        write_json(a.json, r)
    return r


if __name__ == "__main__":
    main()
