"""Write a (calibrated) serial robot as a URDF, with yourdfpy's object model and writer.

A URDF joint moves its child link by ``origin · Rot(axis, q)`` (or
``origin · Trans(axis · q)``); an estcal link (:mod:`estcal.kinematics.chain`) is
``C · E_before(η) · J(q + offset + η_jvar) · E_after(η)``. Since
``Rot(a, offset + q) = Rot(a, offset) · Rot(a, q)``, every geometric parameter
and the joint offset fold exactly into the joint origin::

    origin_j = A_{j-1} · C_j · E_before,j · J(offset_j + η_jvar,j) · P_j

where ``P_j`` is the longest prefix of ``E_after,j`` that commutes with the
joint motion (translations along / rotations about the joint axis; for a
prismatic joint every translation) and ``A_{j-1}`` the rest of the previous
link's ``E_after``. For a Khalil–Kleinfinger frame (GECARO eq. 3) the whole
``Trans(z, r)`` commutes, so each URDF link frame *is* Khalil frame j and its
origin is ``ʲ⁻¹T_j`` at q = 0 with the joint axis along z; for standard DH
``Trans(z, d)`` commutes and ``Trans(x, a) Rot(x, α)`` moves to the next origin.

What a URDF cannot hold is reported, never dropped silently: joint gains ≠ 1
(the URDF joint position would have to be ``gain · reading``), coupling
matrices, non-geometric effects and markers (unknown points in the tool frame).

Two modes (docs/export.md):

* **standalone** (any convention): links ``world`` → ``base`` → ``frame_<label>``
  … → ``flange`` → ``tool``; the base and tool frames are the fixed joints
  ``base_joint`` and ``tool_joint``; actuated joints keep the robot's joint
  names, so a dataset's columns drive the URDF unchanged.
* **from an original URDF** (models loaded from a URDF, convention ``urdf``):
  the original is parsed with yourdfpy, only the origins of the calibrated
  chain joints change (``origin_J = F⁻¹ · C_J · E(tx…rz) · J(offset)`` with ``F``
  the original fixed joints merged into ``C_J`` by the loader), and every link,
  visual, collision, inertial, material and joint element is kept. Elements
  yourdfpy does not model (``<transmission>``, ``<gazebo>``, unknown link
  children) are copied from the original XML tree; a non-identity base / tool
  frame adds a ``world`` parent of the root / a ``tool`` child of the tip.
"""
from __future__ import annotations

import copy
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.atomic import atomic_write_bytes

from .chain import SerialRobot
from .transforms import make_transform, rot_axis
from .urdf import fixed_subtree, joint_origin, load_urdf_document

__all__ = ["export_urdf", "UrdfExport", "link_transform_parts", "unexpressible", "chain_origins"]

_TOL = 1e-9  # metres / radians: a model must match the original URDF's fixed structure to this


@dataclass
class UrdfExport:
    """What :func:`export_urdf` wrote: the file, the root and tip links that reproduce the
    model's tool frame (``estcal fk --robot PATH --root ROOT --tip TIP``), the joints whose
    origins carry the calibration, and every warning (what the URDF cannot hold)."""

    path: Path
    root: str
    tip: str
    changed: list = field(default_factory=list)
    warnings: list = field(default_factory=list)


# ------------------------------------------------------------------ transforms
def _elem_T(e, value: float) -> np.ndarray:
    T = np.eye(4)
    ax = "xyz".index(e.axis)
    if e.kind == "R":
        T[:3, :3] = rot_axis(np.eye(3)[ax], value)
    else:
        T[ax, 3] = value
    return T


def _elems_T(elems, theta) -> np.ndarray:
    T = np.eye(4)
    for e in elems:
        T = T @ _elem_T(e, float(theta[e.param]))
    return T


def _joint_T(kind: str, axis, value: float) -> np.ndarray:
    T = np.eye(4)
    if kind == "R":
        T[:3, :3] = rot_axis(axis, value)
    else:
        T[:3, 3] = np.asarray(axis, float) * value
    return T


def _commuting_prefix(link) -> int:
    """Number of leading ``after`` motions that commute with the joint motion (exactly)."""
    ax = np.asarray(link.joint_axis, float)
    unit = [c for c in range(3) if ax[c] == 1.0 and np.count_nonzero(ax) == 1]
    k = 0
    for e in link.after:
        same = bool(unit) and "xyz".index(e.axis) == unit[0]
        if same or (link.joint_kind == "P" and e.kind == "P"):
            k += 1
        else:
            break
    return k


def link_transform_parts(robot: SerialRobot, li: int, theta=None):
    """``(head, tail)`` of link ``li`` at zero joint *position*: the link is
    ``head · J(position) · tail`` with the offset, the joint's own parameter and the
    commuting part of ``after`` folded into ``head`` (see the module docstring)."""
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    link = robot.links[li]
    head = np.asarray(link.const, float) @ _elems_T(link.before, theta)
    if link.joint is None:
        return head @ _elems_T(link.after, theta), np.eye(4)
    j = link.joint
    v = float(theta[robot.offset_idx[j]]) + (float(theta[link.joint_param]) if link.joint_param >= 0 else 0.0)
    head = head @ _joint_T(link.joint_kind, link.joint_axis, v)
    k = _commuting_prefix(link)
    return head @ _elems_T(link.after[:k], theta), _elems_T(link.after[k:], theta)


# ------------------------------------------------------------------ warnings
def unexpressible(robot: SerialRobot, target: str = "a URDF") -> list[str]:
    """One line for each part of ``robot`` that ``target`` (a URDF, a UR kinematics file: joint origins only)
    cannot hold: gains ≠ 1, coupling, effects, gravity other than −z with masses, markers."""
    out = []
    vals = robot.params.values
    gains = {robot.joint_names[j]: float(vals[robot.gain_idx[j]]) for j in range(robot.n_joints)}
    bad = {n: g for n, g in gains.items() if g != 1.0}
    if bad:
        out.append(f"joint gains cannot be expressed in {target} (its joint position would have to be "
                   "gain · reading): " + ", ".join(f"{n} (gain {g:.9g})" for n, g in bad.items())
                   + "; the offsets are folded into the origins"
                   + (", the gains are written as comments" if target == "a URDF" else ", the gains are not written"))
    if robot.coupling is not None:
        out.append(f"the joint coupling matrices (Cj, Cm) cannot be expressed in {target}: its joint "
                   "positions are the coupled joint values, not the readings")
    for eff in robot.effects:
        d = eff.to_dict() if hasattr(eff, "to_dict") else {}
        name = d.get("effect", type(eff).__name__)
        joints = d.get("joints")
        out.append(f"effect {name!r}" + (f" on {', '.join(map(str, joints))}" if joints else "")
                   + f" cannot be expressed in {target} (not written; parameters "
                   + ", ".join(eff.param_names) + ")")
    has_mass = robot.payload_mass > 0 or any(lk.mass for lk in robot.links)
    if has_mass and not np.array_equal(robot.gravity, [0.0, 0.0, -9.81]):
        out.append(f"gravity {robot.gravity.tolist()} m/s² (world frame) cannot be written: URDF tools assume "
                   f"[0, 0, -9.81] in the root frame; set it where the URDF is used")
    if robot.n_markers:
        names = [f"marker{k + 1}" for k in range(robot.n_markers)]
        out.append(f"markers {', '.join(names)} (unknown points in the tool frame) are not part of {target} "
                   f"(not written; they stay in the robot file)")
    return out


def _provenance(robot: SerialRobot, source) -> list[str]:
    lines = [f"written by estcal export from {source or robot.name!r} (robot {robot.name!r}, "
             f"convention {robot.convention}); see docs/export.md"]
    cal = robot.meta.get("calibration") or {}
    if cal:
        items = [f"{k}: {v}" for k, v in cal.items() if k not in ("free", "covariance") and
                 isinstance(v, (str, int, float, bool))]
        if cal.get("free") is not None:
            items.append(f"{len(cal['free'])} free parameters with their covariance (in the robot file)")
        lines.append("calibration: " + "; ".join(items) if items else "calibration: (no provenance given)")
        for d in cal.get("data") or []:  # data files of a saved model (docs/robot-file.md, "Saved models")
            if isinstance(d, dict):
                sha = d.get("sha256")
                lines.append(f"calibration data ({d.get('role', 'data')}): {d.get('file')}"
                             + (f", {d['n_poses']} poses" if d.get("n_poses") is not None else "")
                             + (f", sha256 {sha}" if sha else ""))
    return lines


# ------------------------------------------------------------------ writing
def _write(urdf, path: Path, header: list[str], joint_notes: dict, extra=None) -> None:
    import yourdfpy
    from lxml import etree

    # Mesh file names are written as given (package://…), not resolved on this machine.
    urdf._filename_handler = yourdfpy.filename_handler_null
    tree = urdf.write_xml()
    root = tree.getroot()
    jmap = {el.get("name"): el for el in root.findall("joint")}
    for name, lines in joint_notes.items():
        for note in lines:
            jmap[name].insert(0, etree.Comment(f" {note} "))
    if extra is not None:
        extra(root)
    for i, line in enumerate(header):
        root.insert(i, etree.Comment(f" {line.replace('--', '- -')} "))
    atomic_write_bytes(path, etree.tostring(tree, xml_declaration=True, encoding="utf-8", pretty_print=True))


def _unique(name: str, taken: set) -> str:
    out = name
    while out in taken:
        out = "estcal_" + out
    taken.add(out)
    return out


def _standalone(robot: SerialRobot, theta) -> tuple:
    from yourdfpy import Inertial, Joint, Limit, Link, Robot

    links = robot.links
    taken_j = set(robot.joint_names)
    taken_l: set = set()
    ln = {"world": _unique("world", taken_l), "base": _unique("base", taken_l)}
    frame_names = [_unique(f"frame_{lk.label}", taken_l) for lk in links[1:-1]]
    ln["flange"], ln["tool"] = _unique("flange", taken_l), _unique("tool", taken_l)
    out_links = [Link(name=ln["world"]), Link(name=ln["base"])]
    joints = [Joint(name=_unique("base_joint", taken_j), type="fixed", parent=ln["world"], child=ln["base"],
                    origin=np.asarray(links[0].const, float) @ _elems_T(links[0].before, theta))]
    notes: dict = {}
    parent, pending = ln["base"], np.eye(4)
    vals = theta
    for li, (lk, child) in enumerate(zip(links[1:-1], frame_names), start=1):
        head, tail = link_transform_parts(robot, li, theta)
        origin = pending @ head
        if lk.joint is None:
            jname = _unique(f"frame{lk.label}_joint", taken_j)
            joints.append(Joint(name=jname, type="fixed", parent=parent, child=child, origin=origin))
        else:
            j = lk.joint
            jname = robot.joint_names[j]
            lo, hi = (float(x) for x in robot.limits[j])
            joints.append(Joint(name=jname, type=robot.joint_types[j], parent=parent, child=child, origin=origin,
                                axis=np.asarray(lk.joint_axis, float).copy(),
                                limit=Limit(effort=0.0, velocity=0.0, lower=lo, upper=hi)))
            unit = "rad" if robot.joint_types[j] == "revolute" else "m"
            off, gain = float(vals[robot.offset_idx[j]]), float(vals[robot.gain_idx[j]])
            notes[jname] = [f"estcal: offset {off!r} {unit} folded into the origin; gain {gain!r}"
                            + ("" if gain == 1.0 else " NOT expressible: position = gain * reading")]
        inertial = None
        if lk.mass:
            # estcal's centre of mass is in the frame at the link's end, i.e. after ``tail``
            c = tail @ np.append(np.asarray(lk.com, float), 1.0)
            inertial = Inertial(origin=make_transform(np.eye(3), c[:3]), mass=float(lk.mass),
                                inertia=np.zeros((3, 3)))
        out_links.append(Link(name=child, inertial=inertial))
        parent, pending = child, tail
    tool = links[-1]
    joints.append(Joint(name=_unique("flange_joint", taken_j), type="fixed", parent=parent, child=ln["flange"],
                        origin=pending @ np.asarray(tool.const, float)))
    joints.append(Joint(name=_unique("tool_joint", taken_j), type="fixed", parent=ln["flange"], child=ln["tool"],
                        origin=_elems_T(tool.before, theta)))
    tool_inertial = None
    if robot.payload_mass:
        tool_inertial = Inertial(origin=make_transform(np.eye(3), robot.payload_com), mass=robot.payload_mass,
                                 inertia=np.zeros((3, 3)))
    out_links += [Link(name=ln["flange"]), Link(name=ln["tool"], inertial=tool_inertial)]
    return Robot(name=robot.name, links=out_links, joints=joints), ln["world"], ln["tool"], notes


# ------------------------------------------------------------------ from a URDF
def _path_joints(urdf_robot, root: str, tip: str):
    parent_joint = {j.child: j for j in urdf_robot.joints}
    out, cur = [], tip
    while cur != root:
        if cur not in parent_joint:
            raise ValueError(f"link {tip!r} is not below {root!r} in the original URDF")
        out.append(parent_joint[cur])
        cur = parent_joint[cur].parent
    return out[::-1]


def _guess_chain(urdf_robot, robot: SerialRobot, root, tip):
    """Root and tip of the model's chain in the original URDF (the loader merged the
    fixed joints around them, so the tip is the fixed descendant matching ``tool_origin``)."""
    jmap = {j.name: j for j in urdf_robot.joints}
    missing = [n for n in robot.joint_names if n not in jmap]
    if missing:
        raise ValueError(f"joints {missing} of the model are not in the original URDF "
                         f"(was the model loaded from this URDF?)")
    if root is None:
        children = {j.child for j in urdf_robot.joints}
        roots = [lk.name for lk in urdf_robot.links if lk.name not in children]
        root = roots[0]
    if tip is None:
        last = jmap[robot.joint_names[-1]]
        want = np.asarray(robot.links[-1].const, float)
        found = [name for name, T in fixed_subtree(urdf_robot.joints, last.child)
                 if np.allclose(T, want, atol=_TOL, rtol=0)]
        if len(found) != 1:
            raise ValueError(f"cannot tell the tip link of the model in the original URDF "
                             f"(candidates {found or 'none'}); give --tip LINK")
        tip = found[0]
    return root, tip


def chain_origins(robot: SerialRobot, theta, chain, source, root: str, tip: str) -> list:
    """``[(joint, origin')]`` for each actuated joint of ``chain`` (a description's joints from ``root`` to
    ``tip``, e.g. :func:`estcal.kinematics.urdf.chain_joints`): the calibrated origin
    ``F_J⁻¹ · C_J · E(tx…rz) · J(offset)`` in the joint's parent link, ``F_J`` the fixed joints the loader
    merged into ``C_J``. The model must be this chain: same actuated joints, axes, nominal origins and
    fixed joints after the last one (``tool_origin``) to 1e-9, else a ``ValueError`` naming ``source``."""
    actuated = [j.name for j in chain if j.type != "fixed"]
    if actuated != list(robot.joint_names):
        raise ValueError(f"the chain {root} -> {tip} of {source} has joints {actuated}, the model "
                         f"{list(robot.joint_names)}")
    li_of = {lk.joint: i for i, lk in enumerate(robot.links) if lk.joint is not None}
    out, fixed_before = [], np.eye(4)
    for j in chain:
        if j.type == "fixed":
            fixed_before = fixed_before @ joint_origin(j)
            continue
        link = robot.links[li_of[robot.joint_names.index(j.name)]]
        ax = np.asarray(j.axis, float)
        if not np.allclose(ax / np.linalg.norm(ax), link.joint_axis, atol=_TOL):
            raise ValueError(f"joint {j.name!r}: axis {ax.tolist()} in {source}, {link.joint_axis.tolist()} "
                             f"in the model")
        if not np.allclose(fixed_before @ joint_origin(j), link.const, atol=_TOL, rtol=0):
            raise ValueError(f"joint {j.name!r}: the model's nominal origin differs from {source}'s "
                             f"(was the model loaded from this URDF with --root {root} --tip {tip}?)")
        head, _ = link_transform_parts(robot, li_of[robot.joint_names.index(j.name)], theta)
        out.append((j, np.linalg.solve(fixed_before, head)))
        fixed_before = np.eye(4)
    if not np.allclose(fixed_before, robot.links[-1].const, atol=_TOL, rtol=0):
        raise ValueError(f"the fixed joints after {robot.joint_names[-1]!r} up to {tip!r} differ from the "
                         f"model's tool_origin; give --tip LINK")
    return out


def _from_urdf(robot: SerialRobot, theta, original: Path, root, tip):
    if not all(f"tx_{lk.label}" in robot.params.names for lk in robot.links[1:-1]):
        raise ValueError("--from-urdf needs a model whose every frame is a URDF joint (convention urdf); "
                         "export Khalil/DH models without --from-urdf")
    urdf = load_urdf_document(original)
    ur = urdf.robot
    root, tip = _guess_chain(ur, robot, root, tip)
    changed = []
    for j, new in chain_origins(robot, theta, _path_joints(ur, root, tip), original, root, tip):
        if not np.allclose(new, joint_origin(j), atol=1e-12, rtol=0):  # else keep the original, bit for bit
            j.origin = new
            changed.append(j.name)
    return urdf, root, tip, changed


def _add_frames(urdf, robot, theta, root, tip, warn_list):
    """A non-identity base / tool frame becomes a new parent of the root / child of the tip."""
    from yourdfpy import Joint, Link

    ur = urdf.robot
    links = {lk.name for lk in ur.links}
    jnames = {j.name for j in ur.joints}
    Tb = np.asarray(robot.links[0].const, float) @ _elems_T(robot.links[0].before, theta)
    Tt = _elems_T(robot.links[-1].before, theta)
    new_root, new_tip = root, tip
    if not np.allclose(Tb, np.eye(4), atol=0, rtol=0):
        if any(j.child == root for j in ur.joints):
            warn_list.append(f"the base frame (base_tx … base_rz) cannot be written: link {root!r} has a parent "
                             f"in the original URDF; the URDF's {root!r} is the model's frame 0, not the world")
        else:
            new_root = _unique("world", links)
            ur.links.append(Link(name=new_root))
            ur.joints.append(Joint(name=_unique(f"{new_root}_joint", jnames), type="fixed", parent=new_root,
                                   child=root, origin=Tb))
    if not np.allclose(Tt, np.eye(4), atol=0, rtol=0):
        new_tip = _unique("tool", links)
        ur.links.append(Link(name=new_tip))
        ur.joints.append(Joint(name=_unique(f"{new_tip}_joint", jnames), type="fixed", parent=tip, child=new_tip,
                               origin=Tt))
    return new_root, new_tip


def _graft(original: Path):
    """Copy what yourdfpy's writer does not write from the original XML tree: elements it
    does not model (``<transmission>``, ``<gazebo>``, unknown link children) and the joint
    elements its joint writer omits (``<calibration>``, ``<mimic>``, ``<safety_controller>``;
    its element writers would print ``falling="None"`` for a one-sided calibration)."""
    from lxml import etree

    orig = etree.parse(str(original)).getroot()
    written = {"link": {"inertial", "visual", "collision"},
               "joint": {"parent", "child", "origin", "axis", "limit", "dynamics"}}

    def graft(root):
        by_name = {(el.tag, el.get("name")): el for el in root if el.tag in written}
        for el in orig:
            if not isinstance(el.tag, str):
                continue  # comments: their place in the file is not kept by the writer
            if el.tag in written:
                target = by_name.get((el.tag, el.get("name")))
                for sub in el:
                    if isinstance(sub.tag, str) and sub.tag not in written[el.tag] and target is not None:
                        target.append(copy.deepcopy(sub))
            elif el.tag != "material":
                root.append(copy.deepcopy(el))

    return graft


# ------------------------------------------------------------------ entry point
def export_urdf(robot: SerialRobot, path, from_urdf=None, root: str | None = None, tip: str | None = None,
                source=None, warn: bool = True) -> UrdfExport:
    """Write ``robot`` (current parameter values) as a URDF at ``path`` (atomically).

    Parameters
    ----------
    robot : a SerialRobot, e.g. a calibrated model from ``load_robot("model.yaml")``.
    path : output ``.urdf``.
    from_urdf : the original URDF of a model loaded from a URDF; its links, visuals,
        collisions, inertials and every other element are kept and only the calibrated
        joint origins change. ``root`` / ``tip``: the model's chain in it (default: the
        URDF's root link; the fixed descendant of the last joint matching the model).
    source : name of the model file, quoted in the provenance comment.
    warn : also issue each warning with :func:`warnings.warn`.

    Returns a :class:`UrdfExport`; its ``warnings`` name everything the URDF cannot hold.
    """
    import yourdfpy

    path = Path(path)
    for what, src in (("the robot file the model was loaded from", robot.meta.get("robot_file")),
                      ("the URDF the model was loaded from", robot.meta.get("urdf")),
                      ("the original URDF (from_urdf)", from_urdf)):
        if src and path.resolve() == Path(src).resolve():
            raise ValueError(f"{path}: is {what} — write the URDF to another file (inputs are never overwritten)")
    theta = robot.params.values
    warn_list = unexpressible(robot)
    header = _provenance(robot, source)
    vals = theta
    if from_urdf is None:
        urobot, r, t, notes = _standalone(robot, theta)
        urdf = yourdfpy.URDF(robot=urobot, build_scene_graph=False, load_meshes=False)
        changed = list(robot.joint_names)
        header.append(f"chain from root link {r!r} to tip link {t!r}; the joint origins carry the identified "
                      f"geometry and joint offsets; effort and velocity limits are not part of the model "
                      f"(written as 0)")
        _write(urdf, path, header, notes)
    else:
        from_urdf = Path(from_urdf)
        if robot.meta.get("urdf") and Path(robot.meta["urdf"]).resolve() == from_urdf.resolve():
            root, tip = root or robot.meta.get("root"), tip or robot.meta.get("tip")
        urdf, r0, t0, changed = _from_urdf(robot, theta, from_urdf, root, tip)
        r, t = _add_frames(urdf, robot, theta, r0, t0, warn_list)
        notes = {}
        for k, n in enumerate(robot.joint_names):
            off, gain = float(vals[robot.offset_idx[k]]), float(vals[robot.gain_idx[k]])
            unit = "rad" if robot.joint_types[k] == "revolute" else "m"
            notes[n] = [f"estcal: origin calibrated (offset {off!r} {unit} folded in); gain {gain!r}"
                        + ("" if gain == 1.0 else " NOT expressible: position = gain * reading")] \
                if n in changed or gain != 1.0 else []
        header.append(f"calibrated copy of {from_urdf.name}: only the origins of {', '.join(changed) or 'no joint'} "
                      f"changed; chain from root link {r!r} to tip link {t!r}")
        _write(urdf, path, header, notes, extra=_graft(from_urdf))
    if warn:
        for w in warn_list:
            warnings.warn(w, UserWarning, stacklevel=2)
    return UrdfExport(path=path, root=r, tip=t, changed=changed, warnings=warn_list)
