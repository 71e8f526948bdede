"""The main job on an embedded default, end to end: ``estcal demo``.

Simulates a PUMA 560 (textbook Table 6.1 model) whose true geometry differs from the nominal
one, measured with CMM-like noise (textbook Table 6.4), identifies the parameters, and scores the
nominal and the calibrated model on a second, independent set of poses — the whole calibration
workflow in one call, with nothing to download.
"""
from __future__ import annotations

import numpy as np

from estcal.workflows.inputs import input_errors

__all__ = ["run_demo"]


def run_demo(robot: str = "puma560", n_poses: int = 50, seed: int = 0, sigma_pos: float = 5e-5,
             sigma_rot: float = 5e-4, estimator: str = "lm") -> dict:
    """Simulate → calibrate → validate. Returns a JSON-ready summary (mm / mrad)."""
    with input_errors():
        return _demo(robot, n_poses, seed, sigma_pos, sigma_rot, estimator)


def _demo(robot, n_poses, seed, sigma_pos, sigma_rot, estimator) -> dict:
    from estcal.workflows.calibrate import run_calibration
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
