"""The built-in non-geometric effects.

==================  ===========================================  ======================  ===========
registry name       correction                                   parameters              units
==================  ===========================================  ======================  ===========
joint_compliance    δq_j = c_j · τ_j (gravity torque)            ``compliance_<joint>``  rad/(N·m), m/N
backlash            δq_j = b_j · sign(τ_j)  (by load)             ``backlash_<joint>``    rad, m
                    or −b_j · sign(a_j)     (by approach)         ``backlash_approach_<j>``
gear_harmonic       δq_j = Σ_k a_kj sin(kφ_j) + b_kj cos(kφ_j)    ``harmonic<k>_sin_<j>`` rad
                                                                 ``harmonic<k>_cos_<j>``
encoder_gain        δq_j = g_j · r_j                             ``encgain_<joint>``     1
thermal_expansion   δx = α · ΔT · (x − o_base)   (every point)    ``thermal_alpha``       1/K
                    or α · ΔT · (flange − o_base) (links only)    ``thermal_alpha_links``
drift               δq_j = v_j · (t − t0)                         ``drift_<joint>``       rad/s, m/s
link_tilt           δx = Σ_j t_j · M⊥_j × (x − o_j) (every point) ``tilt_<joint>``        rad/(N·m)
==================  ===========================================  ======================  ===========

All corrections are linear in their parameters, so their derivatives (the
Jacobian columns of the effect parameters) are exact. Every parameter is zero
at its nominal value (no effect).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from estcal.kinematics.transforms import cross, cross_at

from .base import Effect, JointEffect, register_effect

__all__ = ["JointCompliance", "Backlash", "GearHarmonic", "EncoderGain", "ThermalExpansion", "Drift", "LinkTilt",
           "across_axis_moments"]


def _ctx(context: dict, key: str, N: int) -> np.ndarray | None:
    if context is None or key not in context or context[key] is None:
        return None
    a = np.asarray(context[key], float)
    try:
        return np.broadcast_to(a.reshape(-1) if a.ndim else a, (N,))
    except ValueError:
        raise ValueError(f"context {key!r} has {a.size} values for {N} poses") from None


class JointCompliance(JointEffect):
    """Joint compliance under gravity: ``δq_j = c_j · τ_j``.

    ``τ_j`` is the static gravity torque (N·m; force in N for a prismatic joint)
    on joint j from the masses of the links it carries and the payload
    (:meth:`SerialRobot.gravity_torques`; the per-pose ``payload`` context column,
    in kg, overrides the robot file's payload mass). ``c_j`` (``compliance_<joint>``)
    is in rad/(N·m) (m/N for a prismatic joint). Klimchik's elastostatic model
    reduced to the joint stiffness ``k_j = 1/c_j`` (GECARO §5 "non-geometric";
    Klimchik 2012 eq. 5). The torque is evaluated on the rigid model at the
    current parameters; its own dependence on geometry is second order.
    """

    name = "joint_compliance"
    prefixes = ("compliance",)

    def context_keys(self):
        return ["payload"]

    def features(self, robot, readings, q, theta, context):
        tau = robot.gravity_torques(readings, theta, context)
        return tau[:, None, self.joint_index]


class Backlash(JointEffect):
    """Backlash (half free-play) ``b_j`` (rad or m, ≥ 0 physically).

    Which flank of the gear the link rests against decides the sign of ``δq_j = ±b_j``; ``by`` says which
    record decides it:

    * ``"load"`` — the side its gravity load pushes it to: ``δq_j = b_j · sign(τ_j)`` (τ as in
      :class:`JointCompliance`); parameter ``backlash_<joint>``. A context column ``load_side_<joint>`` (±1)
      fixes the load's side instead of evaluating it at the current parameters: a fit that moves the geometry
      would otherwise flip it at a posture whose load is near zero, and the residual steps there
      (``estcal diagnose`` fixes it at the registration fit, then once more at the fitted model).
    * ``"approach"`` — the side the motor last moved from, where the load is too small to push the link across
      its free play (or transmission friction holds it): the link lags the motor,
      ``δq_j = −b_j · sign(approach_j)``, with the context column ``approach_<joint>`` (the sign of the joint
      velocity just before the pose was reached: +1 / −1 / 0); parameter ``backlash_approach_<joint>``.
      A Coulomb friction in the transmission gives the same lag. Without the column the correction is 0 (either
      side as likely: the midpoint, uncertain by ±b_j).
    * ``"auto"`` (default, as before ``by`` existed) — the approach column when the data have one, else the load.

    ``estcal diagnose`` offers both ``"load"`` and ``"approach"`` as candidates when the data carry approach
    directions (docs/effects.md): a joint may show either, or both (a heavy link on its load side, a light one
    left where the motor put it).
    """

    name = "backlash"
    BY = ("auto", "load", "approach")

    def __init__(self, robot, joints: Sequence[str] | None = None, by: str = "auto"):
        if by not in self.BY:
            raise ValueError(f"effect 'backlash': by must be one of {', '.join(self.BY)}, got {by!r}")
        self.by = by
        self.prefixes = ("backlash_approach",) if by == "approach" else ("backlash",)
        super().__init__(robot, joints)

    def options(self):
        return {} if self.by == "auto" else {"by": self.by}

    def context_keys(self):
        keys = [] if self.by == "load" else [f"approach_{j}" for j in self.joints]
        return keys if self.by == "approach" else ["payload"] + keys + [f"load_side_{j}" for j in self.joints]

    def features(self, robot, readings, q, theta, context):
        N = q.shape[0]
        keys = [None if self.by == "load" else _ctx(context, f"approach_{j}", N) for j in self.joints]
        sides = [_ctx(context, f"load_side_{j}", N) for j in self.joints]
        S = np.empty((N, 1, len(self.joints)))
        tau = None
        for i, (j, a, side) in enumerate(zip(self.joint_index, keys, sides)):
            if a is not None:
                S[:, 0, i] = -np.sign(a)
            elif self.by == "approach":
                # no record of the approach: either side is as likely, the expected correction is zero (±b_j)
                S[:, 0, i] = 0.0
            elif side is not None:
                S[:, 0, i] = np.sign(side)
            else:
                if tau is None:
                    tau = robot.gravity_torques(readings, theta, context)
                S[:, 0, i] = np.sign(tau[:, j])
        return S


class GearHarmonic(JointEffect):
    """Periodic transmission error: ``δq_j = Σ_k a_kj sin(k φ_j) + b_kj cos(k φ_j)``.

    ``φ_j = ρ_j · r_j`` with ``r_j`` the joint reading (rad) and ``ρ_j`` the gear
    ratio (``gear_ratio`` in the robot file, stored in ``robot.meta["gear_ratio"]``;
    1 when absent, i.e. harmonics of the joint angle). Using the reading rather
    than the corrected joint value keeps the correction independent of the other
    parameters. Parameters ``harmonic<k>_sin_<joint>`` (a) and
    ``harmonic<k>_cos_<joint>`` (b) in rad, for ``k in orders`` (default 1, 2, 3).
    Revolute joints only.
    """

    name = "gear_harmonic"
    allowed_types = ("revolute",)

    def __init__(self, robot, joints: Sequence[str] | None = None, orders: Sequence[int] = (1, 2, 3),
                 gear_ratio=None):
        super().__init__(robot, joints)
        self.orders = [int(k) for k in orders]
        if not self.orders or any(k < 1 for k in self.orders) or len(set(self.orders)) != len(self.orders):
            raise ValueError(f"effect 'gear_harmonic': orders must be distinct positive integers, got {orders}")
        self.prefixes = tuple(p for k in self.orders for p in (f"harmonic{k}_sin", f"harmonic{k}_cos"))
        meta = dict(robot.meta.get("gear_ratio", {}) or {})
        if gear_ratio is not None:
            meta.update(gear_ratio if isinstance(gear_ratio, dict) else {j: float(gear_ratio) for j in self.joints})
        self.gear_ratio = {j: float(meta.get(j, 1.0)) for j in self.joints}
        self._rho = np.array([self.gear_ratio[j] for j in self.joints])
        self._explicit_ratio = gear_ratio

    def options(self):
        d = {"orders": list(self.orders)}
        if self._explicit_ratio is not None:
            d["gear_ratio"] = dict(self.gear_ratio)
        return d

    def features(self, robot, readings, q, theta, context):
        phi = readings[:, self.joint_index] * self._rho  # (N, s)
        F = []
        for k in self.orders:
            F.append(np.sin(k * phi))
            F.append(np.cos(k * phi))
        return np.stack(F, 1)


class EncoderGain(JointEffect):
    """Encoder gain error: ``δq_j = g_j · r_j`` (``encgain_<joint>``, dimensionless).

    ``r_j`` is the joint reading; the effect duplicates the built-in ``gain_<frame>``
    parameters on purpose (a discrepancy model fitted without gains names it).
    """

    name = "encoder_gain"
    prefixes = ("encgain",)

    def features(self, robot, readings, q, theta, context):
        return readings[:, None, self.joint_index]


class Drift(JointEffect):
    """Slow joint-offset drift: ``δq_j = v_j · (t − t0)`` (``drift_<joint>``, rad/s or m/s).

    Needs the per-pose time ``t`` (s) in the dataset; ``t0`` (s, default 0) is the
    time at which the offsets are those of the geometric model.
    """

    name = "drift"
    prefixes = ("drift",)

    def __init__(self, robot, joints: Sequence[str] | None = None, t0: float = 0.0):
        super().__init__(robot, joints)
        self.t0 = float(t0)

    def options(self):
        return {"t0": self.t0}

    def context_keys(self):
        return ["t"]

    def features(self, robot, readings, q, theta, context):
        t = _ctx(context, "t", q.shape[0])
        if t is None:
            raise ValueError("effect 'drift' needs the time column 't' (s) in the dataset")
        return np.broadcast_to((t - self.t0)[:, None, None], (q.shape[0], 1, len(self.joints)))


class ThermalExpansion(Effect):
    """Uniform thermal expansion of the arm: ``δx = α · ΔT · (x − o)`` (``scope="arm"``)
    or of its links only: ``δx = α · ΔT · (f − o)`` (``scope="links"``).

    Applied to every measured point ``x`` — the tool origin and the markers —, so
    it acts on tool positions, full poses (position part; a uniform expansion
    leaves orientations unchanged), marker points and the link/plane/distance
    methods. ``o`` is the world position of frame 0 (``base_tx, base_ty, base_tz``):
    the base mount (world → frame 0) never expands. With ``scope="arm"`` all link
    lengths, the tool and the marker offsets scale by ``1 + α ΔT``; with
    ``scope="links"`` only the chain from frame 0 to the last joint frame ``f``
    (the flange) does, and the tool and markers, often on a separate
    thermally stable fixture, keep their size: every point moves by the flange's
    displacement ``αΔT (f − o)``. ``ΔT = temperature − T_ref``
    (°C, ``T_ref`` = ``reference``, default 20 °C) and ``α`` (``thermal_alpha``; ``thermal_alpha_links``
    for the links only)
    is in 1/K (steel ≈ 1.2e-5, aluminium ≈ 2.3e-5). Without a ``temperature``
    column the effect falls back to ``ΔT = t − t_reference`` (warm-up proxy; α
    then in 1/s); with neither it is zero.

    The derivative with respect to α is exact. The other parameters' point
    columns change by O(α ΔT) (the expanded point is not rigidly attached); for
    ``scope="arm"`` :meth:`correct_jacobian` makes them exact when the chain
    passes the pose Jacobian ``J`` to ``point_correction``; for ``scope="links"``
    (which would need the flange's parameter Jacobian) that relative 1e-4 term
    is neglected — it changes the convergence path of a Gauss–Newton step, not
    the fixed point.
    """

    name = "thermal_expansion"
    prefixes = ()

    SCOPES = ("arm", "links")

    def __init__(self, robot, joints: Sequence[str] | None = None, reference: float = 20.0,
                 t_reference: float = 0.0, scope: str = "arm"):
        if joints:
            raise ValueError("effect 'thermal_expansion' acts on the whole arm; it takes no joints")
        if scope not in self.SCOPES:
            raise ValueError(f"effect 'thermal_expansion': scope must be one of {self.SCOPES}, got {scope!r}")
        self.scope = scope
        self.robot_joints = list(robot.joint_names)
        self.joints = []
        self.joint_index = np.zeros(0, int)
        self.indices = None
        self.reference = float(reference)
        self.t_reference = float(t_reference)
        self._base_idx = robot.params.indices(["base_tx", "base_ty", "base_tz"])

    @property
    def param_names(self):
        # one name per form, so that both forms can be candidates of one model (the diagnosis's)
        return ["thermal_alpha"] if self.scope == "arm" else ["thermal_alpha_links"]

    @property
    def param_frames(self):
        return ["base"]

    def options(self):
        d = {"reference": self.reference, "t_reference": self.t_reference}
        if self.scope != "arm":
            d["scope"] = self.scope
        return d

    def context_keys(self):
        return ["temperature", "t"]

    def delta_T(self, context, N) -> np.ndarray:
        T = _ctx(context, "temperature", N)
        if T is not None:
            return T - self.reference
        t = _ctx(context, "t", N)
        if t is not None:
            return t - self.t_reference
        return np.zeros(N)

    def point_correction(self, robot, readings, points, theta, context, derivatives, J_points=None, J=None,
                         link_p=None):
        N = points.shape[0]
        o = np.asarray(theta, float)[self._base_idx]
        dT = self.delta_T(context, N)
        s = self.values(theta)[0] * dT  # (N,)
        if self.scope == "links":
            if link_p is None:
                raise ValueError("effect 'thermal_expansion' with scope='links' needs the link frames (link_p)")
            # frame 0 = end of the base link, flange = end of the last link before the tool
            arm = (link_p[:, -2] - link_p[:, 0])[:, None, :]  # (N, 1, 3), rigid: no undoing needed
            d = np.broadcast_to(s[:, None, None] * arm, points.shape)
            if not derivatives:
                return d, None
            return d, np.broadcast_to((dT[:, None, None] * arm)[..., None], points.shape + (1,))
        if not derivatives:
            return s[:, None, None] * (points - o), None
        # With derivatives the chain passes the already corrected points x' = x + s (x - o).
        rel = (points - o) / (1.0 + s)[:, None, None]
        if J_points is not None and J is not None:
            self.correct_jacobian(J_points, J, points, o, s)
        return s[:, None, None] * rel, (dT[:, None, None] * rel)[..., None]

    def correct_jacobian(self, J_points, J, points, o, s) -> None:
        """Make the other parameters' point columns exact (in place).

        The chain differentiates the corrected point ``x' = o + (1+s)(x − o)`` as if it
        were rigidly attached, giving ``v_i(x')``; the exact column is
        ``(1+s) v_i(x) − s ∂o/∂θ_i = v_i(x') + s (v_i(x') + ω_i × (o − x') − ∂o/∂θ_i)``,
        with ``ω_i`` the tool's angular velocity column (rows 3–5 of the pose Jacobian
        ``J``) and ``∂o/∂θ`` the unit columns of ``base_tx, base_ty, base_tz``. Used
        when the chain passes ``J``; otherwise the O(α ΔT) difference is neglected.
        """
        # every point at once, in one (N, k, 3, P) buffer: ω × d, + v(x'), − ∂o/∂θ, × s
        corr = cross_at(np.ascontiguousarray(J[:, None, 3:, :]), (o - points)[..., None], 2)
        np.add(J_points, corr, out=corr)
        corr[:, :, [0, 1, 2], self._base_idx] -= 1.0
        np.multiply(s[:, None, None, None], corr, out=corr)
        J_points += corr


def across_axis_moments(robot, readings, theta=None, context=None):
    """``(M⊥ (N, n, 3) N·m, o (N, n, 3) m)``: the gravity moment about every joint's origin ``o_j`` across
    its world axis ``a_j``, ``M⊥_j = M_j − (a_jᵀ M_j) a_j`` (:meth:`SerialRobot.gravity_moments` on the rigid
    frames), and the origins — the load :class:`LinkTilt` deflects under, and what the diagnosis screens its
    candidates by."""
    kin = robot.rigid_kinematics(readings, theta)
    M = robot.gravity_moments(readings, theta, context, kin=kin)
    a = kin.joint_axis
    return M - np.sum(M * a, -1, keepdims=True) * a, kin.joint_origin


class LinkTilt(Effect):
    """Tilt of a joint's bearing and link under the gravity moment across its axis:
    ``δx = Σ_j t_j · M⊥_j × (x − o_j)`` for every measured point ``x``.

    :class:`JointCompliance` deflects a joint about its own axis under the torque along it; the
    same gravity load has a moment *across* the axis, ``M⊥_j = M_j − (a_jᵀ M_j) a_j``
    (:meth:`SerialRobot.gravity_moments`: the moment about the joint origin ``o_j`` of the links it
    moves and the payload; ``a_j`` its world axis), which the bearing, the gear's output stage and
    the link carrying the joint resist with a finite stiffness: everything beyond the joint turns
    by the small rotation ``t_j M⊥_j`` about ``o_j``. It is the two across-axis rotations of
    Klimchik's virtual-joint elastostatic model (Klimchik et al. 2012, the 6×6 compliance of a link
    and its joint, reduced to one isotropic bending compliance per joint), the part a joint-space
    effect cannot express: the rotation is about an axis the joint does not have, so no joint value
    and no constant geometric parameter reproduces it — its direction follows the load, which turns
    with the posture. For a prismatic joint (a lift column) ``M⊥`` is the column's bending moment.

    ``t_j`` (``tilt_<joint>``) is in rad/(N·m), ≥ 0 physically. The loads are evaluated on the rigid
    model at the current parameters (their own dependence on the geometry is second order, as for
    :class:`JointCompliance`); the derivative with respect to ``t`` is exact. Applied to every measured
    point — the tool origin and the markers — so it acts on every measurement method; a full pose's
    orientation is not turned (the points, not the frame, carry the effect).
    """

    name = "link_tilt"
    prefixes = ("tilt",)

    def context_keys(self):
        return ["payload"]

    def loads(self, robot, readings, theta, context):
        """``(M⊥ (N, s, 3) N·m, o (N, s, 3) m)`` of the selected joints (:func:`across_axis_moments`)."""
        Mp, o = across_axis_moments(robot, readings, theta, context)
        return Mp[:, self.joint_index], o[:, self.joint_index]

    def point_correction(self, robot, readings, points, theta, context, derivatives, J_points=None, J=None):
        if not len(self.joints):
            return np.zeros_like(points), (np.zeros(points.shape + (0,)) if derivatives else None)
        Mp, o = self.loads(robot, readings, theta, context)
        t = self.values(theta)
        phi = np.einsum("nsi,s->ni", Mp, t)  # the total small rotation (N, 3)
        b = np.einsum("nsi,s->ni", cross(Mp, o), t)  # Σ t_j M⊥_j × o_j
        x = points
        if derivatives:
            # The chain passes the already corrected points x' = x + φ × x − b. Solve (I + [φ]×) x = v with
            # v = x' + b by its closed form x = (v − φ × v + φ (φ·v)) / (1 + |φ|²) — (I + K)(I − K + φφᵀ) =
            # (1 + |φ|²) I for K = [φ]×, as K φ = 0 and K² = φφᵀ − |φ|² I —, so that the derivative columns
            # are those of the uncorrected points (exact, not O(t²)).
            v, P = points + b[:, None, :], phi[:, None, :]
            x = (v - cross(P, v) + P * np.sum(P * v, -1, keepdims=True)) / (1.0 + np.sum(P * P, -1, keepdims=True))
        d = cross(phi[:, None, :], x) - b[:, None, :]
        if not derivatives:
            return d, None
        if J_points is not None and J is not None:
            self.correct_jacobian(J_points, J, d, phi)
        rel = x[:, :, None, :] - o[:, None, :, :]  # (N, K, s, 3)
        F = cross(Mp[:, None], rel)  # (N, K, s, 3): the point's motion per unit t_j
        return d, np.ascontiguousarray(F.transpose(0, 1, 3, 2))

    @staticmethod
    def correct_jacobian(J_points, J, d, phi) -> None:
        """Make the other parameters' point columns those of the tilted point (in place).

        The chain differentiates the tilted point ``x' = x + d`` as if it were rigidly attached, giving
        ``v_i(x') = v_i(x) + ω_i × d``; the tilted point moves by ``(I + [φ]×) v_i(x)``. So the exact
        column is ``(I + [φ]×)(v_i(x') − ω_i × d)`` with ``ω_i`` the tool's angular velocity column (rows
        3–5 of the pose Jacobian ``J``) — exact for every parameter the loads do not depend on (the other
        effects'); for the geometric ones the loads' own variation is second order and neglected.
        """
        # every point at once on the (N, k, 3, P) columns as they are: v = v(x') − ω × d, then v + φ × v
        v = cross_at(np.ascontiguousarray(J[:, None, 3:, :]), d[..., None], 2)
        np.subtract(J_points, v, out=v)
        np.add(v, cross_at(phi[:, None, :, None], v, 2), out=J_points)


for _cls in (JointCompliance, Backlash, GearHarmonic, EncoderGain, ThermalExpansion, Drift, LinkTilt):
    register_effect(_cls.name, _cls, overwrite=True)
