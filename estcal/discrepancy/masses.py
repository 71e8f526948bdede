"""Link masses of a URDF chain including the links after the last actuated joint.

Gravity-driven effects (joint compliance, backlash by the sign of the load)
need the mass each actuated joint carries. Until commit 6ff85cc,
:func:`estcal.kinematics.urdf.robot_from_urdf` skipped the *fixed chain joints*
when merging subtrees, so the links between the last actuated joint and the tip
(for TIAGo: ``arm_tool_link``, ``wrist_ft_link``, ``wrist_ft_tool_link`` and the
gripper hanging from them, 1.065 kg in total) carried no mass; the loader now
includes them, and this module is an independent computation of the same
masses (used by the diagnosis on URDF robots, and as a check).
:func:`urdf_chain_masses` recomputes each actuated joint's link mass and centre
of mass as the total of its child link and everything rigidly attached to it up
to the next actuated chain joint (off-chain movable joints at zero).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from estcal.kinematics.chain import SerialRobot
from estcal.kinematics.urdf import load_urdf

__all__ = ["urdf_chain_masses", "with_urdf_masses"]


def urdf_chain_masses(urdf_path, joint_names) -> dict:
    """``{joint: (mass kg, com (3,) in the joint's child-link frame)}`` for the chain joints."""
    urdf = load_urdf(urdf_path)
    children = {}
    for j in urdf.robot.joints:
        children.setdefault(j.parent, []).append(j)
    links = {lk.name: lk for lk in urdf.robot.links}
    joints = {j.name: j for j in urdf.robot.joints}
    out = {}
    names = list(joint_names)
    for i, jn in enumerate(names):
        stop = set(names[i + 1:])
        total, moment = 0.0, np.zeros(3)
        stack = [(joints[jn].child, np.eye(4))]
        while stack:
            ln, T = stack.pop()
            lk = links[ln]
            if lk.inertial is not None and lk.inertial.mass:
                m = float(lk.inertial.mass)
                o = np.asarray(lk.inertial.origin, float) if lk.inertial.origin is not None else np.eye(4)
                total += m
                moment += m * (T @ o)[:3, 3]
            for j in children.get(ln, []):
                if j.name in stop:
                    continue
                stack.append((j.child, T @ (np.eye(4) if j.origin is None else np.asarray(j.origin, float))))
        out[jn] = (total, moment / total if total > 0 else np.zeros(3))
    return out


def with_urdf_masses(robot, urdf_path=None):
    """Copy of a URDF-built ``robot`` whose actuated links carry :func:`urdf_chain_masses`.

    The link frame at the end of a URDF link is the joint's child-link frame
    (the chain applies origin · placement error · joint motion and nothing after),
    so the centres of mass are used as computed.
    """
    path = urdf_path or robot.meta.get("urdf")
    if path is None:
        raise ValueError(f"robot {robot.name!r} was not built from a URDF; give urdf_path")
    masses = urdf_chain_masses(path, robot.joint_names)
    links = []
    for lk in robot.links:
        if lk.joint is not None and lk.after:
            raise ValueError("with_urdf_masses expects URDF links (no parameter motions after the joint)")
        if lk.joint is not None:
            m, c = masses[robot.joint_names[lk.joint]]
            lk = dataclasses.replace(lk, mass=m, com=np.asarray(c, float))
        links.append(lk)
    return SerialRobot(robot.name, links, robot.params.copy(), robot.joint_names, robot.joint_types, robot.limits,
                       robot.offset_idx, robot.gain_idx, robot.marker_idx, robot.gravity, robot.payload_mass,
                       robot.payload_com, robot.coupling, robot.convention, list(robot.effects), robot.meta)
