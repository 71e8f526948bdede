"""``estcal demo``: the main job on an embedded default, end to end.

Simulates a PUMA 560 (textbook Table 6.1 model) whose true geometry differs
from the nominal one, measured with CMM-like noise (textbook Table 6.4),
identifies the parameters, and scores the nominal and the calibrated model on
a second, independent set of poses — the whole calibration workflow in one
command, with nothing to download.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from estcal.base.jsonio import write_json


def run_demo(robot: str = "puma560", n_poses: int = 50, seed: int = 0, sigma_pos: float = 5e-5,
             sigma_rot: float = 5e-4, estimator: str = "lm") -> dict:
    """Simulate → calibrate → validate. Returns a JSON-ready summary (mm / mrad)."""
    from estcal.estimate.levels import run_calibration
    from estcal.io.robotfile import load_robot
    from estcal.methods import NoiseModel
    from estcal.simulate import simulate

    nominal = load_robot(robot)
    noise = {"position": sigma_pos, "orientation": sigma_rot}
    train = simulate(nominal, n_poses=n_poses, measure="pose", errors="random", noise=noise, seed=seed)
    train.dataset.path = "the simulated calibration set"  # named in messages
    # the same true robot, other poses: simulate with the train truth as explicit errors
    truth = {n: v for n, v in zip(nominal.params.names, train.true_robot.params.values - nominal.params.values)
             if v != 0.0}
    valid = simulate(nominal, n_poses=n_poses, measure="pose", errors=truth, noise=noise, seed=seed + 1)
    res, sel, problem = run_calibration(
        nominal, train.dataset, level="full", validate=[valid.dataset],
        noise=NoiseModel(position=sigma_pos, orientation=sigma_rot, known=True), estimator=estimator,
        selection="structural",  # the full identifiable set (QR), as the textbook counts it
        checks=True)  # the refusals of `estcal calibrate` (dof ≤ 0, non-convergence, ill-conditioning)
    # The estimated (base) parameters absorb the errors of the regrouped ones, so the
    # truth to compare with is the same model fitted to noise-free measurements.
    from estcal.estimate import calibrate_lsq
    from estcal.methods import Problem

    exact = train.dataset.subset(slice(None))
    exact.readings, exact.R, exact.p = train.true_readings, train.true_R, train.true_p
    ref = calibrate_lsq(Problem(problem.robot.with_values(res.theta), [(None, exact)]), free=res.names,
                        tol=1e-14)
    d = res.estimate - ref.estimate
    nees = float(d @ np.linalg.solve(res.covariance, d))
    acc = res.accuracy
    return {
        "robot": nominal.name, "n_poses": n_poses, "seed": seed,
        "noise": {"position_mm": sigma_pos * 1e3, "orientation_mrad": sigma_rot * 1e3},
        "n_estimated": len(res.names), "n_iterations": res.n_iterations, "converged": res.converged,
        "sigma0": res.sigma0,
        "train": {"nominal": acc["train"]["before"], "calibrated": acc["train"]["after"]},
        "validation": {"nominal": acc["validation"][0]["before"], "calibrated": acc["validation"][0]["after"]},
        "nees": nees, "nees_dof": len(res.names),
        "result": res,
    }


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        robot: str = typer.Option("puma560", help="Built-in robot, robot file or URDF."),
        n: int = typer.Option(50, "--n", help="Poses in the calibration set (and in the validation set)."),
        seed: int = typer.Option(0, help="Random seed (errors, poses, noise)."),
        estimator: str = typer.Option("lm", help="Estimator (lm, gauss-newton, iterated-lls, gtsam, kalman, mcmc…)."),
        json_path: Path = typer.Option(None, "--json", help="Write the summary as JSON."),
    ):
        """Simulate a robot with unknown geometric errors, calibrate it, validate on new poses."""
        from rich.console import Console
        from rich.table import Table

        from estcal.cli.common import fail, message

        from estcal.base.errors import NumericalRefusal

        try:
            out = run_demo(robot, n, seed, estimator=estimator)
        except NumericalRefusal as exc:
            from estcal.cli.common import refuse

            refuse(f"--n {n}: {exc} (here: raise --n)")
        except (ValueError, KeyError, FileNotFoundError) as exc:
            fail(message(exc))
        res = out.pop("result")
        con = Console()
        con.print(f"[bold]estcal demo[/]: {out['robot']}, {n} simulated poses (full pose, CMM noise "
                  f"{out['noise']['position_mm']:.3f} mm / {out['noise']['orientation_mrad']:.2f} mrad), "
                  f"{out['n_estimated']} identifiable parameters, {out['n_iterations']} iterations, "
                  f"converged={out['converged']}")
        t = Table(title="Position / orientation error (RMSE, max)")
        for c in ("data", "model", "RMSE mm", "max mm", "RMSE mrad", "max mrad"):
            t.add_column(c, justify="right" if c not in ("data", "model") else "left")
        for d in ("train", "validation"):
            for m in ("nominal", "calibrated"):
                a = out[d][m]
                t.add_row(d, m, f"{a['rmse_mm']:.4f}", f"{a['max_mm']:.4f}", f"{a['rmse_mrad']:.4f}",
                          f"{a['max_mrad']:.4f}")
        con.print(t)
        con.print(f"NEES of the estimate against the simulated truth: {out['nees']:.1f} "
                  f"(χ² with {out['nees_dof']} dof: mean {out['nees_dof']}, 95% < "
                  f"{__import__('scipy.stats').stats.chi2.ppf(0.95, out['nees_dof']):.1f})")
        if json_path:
            out["parameters"] = res.to_dict()["parameters"]
            write_json(json_path, out)
