"""URDF chains (parsed with yourdfpy) between a root link and a tip link.

Fixed joints are merged: those before the first actuated joint into its
origin, those after the last one into the constant part of the tool link, so
the tool parameters (``tool_tx`` …) describe an error of the tip frame. Every
actuated joint gets a 6-D placement error (``tx_J … rz_J``, FIGAROH's
"full_params") applied after its URDF origin, an offset and a gain.

Link inertials give the masses used for gravity torques: each actuated
joint's link carries the mass of every link rigidly attached to it (fixed
joints, and off-chain branches evaluated at their zero position).
"""
from __future__ import annotations

import contextlib
import difflib
import io
from pathlib import Path

import numpy as np

from estcal.base.errors import RobotFileError
from estcal.base.textinput import read_text

from .builder import MAX_LENGTH_M, MAX_LIMIT_RAD, build_robot
from .chain import SerialRobot

__all__ = ["robot_from_urdf", "load_urdf", "root_links", "joint_origin", "fixed_subtree"]


def load_urdf(path):
    """Parse a URDF file with yourdfpy (no meshes); the file is read and checked by
    :func:`estcal.base.textinput.read_text` first (folder, binary, encoding)."""
    import yourdfpy

    path = Path(path)
    text = read_text(path, "URDF", RobotFileError)
    _check_xml(text, path)
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
    _check_tree(urdf, path)
    return urdf


def _check_xml(text: str, path) -> None:
    """Strict XML parse with the position of the first error, and the elements a
    kinematic chain needs (a <robot> with named links; joints with name, type,
    parent and child)."""
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
    urdf = load_urdf(path)
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
