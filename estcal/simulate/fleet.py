"""A simulated fleet: per-robot calibration and validation data with their truth, written as
folders or generated on demand from a seed and the robot's index.

Every robot of the fleet is the same nominal model (one shared robot file at
the fleet's top level, as a factory calibrating one product line) with its own
random geometric errors (:func:`estcal.simulate.random_errors` magnitudes) and,
with probability ``p_effect``, one non-geometric effect drawn from
``effects`` on a random major joint (magnitudes in :func:`_effect_spec`).

Two layouts (both read by :mod:`estcal.workflows.fleet`):

* folders (``estcal simulate --fleet N --out OUT``)::

      OUT/robot.yaml                  nominal robot (shared)
      OUT/robot_0000/data.csv         calibration dataset (n_poses)
      OUT/robot_0000/validate.csv     validation dataset (n_validate new poses, same robot)
      OUT/robot_0000/truth.json       ground truth (errors, effects, noise)

* on demand (``--on-demand``): only ``OUT/robot.yaml`` and ``OUT/fleet.yaml``, a
  :class:`FleetSpec` (:data:`SPEC_FILE`); the task that calibrates robot ``i``
  simulates its data in memory (:meth:`FleetSpec.generate`) — no file per robot,
  whatever the fleet size.

Robot ``i`` uses seed ``SeedSequence(seed).spawn(n)[i]`` (``SeedSequence(seed,
spawn_key=(i,))``), so a robot's data depend neither on the fleet size, nor on the
layout, nor on which worker simulated it.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.errors import InputError
from estcal.io.dataset import write_dataset
from estcal.io.robotfile import load_robot, save_robot
from estcal.scale.runner import run_tasks

from estcal.methods.base import NoiseModel

from .core import simulate

__all__ = ["FLEET_EFFECTS", "SPEC_FILE", "FleetSpec", "GeneratedRobot", "simulate_fleet", "simulate_robot"]

# Effects drawn for a fleet robot, on one of its first three (major) joints, with magnitudes
# well above a CMM's noise (so that `estcal fleet --diagnose` has something to find):
# a first-order gear harmonic of amplitude 1 mrad (random phase), an encoder gain error of
# ±2e-3, joint compliance of 1–3e-5 rad/(N·m) on j2, j3 (robots with link masses only).
FLEET_EFFECTS = ("gear_harmonic", "encoder_gain", "joint_compliance")

#: the description of a fleet generated on demand, at the fleet folder's top level
SPEC_FILE = "fleet.yaml"


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


@dataclass(frozen=True)
class GeneratedRobot:
    """One simulated fleet robot: its calibration and validation datasets (validation ``None``
    without validation poses), the nominal model they are measured on, the ground truth and the
    effects' labels (``"gear_harmonic:j2"``)."""

    dataset: object
    validation: object
    nominal: object
    truth: dict
    effects: list
    nominal_rms_mm: float


def _generate(nominal, n_poses, n_validate, measure, noise_pos, noise_rot, p_effect, effects, seed) -> GeneratedRobot:
    rng = np.random.default_rng(seed)
    eff = []
    if effects and rng.random() < p_effect:
        spec = _effect_spec(effects[int(rng.integers(len(effects)))], rng, nominal)
        eff = [spec] if spec is not None else []
    sim_seed = int(rng.integers(2 ** 63))
    res = simulate(nominal, n_poses=n_poses + n_validate, measure=measure, errors="random", effects=eff,
                   noise=NoiseModel(position=noise_pos, orientation=noise_rot), seed=sim_seed)
    idx = np.arange(n_poses + n_validate)
    labels = [f"{e['effect']}:{','.join(e.get('joints') or [])}" for e in eff]
    truth = dict(res.truth)
    truth["fleet"] = {"calibration_poses": n_poses, "validation_poses": n_validate, "effects": labels}
    return GeneratedRobot(res.dataset.subset(idx[:n_poses]),
                          res.dataset.subset(idx[n_poses:]) if n_validate else None, res.nominal_robot, truth,
                          labels, float(res.summary.nominal_rms_mm))


@functools.lru_cache(maxsize=4)
def _nominal(robot: str, stamp):  # one parse per worker process (stamp: the file's size and mtime)
    return load_robot(robot)


@functools.lru_cache(maxsize=4)
def _digest(robot: str, stamp) -> str:
    if stamp is None:
        return robot
    return hashlib.sha256(Path(robot).read_bytes()).hexdigest()


def _stamp(robot: str):
    try:
        st = os.stat(robot)
        return st.st_size, st.st_mtime_ns
    except OSError:  # a built-in robot name
        return None


@dataclass(frozen=True)
class FleetSpec:
    """How to generate a fleet of ``robots`` simulated robots on demand (the content of ``fleet.yaml``).

    robot : the shared nominal robot — a robot file (relative paths are read from the fleet
        folder) or a built-in name; ``poses``/``validation_poses`` per robot; ``measure``
        ``pose`` | ``points`` | ``position``; ``noise_pos`` (m) / ``noise_rot`` (rad): σ of the
        measurement noise (SI, as in robot files); ``p_effect``: probability that a robot has one of
        ``effects``; ``seed``: the fleet's seed.
    """

    robots: int
    robot: str = "robot.yaml"
    poses: int = 50
    validation_poses: int = 50
    measure: str = "pose"
    noise_pos: float = 5e-5
    noise_rot: float = 5e-4
    p_effect: float = 0.5
    effects: tuple = FLEET_EFFECTS
    seed: int = 0

    @property
    def width(self) -> int:
        return max(4, len(str(self.robots - 1)))

    def name(self, index: int) -> str:
        """The robot's name, ``robot_0042`` (as the folder of the same robot in the folder layout)."""
        return f"robot_{index:0{self.width}d}"

    def key(self) -> str:
        """A digest of what a robot's generated data depend on, with its index: the description, with the
        nominal robot file's content in place of its path (a fleet folder may move)."""
        d = {**asdict(self), "robot": _digest(self.robot, _stamp(self.robot))}
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=list).encode()).hexdigest()[:16]

    def seed_of(self, index: int) -> np.random.SeedSequence:
        """``SeedSequence(seed).spawn(robots)[index]``, without spawning the others."""
        return np.random.SeedSequence(self.seed, spawn_key=(index,))

    def generate(self, index: int) -> GeneratedRobot:
        """Simulate robot ``index`` in memory: the same data as its folder would hold (the folder's CSV
        rounds them to 15 significant digits)."""
        if not 0 <= index < self.robots:
            raise IndexError(f"robot index {index} outside the fleet's 0 … {self.robots - 1}")
        nominal = _nominal(self.robot, _stamp(self.robot))
        return _generate(nominal, self.poses, self.validation_poses, self.measure, self.noise_pos,
                         self.noise_rot, self.p_effect, self.effects, self.seed_of(index))

    def to_yaml(self) -> str:
        import yaml

        d = asdict(self)
        d["effects"] = list(self.effects)
        return ("# estcal fleet generated on demand: robot i is simulated from the seed and i (SI units)\n"
                + yaml.safe_dump({"simulated_fleet": d}, sort_keys=False))

    @classmethod
    def read(cls, path) -> "FleetSpec":
        """Read ``fleet.yaml``; a wrong or missing key is one :class:`InputError` naming the file and key.
        A relative robot path is made absolute against the file's folder."""
        from estcal.base.textinput import read_yaml

        path = Path(path)
        doc = read_yaml(path, "fleet description")
        d = doc.get("simulated_fleet") if isinstance(doc, dict) else None
        if not isinstance(d, dict):
            raise InputError(f"{path}: expected a 'simulated_fleet:' mapping (estcal simulate --fleet N --on-demand "
                             f"writes one)")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"{path}: unknown key(s) {', '.join(unknown)} under simulated_fleet (known: "
                             f"{', '.join(sorted(known))})")
        if "robots" not in d:
            raise InputError(f"{path}: simulated_fleet needs 'robots: N' (the number of robots)")
        try:
            spec = cls(robots=int(d["robots"]), robot=str(d.get("robot", "robot.yaml")),
                       poses=int(d.get("poses", 50)), validation_poses=int(d.get("validation_poses", 50)),
                       measure=str(d.get("measure", "pose")), noise_pos=float(d.get("noise_pos", 5e-5)),
                       noise_rot=float(d.get("noise_rot", 5e-4)), p_effect=float(d.get("p_effect", 0.5)),
                       effects=tuple(d.get("effects", FLEET_EFFECTS)), seed=int(d.get("seed", 0)))
        except (TypeError, ValueError) as exc:
            raise InputError(f"{path}: simulated_fleet: {exc}") from None
        spec.check(path)
        rob = Path(spec.robot)
        if not rob.is_absolute() and (path.parent / rob).is_file():
            spec = cls(**{**asdict(spec), "robot": str((path.parent / rob).resolve())})
        return spec

    def check(self, where="fleet description") -> None:
        """Refuse counts and probabilities out of range and unknown effects, naming the key."""
        bad = [(k, v, why) for k, v, why in (
            ("robots", self.robots, self.robots >= 1), ("poses", self.poses, self.poses >= 1),
            ("validation_poses", self.validation_poses, self.validation_poses >= 0),
            ("p_effect", self.p_effect, 0 <= self.p_effect <= 1), ("noise_pos", self.noise_pos, self.noise_pos >= 0),
            ("noise_rot", self.noise_rot, self.noise_rot >= 0),
            ("measure", self.measure, self.measure in ("pose", "points", "position")),
            ("effects", list(self.effects), set(self.effects) <= set(FLEET_EFFECTS))) if not why]
        if bad:
            k, v, _ = bad[0]
            raise InputError(f"{where}: simulated_fleet.{k} = {v!r} is out of range (robots, poses ≥ 1; "
                             f"validation_poses, noise ≥ 0; 0 ≤ p_effect ≤ 1; measure pose|points|position; effects "
                             f"among {', '.join(FLEET_EFFECTS)})")


def simulate_robot(job) -> dict:
    """Simulate one robot folder (a task of :func:`simulate_fleet`); returns its summary row."""
    (folder, robot_file, n_poses, n_validate, measure, noise_pos, noise_rot, p_effect, effects, seed) = job
    folder = Path(folder)
    g = _generate(load_robot(robot_file), n_poses, n_validate, measure, noise_pos, noise_rot, p_effect, effects,
                  seed)
    folder.mkdir(parents=True, exist_ok=True)
    write_dataset(folder / "data.csv", g.dataset, float_format="%.15g")
    if n_validate:
        write_dataset(folder / "validate.csv", g.validation, float_format="%.15g")
    atomic_write_text(folder / "truth.json", json.dumps(g.truth, indent=2))
    return {"robot": folder.name, "effects": g.effects, "nominal_rms_mm": g.nominal_rms_mm}


def simulate_fleet(n: int, out, robot="puma560", n_poses: int = 50, n_validate: int = 50,
                   measure: str = "pose", noise_pos: float = 5e-5, noise_rot: float = 5e-4,
                   p_effect: float = 0.5, effects=FLEET_EFFECTS, seed: int = 0, scheduler="serial",
                   n_workers: int | None = None, progress="auto", on_demand: bool = False):
    """Write a simulated fleet of ``n`` robots to ``out`` (see the module docstring).

    Returns the :class:`~estcal.scale.runner.RunResult` of the per-robot simulations
    (one summary row per robot: name, effects, nominal-vs-true RMS in mm); with
    ``on_demand`` only the nominal robot file and the :class:`FleetSpec` are written,
    and the :class:`FleetSpec` is returned.
    """
    if n < 1:
        raise ValueError(f"--fleet: the number of robots must be ≥ 1, got {n}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    nominal = load_robot(robot)
    robot_file = save_robot(nominal, out / "robot.yaml")
    spec = FleetSpec(robots=n, robot="robot.yaml", poses=n_poses, validation_poses=n_validate, measure=measure,
                     noise_pos=noise_pos, noise_rot=noise_rot, p_effect=p_effect,
                     effects=tuple(effects), seed=int(seed))
    spec.check("--fleet")
    if on_demand:
        atomic_write_text(out / SPEC_FILE, spec.to_yaml())
        return FleetSpec.read(out / SPEC_FILE)
    jobs = [(str(out / spec.name(i)), str(robot_file), n_poses, n_validate, measure, noise_pos,
             noise_rot, p_effect, tuple(effects), spec.seed_of(i)) for i in range(n)]
    return run_tasks(simulate_robot, jobs, scheduler=scheduler, n_workers=n_workers, progress=progress,
                     desc="simulate fleet")
