"""Serial kinematic chains with analytic identification Jacobians.

One representation serves every convention. A chain is a list of *links*;
a link is a product of elementary motions (rotation or translation about a
local axis, each driven by one named parameter), optionally preceded by a
constant transform (URDF joint origin, merged fixed joints) and containing
at most one joint motion::

    T_link = C_const · E_1(η_1) ··· E_a(η_a) · J(q_j + η_jvar) · E_{a+1} ··· E_b

* Khalil–Kleinfinger (GECARO eq. [3]), revolute:
  ``Rot(y,β) Rot(x,α) Trans(x,d) · Rot(z, θ + q) · Trans(z,r)``;
  prismatic: ``Rot(y,β) Rot(x,α) Trans(x,d) Rot(z,θ) · Trans(z, r + q)``;
  constant frame (σ = 2): the five motions without a joint.
* Standard DH: ``Rot(z, θ + q) · Trans(z,d) Trans(x,a) Rot(x,α)`` (prismatic:
  ``Rot(z,θ) · Trans(z, d + q) · Trans(x,a) Rot(x,α)``).
* URDF joint: ``C_origin · Trans(x,y,z)(tx,ty,tz) Rot(x,rx) Rot(y,ry) Rot(z,rz) · Rot(axis, q)``
  with the 6-D placement error at nominal zero.
* Base (world → frame 0) and tool (frame n → tool): ``Trans(tx,ty,tz) Rot(z,rz) Rot(y,ry) Rot(x,rx)``
  i.e. a URDF ``xyz/rpy`` pair.

The joint value is ``q = Cj · diag(K) · Cm · reading + offset`` (GECARO eq. [4],
coupling matrices optional) plus any joint-space correction contributed by a
non-geometric effect.

Jacobian
--------
Differentiating the chain through an elementary rotation about the world axis
``w`` through the world point ``o`` moves any downstream point ``x`` by
``w × (x − o)`` and turns the tool by ``w``; a translation along ``w`` moves
it by ``w``. These are GECARO Appendix II's columns (eq. [27]) —
``j_α = [s_{j−1} × L ; s_{j−1}]``, ``j_d = [s_{j−1}; 0]`` … — evaluated at the
current (not only nominal) parameter values, so they are exact for every
convention. Joint offsets use the joint column; gains use
``Σ_l j_q_l ∂q_l/∂K_j`` (GECARO App. II, with coupling). Rows are
``(dx, dy, dz, δx, δy, δz)`` in the world frame; the rotational rows are the
world-frame rotation vector of ``R(η+dη) R(η)ᵀ``.
"""
from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Sequence

import numpy as np

from .parameters import ParameterVector
from .transforms import cross, rot_axis

__all__ = ["Elementary", "Link", "SerialRobot", "Kinematics"]

_OTHER = {0: (1, 2), 1: (2, 0), 2: (0, 1)}  # Rot(axis) mixes these columns (cyclic order)
_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


@dataclass(frozen=True)
class Elementary:
    """One elementary motion: ``kind`` 'R' (rotation) or 'P' (translation) along ``axis``
    by the value of parameter ``param`` (index into the parameter vector)."""

    kind: str
    axis: str  # 'x', 'y' or 'z'
    param: int


@dataclass
class Link:
    """One link of the chain (see module docstring).

    Attributes
    ----------
    label : str
        Frame label used in parameter names (``"3"``, ``"arm_1_joint"``, ``"base"``).
    const : (4, 4) array
        Constant transform applied first (URDF origin / merged fixed joints).
    before, after : list of Elementary
        Parameter-driven motions before and after the joint motion.
    joint : int or None
        Index of the actuated joint (0-based) moving this link, ``None`` for constant frames.
    joint_kind : 'R' or 'P'
    joint_axis : (3,) unit vector in the local frame
    joint_param : int
        Parameter added to the joint value (Khalil θ_j / r_j, DH θ_j / d_j), or -1.
    mass : float, com : (3,)
        Mass (kg) and centre of mass in the frame at the *end* of the link.
    """

    label: str
    const: np.ndarray = field(default_factory=lambda: np.eye(4))
    before: list = field(default_factory=list)
    joint: int | None = None
    joint_kind: str = "R"
    joint_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    joint_param: int = -1
    after: list = field(default_factory=list)
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class Kinematics:
    """Forward kinematics of N poses (all arrays have N as first axis).

    Attributes
    ----------
    q : (N, n) joint values (after gains, offsets and effects), rad / m
    R, p : (N, 3, 3), (N, 3) tool frame in the world (``T_world_tool``)
    points : (N, k, 3) marker points in the world (empty if no markers)
    J : (N, 6, P) Jacobian of the tool pose w.r.t. the full parameter vector
    J_points : (N, k, 3, P) Jacobian of each marker point
    J_q : (N, 6, n) Jacobian of the tool pose w.r.t. the joint values
    link_R, link_p : (N, L, 3, 3), (N, L, 3) frame at the end of every link
    joint_axis, joint_origin : (N, n, 3) world axis and a point on it, per joint
    """

    q: np.ndarray
    R: np.ndarray
    p: np.ndarray
    points: np.ndarray
    J: np.ndarray | None
    J_points: np.ndarray | None
    J_q: np.ndarray | None
    link_R: np.ndarray
    link_p: np.ndarray
    joint_axis: np.ndarray
    joint_origin: np.ndarray

    @property
    def T(self) -> np.ndarray:
        """Tool frames as homogeneous (N, 4, 4) matrices."""
        from .transforms import make_transform

        return make_transform(self.R, self.p)


@functools.lru_cache(maxsize=256)
def _parameters_of(func) -> frozenset:
    """The parameter names of ``func`` — an effect's ``point_correction``, asked on every evaluation: read
    once per function (``inspect.signature`` was 4 % of a two-session diagnosis)."""
    return frozenset(inspect.signature(func).parameters)


def _accepts(method, name: str) -> bool:
    """Whether the (bound) ``method`` takes a parameter ``name``."""
    return name in _parameters_of(getattr(method, "__func__", method))


def _frames_kw(eff, link_p) -> dict:
    """``link_p`` (N, L, 3) for Cartesian effects that ask for the link frames."""
    return {"link_p": link_p} if _accepts(eff.point_correction, "link_p") else {}


def _screw_at(w, o, rot, x):
    """Velocity of point x (3, 1, N) for unit motions about (rot) / along axes w through o (3, C, N)."""
    d0, d1, d2 = x[0] - o[0], x[1] - o[1], x[2] - o[2]
    out = np.empty_like(w)
    np.subtract(w[1] * d2, w[2] * d1, out=out[0])
    np.subtract(w[2] * d0, w[0] * d2, out=out[1])
    np.subtract(w[0] * d1, w[1] * d0, out=out[2])
    if not rot.all():
        tr = ~rot
        out[:, tr] = w[:, tr]
    return out


def _add_joint_blocks(JT, JqT, blocks):
    """JT[:, idx] += JqT · dq/dθ_idx for each block; JT (r, P, N), JqT (r, n, N).

    Block kinds: 'eye' (D = joint index of each parameter), 'diag' (D (N, n): the
    parameter of joint l scales column l, e.g. gains), 'cols' (D = (joint of each parameter (m,),
    its derivative (N, m)): one joint per parameter, an effect's) and 'dense' (D (N, n, m))."""
    for idx, D, kind in blocks or ():
        if kind == "eye":
            JT[:, idx] += JqT[:, D]
        elif kind == "diag":
            JT[:, idx] += JqT * D.T[None]
        elif kind == "cols":
            JT[:, idx] += JqT[:, D[0]] * D[1].T[None]
        else:
            JT[:, idx] += np.einsum("rln,nlm->rmn", JqT, np.broadcast_to(D, (JqT.shape[2],) + D.shape[1:]))


def _rot_mat(R, C):
    """R (3, 3, N) @ C (3, 3) -> (3, 3, N); or C (3, 3, W), one per walker, with the N = W·N'
    poses walker-major (nine component sums: several times faster than stacked matmuls)."""
    if C.ndim == 2:
        return np.einsum("ikn,kj->ijn", R, C)
    R4 = R.reshape(3, 3, C.shape[2], -1)
    out = np.empty_like(R4)
    for i in range(3):
        for j in range(3):
            out[i, j] = R4[i, 0] * C[0, j, :, None] + R4[i, 1] * C[1, j, :, None] + R4[i, 2] * C[2, j, :, None]
    return out.reshape(R.shape)


def _rot_vec(R, v):
    """R (3, 3, N) @ v (3,) -> (3, N); or v (3, W), one per walker (poses walker-major)."""
    if v.ndim == 1:
        if R.shape[2] <= 16:
            # a few poses (a stream of single poses): one matmul call, not five array temporaries
            return (R.transpose(2, 0, 1) @ v).T
        # one einsum call instead of five array temporaries (several times faster up to thousands of poses)
        return np.einsum("ijn,j->in", R, v)
    R4 = R.reshape(3, 3, v.shape[1], -1)
    return (R4[:, 0] * v[0][:, None] + R4[:, 1] * v[1][:, None] + R4[:, 2] * v[2][:, None]).reshape(3, -1)


def _merge_blocks(per_walker, N):
    """Joint-derivative blocks of W walkers (same parameters, same kinds) as blocks over W·N poses."""
    out = []
    for parts in zip(*per_walker):
        idx, D, kind = parts[0]
        if kind == "cols":
            D = (D[0], np.concatenate([d[1] for _, d, _ in parts]))
        elif kind != "eye":
            D = np.concatenate([np.broadcast_to(d, (N,) + d.shape[1:]) for _, d, _ in parts])
        out.append((idx, D, kind))
    return out


class SerialRobot:
    """A serial robot: links, joints, named parameters and optional effects.

    Build one with :mod:`estcal.kinematics.robots` (built-ins), the robot-file
    loader :func:`estcal.io.robotfile.load_robot`, or the URDF loader
    :func:`estcal.kinematics.urdf.robot_from_urdf`.

    Parameters
    ----------
    name : str
    links : list of Link
        In chain order; the first is usually the base link, the last the tool link.
    params : ParameterVector
    joint_names : list of str
    joint_types : list of {'revolute', 'prismatic'}
    limits : (n, 2) array, joint-value limits (rad / m)
    offset_idx, gain_idx : (n,) int arrays into the parameter vector
    marker_idx : (k, 3) int array, marker coordinates in the tool frame
    gravity : (3,) world gravity (m/s²)
    payload_mass, payload_com : payload in the tool frame
    coupling : optional ``(Cj, Cm)`` coupling matrices (GECARO eq. [4])
    convention : 'khalil', 'dh' or 'urdf' (informational)
    """

    def __init__(self, name: str, links: list[Link], params: ParameterVector, joint_names: Sequence[str],
                 joint_types: Sequence[str], limits, offset_idx, gain_idx, marker_idx=None,
                 gravity=(0.0, 0.0, -9.81), payload_mass: float = 0.0, payload_com=(0.0, 0.0, 0.0),
                 coupling=None, convention: str = "khalil", effects: list | None = None,
                 meta: dict | None = None):
        self.name = name
        self.links = links
        self.params = params
        self.joint_names = list(joint_names)
        self.joint_types = list(joint_types)
        self.limits = np.asarray(limits, float).reshape(len(self.joint_names), 2)
        self.offset_idx = np.asarray(offset_idx, int)
        self.gain_idx = np.asarray(gain_idx, int)
        self.marker_idx = np.zeros((0, 3), int) if marker_idx is None else np.asarray(marker_idx, int).reshape(-1, 3)
        self.gravity = np.asarray(gravity, float)
        self.payload_mass = float(payload_mass)
        self.payload_com = np.asarray(payload_com, float)
        self.coupling = coupling
        self.convention = convention
        self.effects = list(effects or [])
        self.meta = dict(meta or {})
        self._rigid_memo = None  # the last rigid_kinematics: (key, frames)
        self._compile()

    # ----------------------------------------------------------------- set-up
    def _compile(self) -> None:
        """Precompute index arrays used by the vectorised Jacobian."""
        n = self.n_joints
        self._joint_link = np.full(n, -1)
        for li, link in enumerate(self.links):
            if link.joint is not None:
                self._joint_link[link.joint] = li
        if np.any(self._joint_link < 0):
            missing = [self.joint_names[j] for j in np.flatnonzero(self._joint_link < 0)]
            raise ValueError(f"joints {missing} are not attached to any link")
        elem_params = [e.param for link in self.links for e in link.before + link.after]
        if len(set(elem_params)) != len(elem_params):
            raise ValueError("a parameter drives more than one elementary motion")
        self._elem_param = np.array(elem_params, int)
        self._jvar_param = np.array([self.links[self._joint_link[j]].joint_param for j in range(n)], int)
        self._joint_is_rot = np.array([self.links[self._joint_link[j]].joint_kind == "R" for j in range(n)])

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_markers(self) -> int:
        return self.marker_idx.shape[0]

    @property
    def n_params(self) -> int:
        return len(self.params)

    def copy(self, params: ParameterVector | None = None, effects: list | None = None) -> "SerialRobot":
        """Shallow copy with (optionally) another parameter vector / effect list."""
        return SerialRobot(self.name, self.links, (params or self.params).copy(), self.joint_names,
                           self.joint_types, self.limits, self.offset_idx, self.gain_idx, self.marker_idx,
                           self.gravity, self.payload_mass, self.payload_com, self.coupling,
                           self.convention, list(self.effects if effects is None else effects), self.meta)

    def with_values(self, values) -> "SerialRobot":
        """Copy whose parameter values are ``values`` (full vector)."""
        return self.copy(self.params.with_values(values))

    def add_effect(self, effect) -> "SerialRobot":
        """Copy with a non-geometric effect appended; its parameters join the vector.

        The effect protocol (implemented in :mod:`estcal.effects`):

        * ``param_names`` (list of str), ``initial_values()`` -> array, optional
          ``param_frames``; ``bind(indices)`` stores ``self.indices`` (positions of
          its parameters in the robot's vector). The effect is copied before binding.
        * ``joint_correction(robot, readings, q, theta, context)`` ->
          ``(dq (N, n), d(dq)/d(θ_effect) (N, n, m) or None)``: added to the joint values.
        * and/or ``point_correction(robot, readings, points, theta, context,
          derivatives, J_points=None)`` -> ``(dx (N, k, 3), d(dx)/d(θ_effect) (N, k, 3, m) or None)``:
          added to every measured point — the tool origin and the markers — (e.g.
          thermal expansion); effects whose signature has ``link_p`` also receive the
          link frame origins (N, L, 3).

        Jacobian columns of effect parameters are exact; the dependence of an
        effect's correction on the geometric parameters (e.g. of a gravity torque
        on link lengths) is second order and neglected.
        """
        import copy as _copy

        effect = _copy.copy(effect)
        names = list(effect.param_names)
        params = self.params.extend(names, effect.initial_values(), kind="effect",
                                    frames=getattr(effect, "param_frames", None))
        new = self.copy(params, self.effects + [effect])
        effect.bind(new.params.indices(names))
        return new

    def check_readings(self, q, where: str = "joint readings") -> np.ndarray:
        q = np.asarray(q, float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f"{where}: expected shape (N, {self.n_joints}) for joints {self.joint_names}, "
                             f"got {q.shape}")
        if not np.all(np.isfinite(q)):
            bad = np.argwhere(~np.isfinite(q))[0]
            raise ValueError(f"{where}: non-finite value at row {bad[0]}, joint {self.joint_names[bad[1]]!r}")
        return q

    # -------------------------------------------------------------- joints
    def joint_values(self, readings, theta=None, context: dict | None = None, derivatives: bool = False):
        """Joint values from readings: ``q = Cj diag(K) Cm r + offset (+ effects)``.

        Returns ``q`` (N, n) and, with ``derivatives=True``, ``dq/dθ`` as a dense (N, n, P) array.
        """
        theta = self.params.values if theta is None else np.asarray(theta, float)
        q, blocks = self._joint_values(np.asarray(readings, float), theta, context, derivatives)
        if not derivatives:
            return q, None
        N, n = q.shape
        dqT = np.zeros((n, len(theta), N))
        _add_joint_blocks(dqT, np.broadcast_to(np.eye(n)[:, :, None], (n, n, N)), blocks)
        return q, dqT.transpose(2, 0, 1)

    def _joint_values(self, r, theta, context, derivatives, effects: bool = True):
        """q and dq/dθ as blocks ``(param indices (m,), D (N or 1, n, m))`` (sparse in θ)."""
        N, n = r.shape
        K = theta[self.gain_idx]
        off = theta[self.offset_idx]
        blocks = []  # (param indices, D, kind); 'eye': D = joint index per param
        if self.coupling is None:
            u = r
            q = K * u + off
            if derivatives:
                blocks.append((self.gain_idx, u, "diag"))
        else:
            Cj, Cm = (np.asarray(c, float) for c in self.coupling)
            u = r @ Cm.T
            q = (K * u) @ Cj.T + off
            if derivatives:  # dq_l/dK_j = Cj[l, j] u_j
                blocks.append((self.gain_idx, Cj[None, :, :] * u[:, None, :], "dense"))
        if derivatives:
            blocks.append((self.offset_idx, np.arange(n), "eye"))
            valid = self._jvar_param >= 0
            if valid.any():
                blocks.append((self._jvar_param[valid], np.flatnonzero(valid), "eye"))
        for eff in (self.effects if effects else ()):
            if hasattr(eff, "joint_correction"):
                d, dd = eff.joint_correction(self, r, q, theta, context or {})
                q = q + d
                if derivatives and dd is not None:
                    jk = getattr(eff, "param_joints", None)
                    if jk is not None:  # one joint per parameter: its column only (the dense product sums zeros)
                        blocks.append((np.asarray(eff.indices), (jk, dd[:, jk, np.arange(len(jk))]), "cols"))
                    else:
                        blocks.append((np.asarray(eff.indices), dd, "dense"))
        return q, blocks

    # --------------------------------------------------------------- FK + J
    def kinematics(self, readings, theta=None, context: dict | None = None, jacobian: bool = True,
                   q_override=None) -> Kinematics:
        """Tool pose, marker points and analytic Jacobians for N poses at once.

        Parameters
        ----------
        readings : (N, n) joint readings (rad / m), column order ``joint_names``.
        theta : (P,) full parameter vector; default the robot's current values.
        context : dict of per-pose arrays (``t``, ``temperature``, ``payload``) for effects.
        jacobian : compute ``J`` (N, 6, P) and ``J_points`` (N, k, 3, P).
        q_override : (N, n) joint values used instead of the joint model (internal).

        Many parameter vectors at once (MCMC walkers, sigma points): with ``theta`` of
        shape (W, P) every output gains a leading walker axis — ``R`` (W, N, 3, 3),
        ``p`` (W, N, 3), ``points`` (W, N, k, 3), ``J`` (W, N, 6, P) … — equal to W
        single-θ calls (``tests/test_kinematics_batch.py``, 1e-12) in one pass of the
        chain over the W·N (walker, pose) pairs. Effects are included: their
        corrections are evaluated walker by walker, with that walker's θ.
        """
        readings = self.check_readings(readings)
        theta = self.params.values if theta is None else np.asarray(theta, float)
        many = theta.ndim == 2
        if theta.shape[-1:] != (self.n_params,) or theta.ndim > 2:
            raise ValueError(f"theta must have {self.n_params} entries (or shape (W, {self.n_params})), "
                             f"got {theta.shape}")
        n_w = theta.shape[0] if many else 1
        q, dqdth, seg = self._joint_stage(readings, theta, context, jacobian, q_override)
        N = n_w * readings.shape[0]
        ch = self._chain_pass(q, theta, seg, N, many)
        points = self._marker_points(ch.R, ch.p, theta, n_w, N, many)
        # Cartesian effects (thermal expansion) move every measured point: the tool origin and the
        # markers, so they act on tool positions, full poses, markers and the link/plane/distance
        # methods alike. With many parameter vectors they are evaluated walker by walker.
        cart = [eff for eff in self.effects if hasattr(eff, "point_correction")]
        walkers = ([(w, slice(w * (N // n_w), (w + 1) * (N // n_w))) for w in range(n_w)] if many
                   else [(None, slice(None))])
        p, allp = ch.p, None
        if cart:
            p, points, allp = self._cartesian_points(cart, walkers, readings, theta, context, ch, points)
        J = J_points = J_q = None
        if jacobian:
            J, J_points, J_q = self._jacobians(ch, p, points, dqdth, N)
            if cart:
                J, J_points = self._cartesian_jacobians(cart, walkers, readings, theta, context, ch, allp, J, J_points)
        out = [q, np.ascontiguousarray(ch.R.transpose(2, 0, 1)), np.ascontiguousarray(p.T), points, J, J_points, J_q,
               ch.link_R.transpose(3, 0, 1, 2), ch.link_p.transpose(2, 0, 1), ch.ja.transpose(2, 1, 0),
               ch.jo.transpose(2, 1, 0)]
        if many:
            out = [None if a is None else a.reshape((n_w, N // n_w) + a.shape[1:]) for a in out]
        return Kinematics(*out)

    def _joint_stage(self, readings, theta, context, jacobian, q_override):
        """``(q, dq/dθ, segment)``: the joint values of every pose (walker-major for many θ) and the
        function that composes the constant and parameter motions of one segment."""
        if theta.ndim == 2:
            if q_override is not None:
                raise ValueError("q_override needs a single parameter vector")
            q, dqdth = self._joint_values_many(readings, theta, context, jacobian)
            return q, dqdth, lambda const, elems, R, p, W, O, is_rot, k: self._segment_many(
                const, elems, theta, R, p, W, O, is_rot, k, jacobian)
        if q_override is None:
            q, dqdth = self._joint_values(readings, theta, context, jacobian)
        else:
            q, dqdth = np.asarray(q_override, float), None
        return q, dqdth, lambda const, elems, R, p, W, O, is_rot, k: self._segment(
            const, elems, theta, R, p, W, O, is_rot, k, jacobian)

    def _chain_pass(self, q, theta, seg, N, many) -> SimpleNamespace:
        """One pass of the chain for the N poses: the tool frame ``R`` (3, 3, N), ``p`` (3, N), every
        link frame, the joint axes ``ja`` and points on them ``jo`` (3, n, N), and the world axis ``W``
        and point ``O`` (3, E, N) of every elementary motion (``is_rot``: rotation or translation).

        The layout is component-major with poses last, so that every operation runs on contiguous
        length-N rows; constant and parameter motions compose into one local transform per segment
        (one small product per segment instead of one per motion)."""
        R = np.zeros((3, 3, N))
        R[0, 0] = R[1, 1] = R[2, 2] = 1.0
        p = np.zeros((3, N))
        n_links, n, n_el = len(self.links), self.n_joints, len(self._elem_param)
        link_R, link_p = np.empty((n_links, 3, 3, N)), np.empty((n_links, 3, N))
        ja, jo = np.empty((3, n, N)), np.empty((3, n, N))
        W, O, is_rot = np.empty((3, n_el, N)), np.empty((3, n_el, N)), np.empty(n_el, bool)
        k = 0
        for li, link in enumerate(self.links):
            Cb_R, Cb_p, k = seg(link.const, link.before, R, p, W, O, is_rot, k)
            p = p + _rot_vec(R, Cb_p)
            R = _rot_mat(R, Cb_R)
            if link.joint is not None:
                R, p = self._joint_motion(link, q, theta, R, p, ja, jo, N, many)
            if link.after:
                Ca_R, Ca_p, k = seg(None, link.after, R, p, W, O, is_rot, k)
                p = p + _rot_vec(R, Ca_p)
                R = _rot_mat(R, Ca_R)
            link_R[li] = R
            link_p[li] = p
        return SimpleNamespace(R=R, p=p, link_R=link_R, link_p=link_p, ja=ja, jo=jo, W=W, O=O, is_rot=is_rot)

    @staticmethod
    def _joint_motion(link, q, theta, R, p, ja, jo, N, many):
        """The joint's rotation or translation by its value; records its world axis and a point on it."""
        j = link.joint
        jv = theta[..., link.joint_param] if link.joint_param >= 0 else 0.0
        val = q[:, j] + (np.repeat(jv, N // len(jv)) if many and link.joint_param >= 0 else jv)
        ax = link.joint_axis
        jo[:, j] = p
        z_axis = ax[0] == 0.0 and ax[1] == 0.0 and ax[2] == 1.0
        ja[:, j] = R[:, 2] if z_axis else _rot_vec(R, ax)  # R (0, 0, 1) is R's third column
        if link.joint_kind != "R":
            return R, p + ja[:, j] * val
        if z_axis:
            c, s_ = np.cos(val), np.sin(val)
            x0, y0 = R[:, 0], R[:, 1]
            x1 = c * x0 + s_ * y0  # both new columns from the old ones before either is written
            R[:, 1] = c * y0 - s_ * x0
            R[:, 0] = x1
            return R, p
        return np.einsum("ikn,nkj->ijn", R, rot_axis(ax, val)), p  # rot_axis: (N, 3, 3)

    def _marker_points(self, R, p, theta, n_w, N, many) -> np.ndarray:
        """(N, k, 3) marker points ``p + R m`` (each walker's markers for many θ)."""
        if many:
            m = theta[:, self.marker_idx] if self.n_markers else np.zeros((n_w, 0, 3))
            Rm = np.einsum("ijwn,wkj->ikwn", R.reshape(3, 3, n_w, -1), m).reshape(3, m.shape[1], N)
            pts = p[:, None, :] + Rm
        else:
            m = theta[self.marker_idx] if self.n_markers else np.zeros((0, 3))
            pts = p[:, None, :] + np.einsum("ijn,kj->ikn", R, m)  # (3, k, N)
        return pts.transpose(2, 1, 0).copy()

    def _cartesian_points(self, cart, walkers, readings, theta, context, ch, points):
        """``(p (3, N), points, allp)``: the tool origin (row 0 of ``allp``) and the markers moved by the
        Cartesian effects."""
        link_pn = ch.link_p.transpose(2, 0, 1)
        allp = np.concatenate([ch.p.T[:, None, :], points], 1)
        for eff in cart:
            for w, sl in walkers:
                d, _ = eff.point_correction(self, readings, allp[sl], theta if w is None else theta[w],
                                            context or {}, derivatives=False, **_frames_kw(eff, link_pn[sl]))
                allp[sl] = allp[sl] + d
        return np.ascontiguousarray(allp[:, 0].T), allp[:, 1:].copy(), allp

    def _jacobians(self, ch, p, points, dqdth, N):
        """``(J (N, 6, P), J_points (N, k, 3, P), J_q (N, 6, n))``: the screw of every elementary motion
        and joint at the tool origin and at each marker, chained with dq/dθ (joint offsets, gains)."""
        P = self.n_params
        jrot, el = self._joint_is_rot, self._elem_param
        W, O, is_rot, ja, jo = ch.W, ch.O, ch.is_rot, ch.ja, ch.jo
        # tool pose: JT (6, P, N) -> J (N, 6, P) as a view
        JqT = np.concatenate([_screw_at(ja, jo, jrot, p[:, None, :]), ja * jrot[:, None]], 0)  # (6, n, N)
        JT = np.zeros((6, P, N))
        JT[:3, el] = _screw_at(W, O, is_rot, p[:, None, :])
        JT[3:, el] = W * is_rot[:, None]
        _add_joint_blocks(JT, JqT, dqdth)
        JpT = np.zeros((self.n_markers, 3, P, N))
        for i in range(self.n_markers):
            x = points[:, i].T[:, None, :]
            JpT[i][:, el] = _screw_at(W, O, is_rot, x)
            _add_joint_blocks(JpT[i], _screw_at(ja, jo, jrot, x), dqdth)
            JpT[i][:, self.marker_idx[i]] += ch.R  # d(p + R m)/dm = R, R[a, c] per pose
        return JT.transpose(2, 0, 1), JpT.transpose(3, 0, 1, 2), JqT.transpose(2, 0, 1)

    def _cartesian_jacobians(self, cart, walkers, readings, theta, context, ch, allp, J, J_points):
        """The position rows of the tool origin and the markers corrected by the Cartesian effects."""
        link_pn = ch.link_p.transpose(2, 0, 1)
        Jall = np.concatenate([J[:, None, :3, :], J_points], 1)
        for eff in cart:
            # Effects that scale the whole point (thermal) also need the pose Jacobian to correct the
            # other columns; older effects may not take it.
            wants_J = _accepts(eff.point_correction, "J")
            for w, sl in walkers:
                Jp = Jall[sl]
                kw = {"J_points": Jp, **({"J": J[sl]} if wants_J else {}), **_frames_kw(eff, link_pn[sl])}
                _, dd = eff.point_correction(self, readings, allp[sl], theta if w is None else theta[w],
                                             context or {}, derivatives=True, **kw)
                if dd is not None:
                    Jp[..., eff.indices] += dd
        J[:, :3] = Jall[:, 0]
        return J, Jall[:, 1:]

    def _joint_values_many(self, r, TH, context, derivatives):
        """Joint values of W parameter vectors: q (W·N, n), walker-major, and merged dq/dθ blocks."""
        n_w, (N, n) = TH.shape[0], r.shape
        if any(hasattr(e, "joint_correction") for e in self.effects):
            outs = [self._joint_values(r, th, context, derivatives) for th in TH]
            return np.concatenate([o[0] for o in outs]), _merge_blocks([o[1] for o in outs], N)
        K = TH[:, self.gain_idx][:, None, :]
        off = TH[:, self.offset_idx][:, None, :]
        blocks = []
        if self.coupling is None:
            q = K * r[None] + off
            if derivatives:
                blocks.append((self.gain_idx, np.tile(r, (n_w, 1)), "diag"))
        else:
            Cj, Cm = (np.asarray(c, float) for c in self.coupling)
            u = r @ Cm.T
            q = (K * u[None]) @ Cj.T + off
            if derivatives:
                blocks.append((self.gain_idx, np.tile(Cj[None, :, :] * u[:, None, :], (n_w, 1, 1)), "dense"))
        if derivatives:
            blocks.append((self.offset_idx, np.arange(n), "eye"))
            valid = self._jvar_param >= 0
            if valid.any():
                blocks.append((self._jvar_param[valid], np.flatnonzero(valid), "eye"))
        return q.reshape(n_w * N, n), blocks

    def _segment_many(self, const, elems, TH, R, p, W, O, is_rot, k, jacobian):
        """:meth:`_segment` for W parameter vectors: local frame per walker (3, 3, W), (3, W)."""
        LR0 = np.eye(3) if const is None else const[:3, :3]
        Lp0 = np.zeros(3) if const is None else const[:3, 3]
        if not elems:
            return LR0.copy(), Lp0.copy(), k
        n_w = TH.shape[0]
        LR = np.broadcast_to(LR0, (n_w, 3, 3)).copy()
        Lp = np.broadcast_to(Lp0, (n_w, 3)).copy()
        for i, e in enumerate(elems):
            ai = "xyz".index(e.axis)
            is_rot[k + i] = e.kind == "R"
            if jacobian:  # world axis and a point on it before this motion (Jacobian columns)
                W[:, k + i] = _rot_vec(R, LR[:, :, ai].T)
                O[:, k + i] = p + _rot_vec(R, Lp.T)
            v = TH[:, e.param]
            if e.kind == "R":
                c, s_ = np.cos(v)[:, None], np.sin(v)[:, None]
                i1, i2 = _OTHER[ai]
                a1, a2 = LR[:, :, i1].copy(), LR[:, :, i2].copy()
                LR[:, :, i1] = c * a1 + s_ * a2
                LR[:, :, i2] = c * a2 - s_ * a1
            else:
                Lp = Lp + LR[:, :, ai] * v[:, None]
        return LR.transpose(1, 2, 0), Lp.T.copy(), k + len(elems)

    def _segment(self, const, elems, theta, R, p, W, O, is_rot, k, jacobian: bool = True):
        """Compose ``const`` and ``elems`` locally; record each motion's world axis/point (the Jacobian's
        columns: not formed without ``jacobian``, e.g. the gravity torques' pass)."""
        LR, Lp, A, Oloc, rot = self._segment_local(const, elems, theta)
        if A is None:
            return LR, Lp, k
        m = len(elems)
        if not jacobian:
            return LR, Lp, k + m
        is_rot[k:k + m] = rot
        W[:, k:k + m] = A @ R  # (3, m, N): world axis = R @ a_local
        O[:, k:k + m] = p[:, None, :] + Oloc @ R
        return LR, Lp, k + m

    def _segment_local(self, const, elems, theta):
        """Local part of :meth:`_segment`, a function of θ alone: composed rotation/translation,
        the motions' local axes and points, and which are rotations. Cached for the last θ —
        a stream of single poses at one linearisation point (Kalman, iSAM2) evaluates the chain
        with the same θ many times, and for one pose this per-motion Python work is most of the cost."""
        key = (theta.tobytes(), id(self.links), len(self.links))
        cache = self.__dict__.get("_local_cache")
        if cache is None or cache[0] != key:
            cache = (key, {})
            self.__dict__["_local_cache"] = cache
        ck = (id(const), id(elems), len(elems or ()))  # a robot being built appends motions in place
        hit = cache[1].get(ck)
        if hit is not None and hit[0] is const and hit[1] is elems:
            return hit[2]
        if not cache[1]:  # a new θ: every segment of the chain at once (the common case)
            self._all_segments_local(theta, cache[1])
            hit = cache[1].get(ck)
            if hit is not None and hit[0] is const and hit[1] is elems:
                return hit[2]
        if not elems:
            out = (np.eye(3) if const is None else const[:3, :3].copy(),
                   np.zeros(3) if const is None else const[:3, 3].copy(), None, None, None)
        else:
            # Python floats, not 3-vectors: the same operations in the same order (bit-identical),
            # without a numpy call per component (most of a small robot's kinematics on few poses)
            c0 = np.eye(3) if const is None else const[:3, :3]
            cols = [c0[:, 0].tolist(), c0[:, 1].tolist(), c0[:, 2].tolist()]
            lp = [0.0, 0.0, 0.0] if const is None else const[:3, 3].tolist()
            A, Oloc, rot = [], [], []
            for e in elems:
                ai = "xyz".index(e.axis)
                A.append(cols[ai])
                Oloc.append(lp)
                v = float(theta[e.param])
                if e.kind == "R":
                    rot.append(True)
                    # scalar rotation: right-multiplying by Rot(axis, v) mixes the two other columns
                    c, s_ = math.cos(v), math.sin(v)
                    i1, i2 = _OTHER[ai]
                    a1, a2 = cols[i1], cols[i2]
                    cols = list(cols)
                    cols[i1] = [c * a1[k] + s_ * a2[k] for k in range(3)]
                    cols[i2] = [c * a2[k] - s_ * a1[k] for k in range(3)]
                else:
                    rot.append(False)
                    a = cols[ai]
                    lp = [lp[k] + a[k] * v for k in range(3)]
            out = (np.array(cols).T.copy(), np.array(lp), np.array(A), np.array(Oloc), np.array(rot, bool))
        for a in out:
            if a is not None:
                a.flags.writeable = False  # shared between calls
        cache[1][ck] = (const, elems, out)
        return out

    def _all_segments_local(self, theta, store: dict) -> None:
        """:meth:`_segment_local` of every segment of the chain for one θ, into ``store``: the segments
        with the same sequence of motions (URDF chains: tx ty tz rx ry rz after every joint) composed
        together, one array operation per motion for the whole group instead of Python floats per
        segment — the same operations in the same order on each entry (cosines and sines by
        :mod:`math`, as there), so bit-identical. The grouping depends on the chain's structure only
        (:meth:`_segment_plan`, kept across θ)."""
        for segs, keys, LR0, Lp0, pidx, kinds, rot in self._segment_plan():
            LR, Lp = LR0.copy(), Lp0
            m = len(kinds)
            A, Oloc = np.empty((len(segs), m, 3)), np.empty((len(segs), m, 3))
            vals = theta[pidx]  # (G, m)
            for i, (kind, ai, i1, i2) in enumerate(kinds):
                A[:, i] = LR[:, :, ai]
                Oloc[:, i] = Lp
                v = vals[:, i].tolist()
                if kind == "R":
                    c = np.array([math.cos(x) for x in v])[:, None]
                    s_ = np.array([math.sin(x) for x in v])[:, None]
                    a1, a2 = LR[:, :, i1].copy(), LR[:, :, i2].copy()
                    LR[:, :, i1] = c * a1 + s_ * a2
                    LR[:, :, i2] = c * a2 - s_ * a1
                else:
                    Lp = Lp + LR[:, :, ai] * np.array(v)[:, None]
            if Lp is Lp0:
                Lp = Lp0.copy()
            for arr in (LR, Lp, A, Oloc):
                arr.flags.writeable = False  # shared between calls
            for g, (key, (const, elems)) in enumerate(zip(keys, segs)):
                store[key] = (const, elems, (LR[g], Lp[g], A[g], Oloc[g], rot))

    def _segment_plan(self) -> list:
        """The segments of the chain grouped by their sequence of motions, with what does not depend on
        θ: ``(segments, cache keys, constant rotations (G, 3, 3), translations (G, 3), parameter indices
        (G, m), motions (kind, axis index, the two columns a rotation mixes), is-rotation (m,))``. Kept
        until the chain's structure changes (a robot being built appends motions in place)."""
        sig = tuple((id(link.const), id(link.before), len(link.before or ()), id(link.after), len(link.after or ()))
                    for link in self.links)
        cached = self.__dict__.get("_segment_plan_cache")
        if cached is not None and cached[0] is self.links and cached[1] == sig:
            return cached[2]
        groups: dict = {}
        for link in self.links:
            for const, elems in ((link.const, link.before), (None, link.after)):
                if elems:
                    key = (const is None,) + tuple((e.kind, e.axis) for e in elems)
                    groups.setdefault(key, []).append((const, elems))
        plan = []
        for key, segs in groups.items():
            G = len(segs)
            LR0 = np.empty((G, 3, 3))
            Lp0 = np.zeros((G, 3))
            for g, (const, _) in enumerate(segs):
                if const is None:
                    LR0[g] = np.eye(3)
                else:
                    LR0[g] = const[:3, :3]
                    Lp0[g] = const[:3, 3]
            kinds = tuple((kind, "xyz".index(axis)) + _OTHER["xyz".index(axis)] for kind, axis in key[1:])
            pidx = np.array([[e.param for e in elems] for _, elems in segs], dtype=np.intp)
            rot = np.array([kind == "R" for kind, *_ in kinds], bool)
            for arr in (LR0, Lp0, pidx, rot):
                arr.flags.writeable = False
            keys = [(id(const), id(elems), len(elems)) for const, elems in segs]
            plan.append((segs, keys, LR0, Lp0, pidx, kinds, rot))
        self.__dict__["_segment_plan_cache"] = (self.links, sig, plan)
        return plan

    # ------------------------------------------------------------- helpers
    def fk(self, readings, theta=None, context=None):
        """Tool frames ``T_world_tool`` as (N, 4, 4) — convenience wrapper."""
        return self.kinematics(readings, theta, context, jacobian=False).T

    def gravity_torques(self, readings, theta=None, context: dict | None = None, kin: Kinematics | None = None):
        """Static gravity torque (N·m) / force (N) on every joint, shape (N, n).

        τ_j = a_jᵀ Σ_{i ⪰ j} (c_i − o_j) × (m_i g) for a revolute joint with world axis
        a_j through o_j, and a_jᵀ Σ m_i g for a prismatic one; the sum runs over the
        links moved by joint j and the payload (mass ``payload_mass`` at
        ``payload_com`` in the tool frame, or the per-pose ``payload`` column of
        ``context`` in kg). This is the torque gravity exerts, so a compliant joint
        deflects by ``compliance · τ``.
        """
        m_beyond, moment, kin = self._gravity_loads(readings, theta, context, kin)
        g = np.asarray(self.gravity, float)
        prismatic = np.array([t == "prismatic" for t in self.joint_types])[None, :, None]
        arm = np.where(prismatic, m_beyond[..., None] * g, moment)  # a prismatic joint takes the force
        return np.einsum("nji,nji->nj", kin.joint_axis, arm)

    def gravity_moments(self, readings, theta=None, context: dict | None = None, kin: Kinematics | None = None):
        """Static gravity moment (N·m) about every joint's origin, world frame, shape (N, n, 3).

        ``M_j = Σ_{i ⪰ j} (c_i − o_j) × (m_i g)`` over the links joint j moves and the payload, as in
        :meth:`gravity_torques` — of which the revolute torque is the component along the axis,
        ``τ_j = a_jᵀ M_j``. The components across the axis load the joint's bearing and the link
        that carries it (for a prismatic joint: the bending moment of its column); they are what
        the ``link_tilt`` effect deflects under (:class:`estcal.effects.library.LinkTilt`).
        """
        return self._gravity_loads(readings, theta, context, kin)[1]

    def rigid_kinematics(self, readings, theta=None) -> Kinematics:
        """Frames of the rigid model (joint offsets and gains, no effect; no Jacobian) — where the
        gravity loads are evaluated (:meth:`gravity_torques`)."""
        theta = self.params.values if theta is None else np.asarray(theta, float)
        readings = self.check_readings(readings)
        # One evaluation of a model with gravity effects asks for the same rigid frames several times
        # (the compliance and backlash features, the link tilt's points and its Jacobian): the last one is
        # kept, keyed by the readings and θ bit for bit (a key compare, then the stored pair, so a reader
        # never gets another key's frames). The stored frames are never written to.
        key = (readings.shape, readings.tobytes(), theta.tobytes())
        memo = self._rigid_memo
        if memo is not None and memo[0] == key:
            return memo[1]
        # Rigid joint values (no effects): effects such as compliance call this function themselves, and
        # their feedback on the loads is second order. Without the Cartesian effects either: an effect
        # moving the points by the loads (link tilt) would otherwise call itself.
        q, _ = self._joint_values(readings, theta, None, False, effects=False)
        cart = [e for e in self.effects if hasattr(e, "point_correction")]
        rigid = self.copy(effects=[e for e in self.effects if e not in cart]) if cart else self
        kin = rigid.kinematics(readings, theta, jacobian=False, q_override=q)
        self._rigid_memo = (key, kin)
        return kin

    def _gravity_loads(self, readings, theta, context, kin):
        """``(mass beyond each joint (N, n), gravity moment about each joint origin (N, n, 3), kin)``."""
        if kin is None:
            kin = self.rigid_kinematics(readings, theta)
        N = kin.p.shape[0]
        masses = np.array([lk.mass for lk in self.links])
        coms = np.stack([lk.com for lk in self.links])  # (L, 3)
        c_world = kin.link_p + np.einsum("nlij,lj->nli", kin.link_R, coms)  # (N, L, 3)
        pay_m = np.full(N, self.payload_mass)
        if context is not None and "payload" in context:
            pay_m = np.asarray(context["payload"], float).reshape(N)
        pay_c = kin.p + kin.R @ self.payload_com
        g = np.asarray(self.gravity, float)
        # Σ_{i ⪰ j} (c_i − o_j) × m_i g = (Σ m_i c_i − (Σ m_i) o_j) × g: the mass and first moment of
        # everything joint j moves (suffix sums over the links, plus the payload), for all joints at once
        li = np.asarray(self._joint_link[:self.n_joints])
        m_beyond = np.cumsum(masses[::-1])[::-1][li][None, :] + pay_m[:, None]  # (N, n)
        mc = np.cumsum((masses[:, None, None] * c_world.transpose(1, 0, 2))[::-1], axis=0)[::-1]  # (L, N, 3)
        mc_beyond = mc[li].transpose(1, 0, 2) + (pay_m[:, None] * pay_c)[:, None, :]  # (N, n, 3)
        r = mc_beyond - m_beyond[..., None] * kin.joint_origin
        # r × g by components (transforms.cross): np.cross's axis moves were a third of this function's time on
        # 37 poses
        return m_beyond, cross(r, g), kin

    def random_readings(self, n: int, rng=None, margin: float = 0.0) -> np.ndarray:
        """Uniform random readings within joint limits (shrunk by ``margin`` of the range)."""
        rng = np.random.default_rng(rng)
        lo, hi = self.limits[:, 0], self.limits[:, 1]
        span = hi - lo
        return rng.uniform(lo + margin * span, hi - margin * span, size=(n, self.n_joints))

    def __repr__(self) -> str:
        return (f"SerialRobot({self.name!r}, {self.n_joints} joints [{', '.join(self.joint_types)}], "
                f"{self.n_params} parameters, {self.n_markers} markers, convention={self.convention!r})")
