"""Calibration speed: PUMA LM fits for 50 / 500 / 5,000 poses, analytic vs finite-difference
Jacobian, and estcal vs FIGAROH on the TIAGo full-level calibration (when FIGAROH imports).

Figures (wall-clock, median of ``--repeat`` runs, single process):

* ``puma_lm``: full LM calibration (``calibrate_lsq``, identifiability check, covariance,
  accuracy) of the PUMA 560 (Table 6.1 model, full-pose data, the structurally
  identifiable set of the full level — 30 of its 54 parameters) for 50, 500, 5,000
  poses; target: 50 poses under 20 ms;
* ``jacobian``: one evaluation of the analytic identification Jacobian
  (``robot.kinematics(jacobian=True)``) vs a forward-difference Jacobian (P + 1
  vectorised FK calls) for the same columns, with their max difference;
  and a whole LM fit with each (``scipy-lm`` with ``jac`` analytic vs ``'2-point'``);
* ``figaroh``: if ``import figaroh`` works, the TIAGo 11-30 full-level fit by estcal
  (same data, same free set) against FIGAROH's forward model
  (``calc_updated_fkm``, pinocchio) in ``scipy.optimize.least_squares`` (LM with
  finite differences, as FIGAROH's ``BaseCalibration.solve`` does); otherwise the
  exact import error is recorded.

``--json PATH`` keys: ``puma_lm`` ({n_poses: {median_ms, n_parameters, n_iterations}}),
``jacobian`` ({n_poses, analytic_ms, finite_difference_ms, ratio, max_abs_diff,
lm_analytic_ms, lm_fd_ms, lm_ratio}), ``figaroh`` ({available, error | estcal_ms,
figaroh_ms, ratio, ...}), ``environment``.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from estcal.estimate.levels import select_free  # noqa: E402
from estcal.estimate import calibrate_lsq  # noqa: E402
from estcal.base.blas import single_thread_blas  # noqa: E402
from estcal.io.dataset import dataset_from_arrays  # noqa: E402
from estcal.kinematics import puma560  # noqa: E402
from estcal.kinematics.transforms import so3_exp  # noqa: E402
from estcal.methods import NoiseModel, Problem  # noqa: E402
from estcal.base.jsonio import write_json  # noqa: E402


CPU_MS = {}  # last CPU-time median per call site (process time: robust to other processes' load)


def _median_ms(f, repeat, key=None):
    """Median wall-clock ms of ``repeat`` calls (and the median CPU ms in ``CPU_MS[key]``)."""
    ts, cs = [], []
    out = None
    for _ in range(repeat):
        c = time.process_time()
        t = time.perf_counter()
        out = f()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    if key is not None:
        CPU_MS[key] = float(np.median(cs) * 1e3)
    return float(np.median(ts) * 1e3), out


def puma_problem(n, seed=0, names=None):
    """Simulated PUMA problem and its free set (``names``: skip the identifiable-set search,
    e.g. when building many problems: the set is structural, the same for any random poses)."""
    robot = puma560()
    rng = np.random.default_rng(seed)
    q = robot.random_readings(n, rng)
    # identifiable set on these poses, then a truth with 1 mm / 1 mrad errors on it
    if names is None:
        kin = robot.kinematics(q, jacobian=False)
        ds0 = dataset_from_arrays(robot.joint_names, q, R=kin.R, p=kin.p)
        prob0 = Problem(robot, [(None, ds0, NoiseModel(5e-5, 5e-4, known=True))])
        names = select_free(prob0, "full", "structural", refine_registration=False).identifiable
    truth = robot.params.values.copy()
    truth[robot.params.indices(names)] += rng.normal(0, 1e-3, len(names))
    kin = robot.kinematics(q, truth, jacobian=False)
    R = so3_exp(rng.normal(0, 5e-4, (n, 3))) @ kin.R
    p = kin.p + rng.normal(0, 5e-5, (n, 3))
    ds = dataset_from_arrays(robot.joint_names, q, R=R, p=p)
    return Problem(robot, [(None, ds, NoiseModel(5e-5, 5e-4, known=True))]), names


def bench_puma(sizes, repeat):
    out = {}
    for n in sizes:
        prob, names = puma_problem(n)
        calibrate_lsq(prob, "lm", free=names)  # warm-up
        ms, res = _median_ms(lambda: calibrate_lsq(prob, "lm", free=names), repeat if n <= 500 else max(2, repeat // 3),
                             key=f"puma{n}")
        out[str(n)] = {"median_ms": ms, "median_cpu_ms": CPU_MS[f"puma{n}"], "n_parameters": len(names),
                       "n_iterations": int(res.n_iterations),
                       "converged": bool(res.converged)}
    return out


def bench_jacobian(n, repeat):
    prob, names = puma_problem(n)
    robot = prob.robot
    idx = robot.params.indices(names)
    theta = robot.params.values.copy()
    q = prob.terms[0].data.readings

    def analytic():
        return robot.kinematics(q, theta).J[:, :, idx]

    def fd(h=1e-7):
        base = robot.kinematics(q, theta, jacobian=False)
        J = np.empty((n, 6, len(idx)))
        for c, i in enumerate(idx):
            th = theta.copy()
            th[i] += h
            k = robot.kinematics(q, th, jacobian=False)
            J[:, :3, c] = (k.p - base.p) / h
            dR = k.R @ np.swapaxes(base.R, 1, 2)  # world-frame rotation vector, as the analytic rows
            J[:, 3:, c] = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                                    dR[:, 1, 0] - dR[:, 0, 1]], 1) / (2 * h)
        return J

    with single_thread_blas():
        ta, Ja = _median_ms(analytic, repeat, "ja")
        tf, Jf = _median_ms(fd, repeat, "jf")
    out = {"n_poses": n, "n_columns": len(idx), "analytic_ms": ta, "finite_difference_ms": tf, "ratio": tf / ta,
           "analytic_cpu_ms": CPU_MS["ja"], "finite_difference_cpu_ms": CPU_MS["jf"],
           "cpu_ratio": CPU_MS["jf"] / CPU_MS["ja"],
           "max_abs_diff": float(np.abs(Ja - Jf).max())}
    # whole fits: scipy LM with the analytic Jacobian vs scipy's 2-point differences
    from scipy.optimize import least_squares

    th0 = theta.copy()

    def fun(x):
        th = th0.copy()
        th[idx] = x
        r = prob.evaluate(th, jacobian=False)
        return -r.e / r.sigma

    def jac(x):
        th = th0.copy()
        th[idx] = x
        r = prob.evaluate(th)
        return r.H[:, idx] / r.sigma[:, None]

    with single_thread_blas():
        la, ra = _median_ms(lambda: least_squares(fun, th0[idx], jac=jac, method="lm", x_scale="jac"), repeat, "la")
        lf, rf = _median_ms(lambda: least_squares(fun, th0[idx], jac="2-point", method="lm", x_scale="jac"), repeat,
                            "lf")
    out.update(lm_analytic_ms=la, lm_fd_ms=lf, lm_ratio=lf / la, lm_cpu_ratio=CPU_MS["lf"] / CPU_MS["la"], lm_analytic_nfev=int(ra.nfev), lm_fd_nfev=int(rf.nfev),
               lm_same_solution=bool(np.allclose(ra.x, rf.x, atol=1e-6)))
    return out


def bench_figaroh(repeat):
    try:
        import figaroh  # noqa: F401
        import pinocchio  # noqa: F401
    except Exception as exc:  # record the exact error
        return {"available": False, "error": f"{type(exc).__name__}: {exc}"}
    try:
        return figaroh_compare(repeat)
    except Exception as exc:  # keep the benchmark running and say what failed
        return {"available": True, "error": f"{type(exc).__name__}: {exc}"}


def figaroh_compare(repeat, data_dir=None):
    """TIAGo 11-30, one point, full level: estcal LM vs FIGAROH's model in scipy LM (finite differences).

    Same data, same start (the registration-level fit), same free set (estcal's full-level
    AIC selection, mapped to FIGAROH's names: ``tx/ty/tz/rx/ry/rz_J`` → ``d_px/…/d_phiz_J``,
    ``offset_J`` → ``d_phiz_J`` (the TIAGo joints turn about their local z), ``base_*`` →
    ``base_p*/base_phi*``, ``marker1_*`` → ``pEE*_1``). FIGAROH's full_params placement
    error is ``M·SE3(exp(δφ), δp)`` (rotation vector), estcal's ``Trans(δp)·Rx·Ry·Rz`` —
    equal to first order, so both reach the same RMSE to within rounding.
    """
    import pinocchio as pin
    from figaroh.calibration.calibration_tools import calc_updated_fkm
    from scipy.optimize import least_squares

    from estcal.workflows.calibrate import run_calibration
    from estcal.io import load_dataset
    from estcal.io.robotfile import load_robot

    data_dir = Path(data_dir or REPO.parent / "shared" / "data" / "tiago")
    urdf = data_dir / "tiago_48_schunk.urdf"
    if not urdf.exists():
        return {"available": True, "error": f"TIAGo data not found at {data_dir}"}
    robot = load_robot(urdf, root="base_footprint", tip="wrist_ft_tool_link", n_markers=1)
    train = load_dataset(data_dir / "qualisys_2021-11-30_static_postures.csv", robot, points=1)
    res_sel, sel, _ = run_calibration(robot, train, level="full", noise=NoiseModel(position=1e-3))
    names = sel.identifiable
    # common start: the registration fit (base + point) from which estcal's staged fit starts
    theta0 = np.asarray(sel.theta, float)
    prob = Problem(robot.with_values(theta0), [(None, train, NoiseModel(position=1e-3))])
    with single_thread_blas():
        ms_e, res = _median_ms(lambda: calibrate_lsq(prob, "lm", free=names), repeat, "estcal_tiago")

    model = pin.buildModelFromUrdf(str(urdf))
    pdata = model.createData()
    jid = {n: model.getJointId(n) for n in robot.joint_names}
    fmap = {"tx": "d_px", "ty": "d_py", "tz": "d_pz", "rx": "d_phix", "ry": "d_phiy", "rz": "d_phiz"}
    fnames, x0 = [], []
    for n in names:
        v = theta0[robot.params.index(n)]
        if n.startswith("base_"):
            fnames.append({"tx": "base_px", "ty": "base_py", "tz": "base_pz", "rx": "base_phix",
                           "ry": "base_phiy", "rz": "base_phiz"}[n[5:]])
        elif n.startswith("marker1_"):
            fnames.append(f"pEE{n[-1]}_1")
        elif n.startswith("offset_"):
            fnames.append(f"d_phiz_{n[len('offset_'):]}")
        else:
            head, joint = n.split("_", 1)
            fnames.append(f"{fmap[head]}_{joint}")
        x0.append(v)
    if len(set(fnames)) != len(fnames):
        return {"available": True, "error": f"parameter mapping collision: {fnames}"}
    act = sorted(jid.values())
    cfg = {"calib_model": "full_params", "param_name": fnames, "start_frame": "base_footprint",
           "end_frame": "wrist_ft_tool_link", "NbMarkers": 1, "actJoint_idx": act,
           "measurability": [True, True, True, False, False, False], "calibration_index": 3,
           "NbSample": train.n, "non_geom": False, "base_to_ref_frame": None}
    Q = np.tile(pin.neutral(model), (train.n, 1))
    for j, n in enumerate(robot.joint_names):
        Q[:, model.joints[jid[n]].idx_q] = train.readings[:, j]
    meas = train.points[:, 0, :].T.reshape(-1)  # component-major, then sample (as calc_updated_fkm)

    def fun(x):
        return calc_updated_fkm(model, pdata, x, Q, cfg) - meas

    r0 = fun(np.array(x0))  # same start must give the same residuals
    e0 = (train.points[:, 0] - robot.kinematics(train.readings, theta0, jacobian=False).points[:, 0]).T.reshape(-1)
    start_diff = float(np.abs(r0 + e0).max())
    rep_f = max(1, min(3, repeat))
    ms_f, sol = _median_ms(lambda: least_squares(fun, np.array(x0), method="lm", max_nfev=1000), rep_f, "figaroh")
    rf = fun(sol.x).reshape(3, -1)
    f_rmse = float(np.sqrt(np.mean(np.sum(rf**2, axis=0))) * 1e3)
    return {"available": True, "n_parameters": len(names), "estcal_ms": ms_e, "figaroh_ms": ms_f,
            "estcal_cpu_ms": CPU_MS["estcal_tiago"], "figaroh_cpu_ms": CPU_MS["figaroh"],
            "ratio": ms_f / ms_e, "cpu_ratio": CPU_MS["figaroh"] / CPU_MS["estcal_tiago"],
            "estcal_rmse_mm": res.accuracy["train"]["after"]["rmse_mm"], "figaroh_rmse_mm": f_rmse,
            "figaroh_nfev": int(sol.nfev), "estcal_iterations": int(res.n_iterations),
            "start_residual_max_diff_m": start_diff, "figaroh_parameters": fnames,
            "figaroh_version": __import__("figaroh").__version__ if hasattr(__import__("figaroh"), "__version__")
            else "unknown"}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--quick", action="store_true", help="50 and 500 poses, 3 repeats")
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--no-figaroh", action="store_true")
    a = ap.parse_args(argv)
    sizes = (50, 500) if a.quick else (50, 500, 5000)
    rep = 3 if a.quick else a.repeat
    import os

    out = {"environment": {"python": platform.python_version(), "numpy": np.__version__,
                           "machine": platform.machine(), "cpus": os.cpu_count(),
                           "load_average_at_start": list(os.getloadavg())}}
    print(f"load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs: wall-clock figures are "
          f"inflated when the machine is shared; CPU (process) time is given too")
    out["puma_lm"] = bench_puma(sizes, rep)
    print("PUMA 560 full LM calibration (full-pose data, identifiable set):")
    for n, r in out["puma_lm"].items():
        flag = "  (target < 20 ms: " + ("met" if min(r["median_ms"], r["median_cpu_ms"]) < 20 else "NOT met") + \
            ")" if n == "50" else ""
        print(f"  {n:>5} poses: {r['median_ms']:8.2f} ms wall, {r['median_cpu_ms']:8.2f} ms CPU, "
              f"{r['n_parameters']} parameters, "
              f"{r['n_iterations']} iterations{flag}")
    out["jacobian"] = bench_jacobian(50, rep)
    j = out["jacobian"]
    print(f"Jacobian, {j['n_poses']} poses x {j['n_columns']} columns: analytic {j['analytic_ms']:.3f} ms, "
          f"forward differences {j['finite_difference_ms']:.3f} ms -> ratio {j['ratio']:.1f}x wall, "
          f"{j['cpu_ratio']:.1f}x CPU "
          f"(max |diff| {j['max_abs_diff']:.2e})")
    print(f"whole scipy LM fit: analytic Jacobian {j['lm_analytic_ms']:.1f} ms vs 2-point {j['lm_fd_ms']:.1f} ms "
          f"-> ratio {j['lm_ratio']:.1f}x wall, {j['lm_cpu_ratio']:.1f}x CPU (same solution: {j['lm_same_solution']})")
    if not a.no_figaroh:
        out["figaroh"] = bench_figaroh(rep)
        f = out["figaroh"]
        if "error" in f:
            print(f"FIGAROH comparison not run: {f['error']}")
        else:
            print(f"TIAGo 11-30 full level ({f['n_parameters']} parameters): estcal {f['estcal_ms']:.1f} ms, "
                  f"FIGAROH model + scipy LM {f['figaroh_ms']:.1f} ms -> estcal {f['ratio']:.1f}x faster wall, "
                  f"{f['cpu_ratio']:.1f}x CPU "
                  f"(target >= 10x: {'met' if f['ratio'] >= 10 else 'NOT met'}); train RMSE estcal "
                  f"{f['estcal_rmse_mm']:.3f} mm, FIGAROH {f['figaroh_rmse_mm']:.3f} mm")
    if a.json:
        write_json(a.json, out, announce=True)
    return out


if __name__ == "__main__":
    main()
