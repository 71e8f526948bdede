"""Simulated calibration datasets with their ground truth: ``estcal simulate`` (docs/simulation.md).

:func:`simulate` builds the true robot (nominal + parameter errors — random, none, or a file of
``{name: error}`` in SI — + effects), draws poses, measures them with noise and returns the
:class:`~estcal.simulate.SimulationResult`; :func:`simulate_from_fit` does the same for the robot a
diagnosis identified (``--from-fit``); :func:`simulate_fleet` writes a fleet folder. The memory a
simulation needs is checked before the work (:func:`check_memory`).
"""
from __future__ import annotations

import math
from pathlib import Path

from estcal.base.errors import InputError
from estcal.workflows.inputs import input_errors

__all__ = ["simulate", "simulate_fleet", "load_errors", "check_errors", "check_memory", "parse_numbers",
           "BYTES_PER_POSE", "MEASURES"]

MEASURES = ("position", "points", "pose")

#: measured peak memory of `estcal simulate` per pose (0.8 kB position, 1.0 kB three points at 2·10⁵
#: poses; docs/benchmarks.md "Memory on large datasets"), with a margin for effects and context columns
BYTES_PER_POSE = 1500


def available_memory() -> int | None:
    """MemAvailable of /proc/meminfo in bytes (None where there is no such file)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(n: int) -> None:
    """Refuse, before the work, a simulation that would not fit in the memory available now
    (the dataset is built whole, then written atomically): a clear message instead of the
    operating system killing the process after minutes."""
    avail = available_memory()
    need = n * BYTES_PER_POSE
    if avail is not None and need > 0.8 * avail:
        raise InputError(f"--n {n}: simulating {n:,} poses needs about {need / 1e9:.1f} GB of memory and "
                         f"{avail / 1e9:.1f} GB are available — simulate several smaller files (different --seed) "
                         f"or lower --n")


def parse_numbers(text: str | None, what: str):
    """``"1.5"`` → 1.5, ``"0,5"`` → [0.0, 5.0] (comma or semicolon separated); None stays None."""
    if text is None:
        return None
    parts = [p for p in str(text).replace(";", ",").split(",") if p.strip()]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{what}: expected numbers separated by commas, got {text!r}") from None
    return vals[0] if len(vals) == 1 else vals


def load_errors(errors: str):
    """``"random"`` / ``"none"``, or a JSON/YAML file of ``{parameter name: error}`` in SI (a truth
    JSON of an earlier run is read through its ``errors`` key)."""
    low = str(errors).lower()
    if low in ("none", "random"):
        return low
    p = Path(errors)
    if not p.exists():
        raise InputError(f"--errors must be 'random', 'none' or a JSON/YAML file of {{name: delta}}; "
                         f"{errors!r} is none of these")
    from estcal.base.textinput import read_json, read_yaml

    d = read_yaml(p, "errors", InputError) if p.suffix.lower() in (".yaml", ".yml") else read_json(p, "errors",
                                                                                                   InputError)
    if isinstance(d, dict) and "errors" in d and isinstance(d["errors"], dict):
        d = d["errors"]  # a truth JSON from an earlier run
    if not isinstance(d, dict):
        raise InputError(f"{p}: expected a mapping {{parameter name: error}}")
    out = {}
    for k, v in d.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"{p}: error of {k!r} must be a finite number (SI), got {v!r}")
        out[str(k)] = float(v)
    return out


def check_errors(errs: dict, robot, where) -> None:
    """The names of an errors file must be the robot's, and its values SI: an angle error beyond
    π, a length error beyond 1 m or a relative gain error beyond 1 is a unit mistake (degrees,
    millimetres, per cent), not a robot to calibrate."""
    from estcal.base.units import display_unit
    from estcal.kinematics.parameters import unknown_name_message

    for k, v in errs.items():
        if k not in robot.params:
            raise InputError(f"{where}: {unknown_name_message(k, robot.params.names)}")
        unit = display_unit(k, robot)[0]
        limit, what = {"mrad": (math.pi, "rad (degrees?)"), "mm": (1.0, "m (millimetres?)"),
                       "": (1.0, "(relative; per cent?)")}.get(unit, (math.inf, ""))
        if abs(v) > limit:
            raise InputError(f"{where}: the error of {k!r} is {v:g} {what} — the file is in SI units "
                             f"(m, rad, relative gain); beyond ±{limit:g} no calibration model applies")


def _effects(effects, effect_params) -> tuple[list, dict]:
    from estcal.simulate import parse_effect_spec

    specs = [s.strip() for e in effects or [] for s in str(e).split(";") if s.strip()]
    params = {}
    for item in effect_params or []:
        name, _, val = str(item).partition("=")
        try:
            params[name.strip()] = float(val)
        except ValueError:
            raise InputError(f"--effect-param expects NAME=VALUE, got {item!r}") from None
    with input_errors():
        return [parse_effect_spec(s) for s in specs], params


def _context(temperature, payload) -> tuple:
    temp = parse_numbers(temperature, "--temperature")
    if isinstance(temp, list) and len(temp) == 3:
        temp = {"start": temp[0], "end": temp[1], "tau": temp[2]}
    pay = parse_numbers(payload, "--payload")
    if isinstance(pay, list):
        if len(pay) != 2:
            raise InputError("--payload: give M or LO,HI")
        pay = (pay[0], pay[1], "uniform")
    return temp, pay


def simulate(robot, n: int = 50, *, strategy: str = "S4", measure: str = "position", noise=None,
             errors: str = "random", error_std=None, effects=(), effect_params=(), seed: int = 0, margin: float = 0.0,
             dt: float | None = None, temperature: str | None = None, payload: str | None = None,
             approach: bool = False, n_points: int = 3, root=None, tip=None, from_fit=None):
    """A simulated dataset with its ground truth — the job of ``estcal simulate``.

    ``noise``: a :class:`estcal.simulate.NoiseModel` (SI; None: noise-free, or the fit's with
    ``from_fit``); ``errors``: ``random`` | ``none`` | a JSON/YAML file of ``{name: error}`` (SI);
    ``error_std``: an :class:`estcal.simulate.ErrorModel`; ``effects``: ``NAME[:JOINT,JOINT]``
    specs; ``temperature`` / ``payload``: ``T`` or ``START,END[,TAU]`` °C / ``M`` or ``LO,HI`` kg;
    ``from_fit``: a diagnosis JSON (``estcal diagnose --json``) whose robot is simulated instead.
    Returns a :class:`~estcal.simulate.SimulationResult`.
    """
    from estcal.io.robotfile import load_robot
    from estcal.simulate import simulate as _simulate

    if measure == "location":
        measure = "pose"
    check_memory(n)
    with input_errors():
        nominal = load_robot(robot, root=root, tip=tip)
    specs, eparams = _effects(effects, effect_params)
    temp, pay = _context(temperature, payload)
    with input_errors():
        if from_fit is not None:
            from estcal.discrepancy.feedback import simulate_from_fit

            return simulate_from_fit(from_fit, n_poses=n, strategy=strategy,
                                     measure=None if measure == "position" else measure, noise=noise, seed=seed,
                                     context={"temperature": temp, "payload": pay}, margin=margin, dt=dt,
                                     record_approach=approach)
        errs = load_errors(errors)
        if isinstance(errs, dict):
            check_errors(errs, nominal, errors)
        return _simulate(nominal, n_poses=n, strategy=strategy, measure=measure, errors=errs, error_std=error_std,
                         effects=specs, noise=noise, seed=seed, margin=margin, dt=dt, temperature=temp, payload=pay,
                         record_approach=approach, n_points=n_points, effect_params=eparams)


def simulate_fleet(n_robots: int, out, *, robot: str = "puma560", n: int = 50, measure: str = "position",
                   noise_pos: float | None = None, noise_rot: float | None = None, seed: int = 0,
                   scheduler: str = "serial", on_demand: bool = False):
    """A fleet folder of ``n_robots`` simulated robots (:func:`estcal.simulate.fleet.simulate_fleet`):
    measured as full poses unless asked otherwise; noise defaults 0.05 mm / 0.5 mrad (SI here).
    ``on_demand``: only the description ``fleet.yaml`` (returned, a :class:`~estcal.simulate.fleet.FleetSpec`)."""
    from estcal.simulate.fleet import simulate_fleet as _fleet
    from estcal.workflows.fleet import check_scheduler

    if out is None:
        raise InputError("--fleet needs --out DIR (the fleet folder to write)")
    if n_robots < 1:
        raise InputError(f"--fleet: the number of robots must be ≥ 1, got {n_robots}")
    check_scheduler(scheduler)
    if not on_demand:
        check_memory(n * n_robots)
    if measure in ("position", "location"):  # a fleet is measured as full poses unless asked otherwise
        measure = "pose"
    with input_errors():
        return _fleet(n_robots, out, robot=robot, n_poses=n, n_validate=n, measure=measure,
                      noise_pos=noise_pos or 5e-5, noise_rot=noise_rot or 5e-4, seed=seed, scheduler=scheduler,
                      on_demand=on_demand)
