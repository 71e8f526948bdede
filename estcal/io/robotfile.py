"""The estcal robot file (YAML) and the one entry point that resolves any robot spec.

A robot file describes a serial chain in the Khalil–Kleinfinger modified-DH
notation (GECARO eq. [3]) or in standard DH, overridable per joint, plus
base and tool frames, joint models, masses and markers. The full format is in
``docs/robot-file.md``; in short::

    estcal_robot: 1
    name: my_arm
    convention: khalil            # or dh (urdf allowed per joint, see docs)
    units: {length: m, angle: rad}  # optional: mm / in, deg — converted to SI on load
    base: {xyz: [0, 0, 0.5], rpy: [0, 0, 0]}
    tool: {xyz: [0, 0, 0.1], rpy: [0, 0, 0]}
    joints:
      - {name: frame0, type: fixed, theta: 1.5708, r: 0.5}
      - {name: j1, type: revolute, alpha: 0, d: 0, theta: 0, r: 0, beta: 0,
         offset: 0, gain: 1, limits: [-3.14, 3.14], mass: 2.0, com: [0, 0, 0.1]}
    markers: [[0, 0, 0.05]]
    payload: {mass: 1.0, com: [0, 0, 0.05]}
    gravity: [0, 0, -9.81]

:func:`load_robot` accepts a :class:`~estcal.kinematics.SerialRobot`, a
built-in name (:data:`estcal.kinematics.robots.BUILTIN`), the name of a
packaged robot file (``estcal/robots/data/<name>.yaml``), a ``.yaml``/``.yml``
file or a ``.urdf`` file. :func:`save_robot` writes a file that reloads to the
same parameters, limits, masses and forward kinematics.

Every error names the file and the offending key or joint, e.g.
``robot.yaml: joint 'j3': unknown type 'prismatc' (expected revolute, prismatic or fixed)``.
"""
from __future__ import annotations

import dataclasses
import difflib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.errors import RobotFileError
from estcal.base.jsonio import to_jsonable
from estcal.base.textinput import read_text, read_yaml
from estcal.effects import make_effect
from estcal.kinematics.builder import (DH_PARAMS, KHALIL_PARAMS, MAX_ANGLE_RAD, MAX_LENGTH_M, MAX_LIMIT_RAD,
                                       URDF_PARAMS, build_robot, frame_labels)
from estcal.kinematics.chain import SerialRobot
from estcal.kinematics.robots import BUILTIN
from estcal.kinematics.transforms import make_transform, matrix_to_rpy, rpy_to_matrix
from estcal.robots import available

from .integrity import stamp_text, verify_text
from .urdfspec import is_urdf_spec, robot_from_spec

__all__ = ["RobotFileError", "load_robot", "robot_names", "save_robot", "robot_from_dict", "robot_to_dict",
           "read_robot_file", "calibration_covariance", "FORMAT_VERSION", "LENGTH_UNITS", "ANGLE_UNITS"]

FORMAT_VERSION = 1
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254}
ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}

_TOP_KEYS = ("estcal_robot", "name", "description", "convention", "units", "base", "tool", "tool_origin",
             "joints", "markers", "payload", "gravity", "coupling", "effects", "calibration")
_JOINT_COMMON = ("name", "type", "convention", "label", "offset", "gain", "limits", "mass", "com", "gear_ratio")
_CONV_KEYS = {"khalil": KHALIL_PARAMS, "dh": DH_PARAMS, "urdf": ("origin", "axis") + URDF_PARAMS}
# which convention parameters are angles (the others are lengths)
_ANGLE_KEYS = {"alpha", "theta", "beta", "rx", "ry", "rz"}
_TYPES = ("revolute", "prismatic", "fixed")


def _suggest(key: str, valid) -> str:
    close = difflib.get_close_matches(str(key), list(valid), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


class _Ctx:
    """Error context: ``<file>: <where>: message``."""

    def __init__(self, source: str):
        self.source = source

    def err(self, where: str, msg: str) -> RobotFileError:
        return RobotFileError(f"{self.source}: {where + ': ' if where else ''}{msg}")

    def number(self, value, where: str, key: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.err(where, f"{key!r} must be a number, got {value!r}")
        v = float(value)
        if not np.isfinite(v):
            raise self.err(where, f"{key!r} must be finite, got {value!r}")
        return v

    def vector(self, value, n: int, where: str, key: str) -> np.ndarray:
        if not isinstance(value, (list, tuple)) or len(value) != n:
            raise self.err(where, f"{key!r} must be a list of {n} numbers, got {value!r}")
        return np.array([self.number(v, where, key) for v in value])

    def check_keys(self, d, valid, where: str) -> None:
        if not isinstance(d, Mapping):
            raise self.err(where, f"expected a mapping, got {d!r}")
        for k in d:
            if k not in valid:
                raise self.err(where, f"unknown key {k!r}{_suggest(k, valid)}; valid keys: {', '.join(valid)}")


def _check_unit(ctx: _Ctx, where: str, key: str, value_si, angle: bool, limit: bool = False) -> None:
    """Refuse a value beyond the physical range of its unit, naming the likely mistake."""
    v = np.max(np.abs(np.atleast_1d(value_si)))
    if angle:
        top = MAX_LIMIT_RAD if limit else MAX_ANGLE_RAD
        if v > top:
            raise ctx.err(where, f"{key!r} reaches {v:.6g} rad, beyond ±{'4π' if limit else '2π'} — are the angles "
                                 f"in degrees? add `units: {{angle: deg}}` at the top of the file, or convert")
    elif v > MAX_LENGTH_M:
        raise ctx.err(where, f"{key!r} reaches {v:.6g} m, beyond {MAX_LENGTH_M:g} m — are the lengths in "
                             f"millimetres? add `units: {{length: mm}}` at the top of the file, or convert")


def _frame6(ctx: _Ctx, d, key: str, lu: float, au: float) -> dict:
    """``{xyz, rpy}`` -> SI dict (both optional, default zero)."""
    if d is None:
        return {"xyz": np.zeros(3), "rpy": np.zeros(3)}
    ctx.check_keys(d, ("xyz", "rpy"), key)
    return {"xyz": ctx.vector(d.get("xyz", [0, 0, 0]), 3, key, "xyz") * lu,
            "rpy": ctx.vector(d.get("rpy", [0, 0, 0]), 3, key, "rpy") * au}


def robot_from_dict(d: Mapping[str, Any], source: str = "<dict>", strict: bool = False) -> SerialRobot:
    """Build a robot from a parsed robot-file mapping (see module docstring).

    ``source`` is the file name used in error messages. ``strict`` (files read by
    :func:`load_robot`) refuses a joint that states none of its geometric parameters
    (or a URDF-convention joint without ``origin``): in a file written by hand that is
    a forgotten line, not a link of zero length; mappings built in code may rely on
    the zero defaults.
    """
    ctx = _Ctx(source)
    name, convention = _check_header(ctx, d, source)
    lu, au = _file_units(ctx, d)
    joints = d.get("joints")
    if not isinstance(joints, list) or not joints:
        raise ctx.err("joints", "a non-empty list of joints is required")
    frames, gear, extra_values = [], {}, {}
    for i, jd in enumerate(joints):
        frames.append(_joint_frame(ctx, i, jd, convention, lu, au, strict, [f["name"] for f in frames], gear,
                                   extra_values))
    markers = _markers(ctx, d, lu)
    tool_d, tool_mass = _tool_with_mass(ctx, d.get("tool"), lu)
    base_f, tool_f = _frame6(ctx, d.get("base"), "base", lu, au), _frame6(ctx, tool_d, "tool", lu, au)
    if strict:
        for key, fr in (("base", base_f), ("tool", tool_f)):
            _check_unit(ctx, key, "xyz", fr["xyz"], False)
            _check_unit(ctx, key, "rpy", fr["rpy"], True)
        if markers is not None:
            _check_unit(ctx, "markers", "marker", markers, False)
    try:
        robot = build_robot(name, frames, base=base_f, tool=tool_f, markers=markers,
                            gravity=_gravity(ctx, d), payload=_payload(ctx, d, lu), coupling=_coupling(ctx, d, frames),
                            convention=convention, tool_const=_tool_const(ctx, d.get("tool_origin"), lu, au),
                            meta=_meta(ctx, d, source, gear))
    except ValueError as exc:
        raise ctx.err("", str(exc)) from exc
    for pname, v in extra_values.items():
        robot.params[pname] = v
    if tool_mass is not None:
        robot.links = list(robot.links[:-1]) + [dataclasses.replace(robot.links[-1], mass=tool_mass[0],
                                                                   com=tool_mass[1])]
    if d.get("effects"):
        robot = _attach_effects(ctx, robot, d["effects"])
    return robot


def _check_header(ctx: _Ctx, d, source: str) -> tuple[str, str]:
    """``(name, convention)`` after the checks of the top level (format version, keys)."""
    if not isinstance(d, Mapping):
        raise ctx.err("", "a robot file must be a YAML mapping with 'estcal_robot: 1' at the top")
    if "estcal_robot" not in d:
        raise ctx.err("", "missing top-level key 'estcal_robot: 1' (is this an estcal robot file?)")
    if d["estcal_robot"] != FORMAT_VERSION:
        raise ctx.err("estcal_robot", f"unsupported format version {d['estcal_robot']!r} (this estcal reads 1)")
    ctx.check_keys(d, _TOP_KEYS, "")
    convention = d.get("convention", "khalil")
    if convention not in ("khalil", "dh", "urdf"):
        raise ctx.err("convention", f"unknown convention {convention!r} (expected khalil or dh)")
    return str(d.get("name", Path(source).stem)), convention


def _file_units(ctx: _Ctx, d) -> tuple[float, float]:
    """Factors from the file's length and angle units (``units:``) to SI."""
    units = d.get("units") or {}
    ctx.check_keys(units, ("length", "angle"), "units")
    lu_name, au_name = units.get("length", "m"), units.get("angle", "rad")
    if lu_name not in LENGTH_UNITS:
        raise ctx.err("units", f"unknown length unit {lu_name!r} (expected one of {sorted(LENGTH_UNITS)})")
    if au_name not in ANGLE_UNITS:
        raise ctx.err("units", f"unknown angle unit {au_name!r} (expected one of {sorted(ANGLE_UNITS)})")
    return LENGTH_UNITS[lu_name], ANGLE_UNITS[au_name]


def _joint_frame(ctx: _Ctx, i: int, jd, convention: str, lu: float, au: float, strict: bool, seen, gear: dict,
                 extra_values: dict) -> dict:
    """The frame description (:func:`estcal.kinematics.builder.build_robot`) of joint ``i``, in SI;
    gear ratios and URDF placement errors go to ``gear`` and ``extra_values``."""
    if not isinstance(jd, Mapping):
        raise ctx.err(f"joints[{i}]", f"expected a mapping, got {jd!r}")
    jname = str(jd.get("name", f"joint{i + 1}"))
    where = f"joint {jname!r}"
    if "name" not in jd:
        raise ctx.err(f"joints[{i}]", "missing 'name'")
    if jname in seen:
        raise ctx.err(where, "duplicate joint name")
    jtype = jd.get("type", "revolute")
    if jtype not in _TYPES:
        raise ctx.err(where, f"unknown type {jtype!r}{_suggest(jtype, _TYPES)} "
                             f"(expected revolute, prismatic or fixed)")
    conv = jd.get("convention", convention)
    if conv not in _CONV_KEYS:
        raise ctx.err(where, f"unknown convention {conv!r} (expected khalil, dh or urdf)")
    ctx.check_keys(jd, _JOINT_COMMON + _CONV_KEYS[conv], where)
    f: dict[str, Any] = {"name": jname, "type": jtype, "convention": conv}
    if "label" in jd:
        f["label"] = str(jd["label"])
    if conv == "urdf":
        _urdf_geometry(ctx, jd, f, where, lu, au, strict, extra_values)
    else:
        _convention_geometry(ctx, jd, f, where, conv, lu, au, strict)
    _joint_variable(ctx, jd, f, where, jtype, lu, au, strict, gear)
    if "mass" in jd:
        m = ctx.number(jd["mass"], where, "mass")
        if m < 0:
            raise ctx.err(where, f"'mass' must be >= 0 kg, got {m}")
        f["mass"] = m
    if "com" in jd:
        f["com"] = ctx.vector(jd["com"], 3, where, "com") * lu
    return f


def _urdf_geometry(ctx: _Ctx, jd, f: dict, where: str, lu: float, au: float, strict: bool, extra_values: dict):
    """A URDF-convention joint: its origin, axis and 6-D placement errors (set after building)."""
    if strict and "origin" not in jd:
        raise ctx.err(where, "no 'origin' {xyz, rpy} — give it ({xyz: [0, 0, 0], rpy: [0, 0, 0]} where "
                             "the joint frame is the parent's) so that a missing line is not read as zeros")
    o = _frame6(ctx, jd.get("origin"), f"{where}: origin", lu, au)
    if strict:
        _check_unit(ctx, f"{where}: origin", "xyz", o["xyz"], False)
        _check_unit(ctx, f"{where}: origin", "rpy", o["rpy"], True)
    f["origin"] = make_transform(rpy_to_matrix(o["rpy"]), o["xyz"])
    ax = ctx.vector(jd.get("axis", [0, 0, 1]), 3, where, "axis")
    if np.linalg.norm(ax) == 0:
        raise ctx.err(where, "'axis' must be non-zero")
    f["axis"] = ax
    for k in URDF_PARAMS:  # the builder does not take the 6-D placement errors
        if k in jd:
            extra_values[f"{k}_{f.get('label', f['name'])}"] = ctx.number(jd[k], where, k) * (
                au if k in _ANGLE_KEYS else lu)


def _convention_geometry(ctx: _Ctx, jd, f: dict, where: str, conv: str, lu: float, au: float, strict: bool):
    """A Khalil or DH joint: its geometric parameters in SI."""
    if strict and not any(k in jd for k in _CONV_KEYS[conv]):
        # a forgotten line would otherwise be read as a zero-length, untwisted link
        raise ctx.err(where, f"no geometric parameters ({', '.join(_CONV_KEYS[conv])}) — give them "
                             f"(0 where zero) so that a missing line is not read as zeros")
    for k in _CONV_KEYS[conv]:
        if k in jd:
            f[k] = ctx.number(jd[k], where, k) * (au if k in _ANGLE_KEYS else lu)
            if strict:
                _check_unit(ctx, where, k, f[k], k in _ANGLE_KEYS)


def _joint_variable(ctx: _Ctx, jd, f: dict, where: str, jtype: str, lu: float, au: float, strict: bool,
                    gear: dict):
    """The joint model: offset, gain, limits (in the unit of the joint variable) and gear ratio."""
    ju = au if jtype == "revolute" else lu  # unit of the joint variable
    if jtype == "fixed":
        for k in ("offset", "gain", "limits", "gear_ratio"):
            if k in jd:
                raise ctx.err(where, f"{k!r} is not allowed on a fixed frame")
        return
    if "offset" in jd:
        f["offset"] = ctx.number(jd["offset"], where, "offset") * ju
        if strict:
            _check_unit(ctx, where, "offset", f["offset"], jtype == "revolute")
    if "gain" in jd:
        f["gain"] = ctx.number(jd["gain"], where, "gain")
        if f["gain"] == 0:
            raise ctx.err(where, "'gain' must be non-zero (q = gain · reading + offset: a zero gain "
                                 "freezes the joint; 1 for a transmission without error)")
    if "limits" in jd:
        lim = ctx.vector(jd["limits"], 2, where, "limits") * ju
        if not lim[0] < lim[1]:
            raise ctx.err(where, f"'limits' must be [lower, upper] with lower < upper, got {jd['limits']}")
        if strict:
            _check_unit(ctx, where, "limits", lim, jtype == "revolute", limit=True)
        f["limits"] = lim.tolist()
    elif jtype == "prismatic":
        raise ctx.err(where, "a prismatic joint needs 'limits' (metres)")
    if "gear_ratio" in jd:
        g = ctx.number(jd["gear_ratio"], where, "gear_ratio")
        if g == 0:
            raise ctx.err(where, "'gear_ratio' must be non-zero")
        gear[f["name"]] = g


def _markers(ctx: _Ctx, d, lu: float):
    """(k, 3) marker points on the tool (m), or None."""
    if d.get("markers") is None:
        return None
    mk = d["markers"]
    if not isinstance(mk, list):
        raise ctx.err("markers", "expected a list of [x, y, z] points (tool frame)")
    markers = np.array([ctx.vector(m, 3, f"markers[{i}]", "marker") for i, m in enumerate(mk)]) * lu
    return markers.reshape(-1, 3) if len(markers) else None


def _payload(ctx: _Ctx, d, lu: float):
    if d.get("payload") is None:
        return None
    ctx.check_keys(d["payload"], ("mass", "com"), "payload")
    return {"mass": ctx.number(d["payload"].get("mass", 0.0), "payload", "mass"),
            "com": ctx.vector(d["payload"].get("com", [0, 0, 0]), 3, "payload", "com") * lu}


def _gravity(ctx: _Ctx, d) -> tuple:
    if d.get("gravity") is None:
        return (0.0, 0.0, -9.81)
    return tuple(ctx.vector(d["gravity"], 3, "gravity", "gravity"))


def _coupling(ctx: _Ctx, d, frames):
    """``(joint, motor)`` coupling matrices (n × n over the actuated joints), or None."""
    if d.get("coupling") is None:
        return None
    c = d["coupling"]
    ctx.check_keys(c, ("joint", "motor"), "coupling")
    n = sum(f["type"] != "fixed" for f in frames)
    mats = []
    for k in ("joint", "motor"):
        try:
            M = np.array(c.get(k, np.eye(n).tolist()), float)
        except (TypeError, ValueError):
            raise ctx.err("coupling", f"{k!r} must be a {n}x{n} matrix of numbers") from None
        if M.shape != (n, n):
            raise ctx.err("coupling", f"{k!r} must be {n}x{n}, got shape {M.shape}")
        mats.append(M)
    return tuple(mats)


def _meta(ctx: _Ctx, d, source: str, gear: dict) -> dict:
    """The robot's ``meta``: the file, its description, gear ratios and a saved model's calibration block."""
    meta: dict[str, Any] = {"robot_file": source}
    if "description" in d:
        meta["source"] = str(d["description"])
    if gear:
        meta["gear_ratio"] = gear
    if d.get("calibration") is not None:
        if not isinstance(d["calibration"], dict):
            raise ctx.err("calibration", "expected a mapping (provenance of a saved model)")
        meta["calibration"] = _calibration_block(ctx, d["calibration"])
    return meta


def _tool_with_mass(ctx: _Ctx, tool_d, lu: float):
    """``(tool frame mapping, (mass kg, com m) or None)``: the mass carried by the tool link itself
    (e.g. the lumped mass model of a diagnosed robot) split from its placement."""
    if not (isinstance(tool_d, Mapping) and ("mass" in tool_d or "com" in tool_d)):
        return tool_d, None
    ctx.check_keys(tool_d, ("xyz", "rpy", "mass", "com"), "tool")
    tool_mass = (ctx.number(tool_d.get("mass", 0.0), "tool", "mass"),
                 ctx.vector(tool_d.get("com", [0, 0, 0]), 3, "tool", "com") * lu)
    if tool_mass[0] < 0:
        raise ctx.err("tool", f"'mass' must be >= 0 kg, got {tool_mass[0]}")
    return {k: v for k, v in tool_d.items() if k in ("xyz", "rpy")}, tool_mass


def _calibration_block(ctx, c: dict) -> dict:
    """Check the ``calibration:`` block of a saved model: ``free`` (names) and
    ``covariance`` (square, SI units, in the order of ``free``) must agree."""
    free, cov = c.get("free"), c.get("covariance")
    if (free is None) != (cov is None):
        raise ctx.err("calibration", "'free' and 'covariance' must be given together")
    if free is not None:
        if not isinstance(free, list) or not all(isinstance(n, str) for n in free):
            raise ctx.err("calibration.free", "expected a list of parameter names")
        try:
            C = np.array(cov, dtype=float)
        except (TypeError, ValueError):
            raise ctx.err("calibration.covariance", "expected a square matrix of numbers") from None
        if C.shape != (len(free), len(free)):
            raise ctx.err("calibration.covariance",
                          f"expected {len(free)}x{len(free)} (one row per name of 'free'), got shape {C.shape}")
        if not np.all(np.isfinite(C)):
            raise ctx.err("calibration.covariance", "contains NaN or infinite values")
    return dict(c)


def calibration_covariance(robot: SerialRobot):
    """``(names, C)`` of a saved model's ``calibration:`` block (SI units), or ``None``.

    ``C`` is the covariance of the free parameters ``names`` as estimated by the
    calibration that produced the file (see docs/robot-file.md, "Saved models").
    """
    c = robot.meta.get("calibration") or {}
    if c.get("free") is None:
        return None
    names = list(c["free"])
    missing = [n for n in names if n not in robot.params.names]
    if missing:
        raise RobotFileError(f"{robot.name}: calibration.free names unknown parameters {missing[:5]}")
    return names, np.array(c["covariance"], dtype=float)


def _tool_const(ctx, d, lu, au):
    if d is None:
        return None
    o = _frame6(ctx, d, "tool_origin", lu, au)
    return make_transform(rpy_to_matrix(o["rpy"]), o["xyz"])


def _attach_effects(ctx: _Ctx, robot: SerialRobot, effects) -> SerialRobot:
    """``effects: [{effect: joint_compliance, joints: [j2], params: {compliance_j2: 1e-6}}, ...]``."""
    if not isinstance(effects, list):
        raise ctx.err("effects", "expected a list of {effect, joints, params} mappings")
    for i, e in enumerate(effects):
        where = f"effects[{i}]"
        ctx.check_keys(e, ("effect", "joints", "options", "params"), where)
        if "effect" not in e:
            raise ctx.err(where, "missing 'effect' (the effect name)")
        try:
            eff = make_effect(e["effect"], robot, joints=e.get("joints"), **(e.get("options") or {}))
        except (KeyError, ValueError, TypeError) as exc:
            raise ctx.err(where, str(exc).strip("'\"")) from exc
        robot = robot.add_effect(eff)
        for pname, v in (e.get("params") or {}).items():
            if pname not in eff.param_names:
                raise ctx.err(where, f"parameter {pname!r} is not one of this effect's parameters "
                                     f"{eff.param_names}")
            robot.params[pname] = ctx.number(v, where, pname)
    return robot


def read_robot_file(path) -> dict:
    """Parse a YAML robot file into a mapping (clear error on YAML syntax problems)."""

    verify_text(read_text(path, "robot", RobotFileError), str(path), RobotFileError, "robot file")
    return read_yaml(path, "robot", RobotFileError)


def _is_gough(spec: str) -> bool:
    try:
        from estcal.parallel import is_gough_file
    except ImportError:  # pragma: no cover
        return False
    return is_gough_file(spec)


def _gough_names() -> list[str]:
    try:
        from estcal.parallel.gough import BUILTINS
    except ImportError:  # pragma: no cover
        return []
    return sorted(BUILTINS)


def robot_names() -> list[str]:
    """Every robot name :func:`load_robot` accepts besides files: built-ins and packaged robot files."""

    return sorted(set(BUILTIN) | set(available()))


def _packaged(name: str) -> Path | None:
    p = Path(__file__).resolve().parents[1] / "robots" / "data" / f"{name}.yaml"
    return p if p.exists() else None


def load_robot(spec, root: str | None = None, tip: str | None = None, n_markers: int | None = None
               ) -> SerialRobot:
    """Resolve a robot specification.

    Parameters
    ----------
    spec : SerialRobot, str or Path
        A robot object (returned as is), a built-in name (``puma560``, ``stanford``,
        ``5r1p``, ``planar2``, ``puma560_fu``, ``tiago``), a packaged robot-file
        name, a ``.yaml``/``.yml`` robot file, a ``.urdf`` file, or a URDF robot spec (a ``.yaml``
        naming a ``urdf`` and, for a UR arm, a kinematics file: :mod:`estcal.io.urdfspec`).
    root, tip : str, optional
        URDF links delimiting the chain (root defaults to the URDF's root link;
        tip is required unless the URDF has a single leaf link).
    n_markers : int, optional
        Number of points measured on the tool (``x1,y1,z1 … xk,yk,zk`` datasets).
        Robots without markers get ``n_markers`` unknown points initialised at the
        tool origin; a robot file that already lists a different number is an error.
    """
    if isinstance(spec, SerialRobot):
        robot = spec
    else:
        s = str(spec)
        suffix = Path(s).suffix.lower()
        if suffix in (".yaml", ".yml"):
            d = read_robot_file(s)
            if is_urdf_spec(d):  # a URDF, its chain, a UR kinematics file (docs/export.md)
                return robot_from_spec(d, s, root, tip, n_markers)
            robot = robot_from_dict(d, source=s, strict=True)
        elif suffix == ".urdf":
            from estcal.kinematics.urdf import robot_from_urdf

            robot = robot_from_urdf(s, root=root, tip=tip,
                                    markers=np.zeros((n_markers, 3)) if n_markers else None)
        else:
            from estcal.kinematics.robots import BUILTIN

            key = s.lower()
            if key in BUILTIN:
                robot = BUILTIN[key](n_markers=n_markers or 0) if key == "tiago" else BUILTIN[key]()
            elif _packaged(key) is not None:
                robot = robot_from_dict(read_robot_file(_packaged(key)), source=str(_packaged(key)), strict=True)
            elif _is_gough(s):
                raise RobotFileError(f"{s}: is a Gough–Stewart (parallel) platform — this command needs a serial "
                                     f"robot; `estcal calibrate` and `estcal identifiable` handle platforms")
            elif Path(s).is_dir():
                raise RobotFileError(f"{s}: is a folder, not a robot — give a built-in name, a robot file "
                                     f"(.yaml) or a URDF (.urdf)")
            elif Path(s).exists():
                raise RobotFileError(f"{s}: unknown robot file type {suffix!r} (expected .yaml, .yml or .urdf)")
            else:
                raise RobotFileError(f"unknown robot {s!r}: not a built-in robot ({', '.join(robot_names())}; "
                                     f"parallel: {', '.join(_gough_names())}) and no such file (.yaml robot "
                                     f"file or .urdf)")
        if (root or tip) and suffix != ".urdf":
            raise ValueError(f"{s}: --root/--tip only apply to URDF files")
    if n_markers is not None and n_markers != robot.n_markers:
        if robot.n_markers:
            raise ValueError(f"{getattr(robot, 'name', spec)}: the robot defines {robot.n_markers} markers "
                             f"but {n_markers} were requested")
        d = robot_to_dict(robot)
        d["markers"] = [[0.0, 0.0, 0.0]] * n_markers
        robot = robot_from_dict(d, source=str(robot.meta.get("robot_file", robot.name)))
    return robot


# ------------------------------------------------------------------- saving
def _f(x) -> float | list:
    """Plain Python floats for YAML (repr round-trips float64 exactly)."""
    a = np.asarray(x, float)
    return float(a) if a.ndim == 0 else [float(v) for v in a.reshape(-1)]


def _frame6_out(values: dict) -> dict:
    return {"xyz": _f([values["tx"], values["ty"], values["tz"]]),
            "rpy": _f([values["rx"], values["ry"], values["rz"]])}


def robot_to_dict(robot: SerialRobot) -> dict:
    """The robot-file mapping (SI units) of a robot built by :func:`build_robot`.

    Uses the current parameter values, so a calibrated robot is saved as calibrated.
    Effects are saved with their options and parameter values when they provide
    ``to_dict()`` (all effects of :mod:`estcal.effects` do).
    """
    pv = robot.params
    val = {n: float(v) for n, v in zip(pv.names, pv.values)}

    def group(prefix):
        return {k: val[f"{prefix}_{k}"] for k in ("tx", "ty", "tz", "rx", "ry", "rz")}

    links = robot.links
    if links[0].label != "base" or links[-1].label != "tool":
        raise ValueError(f"{robot.name}: cannot save a robot whose first/last links are not base/tool")
    conv_top = robot.convention if robot.convention in ("khalil", "dh", "urdf") else "khalil"
    out: dict[str, Any] = {"estcal_robot": FORMAT_VERSION, "name": robot.name, "convention": conv_top}
    if "source" in robot.meta:
        out["description"] = str(robot.meta["source"])
    out["base"] = _frame6_out(group("base"))
    out["tool"] = _frame6_out(group("tool"))
    if links[-1].mass:
        out["tool"].update(mass=float(links[-1].mass), com=_f(links[-1].com))
    tc = links[-1].const
    if not np.allclose(tc, np.eye(4), atol=0, rtol=0):
        out["tool_origin"] = {"xyz": _f(tc[:3, 3]), "rpy": _f(matrix_to_rpy(tc[:3, :3]))}
    gear = robot.meta.get("gear_ratio", {}) or {}
    joints, labels = [], []
    for link in links[1:-1]:
        lab = link.label
        if f"tx_{lab}" in val or (not link.before and not link.after):
            conv = "urdf"
        elif f"a_{lab}" in val:
            conv = "dh"
        elif f"r_{lab}" in val:
            conv = "khalil"
        else:
            raise ValueError(f"{robot.name}: cannot tell the convention of frame {lab!r}")
        if link.joint is None:
            jd: dict[str, Any] = {"name": f"frame{lab}", "type": "fixed"}
        else:
            j = link.joint
            jname = robot.joint_names[j]
            jd = {"name": jname, "type": robot.joint_types[j]}
        if conv != conv_top:
            jd["convention"] = conv
        if conv == "urdf":
            jd["origin"] = {"xyz": _f(link.const[:3, 3]), "rpy": _f(matrix_to_rpy(link.const[:3, :3]))}
            jd["axis"] = _f(link.joint_axis)
            for k in URDF_PARAMS:
                if f"{k}_{lab}" in val and val[f"{k}_{lab}"] != 0.0:
                    jd[k] = val[f"{k}_{lab}"]
        else:
            if not np.allclose(link.const, np.eye(4), atol=0, rtol=0):
                raise ValueError(f"{robot.name}: frame {lab!r} has a constant transform; not expressible in {conv}")
            for k in (KHALIL_PARAMS if conv == "khalil" else DH_PARAMS):
                jd[k] = val[f"{k}_{lab}"]
        if link.joint is not None:
            j = link.joint
            jd["offset"] = float(pv.values[robot.offset_idx[j]])
            jd["gain"] = float(pv.values[robot.gain_idx[j]])
            jd["limits"] = _f(robot.limits[j])
            if robot.joint_names[j] in gear:
                jd["gear_ratio"] = float(gear[robot.joint_names[j]])
        if link.mass:
            jd["mass"] = float(link.mass)
            jd["com"] = _f(link.com)
        joints.append(jd)
        labels.append(lab)
    # explicit labels only where the default numbering would differ

    if conv_top == "urdf":
        default = [jd["name"] for jd in joints]
    else:
        default = frame_labels([{"type": jd["type"]} for jd in joints])
    for jd, lab, dl in zip(joints, labels, default):
        if lab != dl:
            jd["label"] = lab
    out["joints"] = joints
    if robot.n_markers:
        out["markers"] = [_f(pv.values[idx]) for idx in robot.marker_idx]
    if robot.payload_mass or np.any(robot.payload_com):
        out["payload"] = {"mass": float(robot.payload_mass), "com": _f(robot.payload_com)}
    out["gravity"] = _f(robot.gravity)
    if robot.coupling is not None:
        out["coupling"] = {"joint": np.asarray(robot.coupling[0], float).tolist(),
                           "motor": np.asarray(robot.coupling[1], float).tolist()}
    effs = []
    for eff in robot.effects:
        if not hasattr(eff, "to_dict"):
            raise ValueError(f"{robot.name}: effect {type(eff).__name__} has no to_dict(); cannot save it")
        e = eff.to_dict()
        e["params"] = {n: float(pv[n]) for n in eff.param_names}
        effs.append(e)
    if effs:
        out["effects"] = effs
    if robot.meta.get("calibration"):
        out["calibration"] = _plain(robot.meta["calibration"])
    return out


def _plain(x):
    """YAML-safe plain data (numpy arrays and scalars to lists and floats; the JSON rules)."""
    return to_jsonable(x)


def save_robot(robot: SerialRobot, path, checksum: bool = False) -> Path:
    """Write ``robot`` as a YAML robot file (SI units) that :func:`load_robot` reads back.

    Floats are written with Python's shortest round-trip repr, so the reloaded
    robot has bit-identical parameter values and forward kinematics. ``checksum``: a
    ``# content-sha256:`` line (:mod:`estcal.io.integrity`) that makes a later change or cut
    refused on reading — saved models carry it; a robot file meant to be edited does not.
    """
    import yaml

    path = Path(path)
    d = robot_to_dict(robot)

    # libyaml's emitter when available: same text, ~5× faster on a saved model's covariance
    # (it dominated the per-robot cost of `estcal fleet`, docs/scaling.md)
    class _Dumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):
        pass

    def _flow_list(dumper, data):
        flow = all(isinstance(x, (int, float)) for x in data) or all(isinstance(x, list) for x in data) and \
            all(all(isinstance(y, (int, float)) for y in x) for x in data) and sum(map(len, data)) <= 40
        # (a large matrix — a saved model's covariance — is written one flow row per line)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)

    _Dumper.add_representer(list, _flow_list)
    header = (f"# estcal robot file (SI units: metres, radians, kg); see docs/robot-file.md\n"
              f"# written by estcal.io.robotfile.save_robot from robot {robot.name!r}\n")


    body = yaml.dump(d, Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=110)
    # the checksum line lets a reader refuse a file cut at a line boundary or changed by a digit
    atomic_write_text(path, stamp_text(header, body) if checksum else header + body)
    return path
