"""Benchmark: vectorised forward kinematics + full identification Jacobian.

Measures, for a 6-joint robot (PUMA 560, Table 6.1 model: 54 parameters) and
N = 10,000 poses (target: FK + Jacobian < 50 ms on this machine):

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
from estcal.base.jsonio import write_json  # noqa: E402


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


def _pinocchio_chain(robot, urdf, tip):
    """Pinocchio model of ``urdf`` reduced to the joints of ``robot`` (the others locked at
    their neutral value), its data and the tool frame id; ``None`` when pin is absent."""
    try:
        import pinocchio as pin
    except ImportError:
        return None
    full = pin.buildModelFromUrdf(str(urdf))
    keep = set(robot.joint_names)
    lock = [full.getJointId(n) for n in list(full.names)[1:] if n not in keep]
    model = pin.buildReducedModel(full, lock, pin.neutral(full))
    if list(model.names)[1:] != list(robot.joint_names):
        raise ValueError(f"Pinocchio joint order {list(model.names)[1:]} differs from estcal's {robot.joint_names}")
    return pin, model, model.createData(), model.getFrameId(tip)


def vs_pinocchio(n_poses: int = 10_000, repeats: int = 5) -> dict | None:
    """estcal vs Pinocchio on the TIAGo arm chain (``base_footprint`` → ``wrist_ft_tool_link``).

    * estcal: one vectorised ``SerialRobot.kinematics`` call over the N poses — tool pose and its
      Jacobian (N, 6, P) w.r.t. *every* parameter of the identification model (6 base, 6 URDF
      placement parameters per joint, joint offsets and gains: P = 76);
    * Pinocchio (C++): per pose, in a Python loop (Pinocchio has no batched FK/Jacobian),
      ``computeJointJacobians`` (forward kinematics + joint Jacobians), ``updateFramePlacement``
      and ``getFrameJacobian(LOCAL_WORLD_ALIGNED)`` of the tool frame: (6, 8) — the columns of
      the 8 joint variables only. The loop's binding overhead is measured by the same loop with
      only ``updateFramePlacement`` (one SE(3) product) and reported, so the C++ cost can be bounded.

    Checks: tool positions agree to 1e-9 m and rotations to 1e-9; the joint-offset columns of
    estcal's Jacobian equal Pinocchio's joint Jacobian (rows reordered: estcal [v; ω], pin [v; ω]).
    Timing: runs interleaved (estcal, pin, estcal, …) so both see the same machine load; median
    and best of ``repeats``, wall and CPU time. ``None`` when pin or the TIAGo URDF is absent.
    """
    from estcal.kinematics.robots import shared_dir, tiago

    urdf = shared_dir() / "data" / "tiago" / "tiago_48_schunk.urdf"
    if not urdf.exists():
        return None
    robot = tiago(0)
    pc = _pinocchio_chain(robot, urdf, "wrist_ft_tool_link")
    if pc is None:
        return None
    pin, model, data, fid = pc
    q = robot.random_readings(n_poses, np.random.default_rng(0))
    theta = robot.params.values.copy()
    n = robot.n_joints
    P, R, J = np.empty((n_poses, 3)), np.empty((n_poses, 3, 3)), np.empty((n_poses, 6, n))
    frame = pin.LOCAL_WORLD_ALIGNED

    def run_pin():
        for i in range(n_poses):
            pin.computeJointJacobians(model, data, q[i])
            pin.updateFramePlacement(model, data, fid)
            J[i] = pin.getFrameJacobian(model, data, fid, frame)
            M = data.oMf[fid]
            P[i] = M.translation
            R[i] = M.rotation

    def run_overhead():
        for i in range(n_poses):
            pin.updateFramePlacement(model, data, fid)

    def run_estcal():
        return robot.kinematics(q, theta, jacobian=True)

    fns = {"estcal": run_estcal, "pinocchio": run_pin, "pin_loop_overhead": run_overhead}
    for f in fns.values():
        f()  # warm-up
    wall = {k: [] for k in fns}
    cpu = {k: [] for k in fns}
    load = []
    for _ in range(repeats):
        for k, f in fns.items():
            t, c = time.perf_counter(), time.process_time()
            f()
            wall[k].append(time.perf_counter() - t)
            cpu[k].append(time.process_time() - c)
        load.append(os.getloadavg()[0])
    kin = run_estcal()
    out = {"robot": "tiago (base_footprint -> wrist_ft_tool_link)", "n_poses": n_poses, "n_joints": n,
           "n_params_estcal": robot.n_params, "jacobian_columns_pinocchio": n, "repeats": repeats,
           "loadavg_1min": load, "pin_version": pin.__version__,
           "max_position_diff_m": float(np.abs(kin.p - P).max()),
           "max_rotation_diff": float(np.abs(kin.R - R).max()),
           "max_joint_jacobian_diff": float(np.abs(kin.J[:, :, robot.offset_idx] - J).max())}
    for k in fns:
        for kind, d in (("wall", wall), ("cpu", cpu)):
            out[f"{k}_{kind}_ms_median"] = float(np.median(d[k]) * 1e3)
            out[f"{k}_{kind}_ms_best"] = float(np.min(d[k]) * 1e3)
            out[f"{k}_{kind}_us_per_pose_median"] = float(np.median(d[k]) / n_poses * 1e6)
    for kind in ("wall", "cpu"):
        for stat in ("median", "best"):
            out[f"ratio_estcal_to_pin_{kind}_{stat}"] = (out[f"estcal_{kind}_ms_{stat}"]
                                                         / out[f"pinocchio_{kind}_ms_{stat}"])
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robot", default="puma560")
    ap.add_argument("--poses", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--quick", action="store_true", help="1,000 poses, 3 repeats")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--no-pinocchio", action="store_true", help="skip the TIAGo estcal-vs-Pinocchio row")
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
    if not a.no_pinocchio:
        pv = vs_pinocchio(a.poses, 3 if a.quick else 5)
        r["vs_pinocchio"] = pv
        if pv is None:
            print("TIAGo vs Pinocchio: skipped (pip install 'estcal[bench]' for pin; needs ../shared/data/tiago)")
        else:
            print(f"TIAGo arm ({pv['n_joints']} joints), {pv['n_poses']} poses, pin {pv['pin_version']} "
                  f"(median [best] of {pv['repeats']}, interleaved; load {', '.join(f'{x:.1f}' for x in pv['loadavg_1min'])}):")
            for k, label in (("estcal", f"estcal FK + J w.r.t. {pv['n_params_estcal']} params (vectorised)"),
                             ("pinocchio", f"Pinocchio FK + frame J, {pv['jacobian_columns_pinocchio']} joints (Python loop)"),
                             ("pin_loop_overhead", "  of which loop + binding overhead (est.)")):
                print(f"  {label:<58} wall {pv[k + '_wall_ms_median']:8.1f} ms [{pv[k + '_wall_ms_best']:.1f}]  "
                      f"CPU {pv[k + '_cpu_ms_median']:8.1f} ms [{pv[k + '_cpu_ms_best']:.1f}]  "
                      f"{pv[k + '_cpu_us_per_pose_median']:.2f} µs/pose CPU")
            print(f"  ratio estcal / Pinocchio: wall {pv['ratio_estcal_to_pin_wall_median']:.2f} "
                  f"[{pv['ratio_estcal_to_pin_wall_best']:.2f}], CPU {pv['ratio_estcal_to_pin_cpu_median']:.2f} "
                  f"[{pv['ratio_estcal_to_pin_cpu_best']:.2f}]   (target ≤ 2)")
            print(f"  same tool pose: max |Δp| {pv['max_position_diff_m']:.1e} m, max |ΔR| {pv['max_rotation_diff']:.1e}; "
                  f"joint-offset columns vs Pinocchio's joint Jacobian: max |Δ| {pv['max_joint_jacobian_diff']:.1e}")
    if a.json:
        write_json(a.json, r)
    return r


if __name__ == "__main__":
    main()
