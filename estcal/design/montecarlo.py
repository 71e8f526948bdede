"""Monte-Carlo check of a plan's predicted accuracy: simulate, calibrate, measure the error.

Each repetition draws "true" parameters ``θ_true = θ_nominal + δ`` (δ ~ N(0,
diag(param_std²)) on the free parameters), simulates the plan's measurements
with Gaussian noise σ per coordinate, calibrates, and records the position
error at the test pose(s) ``‖p(q0; θ̂) − p(q0; θ_true)‖``. Its root mean
square is compared with the predicted ρ0 = sqrt(trace(J0 C J0ᵀ)).

* ``nonlinear=True``: each repetition is a real calibration with
  :func:`estcal.estimate.lsq.calibrate_lsq` (Levenberg–Marquardt, known noise)
  on a :class:`estcal.methods.problem.Problem`; repetitions are independent
  tasks of :func:`estcal.scale.run_tasks` (``scheduler=``).
* ``nonlinear=False``: the linearised model ``Δy = J δ + ε`` solved by
  weighted least squares for all repetitions at once (fast; exactly the
  model behind ρ0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.estimate.lsq import calibrate_lsq
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.transforms import so3_exp
from estcal.methods.base import NoiseModel
from estcal.methods.problem import Problem

from .model import DesignModel

__all__ = ["MonteCarloResult", "monte_carlo_test_pose_error"]


@dataclass
class MonteCarloResult:
    """RMS error at the test poses over ``n_reps`` calibrations vs the prediction (m)."""

    n_reps: int
    rms: float
    predicted: float
    rel_se: float
    nonlinear: bool
    mean_error: float

    @property
    def ratio(self) -> float:
        return self.rms / self.predicted

    def to_dict(self) -> dict:
        return {"n_reps": self.n_reps, "rms_m": self.rms, "predicted_m": self.predicted, "ratio": self.ratio,
                "rel_se": self.rel_se, "nonlinear": self.nonlinear, "mean_error_m": self.mean_error}

    def __str__(self) -> str:
        return (f"Monte Carlo ({'nonlinear LM' if self.nonlinear else 'linearised'}, {self.n_reps} reps): "
                f"RMS error {self.rms:.4g} m vs predicted {self.predicted:.4g} m (ratio {self.ratio:.3f} "
                f"± {self.rel_se:.3f})")


def _noise_draws(model, n_poses, rng):
    """Standard-normal draws of one repetition's measurement noise, in the simulator's order
    (orientation then position for poses). ``normal(0, s) = s · standard_normal``, so scaling
    them later reproduces the draws of ``rng.normal(0, s, …)`` bit for bit."""
    if model.method == "pose":
        return rng.standard_normal((n_poses, 3)), rng.standard_normal((n_poses, 3))
    if model.method == "points":
        return (rng.standard_normal((n_poses, model.robot.n_markers, 3)),)
    return (rng.standard_normal((n_poses, 3)),)


def _simulate_measurements(model, robot_true, Q, z):

    kin = robot_true.kinematics(Q, jacobian=False)
    names = robot_true.joint_names
    s = model.sigma
    if model.method == "pose":
        R = so3_exp(model.sigma_rot * z[0]) @ kin.R
        return dataset_from_arrays(names, Q, R=R, p=kin.p + s * z[1])
    if model.method == "points":
        return dataset_from_arrays(names, Q, points=kin.points + s * z[0])
    pts = kin.points[:, 0] if robot_true.n_markers else kin.p
    return dataset_from_arrays(names, Q, points=pts + s * z[0])


def _one_calibration(draw, model, Q, q_test, std, planar):
    """One Monte-Carlo repetition (a task of :func:`estcal.scale.run_tasks`): draw the truth,
    simulate, calibrate by LM, return the RMS position error at the test poses (m)."""

    z_theta, z_noise = draw
    robot = model.robot
    idx = robot.params.indices(model.free)
    rb = robot.copy(robot.params.with_free(model.free))
    noise_model = NoiseModel(position=model.sigma, orientation=model.sigma_rot or 1.0, known=True)
    meth = {"position": "position", "pose": "pose", "points": "points"}[model.method]
    th = model.theta.copy()
    th[idx] += z_theta * std
    truth = robot.with_values(th)
    data = _simulate_measurements(model, truth, Q, z_noise)
    if planar and data.points is not None:
        data.points[..., 2] = truth.kinematics(Q, jacobian=False).p[:, None, 2]
    res = calibrate_lsq(Problem(rb.with_values(model.theta), [(meth, data, noise_model)]), check=False)
    th_hat = np.asarray(res.theta)[: robot.n_params]
    e = robot.kinematics(q_test, th_hat, jacobian=False).p - truth.kinematics(q_test, jacobian=False).p
    return float(np.sqrt(np.mean(np.sum(e ** 2, -1))))


def monte_carlo_test_pose_error(model: DesignModel, readings, q_test, n_reps: int = 200, rng=None,
                                param_std=1e-3, nonlinear: bool = True, planar: bool = False,
                                scheduler="serial", n_workers: int | None = None) -> MonteCarloResult:
    """Calibrate ``n_reps`` times with plan ``readings`` and compare the test-pose error with ρ0.

    Parameters
    ----------
    param_std : float or (p,) spread of the true parameter errors (SI units).
    planar : the robot moves in the xy plane and only x, y are measured (z noise
        set to zero), as in Klimchik's 2-link example — z rows carry no information
        there, so this only avoids simulating irrelevant noise.
    scheduler, n_workers : where the nonlinear repetitions run (:func:`estcal.scale.run_tasks`:
        ``serial``, ``processes``, ``local``, a Dask address or ``Client``); every random draw
        is made here first, so the result is identical on every scheduler.
    """
    rng = np.random.default_rng(rng)
    Q = np.atleast_2d(np.asarray(readings, float))
    q_test = np.atleast_2d(np.asarray(q_test, float))
    std = np.broadcast_to(np.asarray(param_std, float), (model.p,))
    J0 = model.position_jacobian(q_test)
    C = model.covariance(Q)
    pred = float(np.sqrt(np.mean(np.einsum("tap,pq,taq->t", J0, C, J0))))
    errs = np.empty(n_reps)
    if not nonlinear:
        J = model.jacobian(Q).reshape(-1, model.p)
        w = np.tile(1.0 / model.row_sigma, len(Q))
        d = rng.normal(0, 1, (n_reps, model.p)) * std
        noise = rng.normal(0, 1, (n_reps, J.shape[0])) / w
        if planar:
            noise[:, 2::3] = 0.0
        y = d @ J.T + noise
        est = np.linalg.lstsq(J * w[:, None], (y * w).T, rcond=None)[0].T
        e = np.einsum("tap,np->nta", J0, est - d)
        errs = np.sqrt(np.mean(np.sum(e ** 2, -1), -1))
    else:
        import functools

        from estcal.scale.runner import run_tasks

        # every draw is made here, in the order of a serial loop, so the result does not
        # depend on the scheduler (nor on which worker ran which repetition)
        draws = []
        for _ in range(n_reps):
            z = rng.normal(0, 1, model.p)
            draws.append((z, _noise_draws(model, len(Q), rng)))
        run = run_tasks(functools.partial(_one_calibration, model=model, Q=Q, q_test=q_test, std=std,
                                          planar=planar), draws, scheduler=scheduler, n_workers=n_workers,
                        progress="auto", desc="Monte Carlo calibrations")
        errs = np.asarray(run.values(), float)
    e2 = errs ** 2
    rms = float(np.sqrt(e2.mean()))
    rel_se = float(e2.std(ddof=1) / e2.mean() / np.sqrt(n_reps) / 2) if n_reps > 1 else float("nan")
    return MonteCarloResult(int(n_reps), rms, pred, rel_se, bool(nonlinear), float(errs.mean()))
