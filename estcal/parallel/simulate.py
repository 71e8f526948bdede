"""Simulated Gough-platform calibration data, with the shared simulator's noise/error models.

``simulate_gough`` is the parallel counterpart of :func:`estcal.simulate.simulate`:
true robot = nominal + random (or given) parameter errors, random workspace
poses, noise from :class:`estcal.simulate.NoiseModel` (``position`` on each
coordinate of the measured platform position, ``orientation`` on each
rotation-vector component of the measured platform orientation, ``joint`` on
each leg reading; Gaussian σ or uniform half-width), parameter errors with
:class:`estcal.simulate.ErrorModel` σ's (``length`` for the attachment
points, ``offset`` for Δρ_k).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.jsonio import write_json

from ._rot import make_T, so3_exp
from .calibration import GoughData
from .daney import generate_random_poses
from .gough import GoughPlatform, load_gough, split_pose

__all__ = ["simulate_gough", "GoughSimulation"]


@dataclass
class GoughSimulation:
    """Output of :func:`simulate_gough` (``truth`` is JSON-ready)."""

    data: GoughData
    true_robot: GoughPlatform
    nominal_robot: GoughPlatform
    errors: dict
    true_T: np.ndarray
    true_rho: np.ndarray
    truth: dict

    def write(self, csv_path, truth_path=None, true_robot_path=None):
        """Write the measurements CSV (``load_gough_data`` format), the ground truth
        JSON and the true robot file (YAML), when the paths are given."""
        self.data.save_csv(csv_path)
        if truth_path is not None:
            d = dict(self.truth)
            d["dataset"] = str(csv_path)
            write_json(truth_path, d)
        if true_robot_path is not None:
            import yaml

            atomic_write_text(true_robot_path, yaml.safe_dump(self.true_robot.to_dict()))
        return Path(csv_path)

    def to_dict(self) -> dict:
        return self.truth


def simulate_gough(robot: GoughPlatform | str | Path | Mapping = "left_hand", n_poses: int = 50,
                   errors=None, error_std=None, noise=None, seed: int | None = 0,
                   T: np.ndarray | None = None) -> GoughSimulation:
    """Simulate a Gough calibration dataset.

    Parameters
    ----------
    robot : nominal robot (object, built-in name, robot file, dict).
    n_poses : number of random workspace poses (ignored if ``T`` is given).
    errors : None / ``"none"`` (true = nominal), ``"random"`` (N(0, σ²) with
        ``error_std.length`` for ``a_k, b_k`` and ``error_std.offset`` for
        ``drho_k``) or ``{name: δ}``.
    error_std : :class:`estcal.simulate.ErrorModel` or dict of its fields.
    noise : :class:`estcal.simulate.NoiseModel` or dict (default noise-free).
    seed : seeds independent streams for errors, poses and noise.
    """
    from estcal.simulate import ErrorModel, NoiseModel

    nominal = robot if isinstance(robot, GoughPlatform) else load_gough(robot)
    noise = noise if isinstance(noise, NoiseModel) else NoiseModel(**(noise or {}))
    em = error_std if isinstance(error_std, ErrorModel) else ErrorModel(**(error_std or {}))
    r_err, r_pose, r_noise = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    pv = nominal.parameter_vector(42)
    if errors is None or errors == "none":
        err = {}
    elif errors == "random":
        err = {n: float(r_err.normal(0.0, em.offset if k == "offset" else em.length))
               for n, k in zip(pv.names, pv.kinds)}
    elif isinstance(errors, Mapping):
        err = {str(k): float(v) for k, v in errors.items()}
        for n in err:
            pv.index(n)  # clear error for unknown names
    else:
        raise ValueError(f"errors must be None, 'none', 'random' or a dict, got {errors!r}")
    theta = pv.values.copy()
    for n, v in err.items():
        theta[pv.index(n)] += v
    true = nominal.with_theta(theta)
    true.name = f"{nominal.name}_true"
    Tt = generate_random_poses(true, n_poses, r_pose) if T is None else np.asarray(T, float).reshape(-1, 4, 4)
    rho_t = true.leg_lengths(Tt)
    P, R = split_pose(Tt)
    Pm = P + noise.draw(noise.position, P.shape, r_noise)
    Rm = so3_exp(noise.draw(noise.orientation, P.shape, r_noise)) @ R
    rho_m = rho_t + noise.draw(noise.joint, rho_t.shape, r_noise)
    data = GoughData(make_T(Pm, Rm), rho_m, noise.std(noise.joint) or None, noise.std(noise.position) or None,
                     noise.std(noise.orientation) or None, "simulated")
    truth = {
        "robot": nominal.name, "n_poses": int(len(Tt)), "seed": seed,
        "errors": err, "true_parameters": dict(zip(pv.names, theta.tolist())),
        "nominal_parameters": dict(zip(pv.names, pv.values.tolist())),
        "noise": noise.to_dict() | {"meaning": {"position": "platform position, each coordinate (m)",
                                                "orientation": "rotation-vector component (rad)",
                                                "joint": "leg reading (m)"}},
        "error_std": em.to_dict(),
    }
    return GoughSimulation(data, true, nominal, err, Tt, rho_t, truth)
