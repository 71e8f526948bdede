"""Universal Robots kinematics files: ``ur_description``'s ``config/<model>/default_kinematics.yaml``.

A UR arm's calibration reaches ROS, its driver and MoveIt as a YAML file (ros-industrial
``universal_robot`` and ``Universal_Robots_ROS2_Description``; the ``ur_calibration`` tool extracts
a controller's factory calibration in the same format)::

    kinematics:
      shoulder:  {x: …, y: …, z: …, roll: …, pitch: …, yaw: …}
      upper_arm: {…}
      forearm:   {…}
      wrist_1:   {…}
      wrist_2:   {…}
      wrist_3:   {…}
      hash: calib_…

The description's xacro writes each entry as the ``<origin xyz="x y z" rpy="roll pitch yaw"/>`` of
one joint — ``shoulder`` of ``shoulder_pan_joint`` (parent ``base_link_inertia``), ``upper_arm`` of
``shoulder_lift_joint``, ``forearm`` of ``elbow_joint``, ``wrist_1`` … ``wrist_3`` of
``wrist_1_joint`` … ``wrist_3_joint`` — each joint turning about its ``z`` axis. ``hash`` names the
calibration (the driver compares it with the controller's).

Writing (:func:`ur_origins`): a calibrated URDF-convention link is
``C_J · E(tx…rz) · Rot(axis, q + offset)``, where ``C_J = F_J · O_J`` holds the URDF's fixed joints
``F_J`` before joint J (merged by the loader) and its origin ``O_J``. Since
``Rot(a, q + offset) = Rot(a, offset) · Rot(a, q)``, the calibrated origin is exactly::

    O'_J = F_J⁻¹ · C_J · E(tx…rz) · Rot(axis, offset)

so the joint offset becomes a rotation of the origin about the joint axis. Its ``rpy`` is the
solution nearest the nominal triple (a rotation has two, each modulo 2π), so a small calibration
changes the numbers little. An origin the calibration leaves unchanged (to 1e-12) keeps the
nominal numbers bit for bit — which makes reading a file back and writing it again byte-identical.

Reading (:func:`apply_to_tree`): the entries replace the origins of the six joints of a URDF, as
the xacro would (:func:`estcal.kinematics.urdf.origin_matrix`, the URDF reader's own composition).

The hash is ``calib_estcal_`` + the first 16 hex digits of the SHA-256 of the 36 numbers as written
(:func:`ur_hash`): deterministic over the numbers, so the same calibration always has the same name
and an edited file is recognised. (The ROS tool's ``calib_<digits>`` is C++ ``std::hash`` of the
controller's DH table: neither portable nor reproducible outside it.)
"""
from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_write_text
from estcal.base.errors import EstcalWarning, NumericalRefusal, RobotFileError

from .chain import SerialRobot
from .transforms import matrix_to_rpy, rpy_to_matrix
from .urdf import chain_joints, joint_origin, origin_matrix

__all__ = ["ENTRIES", "UR_JOINTS", "KEYS", "HASH_PREFIX", "MAX_SHIFT_M", "MAX_TILT_RAD", "UrKinematics",
           "UrOrigins", "read_ur_kinematics", "ur_hash", "apply_to_tree", "ur_origins", "rpy_near", "ur_prefix"]

ENTRIES = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
UR_JOINTS = dict(zip(ENTRIES, ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                               "wrist_2_joint", "wrist_3_joint")))
KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
HASH_PREFIX = "calib_estcal_"
#: an origin further than this from the URDF's (translation) is another robot's, not a calibration of
#: this one: UR models differ by 19 mm (UR3 / UR3e) to 0.2 m; a calibration moves an origin by millimetres
MAX_SHIFT_M = 0.015
#: a joint axis tilted further than this from the URDF's is another robot's (the rotation *about* the
#: axis is free: that is the joint offset)
MAX_TILT_RAD = 0.1
_SAME = 1e-12  # m / rad: an origin this close to the nominal keeps the nominal numbers


def _num(v: float) -> str:
    """The text of a number in the file: Python's shortest round-trip repr (−0 written as 0), with a
    ``.0`` before a bare exponent (YAML 1.1 reads ``1e-05`` as a string, ``1.0e-05`` as a float)."""
    s = repr(float(v) + 0.0)
    if "e" in s and "." not in s:
        mant, exp = s.split("e")
        s = f"{mant}.0e{exp}"
    return s


def ur_hash(entries: dict) -> str:
    """``calib_estcal_`` + the first 16 hex digits of the SHA-256 of ``entry.key=number`` lines (the
    numbers as written in the file, in the file's order)."""
    text = "".join(f"{e}.{k}={_num(v)}\n" for e in ENTRIES for k, v in zip(KEYS, entries[e]))
    return HASH_PREFIX + hashlib.sha256(text.encode("ascii")).hexdigest()[:16]


@dataclass
class UrKinematics:
    """The six joint origins of a UR kinematics file (``entries[name] = (x, y, z, roll, pitch, yaw)``, m
    and rad) and its ``hash``."""

    entries: dict
    hash: str
    path: Path | None = None

    def origin(self, entry: str) -> np.ndarray:
        """The origin of ``entry`` as 4×4, composed as the URDF reader composes ``<origin>``."""
        v = self.entries[entry]
        return origin_matrix(v[:3], v[3:])

    def text(self) -> str:
        """The file: a header, then ``kinematics:`` in ``ur_description``'s layout."""
        lines = ["# UR kinematics file (ur_description's config/<model>/default_kinematics.yaml format), "
                 "written by estcal export",
                 "# each entry is one joint's origin, parent link -> child link: x y z in m, roll pitch yaw in rad "
                 "(URDF fixed-axis rpy);",
                 "# joint offsets are folded in as rotations of the origin about its joint axis (docs/export.md)",
                 f"# hash: {HASH_PREFIX} + the first 16 hex digits of the SHA-256 of the 36 numbers as written",
                 "kinematics:"]
        for e in ENTRIES:
            lines.append(f"  {e}:")
            lines += [f"    {k}: {_num(v)}" for k, v in zip(KEYS, self.entries[e])]
        lines.append(f"  hash: {self.hash}")
        return "\n".join(lines) + "\n"

    def write(self, path) -> Path:
        """Write :meth:`text` atomically (``estcal.base.atomic``)."""
        return atomic_write_text(Path(path), self.text())


# ------------------------------------------------------------------ reading
def _entry_values(path, e: str, d) -> tuple:
    where = f"{path}: kinematics.{e}"
    if not isinstance(d, dict):
        raise RobotFileError(f"{where}: expected a mapping with keys {', '.join(KEYS)}, got {type(d).__name__}")
    extra = [k for k in d if k not in KEYS]
    if extra:
        raise RobotFileError(f"{where}: unknown key {extra[0]!r} (expected {', '.join(KEYS)})")
    out = []
    for k in KEYS:
        if k not in d:
            raise RobotFileError(f"{where}: missing key {k!r} (every entry has {', '.join(KEYS)})")
        v = d[k]
        try:
            if isinstance(v, bool):
                raise TypeError
            x = float(v)
        except (TypeError, ValueError):
            raise RobotFileError(f"{where}.{k}: expected a number ({'m' if k in 'xyz' else 'rad'}), got {v!r}") \
                from None
        if not math.isfinite(x):
            raise RobotFileError(f"{where}.{k}: {v!r} is not a finite number")
        if k in "xyz" and abs(x) > 5.0:
            raise RobotFileError(f"{where}.{k}: {x:g} m is not a UR link length (millimetres? the file is in m)")
        if k not in "xyz" and abs(x) > 2 * math.pi:
            raise RobotFileError(f"{where}.{k}: {x:g} rad is beyond ±2π (degrees? the file is in rad)")
        out.append(x)
    return tuple(out)


def read_ur_kinematics(path) -> UrKinematics:
    """Read and check a UR kinematics file: ``kinematics`` with the six entries (each ``x y z roll pitch
    yaw``, numbers) and ``hash``. Every error is one :class:`RobotFileError` line naming the file and the
    key; a ``calib_estcal_`` hash that does not name the numbers (the file was edited) is warned."""
    from estcal.base.textinput import read_yaml

    path = Path(path)
    d = read_yaml(path, "UR kinematics", RobotFileError)
    if not isinstance(d, dict) or "kinematics" not in d:
        raise RobotFileError(f"{path}: no top-level 'kinematics' key — a UR kinematics file reads "
                             f"kinematics: {{shoulder, upper_arm, forearm, wrist_1, wrist_2, wrist_3, hash}}")
    extra = [k for k in d if k != "kinematics"]
    if extra:
        raise RobotFileError(f"{path}: unknown top-level key {extra[0]!r} (a UR kinematics file has only "
                             f"'kinematics')")
    kin = d["kinematics"]
    if not isinstance(kin, dict):
        raise RobotFileError(f"{path}: kinematics: expected a mapping of {', '.join(ENTRIES)} and hash")
    extra = [k for k in kin if k not in ENTRIES + ("hash",)]
    if extra:
        raise RobotFileError(f"{path}: kinematics: unknown key {extra[0]!r} (expected {', '.join(ENTRIES)}, hash)")
    for e in ENTRIES + ("hash",):
        if e not in kin:
            raise RobotFileError(f"{path}: kinematics: missing key {e!r} (a UR kinematics file has "
                                 f"{', '.join(ENTRIES)} and hash)")
    if not isinstance(kin["hash"], (str, int)) or isinstance(kin["hash"], bool) or str(kin["hash"]).strip() == "":
        raise RobotFileError(f"{path}: kinematics.hash: expected a name such as calib_…, got {kin['hash']!r}")
    out = UrKinematics({e: _entry_values(path, e, kin[e]) for e in ENTRIES}, str(kin["hash"]), path)
    if out.hash.startswith(HASH_PREFIX) and out.hash != ur_hash(out.entries):
        warnings.warn(f"{path}: kinematics.hash {out.hash} does not name the numbers of the file (they hash to "
                      f"{ur_hash(out.entries)}): changed after estcal wrote it?", EstcalWarning, stacklevel=2)
    return out


def ur_prefix(joint_names, where) -> str:
    """The prefix ``p`` (``tf_prefix``) such that ``p + shoulder_pan_joint`` … ``p + wrist_3_joint`` are
    all in ``joint_names``; an error naming ``where`` when there is no such arm or several."""
    names = set(joint_names)
    tail = UR_JOINTS["shoulder"]
    found = sorted(n[:-len(tail)] for n in names if n.endswith(tail)
                   and all(n[:-len(tail)] + j in names for j in UR_JOINTS.values()))
    if len(found) != 1:
        what = "no" if not found else f"{len(found)} ({', '.join(repr(p) for p in found)})"
        raise RobotFileError(f"{where}: {what} UR arms (joints shoulder_pan_joint, shoulder_lift_joint, elbow_joint, "
                             f"wrist_1_joint … wrist_3_joint with one common prefix)"
                             + ("; give --tip to choose one" if found else ""))
    return found[0]


def _tilt(A: np.ndarray, B: np.ndarray) -> float:
    """Angle between the z axes (the joint axes) of two origins."""
    c = float(np.clip(np.dot(A[:3, 2], B[:3, 2]), -1.0, 1.0))
    return math.acos(c)


def apply_to_tree(tree, kin: UrKinematics, urdf_path, joints=None):
    """Put the file's origins on the six UR joints of ``tree`` (a :class:`~estcal.kinematics.urdf.UrdfTree`,
    changed in place and returned), checking that the file belongs to this robot: an origin more than
    :data:`MAX_SHIFT_M` or an axis more than :data:`MAX_TILT_RAD` from the URDF's is refused, naming the key.
    ``joints``: the joint names to look for the arm in (default: all of the tree's)."""
    jmap = {j.name: j for j in tree.robot.joints}
    prefix = ur_prefix(joints if joints is not None else list(jmap), urdf_path)
    for e in ENTRIES:
        j = jmap[prefix + UR_JOINTS[e]]
        if j.type not in ("revolute", "continuous"):
            raise RobotFileError(f"{urdf_path}: joint {j.name!r} is {j.type}, a UR arm's is revolute")
        old, new = joint_origin(j), kin.origin(e)
        shift = new[:3, 3] - old[:3, 3]
        k = int(np.argmax(np.abs(shift)))
        if abs(shift[k]) > MAX_SHIFT_M:
            raise RobotFileError(
                f"{kin.path}: kinematics.{e}.{KEYS[k]} {new[k, 3]:.6g} m is {abs(shift[k]) * 1e3:.1f} mm from "
                f"{urdf_path}'s {j.name} origin ({old[k, 3]:.6g} m) — a kinematics file of another robot? (a "
                f"calibration moves an origin by less than {MAX_SHIFT_M * 1e3:g} mm; give the URDF of its robot)")
        tilt = _tilt(old, new)
        if tilt > MAX_TILT_RAD:
            raise RobotFileError(
                f"{kin.path}: kinematics.{e}: roll/pitch/yaw tilt the joint axis by {tilt:.3g} rad from "
                f"{urdf_path}'s {j.name} — a kinematics file of another robot? (limit {MAX_TILT_RAD:g} rad)")
        j.origin, j.xyz_rpy = new, tuple(kin.entries[e])
    return tree


# ------------------------------------------------------------------ writing
def rpy_near(R: np.ndarray, near) -> np.ndarray:
    """The roll-pitch-yaw of rotation ``R`` nearest the triple ``near``: of the two solutions
    (r, p, y) and (r + π, π − p, y + π), each angle moved by whole turns towards ``near``."""
    base = matrix_to_rpy(R)
    near = np.asarray(near, float)
    best, dist = base, np.inf
    other = np.array([base[0] + np.pi, np.pi - base[1], base[2] + np.pi])
    for c in (base, other):
        c = c + 2 * np.pi * np.round((near - c) / (2 * np.pi))
        d = float(np.abs(c - near).sum())
        if d < dist and np.abs(rpy_to_matrix(c) - R).max() < _SAME:
            best, dist = c, d
    return best


@dataclass
class UrOrigins:
    """The calibrated origins of a UR model in its description (:func:`ur_origins`).

    ``kinematics``: the file's content; ``changed``: ``{entry: (mm, mrad)}`` of the origins the calibration
    moved (translation and rotation from the nominal); ``joints``: ``{entry: joint name}``; ``root``,
    ``tip``: the model's chain; ``mount``: ``(link, T_root_link nominal, calibrated)`` where the arm is
    mounted (``base_link``), ``end``: ``(link, T_wrist3_tip nominal, calibrated)``; ``others``: the model's
    other joints (not the arm's six) whose origins the calibration moved — a UR kinematics file has no place
    for them."""

    kinematics: UrKinematics
    changed: dict
    joints: dict
    root: str
    tip: str
    mount: tuple
    end: tuple
    others: list


def _origin_entry(new: np.ndarray, j, e: str) -> tuple:
    """``(numbers, (mm, mrad) or None)``: the nominal numbers when ``new`` is the nominal origin."""
    old = joint_origin(j)
    nominal = tuple(j.xyz_rpy) if j.xyz_rpy is not None else (0.0,) * 6
    if np.allclose(new, old, atol=_SAME, rtol=0):
        return nominal, None
    shift = float(np.linalg.norm(new[:3, 3] - old[:3, 3]))
    if np.abs(new[:3, 3] - old[:3, 3]).max() > MAX_SHIFT_M or _tilt(old, new) > MAX_TILT_RAD:
        raise NumericalRefusal(f"the calibrated origin of {j.name} ({e}) is {shift * 1e3:.1f} mm / "
                               f"{_tilt(old, new):.3g} rad (axis tilt) from the nominal: beyond what a calibration "
                               f"moves a UR origin ({MAX_SHIFT_M * 1e3:g} mm, {MAX_TILT_RAD:g} rad) — the fit is not "
                               f"to be trusted (check the data, the level and the frames)")
    rpy = rpy_near(new[:3, :3], nominal[3:])
    dR = old[:3, :3].T @ new[:3, :3]
    angle = math.acos(float(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0)))
    return tuple(float(x) for x in new[:3, 3]) + tuple(float(x) for x in rpy), (shift * 1e3, angle * 1e3)


def ur_origins(robot: SerialRobot, tree, source, root: str | None = None, tip: str | None = None) -> UrOrigins:
    """The six calibrated origins of ``robot`` (a URDF-convention model of a UR arm, current parameter
    values) in its nominal description ``tree`` (read from ``source``; ``root``/``tip``: the model's
    chain in it, guessed when None), with the nominal numbers kept where the calibration changed nothing
    (module docstring). Raises ``ValueError`` when the model is not this description's chain, and
    :class:`NumericalRefusal` when an origin moved beyond :data:`MAX_SHIFT_M` / :data:`MAX_TILT_RAD`."""
    from .urdf_export import _guess_chain, chain_origins, link_transform_parts

    if not all(f"tx_{lk.label}" in robot.params.names for lk in robot.links[1:-1]):
        raise RobotFileError(f"{robot.name}: a UR kinematics file needs a model whose frames are the URDF's joints "
                             f"(convention urdf: --robot the UR description's URDF, or a model calibrated from it)")
    prefix = ur_prefix(robot.joint_names, f"the model {robot.name!r}")
    if root is None or tip is None:
        try:
            root, tip = _guess_chain(tree.robot, robot, root, tip)
        except ValueError as exc:
            raise RobotFileError(f"{source}: {exc}") from None
    chain = chain_joints(tree, root, tip, source)
    theta = robot.params.values
    entry_of = {prefix + j: e for e, j in UR_JOINTS.items()}
    by_entry, changed, others = {}, {}, []
    for j, new in chain_origins(robot, theta, chain, source, root, tip):
        if j.name in entry_of:
            e = entry_of[j.name]
            by_entry[e], moved = _origin_entry(new, j, e)
            if moved is not None:
                changed[e] = moved
        elif not np.allclose(new, joint_origin(j), atol=_SAME, rtol=0):
            others.append(j.name)
    entries = {e: by_entry[e] for e in ENTRIES}
    base_T, _ = link_transform_parts(robot, 0, theta)
    tool_T, _ = link_transform_parts(robot, len(robot.links) - 1, theta)
    return UrOrigins(UrKinematics(entries, ur_hash(entries)), changed, {e: prefix + j for e, j in UR_JOINTS.items()},
                     root, tip, _mount(chain, prefix, root, base_T), (tip, robot.links[-1].const, tool_T), others)


def _mount(chain, prefix: str, root: str, base_T: np.ndarray) -> tuple:
    """``(link, T_root_link nominal, calibrated)``: the link the arm is mounted by (``base_link``, else the
    shoulder joint's parent), from the root, without and with the model's base frame."""
    T, link = np.eye(4), root
    for j in chain:
        if j.type != "fixed":
            break
        T = T @ joint_origin(j)
        link = j.child
        if j.child == prefix + "base_link":
            break
    return link, T, base_T @ T
