"""When does the joint-space GP's random restart find a better optimum? The evidence behind the gate of
:func:`estcal.discrepancy.residual._restarts` (Rasmussen & Williams 2006, §5.4.1: the marginal likelihood
can have several local optima; restarts guard against them).

For every joint-space GP fit ``estcal diagnose``'s error budget makes (the fit on all rows, which runs one
random restart when the first run is suspect, and the fits of the five posture-grouped folds, which start
from it and run none), the first L-BFGS-B run is repeated exactly as :func:`~estcal.discrepancy.residual.fit_joint_gp`
runs it (:func:`~estcal.discrepancy.residual.joint_gp_fit_problem`), then ``--restarts`` runs from uniform
draws of the box (the first draw is the one the fit itself would take). Per fit: did the first run converge,
which hyperparameters ended on the box (length scales on their lower bound in particular), and how much
lower (in nats) the first restart and the best of the restarts ended.

Cases: the published data (``../shared/data``: TIAGo 11-26, 11-30 and both sessions, the three TALOS
sessions with ``--drop-flagged``, UR10), each through ``estcal.diagnose`` with its column map; and a
simulated likelihood with two optima: the TIAGo 11-30 design (readings and Jacobians) with residuals drawn
from the model itself, one wrist joint's placement wobbling along its travel at a short length scale
(0.1, 0.15, 0.25 × the joint's spread; signal RMS 0.7, 1 and 2 × the noise's): "a wobble" and "all noise"
both explain such data, the two optima of R&W's Fig. 5.5.

Usage::

    python experiments/gp_restarts.py [--restarts 5] [--sim-seeds 4] [--cases tiago,talos,ur10,sim] [--json out.json]

Figures (quoted in ``_restarts``'s docstring) and the decision: docs/benchmarks.md, "Everyday commands".
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
MAPS = REPO / "docs" / "maps"


def _cases():
    t, ta, u = DATA / "tiago", DATA / "talos", DATA / "ur10"
    tiago = dict(robot="tiago")
    talos = dict(robot=str(ta / "talos_reduced.urdf"), root="base_link", tip="arm_left_7_link",
                 column_map=str(MAPS / "talos.yaml"), drop_flagged=True)
    out = {"tiago": [("tiago 11-30", [t / "qualisys_2021-11-30_static_postures.csv"], tiago),
                     ("tiago 11-26", [t / "qualisys_2021-11-26_static_postures.csv"], tiago),
                     ("tiago both", [t / "qualisys_2021-11-30_static_postures.csv",
                                     t / "qualisys_2021-11-26_static_postures.csv"], tiago)],
           "talos": [(f"talos {f}", [ta / f"{f}.csv"], talos)
                     for f in ("talos_feb_arm_02_07_crane", "talos_feb_arm_02_10_contact", "talos_feb_arm_2_contact")],
           "ur10": [("ur10", [u / "calibration.csv"], dict(robot=str(u / "ur10_robot.urdf"), root="world",
                                                         tip="camera_color_optical_frame",
                                                         column_map=str(MAPS / "ur10.yaml")))]}
    return out


def captured_fits(files, options):
    """The arguments of every ``fit_joint_gp`` call of ``estcal.diagnose`` on ``files`` (the budget's)."""
    import warnings

    import estcal.discrepancy.residual as residual
    from estcal.workflows.diagnose import diagnose

    calls, original = [], residual.fit_joint_gp

    def spy(*a, **k):
        calls.append((a, k))
        return original(*a, **k)

    residual.fit_joint_gp = spy
    try:
        opts = dict(options)
        robot = opts.pop("robot")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            diagnose(robot, [str(f) for f in files] if len(files) > 1 else str(files[0]), budget=True, **opts)
    finally:
        residual.fit_joint_gp = original
    return calls


def on_box(x, bounds, na):
    lo, hi = np.array(bounds, float).T
    tol = 1e-8 * np.maximum(hi - lo, 1.0)
    low, high = x <= lo + tol, x >= hi - tol
    return {"length_scale_on_lower_bound": int(low[na:2 * na].sum()), "length_scale_on_upper_bound": int(high[na:2 * na].sum()),
            "amplitude_on_lower_bound": int(low[:na].sum()), "noise_on_bound": bool(low[-1] or high[-1])}


def study_fit(args, kwargs, restarts):
    """First run and ``restarts`` random restarts of one joint GP fit (module docstring)."""
    from scipy.optimize import minimize

    from estcal.base.blas import single_thread_blas
    from estcal.discrepancy.residual import LBFGS_MEMORY, NLL_FTOL, _suspect, joint_gp_fit_problem

    readings, H, residuals, _, joint_of, joint_names = args[:6]
    fit = joint_gp_fit_problem(readings, H, residuals, joint_of, joint_names, kwargs.get("start"))
    opts = {"maxiter": kwargs.get("maxiter", 200), "ftol": NLL_FTOL, "maxcor": LBFGS_MEMORY}
    gen = np.random.default_rng(kwargs.get("rng", 0))
    with single_thread_blas():
        first = minimize(fit.nll, fit.x0, jac=True, method="L-BFGS-B", bounds=fit.bounds, options=opts)
        runs = [minimize(fit.nll, np.array([gen.uniform(lo, hi) for lo, hi in fit.bounds]), jac=True,
                         method="L-BFGS-B", bounds=fit.bounds, options=opts) for _ in range(restarts)]
    gains = [float(first.fun - r.fun) for r in runs]
    return {"coordinates": int(fit.Y.size), "converged": bool(first.success), "suspect": bool(_suspect(first, fit.bounds)),
            **on_box(first.x, fit.bounds, len(fit.active)), "gain_first_restart_nats": gains[0] if gains else None,
            "gain_best_restart_nats": max(gains) if gains else None,
            "restarts_better_by_half_a_nat": int(sum(g > 0.5 for g in gains)), "restarts": restarts,
            "runs_in_budget": 1 + (kwargs.get("restarts", 1) if _suspect(first, fit.bounds) else 0)}


def simulated_cases(seeds, wobbles=(0.1, 0.15, 0.25), snrs=(0.7, 1.0, 2.0)):
    """The two-optima cases of the module docstring: ``(label, seed, (Q, H, R, names, joint_of, joint_names))``
    per seed, wobble length scale (× the joint's spread) and signal-to-noise ratio (RMS), the last tuple the
    arguments of :func:`~estcal.discrepancy.residual.fit_joint_gp`."""
    from estcal.discrepancy.residual import joint_gp_design
    from estcal.discrepancy.masses import with_urdf_masses
    from estcal.io.dataset import load_dataset
    from estcal.kinematics.robots import tiago

    robot = with_urdf_masses(tiago(n_markers=4))
    data = load_dataset(DATA / "tiago" / "qualisys_2021-11-30_static_postures.csv", robot)
    Q, H, names, jo = joint_gp_design(robot, robot.params.values, data.readings, data.context, 4)
    N, m, p = H.shape
    scale = np.sqrt(np.mean(H.reshape(-1, p) ** 2, axis=0))
    scale[scale < 1e-15] = 1.0
    Hs = H / scale
    j = robot.joint_names.index("arm_6_joint")
    for wobble, snr, seed in ((w, r, s) for w in wobbles for r in snrs for s in range(seeds)):
        g = np.random.default_rng(seed)
        q = Q[:, j]
        Kq = np.exp(-0.5 * (q[:, None] - q[None]) ** 2 / (wobble * q.std()) ** 2) + 1e-9 * np.eye(N)
        c = jo == j
        signal = np.einsum("nic,nc->ni", Hs[:, :, c], np.linalg.cholesky(Kq) @ g.standard_normal((N, c.sum())))
        Y = signal + np.sqrt(np.mean(signal ** 2)) / snr * g.standard_normal(signal.shape)
        yield (f"simulated ℓ={wobble} snr={snr} seed {seed}", seed,
               (Q, H, Y.reshape(N, -1, 3), names, jo, robot.joint_names))


def simulated(seeds, restarts, wobbles=(0.1, 0.15, 0.25), snrs=(0.7, 1.0, 2.0)):
    """:func:`study_fit` of every case of :func:`simulated_cases`."""
    out = []
    for label, seed, args in simulated_cases(seeds, wobbles, snrs):
        d = study_fit(args, {"rng": seed, "restarts": 1}, restarts)
        out.append({"case": label, "fit": "all rows", **d})
        _print(out[-1])
    return out


def _print(d):
    print(f"{d['case']:42s} {d['fit']:8s} M={d['coordinates']:5d} conv={int(d['converged'])} "
          f"ls_lo={d['length_scale_on_lower_bound']} ls_hi={d['length_scale_on_upper_bound']} "
          f"amp_lo={d['amplitude_on_lower_bound']} suspect={int(d['suspect'])} "
          f"first restart {d['gain_first_restart_nats']:+8.2f} best {d['gain_best_restart_nats']:+8.2f} nats "
          f"({d['restarts_better_by_half_a_nat']}/{d['restarts']} > 0.5)", flush=True)


def summary(rows) -> dict:
    """Counts over the fits: all, suspect with a length scale on its lower bound, and the rest."""
    out = {}
    for name, sel in (("all-rows fits", lambda r: r["fit"] == "all rows"), ("fold fits", lambda r: r["fit"] != "all rows")):
        part = [r for r in rows if sel(r)]
        lo = [r for r in part if r["converged"] and r["length_scale_on_lower_bound"] > 0]
        rest = [r for r in part if not (r["converged"] and r["length_scale_on_lower_bound"] > 0)]
        out[name] = {grp: {"fits": len(g), "first restart > 0.5 nat": sum(r["gain_first_restart_nats"] > 0.5 for r in g),
                           "some restart > 0.5 nat": sum(r["gain_best_restart_nats"] > 0.5 for r in g)}
                     for grp, g in (("converged, a length scale on its lower bound", lo), ("other", rest))}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--restarts", type=int, default=5)
    ap.add_argument("--sim-seeds", type=int, default=4)
    ap.add_argument("--cases", default="tiago,talos,ur10,sim")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    wanted = a.cases.split(",")
    rows = []
    cases = _cases()
    for group in ("tiago", "talos", "ur10"):
        if group not in wanted:
            continue
        for label, files, options in cases[group]:
            if not all(f.exists() for f in files):
                print(f"{label}: data not found, skipped")
                continue
            for i, (args, kwargs) in enumerate(captured_fits(files, options)):
                rows.append({"case": label, "fit": "all rows" if kwargs.get("start") is None else f"fold {i}",
                             **study_fit(args, kwargs, a.restarts)})
                _print(rows[-1])
    real = summary(rows)
    sim = simulated(a.sim_seeds, a.restarts) if "sim" in wanted else []
    result = {"real": real, "simulated": summary(sim), "fits": rows + sim}
    print(json.dumps({"real": real, "simulated": result["simulated"]}, indent=1))
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
