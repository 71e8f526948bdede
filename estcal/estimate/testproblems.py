"""Simulated calibration problems for tests, experiments and benchmarks of the estimators.

:func:`simulated_problem` draws random joint readings within the limits, a
"true" robot (nominal values + Gaussian deviations on the chosen parameters),
and measurements of the true robot with Gaussian noise of known standard
deviation; it returns the Problem at the nominal values together with the
truth, so every estimator can be scored against it. :func:`drifting_problem`
makes the true parameters move linearly with the pose index (a slow drift,
stored in the ``t`` context column) — used until the effects engineer's
``drift`` effect exists, and independent of it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estcal.identify.select import observation_matrix, select_identifiable
from estcal.io.dataset import dataset_from_arrays
from estcal.kinematics.robots import get_builtin
from estcal.kinematics.transforms import so3_exp
from estcal.methods.base import NoiseModel
from estcal.methods.problem import Problem

__all__ = ["Simulated", "simulated_problem", "drifting_problem", "puma_free_set", "ordered_free_set", "PUMA_CANDIDATES"]

#: candidate PUMA 560 parameters (the identifiable set is selected among them in order)
PUMA_CANDIDATES = ["base_*", "d_*", "a_*", "alpha_*", "beta_2", "theta_*", "tool_*"]


@dataclass
class Simulated:
    problem: object  # Problem at the nominal parameter values
    truth: np.ndarray  # (P,) true full parameter vector (last pose's for a drifting problem)
    free: list  # free parameter names
    truth_path: np.ndarray | None = None  # (N, P) true vector per pose (drift)

    @property
    def truth_free(self) -> np.ndarray:
        pv = self.problem.params
        return self.truth[pv.indices(self.free)]


def _robot(name):
    return get_builtin(name) if isinstance(name, str) else name


def ordered_free_set(problem, candidates=None) -> list:
    """The candidates (names or patterns, in the given order; default every parameter) kept in that
    order while they add rank: :func:`estcal.identify.select_identifiable` with the structural
    tolerance on the problem's weighted rows — reproducible sets for the simulated problems,
    whatever GECARO's priority rules would prefer."""
    pv = problem.params
    names = list(pv.names) if candidates is None else \
        [n for c in candidates for n in (pv.select(c) if any(ch in c for ch in "*?[") else [c])]
    W, names = observation_matrix(problem, names)
    return select_identifiable(W, names=names).identifiable


def puma_free_set(problem, candidates=None) -> list:
    """Identifiable PUMA free set for ``problem`` (:func:`ordered_free_set` of :data:`PUMA_CANDIDATES`)."""
    return ordered_free_set(problem, PUMA_CANDIDATES if candidates is None else candidates)


def _measure(robot, theta, readings, kind, sigma_p, sigma_r, rng, context=None):
    kin = robot.kinematics(readings, theta, context, jacobian=False)
    N = readings.shape[0]
    if kind == "location":
        p = kin.p + sigma_p * rng.standard_normal((N, 3))
        R = so3_exp(sigma_r * rng.standard_normal((N, 3))) @ kin.R
        return dict(R=R, p=p)
    pts = (kin.points if robot.n_markers else kin.p[:, None, :]) + sigma_p * rng.standard_normal((N, max(1, robot.n_markers), 3))
    return dict(points=pts)


def simulated_problem(robot="puma560", n_poses: int = 100, seed=0, sigma_p: float = 1e-4, sigma_r: float = 1e-4,
                      method: str = "location", free=None, deviation: tuple = (1e-3, 1e-3),
                      known: bool = True, readings=None, truth=None, outliers: float = 0.0,
                      outlier_scale: float = 50.0) -> Simulated:
    """A simulated dataset and its Problem.

    Parameters
    ----------
    robot : built-in name or SerialRobot
    n_poses : random poses (uniform within the joint limits, 5 % margin)
    sigma_p, sigma_r : measurement noise std, m and rad (``known`` marks it as trusted)
    method : ``"location"`` (position + orientation) or ``"position"``
    free : free names (default: identifiable PUMA-style set from :data:`PUMA_CANDIDATES`)
    deviation : std of the true deviations from nominal (m, rad) on the free parameters
    truth : explicit true full vector (overrides ``deviation``)
    outliers : fraction of poses whose position gets an extra error of ``outlier_scale·sigma_p``
    """

    rng = np.random.default_rng(seed)
    rob = _robot(robot)
    q = rob.random_readings(n_poses, rng, margin=0.05) if readings is None else np.asarray(readings, float)
    n_poses = q.shape[0]
    noise = NoiseModel(position=sigma_p, orientation=sigma_r, known=known)
    nominal = rob.params.values.copy()
    meas = _measure(rob, nominal, q, method, 0.0, 0.0, rng)
    prob = Problem(rob, [(method, dataset_from_arrays(rob.joint_names, q, **meas), noise)])
    if free is None:
        free = puma_free_set(prob) if rob.name.startswith("puma") else ordered_free_set(prob)
    pv = prob.params
    if truth is None:
        truth = nominal.copy()
        idx = pv.with_free(free).free_indices
        for i in idx:
            lin = pv.names[i].split("_")[0] in ("d", "a", "r") or pv.names[i].endswith(("_tx", "_ty", "_tz", "_x", "_y", "_z"))
            truth[i] += (deviation[0] if lin else deviation[1]) * rng.standard_normal()
    meas = _measure(rob, truth, q, method, sigma_p, sigma_r, rng)
    if outliers > 0:
        bad = rng.random(n_poses) < outliers
        key = "p" if method == "location" else "points"
        shift = outlier_scale * sigma_p * rng.standard_normal(meas[key][bad].shape)
        meas[key][bad] += shift
    ds = dataset_from_arrays(rob.joint_names, q, **meas)
    prob = Problem(rob, [(method, ds, noise)]).with_free(free)
    return Simulated(prob, truth, list(prob.params.free_names))


def drifting_problem(robot="puma560", n_poses: int = 200, seed=0, drift: dict | None = None, **kw) -> Simulated:
    """Like :func:`simulated_problem`, but the true parameters drift linearly over the poses.

    ``drift`` maps parameter names to the total change over the sequence (SI);
    pose i is measured with ``truth + (i/(N−1)) · drift``; ``t = i`` (s) is stored
    in the dataset context. ``truth`` of the result is the last pose's vector.
    """
    drift = drift or {"theta_2": 2e-3}
    base = simulated_problem(robot, n_poses, seed, **kw)
    prob, pv = base.problem, base.problem.params
    rng = np.random.default_rng(None if seed is None else seed + 1)
    t = base.problem.terms[0]
    d = t.data
    q = d.readings
    dv = np.zeros(len(pv))
    for k, v in drift.items():
        dv[pv.index(k)] = v
    frac = np.arange(n_poses) / max(n_poses - 1, 1)
    path = base.truth[None, :] + frac[:, None] * dv[None, :]
    sig_p, sig_r = t.noise.position, t.noise.orientation
    parts = [_measure(prob.robot, path[i], q[i:i + 1], t.method.name if t.method.name != "pose" else "location",
                      sig_p, sig_r, rng) for i in range(n_poses)]
    meas = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    ds = dataset_from_arrays(d.joint_names, q, context={"t": np.arange(n_poses, dtype=float)}, **meas)
    newp = Problem(prob.robot, [(t.method, ds, t.noise)])
    return Simulated(newp, path[-1].copy(), base.free, path)
