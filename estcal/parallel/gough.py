r"""Gough–Stewart platform with SS legs: model, inverse and forward kinematics.

Model (Daney 1998, ``shared/reference/daney.md`` §1): leg ``k`` joins the base
point ``a_k`` (base frame) to the platform point ``b_k`` (platform frame). For a
platform pose ``(P, R)`` (position of the platform frame origin C and its
rotation, both in the base frame) the physical leg length is

.. math::  L_k = \lVert P + R\,b_k - a_k \rVert

and the leg sensor reads :math:`\rho_k = L_k - \Delta\rho_k` (the true length
is :math:`\rho_k + \Delta\rho_k`). *Model 42* estimates ``a_k, b_k, Δρ_k`` for
the six legs, *Model 36* only ``a_k, b_k`` (offsets known).

Parameter names (stable, 1-based leg index, SI units):
``a{k}_x, a{k}_y, a{k}_z, b{k}_x, b{k}_y, b{k}_z, drho_{k}``, ordered leg by
leg, 7 per leg.

Pose perturbations follow the estcal convention: ``P <- P + dp`` and
``R <- exp([δ]x) R`` (world/base-frame small rotation), columns ordered
``(dx, dy, dz, δx, δy, δz)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from estcal.base.errors import InputError
from estcal.base.textinput import check_input_file, read_json, read_yaml
from estcal.kinematics.parameters import ParameterVector

from ._rot import euler_zyx_to_matrix, make_T, matrix_to_euler_zyx, so3_exp, so3_log

__all__ = [
    "GoughPlatform",
    "Workspace",
    "FKResult",
    "left_hand",
    "load_gough",
    "is_gough_file",
    "gough_parameter_names",
    "split_pose",
]

N_LEGS = 6
_COORD = ("x", "y", "z")


def gough_parameter_names(n_legs: int = N_LEGS) -> list[str]:
    """Stable names ``a1_x … b1_z, drho_1, a2_x …`` (7 per leg)."""
    names: list[str] = []
    for k in range(1, n_legs + 1):
        names += [f"a{k}_{c}" for c in _COORD] + [f"b{k}_{c}" for c in _COORD] + [f"drho_{k}"]
    return names


def split_pose(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N,3) and rotations (N,3,3) from transforms (N,4,4) or (4,4)."""
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4):
        raise InputError(f"expected homogeneous transforms (...,4,4), got shape {T.shape}")
    T = T.reshape(-1, 4, 4)
    return T[:, :3, 3].copy(), T[:, :3, :3].copy()


@dataclass
class Workspace:
    """Box of platform positions and bound on ZYX Euler angles (SI).

    A pose is in the workspace when ``position_min <= P <= position_max``
    component-wise, every ZYX Euler angle ``(ψ, θ, φ)`` satisfies
    ``|angle| <= max_angle`` and every physical leg length lies within the
    robot's leg-length limits.
    """

    position_min: np.ndarray
    position_max: np.ndarray
    max_angle: float  # rad, bound on each ZYX Euler angle

    def __post_init__(self) -> None:
        self.position_min = np.asarray(self.position_min, float).reshape(3)
        self.position_max = np.asarray(self.position_max, float).reshape(3)
        if np.any(self.position_max <= self.position_min):
            raise InputError("workspace: position_max must exceed position_min on every axis")

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.position_min + self.position_max)

    def to_dict(self) -> dict:
        return {
            "position_min": self.position_min.tolist(),
            "position_max": self.position_max.tolist(),
            "max_angle_deg": float(np.degrees(self.max_angle)),
        }


@dataclass
class FKResult:
    """Forward-kinematics solutions for N leg-length vectors.

    Attributes
    ----------
    T : (N, 4, 4) platform poses; rows with ``success == False`` are NaN.
    success : (N,) bool — converged to a pose in the requested assembly mode
        (platform above the base), away from a singularity.
    residual : (N,) max |ρ(pose) − ρ_target| in m (at the best iterate).
    n_solutions : (N,) number of distinct valid poses found from the starts;
        > 1 means the lengths admit several assembly modes near the starts
        and the one closest to the first start was returned (``ambiguous``).
    iterations : (N,) Newton iterations used by the returned start.
    """

    T: np.ndarray
    success: np.ndarray
    residual: np.ndarray
    n_solutions: np.ndarray
    iterations: np.ndarray

    @property
    def ambiguous(self) -> np.ndarray:
        return self.n_solutions > 1

    @property
    def n_failed(self) -> int:
        return int(np.sum(~self.success))

    def to_dict(self) -> dict:
        return {
            "n_poses": int(len(self.success)),
            "n_failed": self.n_failed,
            "n_ambiguous": int(np.sum(self.ambiguous)),
            "max_residual_m": float(np.nanmax(self.residual)) if len(self.residual) else 0.0,
        }


@dataclass
class GoughPlatform:
    """6-leg Gough–Stewart platform with SS legs and leg-sensor offsets.

    Parameters
    ----------
    a : (6, 3) base attachment points ``a_k`` in the base frame [m].
    b : (6, 3) platform attachment points ``b_k`` in the platform frame [m].
    drho : (6,) sensor offsets ``Δρ_k`` [m]; physical length = reading + ``Δρ_k``.
    length_limits : (6, 2) min/max *physical* leg length ``‖A_k B_k‖`` [m].
    home : (4, 4) reference platform pose (default start of the FK solver).
    workspace : :class:`Workspace` used by the pose generators, optional.
    name : label.
    """

    a: np.ndarray
    b: np.ndarray
    drho: np.ndarray
    length_limits: np.ndarray
    home: np.ndarray
    workspace: Workspace | None = None
    name: str = "gough"
    units_note: str = field(default="SI (m, rad)", repr=False)

    def __post_init__(self) -> None:
        self.a = np.array(self.a, float).reshape(N_LEGS, 3)
        self.b = np.array(self.b, float).reshape(N_LEGS, 3)
        self.drho = np.array(self.drho, float).reshape(N_LEGS)
        lim = np.asarray(self.length_limits, float)
        if lim.shape == (2,):
            lim = np.tile(lim, (N_LEGS, 1))
        if lim.shape != (N_LEGS, 2) or np.any(lim[:, 1] <= lim[:, 0]):
            raise InputError(f"{self.name}: leg_length_limits must be [min, max] or 6 such pairs with max > min")
        self.length_limits = lim
        self.home = np.asarray(self.home, float).reshape(4, 4)

    # ---------------------------------------------------------- parameters
    @property
    def theta(self) -> np.ndarray:
        """Flat parameter values in :func:`gough_parameter_names` order (42,)."""
        return np.concatenate([self.a, self.b, self.drho[:, None]], axis=1).reshape(-1)

    @property
    def params(self) -> ParameterVector:
        """All 42 parameters (Model 42), as ``SerialRobot.params`` (for the shared estimators)."""
        return self.parameter_vector(42)

    def parameter_vector(self, model: int = 42) -> ParameterVector:
        """Named parameters; ``model=36`` fixes the offsets ``drho_k``."""
        if model not in (36, 42):
            raise InputError(f"model must be 36 or 42, got {model!r}")
        names = gough_parameter_names()
        kinds = ["offset" if n.startswith("drho") else "geometric" for n in names]
        frames = [f"leg{i // 7 + 1}" for i in range(len(names))]
        free = np.array([model == 42 or not n.startswith("drho") for n in names])
        return ParameterVector(names, self.theta, free, kinds, frames)

    def with_theta(self, theta: np.ndarray) -> "GoughPlatform":
        """Copy with parameters replaced by a full (42,) vector."""
        th = np.asarray(theta, float).reshape(N_LEGS, 7)
        return GoughPlatform(th[:, 0:3], th[:, 3:6], th[:, 6], self.length_limits.copy(),
                             self.home.copy(), self.workspace, self.name)

    # ---------------------------------------------------------- IK
    @staticmethod
    def _unpack(theta: np.ndarray | None, base: "GoughPlatform"):
        if theta is None:
            return base.a, base.b, base.drho
        th = np.asarray(theta, float).reshape(N_LEGS, 7)
        return th[:, 0:3], th[:, 3:6], th[:, 6]

    def leg_vectors(self, P: np.ndarray, R: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """``v_ik = P_i + R_i b_k − a_k`` (N, 6, 3), the vector from A_k to B_k."""
        a, b, _ = self._unpack(theta, self)
        P = np.asarray(P, float).reshape(-1, 3)
        R = np.asarray(R, float).reshape(-1, 3, 3)
        return P[:, None, :] + np.einsum("nij,kj->nki", R, b) - a[None]

    def leg_lengths(self, T: np.ndarray, theta: np.ndarray | None = None, physical: bool = False) -> np.ndarray:
        """Sensor readings ``ρ_ik = ‖P_i + R_i b_k − a_k‖ − Δρ_k`` (N, 6) [m].

        With ``physical=True`` return the physical lengths ``‖A_k B_k‖`` instead.
        """
        P, R = split_pose(T)
        _, _, drho = self._unpack(theta, self)
        L = np.linalg.norm(self.leg_vectors(P, R, theta), axis=-1)
        return L if physical else L - drho[None]

    def leg_jacobians(self, T: np.ndarray, theta: np.ndarray | None = None):
        r"""Analytic Jacobians of the readings ρ (N, 6).

        With ``u_k = v_k/‖v_k‖`` the unit leg vector and ``c_k = R b_k``:

        * ``∂ρ_k/∂a_k = −u_kᵀ``, ``∂ρ_k/∂b_k = u_kᵀ R``, ``∂ρ_k/∂Δρ_k = −1``
          (and zero w.r.t. the other legs' parameters);
        * ``∂ρ_k/∂(dp, δ) = [u_kᵀ, (c_k × u_k)ᵀ]`` — the classical Gough
          inverse Jacobian, since ``d(R b) = δ × R b``.

        Returns
        -------
        J_theta : (N, 6, 42) derivative w.r.t. the parameter vector.
        J_pose : (N, 6, 6) derivative w.r.t. ``(dp, δ)``.
        """
        P, R = split_pose(T)
        a, b, _ = self._unpack(theta, self)
        v = self.leg_vectors(P, R, theta)
        u = v / np.linalg.norm(v, axis=-1, keepdims=True)
        c = np.einsum("nij,kj->nki", R, b)
        n = len(P)
        J_theta = np.zeros((n, N_LEGS, N_LEGS, 7))
        leg = np.arange(N_LEGS)
        J_theta[:, leg, leg, 0:3] = -u
        J_theta[:, leg, leg, 3:6] = np.einsum("nki,nij->nkj", u, R)
        J_theta[:, leg, leg, 6] = -1.0
        J_pose = np.concatenate([u, np.cross(c, u)], axis=-1)
        return J_theta.reshape(n, N_LEGS, 7 * N_LEGS), J_pose

    def in_limits(self, T: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """(N,) True when every physical leg length is within its limits."""
        L = self.leg_lengths(T, theta, physical=True)
        return np.all((L >= self.length_limits[:, 0]) & (L <= self.length_limits[:, 1]), axis=-1)

    def in_workspace(self, T: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """(N,) pose inside the workspace box/angle bound and leg limits."""
        ok = self.in_limits(T, theta)
        if self.workspace is None:
            return ok
        P, R = split_pose(T)
        ws = self.workspace
        ok &= np.all((P >= ws.position_min) & (P <= ws.position_max), axis=-1)
        ok &= np.all(np.abs(matrix_to_euler_zyx(R)) <= ws.max_angle, axis=-1)
        return ok

    # ---------------------------------------------------------- FK
    def forward_kinematics(
        self,
        rho: np.ndarray,
        theta: np.ndarray | None = None,
        guess: np.ndarray | None = None,
        n_starts: int = 6,
        tol: float = 1e-10,
        max_iter: int = 60,
        max_condition: float = 1e8,
        seed: int = 0,
    ) -> FKResult:
        r"""Platform poses from sensor readings by damped Newton, several starts.

        Solves ``ρ(P, R) = ρ_target`` for each row with a Levenberg–Marquardt
        iteration on the 6 pose unknowns (small-rotation update
        ``R <- exp([δ]x) R``), vectorised over rows and starts. Starts: the
        ``guess`` (per-row poses, optional), the ``home`` pose and
        ``n_starts − 1`` poses perturbed around home (fixed ``seed``).

        A start is *valid* when it reaches ``max|ρ − ρ_target| < tol``, keeps
        the platform above the base (every leg points upwards, the assembly
        mode of the home pose) and the inverse Jacobian condition number is
        below ``max_condition``. A row succeeds when some start is valid; the
        valid pose closest to the first start is returned and distinct valid
        poses are counted in ``n_solutions``. Rows with no valid start get a NaN
        pose and ``success=False`` — no pose is reported that does not
        reproduce the lengths.
        """
        rho = np.atleast_2d(np.asarray(rho, float))
        if rho.shape[-1] != N_LEGS:
            raise InputError(f"rho must have 6 columns, got shape {rho.shape}")
        n = len(rho)
        starts = self._fk_starts(n, guess, n_starts, seed)
        S = len(starts)
        T0 = np.concatenate([np.asarray(s, float) for s in starts], axis=0)  # (S*n,4,4)
        target = np.tile(rho, (S, 1))
        P, R = split_pose(T0)
        lam = np.full(len(P), 1e-3)
        r = self.leg_lengths(make_T(P, R), theta) - target
        cost = np.sum(r**2, axis=1)
        it = np.zeros(len(P), int)
        active = np.isfinite(cost)
        for _ in range(max_iter):
            if not np.any(active):
                break
            idx = np.flatnonzero(active)
            T = make_T(P[idx], R[idx])
            _, J = self.leg_jacobians(T, theta)
            H = np.einsum("nki,nkj->nij", J, J)
            g = np.einsum("nki,nk->ni", J, r[idx])
            Hd = H + lam[idx, None, None] * (np.eye(6) + np.eye(6) * np.diagonal(H, axis1=1, axis2=2)[:, :, None])
            try:
                step = -np.linalg.solve(Hd, g[..., None])[..., 0]
            except np.linalg.LinAlgError:
                step = -np.linalg.lstsq(Hd.reshape(-1, 6), g.reshape(-1), rcond=None)[0].reshape(-1, 6)
            Pn = P[idx] + step[:, :3]
            Rn = so3_exp(step[:, 3:]) @ R[idx]
            rn = self.leg_lengths(make_T(Pn, Rn), theta) - target[idx]
            cn = np.sum(rn**2, axis=1)
            better = np.isfinite(cn) & (cn < cost[idx])
            bi = idx[better]
            P[bi], R[bi], r[bi], cost[bi] = Pn[better], Rn[better], rn[better], cn[better]
            lam[bi] = np.maximum(lam[bi] / 10.0, 1e-12)
            wi = idx[~better]
            lam[wi] = lam[wi] * 10.0
            it[idx] += 1
            done = (np.max(np.abs(r[idx]), axis=1) < tol) | (lam[idx] > 1e10)
            active[idx[done]] = False
        Tall = make_T(P, R)
        res = np.max(np.abs(r), axis=1)
        v = self.leg_vectors(P, R, theta)
        upward = np.all(v[..., 2] > 0, axis=-1)
        _, J = self.leg_jacobians(Tall, theta)
        sv = np.linalg.svd(J, compute_uv=False)
        cond = sv[:, 0] / np.maximum(sv[:, -1], 1e-300)
        valid = (res < tol) & upward & (cond < max_condition)
        valid = valid.reshape(S, n)
        Tall = Tall.reshape(S, n, 4, 4)
        res = res.reshape(S, n)
        it = it.reshape(S, n)
        first = np.argmax(valid, axis=0)  # first valid start (starts ordered by preference)
        success = np.any(valid, axis=0)
        cols = np.arange(n)
        T_out = Tall[first, cols].copy()
        T_out[~success] = np.nan
        best_res = np.where(success, res[first, cols], np.min(res, axis=0))
        return FKResult(T_out, success, best_res, _count_distinct(Tall, valid), it[first, cols])

    def _fk_starts(self, n: int, guess, n_starts: int, seed: int) -> list:
        """FK starting poses, each (n, 4, 4), by preference: the guess, home, perturbed homes."""
        starts = []
        if guess is not None:
            g = np.asarray(guess, float)
            starts.append(np.broadcast_to(g, (n, 4, 4)) if g.shape == (4, 4) else g.reshape(n, 4, 4))
        starts.append(np.broadcast_to(self.home, (n, 4, 4)))
        rng = np.random.default_rng(seed)
        if self.workspace is not None:
            scale = 0.25 * float(np.min(self.workspace.position_max - self.workspace.position_min))
        else:
            scale = 0.1 * float(np.mean(np.linalg.norm(self.a, axis=1)))
        Ph, Rh = split_pose(self.home)
        for _ in range(max(0, n_starts - 1)):
            dp = rng.uniform(-scale, scale, 3)
            dw = rng.uniform(-0.25, 0.25, 3)
            starts.append(np.broadcast_to(make_T(Ph[0] + dp, so3_exp(dw) @ Rh[0]), (n, 4, 4)))
        return starts

    # ---------------------------------------------------------- IO
    def to_dict(self, length_unit: str = "m") -> dict:
        """Robot-file dictionary (``type: gough``) in ``length_unit`` (m/cm/mm)."""
        s = 1.0 / _UNIT[length_unit]
        out: dict[str, Any] = {
            "estcal_robot": 1,
            "type": "gough",
            "name": self.name,
            "length_unit": length_unit,
            "base_points": (self.a * s).tolist(),
            "platform_points": (self.b * s).tolist(),
            "leg_offsets": (self.drho * s).tolist(),
            "leg_length_limits": (self.length_limits * s).tolist(),
            "home": {"position": (self.home[:3, 3] * s).tolist(),
                     "euler_zyx_deg": np.degrees(matrix_to_euler_zyx(self.home[:3, :3])).tolist()},
        }
        if self.workspace is not None:
            ws = self.workspace
            out["workspace"] = {"position_min": (ws.position_min * s).tolist(),
                                "position_max": (ws.position_max * s).tolist(),
                                "max_angle_deg": float(np.degrees(ws.max_angle))}
        return out

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str = "<dict>") -> "GoughPlatform":
        """Build from a robot-file dictionary; see :func:`load_gough`."""
        if str(d.get("type", "")).lower() != "gough":
            raise InputError(f"{source}: not a Gough robot file (expected `type: gough`, got {d.get('type')!r})")
        units = d.get("units")
        unit = str(d.get("length_unit", units.get("length", "m") if isinstance(units, Mapping) else "m"))
        if unit not in _UNIT:
            raise InputError(f"{source}: length_unit must be one of {sorted(_UNIT)}, got {unit!r}")
        s = _UNIT[unit]

        def arr(key, shape, default=None):
            if key not in d:
                if default is not None:
                    return default
                raise InputError(f"{source}: missing key {key!r}")
            x = np.asarray(d[key], float)
            if x.shape != shape and not (shape == (6,) and x.shape == ()):
                raise InputError(f"{source}: {key!r} must have shape {shape}, got {x.shape}")
            return np.broadcast_to(x, shape) * s

        a = arr("base_points", (6, 3))
        b = arr("platform_points", (6, 3))
        drho = arr("leg_offsets", (6,), np.zeros(6))
        lim = np.asarray(d.get("leg_length_limits", [0.0, np.inf]), float) * s
        home_d = d.get("home")
        if home_d is None:
            # default home: platform centred above the base, legs at mid-stroke
            # (or twice the base radius when the limits are open)
            lim2 = np.broadcast_to(lim, (6, 2)) if lim.shape == (2,) else lim
            if np.all(np.isfinite(lim2)):
                mid = float(np.mean(lim2))
            else:
                mid = 2.0 * float(np.max(np.linalg.norm(a, axis=1)))
            r_off = float(np.linalg.norm((a - b)[:, :2], axis=1).mean())
            h = np.sqrt(max(mid**2 - r_off**2, 0.25 * mid**2))
            home = make_T(np.array([0, 0, h]), np.eye(3))
        else:
            pos = np.asarray(home_d.get("position"), float) * s
            ang = np.radians(np.asarray(home_d.get("euler_zyx_deg", [0, 0, 0]), float))
            home = make_T(pos, euler_zyx_to_matrix(ang))
        ws = None
        if "workspace" in d:
            w = d["workspace"]
            try:
                ws = Workspace(np.asarray(w["position_min"], float) * s, np.asarray(w["position_max"], float) * s,
                               np.radians(float(w.get("max_angle_deg", 180.0))))
            except KeyError as e:
                raise InputError(f"{source}: workspace needs key {e.args[0]!r}") from None
        return cls(a, b, drho, lim, home, ws, str(d.get("name", "gough")))


def _count_distinct(Tall: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Number of distinct valid poses per row among the starts, ``Tall`` (S, n, 4, 4) and ``valid``
    (S, n): poses closer than 1e-6 m and 1e-6 rad are the same solution."""
    n_sol = np.zeros(Tall.shape[1], int)
    reps: list[np.ndarray] = []
    for s in range(Tall.shape[0]):
        Ts = Tall[s]
        new = valid[s].copy()
        for rep in reps:
            same = (np.linalg.norm(Ts[:, :3, 3] - rep[:, :3, 3], axis=-1) < 1e-6) & (
                np.linalg.norm(so3_log(Ts[:, :3, :3] @ np.swapaxes(rep[:, :3, :3], -1, -2)), axis=-1) < 1e-6
            )
            new &= ~same
        n_sol += new
        reps.append(np.where(new[:, None, None], Ts, np.nan))
    return n_sol


_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001}

# INRIA "Left Hand" (Daney 1998, table of §5), cm.
_LEFT_HAND_A_CM = [[-9.7, 9.1, 0.0], [9.7, 9.1, 0.0], [12.76, 3.9, 0.0],
                   [3.0, -13.0, 0.0], [-3.0, -13.0, 0.0], [-12.76, 3.9, 0.0]]
_LEFT_HAND_B_CM = [[-3.0, 7.3, 0.0], [3.0, 7.3, 0.0], [7.822, -1.052, 0.0],
                   [4.822, -6.248, 0.0], [-4.822, -6.248, 0.0], [-7.822, -1.052, 0.0]]


def left_hand() -> GoughPlatform:
    """The INRIA "Left Hand" of Daney (1998), converted from cm to m.

    Attachment points and Δρ = 15.25 cm are the paper's. The paper gives no
    leg-length limits, home pose or workspace; the values below are *our*
    choice (documented in ``docs/parallel.md``): physical leg length in
    [16, 26] cm, home 21 cm above the base, platform centre in the box
    x, y ∈ [−4, 4] cm, z ∈ [16, 26] cm, every ZYX Euler angle within ±20°.
    """
    d = {
        "type": "gough",
        "name": "left_hand",
        "length_unit": "cm",
        "base_points": _LEFT_HAND_A_CM,
        "platform_points": _LEFT_HAND_B_CM,
        "leg_offsets": [15.25] * 6,
        "leg_length_limits": [16.0, 26.0],
        "home": {"position": [0.0, 0.0, 21.0], "euler_zyx_deg": [0.0, 0.0, 0.0]},
        "workspace": {"position_min": [-4.0, -4.0, 16.0], "position_max": [4.0, 4.0, 26.0],
                      "max_angle_deg": 20.0},
    }
    return GoughPlatform.from_dict(d, "left_hand")


def _read_mapping(path: Path) -> dict:
    d = read_json(path, "robot") if path.suffix.lower() == ".json" else read_yaml(path, "robot")
    if not isinstance(d, dict):
        raise InputError(f"{path}: expected a mapping at the top level")
    return d


def is_gough_file(path: str | Path) -> bool:
    """True when ``path`` is a YAML/JSON robot file with ``type: gough``
    (or the built-in name ``left_hand``)."""
    if str(path) in BUILTINS:
        return True
    p = Path(path)
    if not p.is_file() or p.suffix.lower() not in (".yaml", ".yml", ".json"):
        return False
    try:
        d = _read_mapping(p)
    except Exception:
        return False
    return str(d.get("type", "")).lower() == "gough"


BUILTINS = {"left_hand": left_hand}


def load_gough(src: str | Path | Mapping[str, Any]) -> GoughPlatform:
    """Load a Gough platform from a built-in name, a YAML/JSON file or a dict.

    Robot file keys (lengths in ``length_unit``: ``m`` (default), ``cm``, ``mm``)::

        estcal_robot: 1                            # optional, as the serial robot files
        type: gough
        name: left_hand
        length_unit: cm                            # or units: {length: cm}
        base_points: [[x, y, z], ... 6 rows]       # a_k, base frame
        platform_points: [[x, y, z], ... 6 rows]   # b_k, platform frame
        leg_offsets: [15.25, ...]                  # Δρ_k (or one scalar)
        leg_length_limits: [16, 26]                # physical length, or 6 pairs
        home: {position: [0, 0, 21], euler_zyx_deg: [0, 0, 0]}   # optional
        workspace: {position_min: [...], position_max: [...], max_angle_deg: 20}  # optional
    """
    if isinstance(src, Mapping):
        return GoughPlatform.from_dict(src)
    if str(src) in BUILTINS:
        return BUILTINS[str(src)]()
    p = check_input_file(src, "Gough robot")
    return GoughPlatform.from_dict(_read_mapping(p), str(p))
