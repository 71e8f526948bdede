"""Simulated multi-session data for the repeatability model (tests, studies, notebooks).

Session s measures the robot with parameters ``θ_s = θ_true + u_s`` where
``u_s ~ N(0, diag(std²))`` on the parameters named in ``vary`` (e.g. joint
offsets re-homed every morning) and zero elsewhere; every session has its own
random poses and measurement noise.
"""
from __future__ import annotations

import numpy as np

__all__ = ["simulate_sessions"]


def simulate_sessions(robot, n_sessions: int, n_poses: int, vary: dict, *, measure: str = "position",
                      noise: float = 5e-5, orientation_noise: float = 5e-4, error_std: float = 5e-4,
                      seed: int = 0):
    """Datasets of ``n_sessions`` sessions of ``n_poses`` poses each.

    Parameters
    ----------
    robot : nominal SerialRobot (the model to calibrate).
    vary : ``{parameter name: between-session std}`` (SI: m or rad).
    measure : ``"position"`` (tool point) or ``"location"`` (full pose).
    noise, orientation_noise : measurement noise std (m, rad).
    error_std : std of the fixed geometric errors of the true robot (m and rad alike).

    Returns ``(datasets, truth)`` with ``truth = {"theta": full true vector, "u": (n_s, k),
    "vary": names, "q": variances}``.
    """
    from estcal.methods.generate import measurement_data

    ss = np.random.SeedSequence(seed)
    r_err, r_u, *r_sess = [np.random.default_rng(s) for s in ss.spawn(2 + n_sessions)]
    pv = robot.params
    theta = pv.values.copy()
    geo = [i for i, k in enumerate(pv.kinds) if k in ("geometric", "offset", "base", "tool")]
    theta[geo] += r_err.normal(0, error_std, len(geo))
    names = list(vary)
    idx = np.array(pv.indices(names), int) if names else np.zeros(0, int)
    sd = np.array([float(vary[n]) for n in names])
    u = r_u.normal(0, 1, (n_sessions, len(names))) * sd
    datasets = []
    for s in range(n_sessions):
        th = theta.copy()
        th[idx] += u[s]
        ds = measurement_data(robot, n_poses, measure, r_sess[s], th, position_noise=noise,
                              orientation_noise=orientation_noise if measure != "position" else 0.0)
        datasets.append(ds)
    return datasets, {"theta": theta, "u": u, "vary": names, "q": sd ** 2}
