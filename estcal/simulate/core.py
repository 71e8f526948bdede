"""Simulated calibration datasets with a known ground truth.

A "true" robot is the nominal model plus parameter errors plus non-geometric
effects (:mod:`estcal.effects`). Poses come from the textbook strategies
S1–S4 (:mod:`estcal.simulate.strategies`); the true robot's forward
kinematics at the *true* joint readings, under the per-pose context (time,
temperature, payload), gives the exact measurement, to which measurement noise
is added. The recorded joint readings are the true ones plus reading noise,
rounded to the encoder resolution::

    r_rec = res · round((r_true + n_r) / res)        n_r ~ N(0, σ_r²) or U(−a_r, a_r)
    x_meas = x_true(r_true) + n_x                     n_x ~ N(0, σ_x² I) or U(−a_x, a_x)³
    R_meas = exp([n_w]×) · R_true(r_true)             n_w ~ N(0, σ_w² I) or U(−a_w, a_w)³

(the orientation noise is a world-frame rotation vector, matching estcal's
pose error ``log(R_meas R_predᵀ)``). For uniform noise the numbers given are
half-widths, as in the textbook's ε/2 (Mooring–Roth–Driels §4.6).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from estcal.effects import make_effect
from estcal.io.dataset import dataset_from_arrays, write_dataset
from estcal.io.robotfile import load_robot, robot_from_dict, robot_to_dict
from estcal.kinematics.chain import SerialRobot
from estcal.kinematics.chunked import tool_poses
from estcal.kinematics.transforms import pose_error, so3_exp
from estcal.methods.base import NoiseModel

from .strategies import generate_poses

__all__ = ["ErrorModel", "simulation_noise", "SimulationResult", "SimulationSummary", "simulate", "random_errors",
           "parse_effect_spec", "DEFAULT_EFFECT_STD"]

# Typical magnitudes used when an effect is requested without values (documented in docs/simulation.md).
DEFAULT_EFFECT_STD = {
    "joint_compliance": 1e-5,   # rad/(N·m): 100 N·m -> 1 mrad
    "backlash": 2e-4,           # rad, half free-play (drawn as |N(0, σ²)|)
    "gear_harmonic": 1e-4,      # rad per sin/cos coefficient
    "encoder_gain": 1e-3,       # dimensionless
    "thermal_expansion": 1.2e-5,  # 1/K, steel (used as is, not random)
    "drift": 1e-7,              # rad/s: 0.36 mrad per hour
}
_POSITIVE = {"backlash"}
_FIXED = {"thermal_expansion"}


@dataclass
class ErrorModel:
    """Standard deviations of random parameter errors, by kind (SI units).

    ``angle`` applies to α, θ, β and rotation parameters (including base/tool
    rx, ry, rz), ``length`` to d, a, r and translations (including base/tool),
    ``offset`` to joint offsets (rad, or m for prismatic joints), ``gain`` to
    joint gains (dimensionless; 0 by default, gains are rarely wrong), ``marker``
    to marker coordinates.
    """

    angle: float = 1e-3
    length: float = 1e-3
    offset: float = 1e-3
    gain: float = 0.0
    marker: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


def _param_class(robot: SerialRobot, name: str, kind: str, frame: str) -> str:
    if kind == "gain":
        return "gain"
    if kind == "marker":
        return "marker"
    if kind == "effect":
        return "effect"
    if kind == "offset":
        return "offset"
    head = name.split("_")[-1] if kind in ("base", "tool") else name.split("_")[0]
    return "angle" if head in ("alpha", "theta", "beta", "rx", "ry", "rz") else "length"


def random_errors(robot: SerialRobot, std: ErrorModel | dict | None = None, rng=None) -> dict[str, float]:
    """Random parameter errors ``{name: δ}`` (added to the nominal values), N(0, σ_kind²)."""
    em = std if isinstance(std, ErrorModel) else ErrorModel(**(std or {}))
    rng = np.random.default_rng(rng)
    pv = robot.params
    out = {}
    for name, kind, frame in zip(pv.names, pv.kinds, pv.frames):
        cls = _param_class(robot, name, kind, frame)
        if cls == "effect":
            continue
        s = getattr(em, cls)
        if s:
            out[name] = float(rng.normal(0.0, s))
    return out


def parse_effect_spec(spec) -> dict:
    """``"joint_compliance:j2,j3"`` / ``"thermal_expansion"`` / dict -> ``{effect, joints, options, params}``."""
    if isinstance(spec, dict):
        d = dict(spec)
        if "effect" not in d:
            raise ValueError(f"effect spec {spec!r} needs an 'effect' name")
        return {"effect": d["effect"], "joints": d.get("joints"), "options": dict(d.get("options") or {}),
                "params": dict(d.get("params") or {})}
    s = str(spec).strip()
    name, _, joints = s.partition(":")
    return {"effect": name.strip(), "joints": [j.strip() for j in joints.split(",") if j.strip()] or None,
            "options": {}, "params": {}}


@dataclass
class SimulationSummary:
    """What the simulator produced and how far the nominal model is from the truth.

    ``nominal_rms_mm`` / ``nominal_max_mm``: position error of the nominal model
    at the recorded readings against the true, noise-free measurement (over all
    measured points), i.e. what calibration must remove. ``nominal_rot_*_deg``
    likewise for orientation (pose data). ``noise_rms_mm``: RMS of the added
    position noise.
    """

    robot: str
    n_poses: int
    strategy: str
    measure: str
    columns: list[str]
    n_parameters_with_error: int
    effects: list[str]
    nominal_rms_mm: float
    nominal_max_mm: float
    nominal_rot_rms_deg: float | None
    nominal_rot_max_deg: float | None
    noise_rms_mm: float
    seed: int | None
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def rows(self) -> list[tuple[str, str]]:
        r = [("robot", self.robot), ("poses", str(self.n_poses)), ("strategy", self.strategy),
             ("measure", self.measure), ("columns", ", ".join(self.columns)),
             ("parameters with error", str(self.n_parameters_with_error)),
             ("effects", ", ".join(self.effects) or "none"),
             ("nominal vs true, RMS (mm)", f"{self.nominal_rms_mm:.4f}"),
             ("nominal vs true, max (mm)", f"{self.nominal_max_mm:.4f}")]
        if self.nominal_rot_rms_deg is not None:  # printed in mrad like every table (docs/conventions.md)
            mrad = 1e3 * np.pi / 180
            r += [("nominal vs true, rot RMS (mrad)", f"{self.nominal_rot_rms_deg * mrad:.4f}"),
                  ("nominal vs true, rot max (mrad)", f"{self.nominal_rot_max_deg * mrad:.4f}")]
        r += [("measurement noise RMS (mm)", f"{self.noise_rms_mm:.4f}"), ("seed", str(self.seed))]
        return r

    def __str__(self) -> str:
        w = max(len(k) for k, _ in self.rows())
        return "\n".join(f"{k:<{w}}  {v}" for k, v in self.rows() + [("note", n) for n in self.notes])


@dataclass
class SimulationResult:
    """Output of :func:`simulate`.

    Attributes
    ----------
    dataset : Dataset (recorded readings, noisy measurements, context, extra columns).
    truth : dict — the ground truth written to JSON (see ``docs/simulation.md``).
    true_robot, nominal_robot : SerialRobot — the truth (with effects) and the model to calibrate.
    true_readings : (N, n) noise-free joint readings.
    true_points, true_R, true_p : noise-free measurements.
    summary : SimulationSummary.
    """

    dataset: Any
    truth: dict
    true_robot: SerialRobot
    nominal_robot: SerialRobot
    true_readings: np.ndarray
    true_points: np.ndarray | None
    true_R: np.ndarray | None
    true_p: np.ndarray | None
    summary: SimulationSummary

    def write(self, csv_path, truth_path=None, float_format: str = "%.15g") -> tuple[Path, Path | None]:
        """Write the dataset CSV (documented format) and the ground-truth JSON."""
        p = write_dataset(csv_path, self.dataset, float_format=float_format)
        t = None
        if truth_path is not None:
            from estcal.base.jsonio import write_json

            truth = dict(self.truth)
            truth["dataset"] = str(p)
            t = write_json(truth_path, truth)
        return p, t

    def to_dict(self) -> dict:
        return {"summary": self.summary.to_dict(), "truth": self.truth}

    def __repr__(self) -> str:
        return f"SimulationResult({self.summary.robot!r}, {self.summary.n_poses} poses, {self.summary.measure})"


def _with_markers(robot: SerialRobot, markers) -> SerialRobot:
    d = robot_to_dict(robot)
    d["markers"] = np.asarray(markers, float).reshape(-1, 3).tolist()
    return robot_from_dict(d, source=f"{robot.name} (+markers)")


def _profile(spec, N: int, t: np.ndarray | None, what: str, rng) -> np.ndarray | None:
    """Per-pose profile: None, constant, (start, end) ramp, {start, end, tau} warm-up, (lo, hi, 'uniform'), array."""
    if spec is None:
        return None
    if isinstance(spec, dict):
        start, end = float(spec["start"]), float(spec["end"])
        if "tau" in spec:
            if t is None:
                raise ValueError(f"{what}: a warm-up profile (tau) needs times (dt=...)")
            return end - (end - start) * np.exp(-(t - t[0]) / float(spec["tau"]))
        return np.linspace(start, end, N)
    if isinstance(spec, (int, float)):
        return np.full(N, float(spec))
    a = np.asarray(spec, dtype=object)
    if a.ndim == 1 and len(a) == 3 and a[2] == "uniform":
        return rng.uniform(float(a[0]), float(a[1]), N)
    a = np.asarray(spec, float)
    if a.shape == (2,) and N != 2:
        return np.linspace(a[0], a[1], N)
    if a.shape != (N,):
        raise ValueError(f"{what}: expected a number, (start, end), or {N} values; got shape {a.shape}")
    return a


def simulation_noise(value) -> NoiseModel:
    """The noise of a simulation: ``None`` or 0 is no noise at all (:meth:`NoiseModel.none`), anything
    else is read by the one rule of :meth:`NoiseModel.parse` (docs/conventions.md, "Noise")."""
    if value is None or (isinstance(value, (int, float)) and not isinstance(value, bool) and value == 0):
        return NoiseModel.none()
    return NoiseModel.parse(value)


def simulate(robot, n_poses: int = 50, strategy: str = "S4", measure: str = "position",
             errors=None, error_std: ErrorModel | dict | None = None, effects: Sequence = (),
             noise: NoiseModel | dict | None = None, seed: int | None = 0, margin: float = 0.0,
             readings=None, dt: float | None = None, t=None, temperature=None, payload=None,
             record_approach: bool = False, markers=None, n_points: int = 3,
             effect_params: dict | None = None, home=None) -> SimulationResult:
    """Simulate a calibration dataset.

    Parameters
    ----------
    robot : SerialRobot or robot spec (built-in name, .yaml, .urdf) — the nominal model.
    n_poses : number of poses N (ignored when ``readings`` is given).
    strategy : ``"S1"`` … ``"S4"`` (see :mod:`estcal.simulate.strategies`).
    measure : ``"position"`` (one point: marker 1, or the tool origin), ``"points"``
        (every marker; ``n_points`` default markers are added if the robot has fewer
        than 2) or ``"pose"`` (tool frame).
    errors : None / ``"none"`` (true = nominal), ``"random"`` (N(0, σ²) per kind from
        ``error_std``) or a dict ``{parameter name: δ}`` of errors added to the nominal values.
    effects : effect specs — ``"joint_compliance:j2,j3"``, ``"thermal_expansion"``, or
        dicts ``{effect, joints, options, params}``; parameters not given are drawn
        with :data:`DEFAULT_EFFECT_STD`.
    noise : the measurement and reading noise (:func:`simulation_noise`): any form of
        :meth:`estcal.methods.NoiseModel.parse`; ``None`` or 0: noise-free.
    seed : seed of every random draw (errors, effects, poses, context, noise each use
        an independent stream spawned from it, so changing the noise keeps the poses).
    margin : fraction of each joint range left out at both ends.
    readings : (N, n) true joint readings to use instead of a strategy.
    dt, t : time of each pose — ``t`` (N,) seconds, or ``dt`` seconds between poses.
    temperature : °C — constant, ``(start, end)`` linear ramp, ``{start, end, tau}``
        warm-up ``end − (end − start)·exp(−t/τ)``, or N values.
    payload : kg — constant, ``(lo, hi, "uniform")`` random per pose, or N values
        (written as the ``payload`` column; used by gravity-dependent effects).
    record_approach : write ``approach_<joint>`` columns (random ±1) for backlash joints.
    effect_params : ``{effect parameter name: value}`` for any of the requested effects
        (alternative to the per-effect ``params``).
    home : (n,) home readings of strategy S2 (default mid-range).
    markers : (k, 3) tool-frame points replacing the robot's markers.
    """
    nominal = load_robot(robot)
    if nominal.effects:
        raise ValueError(f"{nominal.name}: the nominal robot already has effects; pass a geometric model "
                         f"and list the effects to simulate in `effects`")
    if measure not in ("position", "points", "pose"):
        raise ValueError(f"measure must be 'position', 'points' or 'pose', got {measure!r}")
    noise = simulation_noise(noise)
    ss = np.random.SeedSequence(seed)
    r_err, r_eff, r_pose, r_ctx, r_noise = (np.random.default_rng(s) for s in ss.spawn(5))
    notes: list[str] = []
    specs = [parse_effect_spec(e) for e in effects]
    names = [s["effect"] for s in specs]
    nominal = _measured_markers(nominal, markers, measure, n_points, r_pose, notes)
    err, error_model = _parameter_errors(nominal, errors, error_std, r_err)
    true = _true_robot(nominal, err, specs, effect_params, r_eff)
    if readings is not None:
        r_true = nominal.check_readings(readings, "readings")
        strategy = "given"
    else:
        r_true = generate_poses(nominal, n_poses, strategy, r_pose, margin=margin, home=home)
        strategy = str(strategy).upper()
    context, columns = _context(true, specs, names, r_true, t, dt, temperature, payload, record_approach, r_ctx, notes)
    meas = _measure(true, nominal, r_true, measure, {**context, **columns}, noise, r_noise)
    rec = _recorded_readings(r_true, noise, r_noise, nominal.n_joints)
    # approach columns are effect context too: in Dataset.context so that code passing
    # ``dataset.context`` to the kinematics sees them (and in columns, as a CSV reload gives)
    ds = dataset_from_arrays(nominal.joint_names, rec, points=meas["points"], R=meas["R"], p=meas["p"],
                             context={**context, **columns}, columns=columns, path=None)
    summary = _summary(nominal, true, rec, meas, measure, strategy, err, context, columns, seed, notes)
    truth = _truth(nominal, true, seed, strategy, measure, margin, noise, error_model, err, context, columns,
                   summary, notes)
    return SimulationResult(ds, truth, true, nominal, r_true, meas["true_points"], meas["true_R"], meas["true_p"],
                            summary)


def _measured_markers(nominal, markers, measure, n_points, r_pose, notes):
    """The nominal robot with the given markers, or with ``n_points`` default markers on the tool when
    ``points`` are measured on a robot with fewer than two."""
    if markers is not None:
        nominal = _with_markers(nominal, markers)
    if measure == "points" and nominal.n_markers < 2:
        k = max(2, int(n_points))
        default = np.array([[0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1], [-0.1, 0, 0], [0, -0.1, 0], [0, 0, -0.1]])
        m = default[:k] if k <= 6 else r_pose.normal(0, 0.1, (k, 3))
        nominal = _with_markers(nominal, m)
        notes.append(f"added {k} markers on the tool (m): {np.round(m, 4).tolist()}")
    return nominal


def _parameter_errors(nominal, errors, error_std, r_err):
    """``({parameter: error}, ErrorModel or None)`` of the forms ``errors`` takes."""
    if errors is None or (isinstance(errors, str) and errors.lower() == "none"):
        return {}, None
    if isinstance(errors, str) and errors.lower() == "random":
        error_model = error_std if isinstance(error_std, ErrorModel) else ErrorModel(**(error_std or {}))
        return random_errors(nominal, error_model, r_err), error_model
    if isinstance(errors, dict):
        err = {str(k): float(v) for k, v in errors.items()}
        for k in err:
            nominal.params.index(k)  # clear error for unknown names
        return err, None
    raise ValueError(f"errors must be None, 'none', 'random' or a dict of parameter errors, got {errors!r}")


def _true_robot(nominal, err, specs, effect_params, r_eff):
    """Nominal + parameter errors + effects (their parameters given, fixed or drawn)."""
    true = nominal.copy()
    for k, v in err.items():
        true.params[k] = nominal.params[k] + v
    given = {str(k): float(v) for k, v in (effect_params or {}).items()}
    owned = set()
    for s in specs:
        eff = make_effect(s["effect"], true, joints=s["joints"], **s["options"])
        s["params"] = {**{k: v for k, v in given.items() if k in eff.param_names}, **s["params"]}
        owned |= set(eff.param_names)
        true = true.add_effect(eff)
        sd = DEFAULT_EFFECT_STD.get(s["effect"], 0.0)
        for pname in eff.param_names:
            if pname in s["params"]:
                v = float(s["params"][pname])
            elif s["effect"] in _FIXED:
                v = sd
            else:
                v = float(r_eff.normal(0.0, sd))
                v = abs(v) if s["effect"] in _POSITIVE else v
            true.params[pname] = v
        unknown = set(s["params"]) - set(eff.param_names)
        if unknown:
            raise ValueError(f"effect {s['effect']!r}: unknown parameters {sorted(unknown)}; "
                             f"its parameters are {eff.param_names}")
    if set(given) - owned:
        raise ValueError(f"effect parameters {sorted(set(given) - owned)} belong to none of the requested "
                         f"effects; their parameters are {sorted(owned)}")
    return true


def _context(true, specs, names, r_true, t, dt, temperature, payload, record_approach, r_ctx, notes):
    """``(context, columns)`` of every pose: time, temperature and payload profiles; random approach
    directions of the backlash joints. Effects that need a context the call lacks get a default."""
    N = r_true.shape[0]
    if t is None and dt is None and "drift" in names:
        dt = 60.0
        notes.append("drift needs time: using dt = 60 s between poses")
    times = None
    if t is not None:
        times = np.asarray(t, float).reshape(-1)
        if times.shape != (N,):
            raise ValueError(f"t must have {N} values, got {times.shape}")
    elif dt is not None:
        times = float(dt) * np.arange(N)
    if temperature is None and "thermal_expansion" in names and times is None:
        temperature = (20.0, 30.0)
        notes.append("thermal_expansion needs temperature: using a 20 -> 30 degC ramp over the poses")
    profiles = {"t": times, "temperature": _profile(temperature, N, times, "temperature", r_ctx),
                "payload": _profile(payload, N, times, "payload", r_ctx)}
    context = {k: v for k, v in profiles.items() if v is not None}
    columns: dict[str, np.ndarray] = {}
    for s, eff in zip(specs, true.effects):
        # a backlash by approach cannot act without the directions: draw them as record_approach does
        if s["effect"] == "backlash" and (record_approach or getattr(eff, "by", "auto") == "approach"):
            for j in eff.joints:
                columns[f"approach_{j}"] = r_ctx.choice([-1.0, 1.0], N)
    if any(n in ("joint_compliance", "backlash") for n in names):
        tau = true.gravity_torques(r_true, context=context)
        if not np.any(tau):
            notes.append("gravity torques are zero (no link masses or payload): compliance/backlash have "
                         "no effect — give masses in the robot file or a payload")
    return context, columns


def _measure(true, nominal, r_true, measure, ctx, noise, r_noise) -> dict:
    """The true measurements at the true readings and the noisy ones (``points`` or ``R, p``), and the
    noise added to the positions (``added``)."""
    # tool frames and points only, 20,000 poses at a time (a million poses would otherwise hold
    # every link frame of every pose: ~3.5 kB per pose)
    kin = tool_poses(true, r_true, context=ctx, fields=("R", "p", "points"))
    out = dict(true_points=None, true_R=None, true_p=None, points=None, R=None, p=None)
    N = r_true.shape[0]
    if measure == "pose":
        out.update(true_R=kin.R, true_p=kin.p)
        out["p"] = kin.p + noise.draw(noise.position, kin.p.shape, r_noise)
        out["R"] = so3_exp(noise.draw(noise.orientation, (N, 3), r_noise)) @ kin.R
        out["added"] = out["p"] - kin.p
        return out
    true_points = kin.points[:, :1] if measure == "position" and nominal.n_markers else kin.points
    if measure == "position" and nominal.n_markers == 0:
        true_points = kin.p[:, None, :]
    out.update(true_points=true_points, points=true_points + noise.draw(noise.position, true_points.shape, r_noise))
    out["added"] = out["points"] - true_points
    return out


def _recorded_readings(r_true, noise, r_noise, n_joints):
    """The recorded joint readings: reading noise, then quantisation to the encoder resolution."""
    rec = r_true + noise.draw(noise.joint, r_true.shape, r_noise)
    res = np.broadcast_to(np.asarray(noise.resolution, float), (n_joints,))
    q_mask = res > 0
    if q_mask.any():
        rec[:, q_mask] = np.round(rec[:, q_mask] / res[q_mask]) * res[q_mask]
    return rec


def _summary(nominal, true, rec, meas, measure, strategy, err, context, columns, seed, notes) -> SimulationSummary:
    """How wrong the nominal model is (at the recorded readings) with respect to the true measurement."""
    kn = tool_poses(nominal, rec, fields=("R", "p", "points"))
    rot_rms = rot_max = None
    if measure == "pose":
        e = pose_error(meas["true_R"], meas["true_p"], kn.R, kn.p)
        dpos = np.linalg.norm(e[:, :3], axis=1)
        drot = np.degrees(np.linalg.norm(e[:, 3:], axis=1))
        rot_rms, rot_max = float(np.sqrt(np.mean(drot**2))), float(drot.max())
    else:
        true_points = meas["true_points"]
        pred = kn.points[:, :true_points.shape[1]] if nominal.n_markers else kn.p[:, None, :]
        dpos = np.linalg.norm(true_points - pred, axis=-1).reshape(-1)
    header = list(nominal.joint_names)
    if measure == "pose":
        header += ["x", "y", "z", "qw", "qx", "qy", "qz"]
    elif meas["points"].shape[1] == 1:
        header += ["x", "y", "z"]
    else:
        header += [f"{c}{k + 1}" for k in range(meas["points"].shape[1]) for c in "xyz"]
    header += list(context) + list(columns)
    return SimulationSummary(
        robot=nominal.name, n_poses=rec.shape[0], strategy=strategy, measure=measure, columns=header,
        n_parameters_with_error=sum(1 for v in err.values() if v != 0.0),
        effects=[f"{e.name}:{','.join(e.joints)}" if e.joints else e.name for e in true.effects],
        nominal_rms_mm=float(np.sqrt(np.mean(dpos**2)) * 1e3), nominal_max_mm=float(dpos.max() * 1e3),
        nominal_rot_rms_deg=rot_rms, nominal_rot_max_deg=rot_max,
        noise_rms_mm=float(np.sqrt(np.mean(meas["added"]**2)) * 1e3), seed=seed, notes=notes)


def _truth(nominal, true, seed, strategy, measure, margin, noise, error_model, err, context, columns, summary,
           notes) -> dict:
    """The ground truth as JSON-ready data (docs/simulation.md, "Truth file")."""
    pv = true.params
    return {
        "estcal_truth": 1,
        "robot": nominal.name,
        "seed": seed,
        "n_poses": summary.n_poses,
        "strategy": strategy,
        "measure": measure,
        "margin": margin,
        "noise": noise.to_dict(simulation=True),
        "error_model": error_model.to_dict() if error_model is not None else None,
        "parameters": {n: float(v) for n, v in zip(pv.names, pv.values)},
        "nominal": {n: float(v) for n, v in zip(nominal.params.names, nominal.params.values)},
        "errors": {n: v for n, v in err.items() if v != 0.0},  # true = nominal + error
        "effects": [{**e.to_dict(), "params": {n: float(pv[n]) for n in e.param_names}} for e in true.effects],
        "context": {"t": "t" in context, "temperature": "temperature" in context, "payload": "payload" in context,
                    "approach": sorted(columns)},
        "units": {"length": "m", "angle": "rad", "t": "s", "temperature": "degC", "payload": "kg"},
        "nominal_robot": robot_to_dict(nominal),
        "true_robot": robot_to_dict(true),
        "summary": summary.to_dict(),
        "notes": notes,
    }
