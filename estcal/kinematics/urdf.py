"""URDF chains between a root link and a tip link.

Fixed joints are merged: those before the first actuated joint into its
origin, those after the last one into the constant part of the tool link, so
the tool parameters (``tool_tx`` …) describe an error of the tip frame. Every
actuated joint gets a 6-D placement error (``tx_J … rz_J``, FIGAROH's
"full_params") applied after its URDF origin, an offset and a gain.

Link inertials give the masses used for gravity torques: each actuated
joint's link carries the mass of every link rigidly attached to it (fixed
joints, and off-chain branches evaluated at their zero position).

Reading: the kinematic part of a URDF (links and their inertials; joints with type, parent, child,
origin, axis, limit and mimic — the ROS URDF specification, wiki.ros.org/urdf/XML/joint) is read
here with the standard library's ElementTree, the parser that already checks the file
(:func:`_check_xml`). yourdfpy, the library that models the whole URDF, is kept for what needs the
whole document — writing a calibrated URDF (:mod:`.urdf_export`, :func:`load_urdf_document`) — and
as the independent reader the kinematic reader is tested against (``tests/test_urdf_reader.py``:
every URDF of the shared data and the test suite, read both ways, equal to the bit). Why not
yourdfpy for reading as well: it imports trimesh (and with it networkx, scipy.spatial and
scipy.ndimage) at module level and uses trimesh names in its annotations, ~0.3 s of CPU at every
command that reads a URDF (``estcal diagnose`` of a TIAGo session: docs/benchmarks.md, "Everyday
commands"), for meshes and scene graphs a kinematic chain never uses. The origin matrix is composed
as yourdfpy composes it (``trimesh.transformations.compose_matrix``: translation, then the static
``sxyz`` Euler rotation of ``rpy``), so both readers give the same bits.
"""
from __future__ import annotations

import contextlib
import difflib
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import RobotFileError
from estcal.base.textinput import read_text

from .builder import MAX_LENGTH_M, MAX_LIMIT_RAD, build_robot
from .chain import SerialRobot

__all__ = ["robot_from_urdf", "robot_from_tree", "load_urdf", "load_urdf_document", "root_links", "joint_origin", "fixed_subtree",
           "origin_matrix", "chain_joints", "UrdfTree", "UrdfRobot", "UrdfJoint", "UrdfLink"]


# ------------------------------------------------------------------ the kinematic part of a URDF
@dataclass
class UrdfLimit:
    """``<limit>``: lower / upper (rad or m), effort, velocity; None where the file gives none."""

    lower: float | None = None
    upper: float | None = None
    effort: float | None = None
    velocity: float | None = None


@dataclass
class UrdfMimic:
    """``<mimic joint multiplier offset>``: q = multiplier · q_joint + offset."""

    joint: str | None
    multiplier: float = 1.0
    offset: float = 0.0


@dataclass
class UrdfInertial:
    """``<inertial>``: mass (kg; None without ``<mass>``) and origin (4×4; None without ``<origin>``)."""

    mass: float | None = None
    origin: np.ndarray | None = None


@dataclass
class UrdfLink:
    name: str
    inertial: UrdfInertial | None = None


@dataclass
class UrdfJoint:
    """``<joint>``: origin (4×4 parent link → joint frame; None without ``<origin>``), axis (3,) (default
    ``1 0 0``, as the specification), limit and mimic (None when absent); ``xyz_rpy``: the six numbers
    of ``<origin xyz rpy>`` as written (None without ``<origin>``), for writers that keep them."""

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray | None = None
    axis: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    limit: UrdfLimit | None = None
    mimic: UrdfMimic | None = None
    xyz_rpy: tuple | None = None


@dataclass
class UrdfRobot:
    name: str
    links: list
    joints: list


@dataclass
class UrdfTree:
    """A URDF's kinematic part; ``.robot`` has the shape of yourdfpy's ``URDF.robot`` (links, joints)."""

    robot: UrdfRobot


def _numbers(text, n, path, where, what) -> list:
    """``n`` finite numbers from an attribute (``None``: not given)."""
    parts = str(text).split()
    try:
        vals = [float(x) for x in parts]
    except ValueError:
        vals = None
    if vals is None or (n is not None and len(vals) != n):
        count = f"{n} numbers" if n is not None else "numbers"
        raise RobotFileError(f"{path}: {where}: {what} needs {count}, got {text!r}")
    if not all(math.isfinite(v) for v in vals):
        raise RobotFileError(f"{path}: {where}: {what} holds a non-finite number ({text!r})")
    return vals


def _number(el, attr, path, where, default=None):
    value = el.get(attr)
    if value is None:
        return default
    return _numbers(value, 1, path, where, f"<{el.tag} {attr}>")[0]


def _euler_sxyz(ai: float, aj: float, ak: float) -> np.ndarray:
    """Rotation of static-frame x-y-z Euler angles (URDF ``rpy``), homogeneous 4×4: the operations and
    their order of ``trimesh.transformations.euler_matrix(ai, aj, ak, "sxyz")`` (Gohlke's
    transformations.py), so that the origin matrices are the same bits as yourdfpy's."""
    ai, aj, ak = np.float64(ai), np.float64(aj), np.float64(ak)  # numpy's sin / cos, as there
    si, sj, sk = np.sin(ai), np.sin(aj), np.sin(ak)
    ci, cj, ck = np.cos(ai), np.cos(aj), np.cos(ak)
    cc, cs = ci * ck, ci * sk
    sc, ss = si * ck, si * sk
    M = np.eye(4)
    M[0, 0] = cj * ck
    M[0, 1] = sj * sc - cs
    M[0, 2] = sj * cc + ss
    M[1, 0] = cj * sk
    M[1, 1] = sj * ss + cc
    M[1, 2] = sj * cs - sc
    M[2, 0] = -sj
    M[2, 1] = cj * si
    M[2, 2] = cj * ci
    return M


def origin_matrix(xyz, rpy) -> np.ndarray:
    """A URDF ``<origin xyz rpy>`` as 4×4, composed as yourdfpy composes it
    (``compose_matrix(translate=xyz, angles=rpy)``: T · R, then / M[3, 3]): the same bits for the same numbers."""
    T = np.identity(4)
    T[:3, 3] = xyz
    M = np.dot(np.dot(np.identity(4), T), _euler_sxyz(*rpy))
    M /= M[3, 3]
    return M


def _origin_numbers(el, path, where):
    """``xyz + rpy`` (six floats) of an ``<origin>`` element, None without one."""
    if el is None:
        return None
    return tuple(_numbers(el.get("xyz", "0 0 0"), 3, path, where, "<origin xyz>")
                 + _numbers(el.get("rpy", "0 0 0"), 3, path, where, "<origin rpy>"))


def _origin(el, path, where):
    """``<origin xyz rpy>`` as 4×4 (:func:`origin_matrix`)."""
    nums = _origin_numbers(el, path, where)
    return None if nums is None else origin_matrix(nums[:3], nums[3:])


def _read_tree(root, path) -> UrdfTree:
    """The links and joints of a checked ``<robot>`` element (:func:`_check_xml`)."""
    links = []
    for lk in root.findall("link"):
        name = lk.get("name")
        inertial = None
        el = lk.find("inertial")
        if el is not None:
            where = f"link {name!r}"
            mass = el.find("mass")
            inertial = UrdfInertial(None if mass is None else _number(mass, "value", path, where, 0.0),
                                    _origin(el.find("origin"), path, where))
        links.append(UrdfLink(name, inertial))
    joints = []
    for j in root.findall("joint"):
        name = j.get("name")
        where = f"joint {name!r}"
        ax = j.find("axis")
        axis = np.array(_numbers(ax.get("xyz", "1 0 0"), None, path, where, "<axis xyz>") if ax is not None
                        else [1.0, 0, 0])
        lim = j.find("limit")
        limit = None if lim is None else UrdfLimit(*(_number(lim, a, path, where)
                                                     for a in ("lower", "upper", "effort", "velocity")))
        mim = j.find("mimic")
        mimic = None if mim is None else UrdfMimic(mim.get("joint"), _number(mim, "multiplier", path, where, 1.0),
                                                   _number(mim, "offset", path, where, 0.0))
        nums = _origin_numbers(j.find("origin"), path, where)
        joints.append(UrdfJoint(name, j.get("type"), j.find("parent").get("link"), j.find("child").get("link"),
                                None if nums is None else origin_matrix(nums[:3], nums[3:]), axis, limit, mimic,
                                nums))
    return UrdfTree(UrdfRobot(root.get("name", ""), links, joints))


def load_urdf(path) -> UrdfTree:
    """The kinematic part of a URDF file (module docstring), checked: XML, the elements a chain needs,
    numbers, a tree over declared links. The file is read by :func:`estcal.base.textinput.read_text`
    first (folder, binary, encoding)."""
    path = Path(path)
    text = read_text(path, "URDF", RobotFileError)
    tree = _read_tree(_check_xml(text, path), path)
    _check_tree(tree, path)
    return tree


def load_urdf_document(path):
    """The whole URDF as yourdfpy's object model (no meshes), for writing a changed copy
    (:mod:`.urdf_export`); checked as :func:`load_urdf`."""
    import yourdfpy

    path = Path(path)
    text = read_text(path, "URDF", RobotFileError)
    _check_tree(_read_tree(_check_xml(text, path), path), path)
    try:
        # yourdfpy prints its parser's complaints and retries; the checks above already
        # named the problems users make, so its chatter is kept off the terminal
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            urdf = yourdfpy.URDF.load(io.BytesIO(text.encode("utf-8")), build_scene_graph=False,
                                      build_collision_scene_graph=False, load_meshes=False,
                                      load_collision_meshes=False)
    except Exception as exc:  # yourdfpy / lxml raise many error types on bad XML  # noqa: BLE001
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise RobotFileError(f"{path}: cannot parse URDF ({msg})") from None
    return urdf


def _check_xml(text: str, path):
    """Strict XML parse with the position of the first error, and the elements a
    kinematic chain needs (a <robot> with named links; joints with name, type,
    parent and child); returns the ``<robot>`` element."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(text.encode("utf-8"))
    except ET.ParseError as exc:
        line, col = exc.position
        msg = str(exc).split(":")[0]
        raise RobotFileError(f"{path}, line {line}, column {col + 1}: not valid XML ({msg})") from None
    if root.tag != "robot":
        raise RobotFileError(f"{path}: the top element is <{root.tag}>, a URDF's is <robot>")
    for i, lk in enumerate(root.findall("link")):
        if not lk.get("name"):
            raise RobotFileError(f"{path}: <link> number {i + 1} has no name attribute")
    for i, j in enumerate(root.findall("joint")):
        name = j.get("name")
        where = f"joint {name!r}" if name else f"<joint> number {i + 1}"
        if not name:
            raise RobotFileError(f"{path}: {where} has no name attribute")
        if not j.get("type"):
            raise RobotFileError(f"{path}: {where} has no type attribute (revolute, continuous, prismatic, fixed …)")
        for tag in ("parent", "child"):
            el = j.find(tag)
            if el is None or not el.get("link"):
                raise RobotFileError(f"{path}: {where} has no <{tag} link=\"…\"/>")
    return root


def _check_tree(urdf, path) -> None:
    """The joints must form a tree over the declared links: every joint names
    existing links, and no link has two parents (a chain would be silently
    re-routed through one of them)."""
    if urdf.robot is None or not urdf.robot.links:
        raise RobotFileError(f"{path}: the URDF has no <link>")
    links = {lk.name for lk in urdf.robot.links}
    parent_of: dict[str, str] = {}
    for j in urdf.robot.joints:
        for role, name in (("parent", j.parent), ("child", j.child)):
            if name not in links:
                raise RobotFileError(f"{path}: joint {j.name!r}: {role} link {name!r} is not declared as a <link>")
        if j.child in parent_of:
            raise RobotFileError(f"{path}: link {j.child!r} has two parent joints ({parent_of[j.child]!r} and "
                                 f"{j.name!r}) — a URDF must be a tree; remove one")
        parent_of[j.child] = j.name
        if j.origin is not None:
            t = np.abs(np.asarray(j.origin, float)[:3, 3]).max()
            if t > MAX_LENGTH_M:
                raise RobotFileError(f"{path}: joint {j.name!r}: <origin xyz> reaches {t:g} m, beyond {MAX_LENGTH_M:g} m "
                                     f"— URDF lengths are metres (is the file in millimetres?)")
    # a closed loop (A → B → … → A) gives every link one parent: follow the parents from each link
    parent_link = {j.child: j.parent for j in urdf.robot.joints}
    done: set = set()
    for start in parent_link:
        seen, cur = [], start
        while cur in parent_link and cur not in done:
            if cur in seen:
                loop = seen[seen.index(cur):]
                raise RobotFileError(f"{path}: the joints form a closed loop through links {' → '.join(loop + [cur])}"
                                     f" — a URDF must be a tree (estcal models serial chains; parallel robots: "
                                     f"docs/parallel.md)")
            seen.append(cur)
            cur = parent_link[cur]
        done.update(seen)


def root_links(urdf) -> list[str]:
    """Links that are no joint's child (a valid URDF has exactly one)."""
    children = {j.child for j in urdf.robot.joints}
    return sorted(lk.name for lk in urdf.robot.links if lk.name not in children)


def _chain(urdf, root: str, tip: str, path=""):
    parent_joint = {j.child: j for j in urdf.robot.joints}
    links = {lk.name for lk in urdf.robot.links}
    for name, what in ((root, "root"), (tip, "tip")):
        if name not in links:
            close = difflib.get_close_matches(str(name), sorted(links), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise RobotFileError(f"{path}: {what} link {name!r} is not in the URDF{hint}; links include "
                             f"{sorted(links)[:20]}{'…' if len(links) > 20 else ''}")
    joints, seen = [], set()
    cur = tip
    while cur != root:
        if cur not in parent_joint or cur in seen:
            raise RobotFileError(f"{path}: link {tip!r} is not below {root!r} in the URDF tree")
        seen.add(cur)
        j = parent_joint[cur]
        joints.append(j)
        cur = j.parent
    return joints[::-1]


def chain_joints(urdf, root: str, tip: str, path="") -> list:
    """The joints from link ``root`` down to link ``tip``, in chain order (an error naming the file when
    a link is missing or ``tip`` is not below ``root``)."""
    return _chain(urdf, root, tip, path)


def joint_origin(j) -> np.ndarray:
    """A URDF joint's origin, parent link → joint frame (4×4; identity when the file gives none)."""
    return np.eye(4) if j.origin is None else np.asarray(j.origin, float)


def fixed_subtree(joints, link: str) -> list[tuple[str, np.ndarray]]:
    """``[(link name, T_link_name)]`` of ``link`` and every link hanging from it through fixed joints
    only, depth first with children in name order (``link`` first, with the identity)."""
    children: dict[str, list] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    out, stack = [], [(link, np.eye(4))]
    while stack:
        name, T = stack.pop()
        out.append((name, T))
        for j in sorted(children.get(name, []), key=lambda j: j.child, reverse=True):
            if j.type == "fixed":
                stack.append((j.child, T @ joint_origin(j)))
    return out


def _subtree_mass(urdf, link_name: str, exclude: set) -> tuple[float, np.ndarray]:
    """Mass and centre of mass (in ``link_name``'s frame) of the link and everything
    hanging from it except the chain joints in ``exclude`` (zero joint positions)."""
    children = {}
    for j in urdf.robot.joints:
        children.setdefault(j.parent, []).append(j)
    lmap = {lk.name: lk for lk in urdf.robot.links}
    total_m, moment = 0.0, np.zeros(3)
    stack = [(link_name, np.eye(4))]
    while stack:
        name, T = stack.pop()
        lk = lmap[name]
        if lk.inertial is not None and lk.inertial.mass is not None:
            m = float(lk.inertial.mass)
            c = (T @ (np.asarray(lk.inertial.origin, float) if lk.inertial.origin is not None else np.eye(4)))[:3, 3]
            total_m += m
            moment += m * c
        for j in children.get(name, []):
            if j.name in exclude:
                continue
            stack.append((j.child, T @ joint_origin(j)))
    com = moment / total_m if total_m > 0 else np.zeros(3)
    return total_m, com


def robot_from_urdf(path, root: str | None = None, tip: str | None = None, markers=None,
                    name: str | None = None) -> SerialRobot:
    """Build a :class:`SerialRobot` for the chain ``root`` → ``tip`` of a URDF.

    Parameters
    ----------
    path : URDF file.
    root : root link (default: the URDF's root link).
    tip : tip link (required unless the tree is a single chain).
    markers : (k, 3) points in the tip frame (metres), optional.
    """
    return robot_from_tree(load_urdf(path), path, root, tip, markers, name)


def robot_from_tree(urdf, path, root: str | None = None, tip: str | None = None, markers=None,
                    name: str | None = None) -> SerialRobot:
    """:func:`robot_from_urdf` of an already read URDF (``urdf.robot`` with links and joints: a
    :class:`UrdfTree`, or yourdfpy's ``URDF`` — the reader test builds the chain from both)."""
    if root is None:
        # yourdfpy's base_link is only set when it builds a scene graph (not done here)
        roots = root_links(urdf)
        if len(roots) != 1:
            raise RobotFileError(f"{path}: the URDF has {len(roots)} root links ({', '.join(roots[:10]) or 'none: a cycle'})"
                             f" — give --root")
        root = roots[0]
    if tip is None:
        leaves = sorted({lk.name for lk in urdf.robot.links} - {j.parent for j in urdf.robot.joints})
        if len(leaves) != 1:
            raise RobotFileError(f"{path}: give --tip; the URDF has {len(leaves)} leaf links "
                             f"({', '.join(leaves[:10])}{'…' if len(leaves) > 10 else ''})")
        tip = leaves[0]
    chain = _chain(urdf, root, tip, path)
    for j in chain:
        if j.type != "fixed" and getattr(j, "mimic", None) is not None:
            m = j.mimic
            raise RobotFileError(f"{path}: joint {j.name!r} on the chain {root!r} → {tip!r} is a <mimic> of "
                                 f"{m.joint!r} (q = {m.multiplier if m.multiplier is not None else 1:g}·q_{m.joint} + "
                                 f"{m.offset if m.offset is not None else 0:g}): estcal reads one column per actuated "
                                 f"joint and does not couple joints from a URDF — choose a tip above it (--tip), or "
                                 f"describe the chain in a robot file")
    # A link carries everything rigidly attached to it, including the fixed chain
    # links after the last actuated joint (tool flange, sensor, hand): only the next
    # actuated chain joint ends its subtree.
    actuated = {j.name for j in chain if j.type != "fixed"}
    frames, pending = [], np.eye(4)
    for j in chain:
        if j.type == "fixed":
            pending = pending @ joint_origin(j)
            continue
        if j.type not in ("revolute", "continuous", "prismatic"):
            raise RobotFileError(f"{path}: joint {j.name!r} has unsupported type {j.type!r}")
        if j.type == "continuous":
            lo, hi = -np.pi, np.pi
        elif j.limit is None or j.limit.lower is None or j.limit.upper is None:
            raise RobotFileError(f"{path}: joint {j.name!r} ({j.type}) has no <limit lower=… upper=…> — add its "
                             f"range ({'rad' if j.type == 'revolute' else 'm'})")
        else:
            lo, hi = float(j.limit.lower), float(j.limit.upper)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise RobotFileError(f"{path}: joint {j.name!r}: <limit> needs lower < upper, got [{lo:g}, {hi:g}]")
            if j.type == "revolute" and max(abs(lo), abs(hi)) > MAX_LIMIT_RAD:
                raise RobotFileError(f"{path}: joint {j.name!r}: <limit> [{lo:g}, {hi:g}] is beyond ±4π rad — URDF "
                                     f"angles are radians (degrees?)")
            if j.type == "prismatic" and max(abs(lo), abs(hi)) > MAX_LENGTH_M:
                raise RobotFileError(f"{path}: joint {j.name!r}: <limit> [{lo:g}, {hi:g}] is beyond {MAX_LENGTH_M:g} m "
                                     f"— URDF lengths are metres (millimetres?)")
        axis = np.asarray(j.axis if j.axis is not None else [1.0, 0.0, 0.0], float)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise RobotFileError(f"{path}: joint {j.name!r}: <axis xyz> must be a non-zero 3-vector, got {j.axis}")
        mass, com = _subtree_mass(urdf, j.child, actuated)
        frames.append({"name": j.name, "label": j.name, "convention": "urdf",
                       "type": "prismatic" if j.type == "prismatic" else "revolute",
                       "origin": pending @ joint_origin(j), "axis": axis,
                       "limits": [float(lo), float(hi)], "mass": mass, "com": com})
        pending = np.eye(4)
    if not frames:
        raise RobotFileError(f"{path}: no actuated joint between {root!r} and {tip!r}")
    robot = build_robot(name or f"{urdf.robot.name}:{root}->{tip}", frames, markers=markers,
                        convention="urdf", tool_const=pending,
                        meta={"urdf": str(Path(path).resolve()), "root": root, "tip": tip,
                              "continuous": [j.name for j in chain if j.type == "continuous"],
                              "urdf_joints": [j.name for j in urdf.robot.joints if j.type != "fixed"]})
    return robot
