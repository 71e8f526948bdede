"""Assemble :class:`SerialRobot` objects from plain frame descriptions.

This is the single place where conventions are turned into elementary
motions and parameter names; the robot-file loader, the URDF loader and the
built-in robots all go through :func:`build_robot`.

A *frame description* is a dict::

    {"name": "j2", "type": "revolute" | "prismatic" | "fixed",
     "convention": "khalil" | "dh" | "urdf",
     # khalil: alpha, d, theta, r, beta   dh: theta, d, a, alpha (+ Hayati beta)
     # urdf:   origin (4x4), axis (3,)
     "offset": 0.0, "gain": 1.0, "limits": [lo, hi],
     "mass": kg, "com": [x, y, z] (in the frame at the end of this link),
     "label": optional explicit label for parameter names}
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .chain import Elementary, Link, SerialRobot
from .parameters import ParameterVector

__all__ = ["build_robot", "frame_labels", "KHALIL_PARAMS", "DH_PARAMS", "URDF_PARAMS", "FRAME6_PARAMS",
           "MAX_LENGTH_M", "MAX_ANGLE_RAD", "MAX_LIMIT_RAD"]

#: physical range of a robot-file or URDF value once in SI; beyond it the file's unit is wrong (a length
#: in millimetres, an angle in degrees without a ``units:`` line). Joint limits may span several turns.
MAX_LENGTH_M = 50.0
MAX_ANGLE_RAD = 2 * np.pi
MAX_LIMIT_RAD = 4 * np.pi

KHALIL_PARAMS = ("alpha", "d", "theta", "r", "beta")
DH_PARAMS = ("theta", "d", "a", "alpha", "beta")  # beta: Hayati Ry, nominal 0
URDF_PARAMS = ("tx", "ty", "tz", "rx", "ry", "rz")
FRAME6_PARAMS = ("tx", "ty", "tz", "rx", "ry", "rz")  # base/tool: xyz + URDF rpy


class _Params:
    def __init__(self):
        self.names, self.values, self.kinds, self.frames = [], [], [], []

    def add(self, name, value, kind, frame) -> int:
        if name in self.names:
            raise ValueError(f"duplicate parameter name {name!r}: give frames distinct names/labels")
        self.names.append(name)
        self.values.append(float(value))
        self.kinds.append(kind)
        self.frames.append(frame)
        return len(self.names) - 1


def _frame6_link(label: str, prefix: str, xyz, rpy, P: _Params, const=None) -> Link:
    """Trans(x,y,z) Rot(z,yaw) Rot(y,pitch) Rot(x,roll): a URDF xyz/rpy pair as 6 motions."""
    idx = {k: P.add(f"{prefix}_{k}", v, prefix if prefix in ("base", "tool") else "geometric", label)
           for k, v in zip(FRAME6_PARAMS, list(xyz) + list(rpy))}
    before = [Elementary("P", "x", idx["tx"]), Elementary("P", "y", idx["ty"]), Elementary("P", "z", idx["tz"]),
              Elementary("R", "z", idx["rz"]), Elementary("R", "y", idx["ry"]), Elementary("R", "x", idx["rx"])]
    return Link(label=label, const=np.eye(4) if const is None else np.asarray(const, float), before=before)


def frame_labels(frames: Sequence[dict]) -> list[str]:
    """Khalil/DH frame numbering: actuated joints 1..n; constant frames before the
    first joint count down from 0, later ones continue the count (GECARO's 0 … n+1)."""
    first = next((i for i, f in enumerate(frames) if f.get("type", "revolute") != "fixed"), len(frames))
    out = []
    for i, f in enumerate(frames):
        if "label" in f:
            out.append(str(f["label"]))
        else:
            out.append(str(i - first + 1))
    return out


def build_robot(name: str, frames: Sequence[dict], base=None, tool=None, markers=None,
                gravity=(0.0, 0.0, -9.81), payload=None, coupling=None, convention: str = "khalil",
                tool_const=None, meta: dict | None = None) -> SerialRobot:
    """Build a robot from frame descriptions (see module docstring).

    Parameters
    ----------
    base, tool : dict with ``xyz`` and ``rpy`` (metres, radians) or None for identity.
    markers : (k, 3) points in the tool frame (metres) or None.
    payload : dict ``{mass, com}`` in the tool frame.
    tool_const : constant (4, 4) transform between the last link and the tool
        parameters (URDF fixed joints after the last actuated joint).
    """
    P = _Params()
    links: list[Link] = []
    b = base or {}
    links.append(_frame6_link("base", "base", b.get("xyz", (0, 0, 0)), b.get("rpy", (0, 0, 0)), P))
    labels = frame_labels(frames) if convention != "urdf" else [f.get("label", f["name"]) for f in frames]
    joint_names, joint_types, limits, offsets, gains = [], [], [], [], []
    for f, label in zip(frames, labels):
        ftype = f.get("type", "revolute")
        conv = f.get("convention", convention)
        if ftype not in ("revolute", "prismatic", "fixed"):
            raise ValueError(f"frame {f.get('name', label)!r}: unknown type {ftype!r} "
                             f"(expected revolute, prismatic or fixed)")
        jidx = None
        if ftype != "fixed":
            jidx = len(joint_names)
            joint_names.append(str(f.get("name", f"joint_{label}")))
            joint_types.append(ftype)
            lim = f.get("limits", (-np.pi, np.pi) if ftype == "revolute" else (0.0, 1.0))
            limits.append([float(lim[0]), float(lim[1])])
            offsets.append((label, float(f.get("offset", 0.0))))
            gains.append((label, float(f.get("gain", 1.0))))
        link = Link(label=label, joint=jidx, joint_kind="P" if ftype == "prismatic" else "R",
                    mass=float(f.get("mass", 0.0)), com=np.asarray(f.get("com", (0, 0, 0)), float))
        if conv == "khalil":
            v = {k: float(f.get(k, 0.0)) for k in KHALIL_PARAMS}
            idx = {k: P.add(f"{k}_{label}", v[k], "geometric", label) for k in KHALIL_PARAMS}
            link.before = [Elementary("R", "y", idx["beta"]), Elementary("R", "x", idx["alpha"]),
                           Elementary("P", "x", idx["d"])]
            if ftype == "revolute":
                link.joint_param = idx["theta"]
                link.after = [Elementary("P", "z", idx["r"])]
            elif ftype == "prismatic":
                link.before.append(Elementary("R", "z", idx["theta"]))
                link.joint_param = idx["r"]
            else:
                link.before += [Elementary("R", "z", idx["theta"]), Elementary("P", "z", idx["r"])]
        elif conv == "dh":
            v = {k: float(f.get(k, 0.0)) for k in DH_PARAMS}
            idx = {k: P.add(f"{k}_{label}", v[k], "geometric", label) for k in DH_PARAMS}
            # Hayati's variant Rz Tz Tx Rx Ry (textbook 2.64 / 4.391); beta = 0 gives standard DH
            tail = [Elementary("P", "x", idx["a"]), Elementary("R", "x", idx["alpha"]),
                    Elementary("R", "y", idx["beta"])]
            if ftype == "revolute":
                link.joint_param = idx["theta"]
                link.after = [Elementary("P", "z", idx["d"])] + tail
            elif ftype == "prismatic":
                link.before = [Elementary("R", "z", idx["theta"])]
                link.joint_param = idx["d"]
                link.after = tail
            else:
                link.before = [Elementary("R", "z", idx["theta"]), Elementary("P", "z", idx["d"])] + tail
        elif conv == "urdf":
            link.const = np.asarray(f.get("origin", np.eye(4)), float)
            if ftype != "fixed":
                idx = {k: P.add(f"{k}_{label}", 0.0, "geometric", label) for k in URDF_PARAMS}
                link.before = [Elementary("P", "x", idx["tx"]), Elementary("P", "y", idx["ty"]),
                               Elementary("P", "z", idx["tz"]), Elementary("R", "x", idx["rx"]),
                               Elementary("R", "y", idx["ry"]), Elementary("R", "z", idx["rz"])]
            ax = np.asarray(f.get("axis", (0, 0, 1)), float)
            link.joint_axis = ax / np.linalg.norm(ax)
        else:
            raise ValueError(f"frame {f.get('name', label)!r}: unknown convention {conv!r} "
                             f"(expected khalil, dh or urdf)")
        links.append(link)
    t = tool or {}
    links.append(_frame6_link("tool", "tool", t.get("xyz", (0, 0, 0)), t.get("rpy", (0, 0, 0)), P,
                              const=tool_const))
    if payload:
        pm, pc = float(payload.get("mass", 0.0)), payload.get("com", (0, 0, 0))
    else:
        pm, pc = 0.0, (0, 0, 0)
    offset_idx = [P.add(f"offset_{lab}", v, "offset", lab) for lab, v in offsets]
    gain_idx = [P.add(f"gain_{lab}", v, "gain", lab) for lab, v in gains]
    marker_idx = []
    for k, m in enumerate(np.zeros((0, 3)) if markers is None else np.asarray(markers, float).reshape(-1, 3)):
        marker_idx.append([P.add(f"marker{k + 1}_{c}", m[i], "marker", "tool") for i, c in enumerate("xyz")])
    params = ParameterVector(P.names, P.values, None, P.kinds, P.frames)
    return SerialRobot(name, links, params, joint_names, joint_types, limits, offset_idx, gain_idx,
                       marker_idx if marker_idx else None, gravity, pm, pc, coupling, convention, meta=meta)
