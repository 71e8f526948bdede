"""A simulated fleet: one folder per robot with its calibration and validation data and its truth.

Every robot of the fleet is the same nominal model (one shared robot file at
the fleet's top level, as a factory calibrating one product line) with its own
random geometric errors (:func:`estcal.simulate.random_errors` magnitudes) and,
with probability ``p_effect``, one non-geometric effect drawn from
``effects`` on a random major joint (magnitudes in :func:`_effect_spec`). Layout (read by :mod:`estcal.workflows.fleet`)::

    OUT/robot.yaml                  nominal robot (shared)
    OUT/robot_0000/data.csv         calibration dataset (n_poses)
    OUT/robot_0000/validate.csv     validation dataset (n_validate new poses, same robot)
    OUT/robot_0000/truth.json       ground truth (errors, effects, noise)

Robot ``i`` uses seed ``SeedSequence(seed).spawn(n)[i]``, so a robot's data do
not depend on the fleet size or on which worker simulated it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.io.dataset import write_dataset
from estcal.io.robotfile import load_robot, save_robot
from estcal.scale.runner import run_tasks, task_seeds

from estcal.methods.base import NoiseModel

from .core import simulate

__all__ = ["FLEET_EFFECTS", "simulate_fleet", "simulate_robot"]

# Effects drawn for a fleet robot, on one of its first three (major) joints, with magnitudes
# well above a CMM's noise (so that `estcal fleet --diagnose` has something to find):
# a first-order gear harmonic of amplitude 1 mrad (random phase), an encoder gain error of
# ±2e-3, joint compliance of 1–3e-5 rad/(N·m) on j2, j3 (robots with link masses only).
FLEET_EFFECTS = ("gear_harmonic", "encoder_gain", "joint_compliance")


def _effect_spec(name: str, rng, robot) -> dict | None:
    joints = robot.joint_names[:3]
    j = joints[int(rng.integers(len(joints)))]
    if name == "gear_harmonic":
        phase = rng.uniform(0, 2 * np.pi)
        return {"effect": name, "joints": [j], "options": {"orders": [1]},
                "params": {f"harmonic1_sin_{j}": 1e-3 * np.cos(phase), f"harmonic1_cos_{j}": 1e-3 * np.sin(phase)}}
    if name == "encoder_gain":
        return {"effect": name, "joints": [j], "params": {f"encgain_{j}": 2e-3 * rng.choice([-1.0, 1.0])}}
    if name == "joint_compliance":
        if not any(lk.mass > 0 for lk in robot.links) or len(joints) < 3:
            return None
        js = joints[1:3]
        return {"effect": name, "joints": js, "params": {f"compliance_{x}": rng.uniform(1e-5, 3e-5) for x in js}}
    return {"effect": name}


def simulate_robot(job) -> dict:
    """Simulate one robot folder (a task of :func:`simulate_fleet`); returns its summary row."""
    (folder, robot_file, n_poses, n_validate, measure, noise_pos, noise_rot, p_effect, effects, seed) = job
    folder = Path(folder)
    nominal = load_robot(robot_file)
    rng = np.random.default_rng(seed)
    eff = []
    if effects and rng.random() < p_effect:
        spec = _effect_spec(effects[int(rng.integers(len(effects)))], rng, nominal)
        eff = [spec] if spec is not None else []
    sim_seed = int(rng.integers(2 ** 63))
    res = simulate(nominal, n_poses=n_poses + n_validate, measure=measure, errors="random", effects=eff,
                   noise=NoiseModel(position=noise_pos, orientation=noise_rot), seed=sim_seed)
    folder.mkdir(parents=True, exist_ok=True)
    idx = np.arange(n_poses + n_validate)
    write_dataset(folder / "data.csv", res.dataset.subset(idx[:n_poses]), float_format="%.15g")
    if n_validate:
        write_dataset(folder / "validate.csv", res.dataset.subset(idx[n_poses:]), float_format="%.15g")
    truth = dict(res.truth)
    labels = [f"{e['effect']}:{','.join(e.get('joints') or [])}" for e in eff]
    truth["fleet"] = {"calibration_poses": n_poses, "validation_poses": n_validate, "effects": labels}
    atomic_write_text(folder / "truth.json", json.dumps(truth, indent=2))
    return {"robot": folder.name, "effects": labels, "nominal_rms_mm": res.summary.nominal_rms_mm}


def simulate_fleet(n: int, out, robot="puma560", n_poses: int = 50, n_validate: int = 50,
                   measure: str = "pose", noise_pos: float = 5e-5, noise_rot: float = 5e-4,
                   p_effect: float = 0.5, effects=FLEET_EFFECTS, seed: int = 0, scheduler="serial",
                   n_workers: int | None = None, progress="auto"):
    """Write a simulated fleet of ``n`` robots to ``out`` (see the module docstring).

    Returns the :class:`~estcal.scale.runner.RunResult` of the per-robot simulations
    (one summary row per robot: name, effects, nominal-vs-true RMS in mm).
    """
    if n < 1:
        raise ValueError(f"--fleet: the number of robots must be ≥ 1, got {n}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    nominal = load_robot(robot)
    robot_file = save_robot(nominal, out / "robot.yaml")
    width = max(4, len(str(n - 1)))
    seeds = task_seeds(seed, n)
    jobs = [(str(out / f"robot_{i:0{width}d}"), str(robot_file), n_poses, n_validate, measure, noise_pos,
             noise_rot, p_effect, tuple(effects), seeds[i]) for i in range(n)]
    return run_tasks(simulate_robot, jobs, scheduler=scheduler, n_workers=n_workers, progress=progress,
                     desc="simulate fleet")
