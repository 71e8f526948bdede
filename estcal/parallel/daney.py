r"""Daney's leg-mobility-constraint calibration of a Gough platform (linear, per leg).

Reference: D. Daney, "Mobility constraints on the legs of a parallel robot to
improve the kinematic calibration", Braunschweig 1998 (digest:
``shared/reference/daney.md``; equation numbers are the paper's).

Clamping leg ``k`` so that its direction and/or length stays constant over a
set of measured platform poses ``(P_i, R_i)`` makes the loop equation of that
leg linear in its attachment points, so each leg is calibrated by ordinary
linear least squares, without initial guess and independently of the others:

* **Type I** (fixed direction, method 3.2, Model 36): from (4),
  ``(P_i + R_i b − a)/L_i = (P_{i+1} + R_{i+1} b − a)/L_{i+1}`` with the
  physical lengths ``L_i = ρ_i + Δρ`` (offset known). Clearing denominators:

  .. math:: (L_i R_{i+1} - L_{i+1} R_i)\,b + (L_{i+1} - L_i)\,a
            = L_{i+1} P_i - L_i P_{i+1}

  — system (5)–(7) with the a-block sign derived from (4) (the printed
  ``(ρ_i − ρ_{i+1}) I`` is inconsistent with (4), see the digest §3).
* **Type II** (fixed direction and length, 3.3.1): the point ``B_k`` is fixed,
  (9)–(12): ``(R_{i+1} − R_i) b = P_i − P_{i+1}``.
* **Type III** (fixed length, 3.3.2): with ``V_i = P_i + R_i b``, (13)–(17):
  ``(V_{i+1} − V_i)ᵀ a = ½(‖V_{i+1}‖² − ‖V_i‖²)``.
* **Offset** (3.3.3), (18)–(19): ``Δρ = ‖P + R b − a‖ − ρ`` (averaged over
  the poses given).

All solvers are batched: inputs carry leading dimensions ``(S, N, ...)`` for
S independent pose sets of N poses; the least-squares problems are solved by
batched QR.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from estcal.base.errors import InputError

from ._rot import euler_zyx_to_matrix, make_T, matrix_to_euler_zyx
from .gough import GoughPlatform, split_pose

__all__ = [
    "type1_system",
    "type2_system",
    "type3_system",
    "batched_lstsq",
    "solve_type1",
    "solve_type2",
    "solve_type3",
    "solve_offset",
    "generate_random_poses",
    "generate_type1",
    "generate_type2",
    "generate_type3",
    "add_uniform_noise",
    "LegDaneyResult",
    "calibrate_leg_daney",
    "daney_initial_theta",
]


# ---------------------------------------------------------------- linear systems
def type1_system(P: np.ndarray, R: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Matrix M (…, 3(N−1), 6) and vector (…, 3(N−1)) of (5)–(6), unknowns ``[b; a]``.

    ``L`` are the *physical* lengths of the clamped leg (reading + offset).
    """
    P, R, L = np.asarray(P, float), np.asarray(R, float), np.asarray(L, float)
    Li, Lj = L[..., :-1, None, None], L[..., 1:, None, None]
    Bb = Li * R[..., 1:, :, :] - Lj * R[..., :-1, :, :]
    Ba = (Lj - Li) * np.eye(3)
    Ba = np.broadcast_to(Ba, Bb.shape)
    M = np.concatenate([Bb, Ba], axis=-1)  # (..., N-1, 3, 6)
    rhs = Lj[..., 0] * P[..., :-1, :] - Li[..., 0] * P[..., 1:, :]
    sh = M.shape[:-3]
    return M.reshape(sh + (-1, 6)), rhs.reshape(sh + (-1,))


def type2_system(P: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A (…, 3(N−1), 3) and B (…, 3(N−1)) of (10)–(11), unknown ``b``."""
    P, R = np.asarray(P, float), np.asarray(R, float)
    A = R[..., 1:, :, :] - R[..., :-1, :, :]
    B = P[..., :-1, :] - P[..., 1:, :]
    sh = A.shape[:-3]
    return A.reshape(sh + (-1, 3)), B.reshape(sh + (-1,))


def type3_system(P: np.ndarray, R: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """C (…, N−1, 3) and D (…, N−1) of (15)–(16), unknown ``a``; ``b`` (…, 3)."""
    P, R, b = np.asarray(P, float), np.asarray(R, float), np.asarray(b, float)
    V = P + np.einsum("...ij,...j->...i", R, b[..., None, :])
    C = V[..., 1:, :] - V[..., :-1, :]
    sq = np.sum(V**2, axis=-1)
    D = 0.5 * (sq[..., 1:] - sq[..., :-1])
    return C, D


def batched_lstsq(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares solutions of stacked systems ``A x ≈ y`` by QR.

    Returns ``x`` (…, p) and the condition number of each ``A`` (…,), from the
    singular values. Rank-deficient systems give NaN solutions (never a
    silently wrong one).
    """
    A, y = np.asarray(A, float), np.asarray(y, float)
    finite = np.isfinite(A).all(axis=(-2, -1)) & np.isfinite(y).all(axis=-1)
    if not finite.all():
        A = np.where(finite[..., None, None], A, np.eye(*A.shape[-2:]))
        y = np.where(finite[..., None], y, 0.0)
    Q, Rm = np.linalg.qr(A)
    qty = np.einsum("...ji,...j->...i", Q, y)
    sv = np.linalg.svd(A, compute_uv=False)
    cond = sv[..., 0] / np.maximum(sv[..., -1], 1e-300)
    cond = np.where(finite, cond, np.inf)
    bad = cond > 1e13
    Rs = np.where(bad[..., None, None], np.eye(Rm.shape[-1]), Rm)
    x = np.linalg.solve(Rs, qty[..., None])[..., 0]
    x[bad] = np.nan
    return x, cond


def solve_type1(P, R, L):
    """Method 3.2: ``(b, a, cond)`` from Type I poses; physical lengths ``L``. Needs N ≥ 3."""
    if np.shape(L)[-1] < 3:
        raise InputError("method 3.2 needs at least 3 Type I poses")
    M, y = type1_system(P, R, L)
    x, cond = batched_lstsq(M, y)
    return x[..., :3], x[..., 3:], cond


def solve_type2(P, R):
    """Method 3.3.1: ``(b, cond)`` from Type II poses (12). Needs N ≥ 3."""
    if np.shape(P)[-2] < 3:
        raise InputError("method 3.3.1 needs at least 3 Type II poses")
    A, y = type2_system(P, R)
    return batched_lstsq(A, y)


def solve_type3(P, R, b):
    """Method 3.3.2: ``(a, cond)`` from Type III poses and ``b`` (17). Needs N ≥ 4."""
    if np.shape(P)[-2] < 4:
        raise InputError("method 3.3.2 needs at least 4 Type III poses")
    C, D = type3_system(P, R, b)
    return batched_lstsq(C, D)


def solve_offset(P, R, rho, a, b):
    """Method 3.3.3, (19): ``Δρ = mean_i(‖P_i + R_i b − a‖ − ρ_i)`` over the poses given."""
    P, R, rho = np.asarray(P, float), np.asarray(R, float), np.asarray(rho, float)
    V = P + np.einsum("...ij,...j->...i", R, np.asarray(b, float)[..., None, :]) - np.asarray(a, float)[..., None, :]
    return np.mean(np.linalg.norm(V, axis=-1) - rho, axis=-1)


# ---------------------------------------------------------------- pose generators
def _random_rotations(rng, shape, max_angle):
    return euler_zyx_to_matrix(rng.uniform(-max_angle, max_angle, shape + (3,)))


def _fill_sets(
    robot: GoughPlatform,
    n_sets: int,
    n_poses: int,
    rng: np.random.Generator,
    anchor: Callable[[np.ndarray], dict],
    propose: Callable[[dict, int], np.ndarray],
    max_rounds: int = 200,
) -> np.ndarray:
    """Rejection-sample ``n_poses`` feasible poses per set, vectorised over sets.

    ``anchor(T)`` derives per-set constants (fixed direction/point/length) from
    one feasible pose per set; ``propose(state, m)`` returns (S, m, 4, 4)
    candidates satisfying the constraint by construction; candidates are kept
    when :meth:`GoughPlatform.in_workspace` accepts them. Sets that cannot be
    filled (anchor near the workspace boundary) are re-anchored.
    """
    out = np.full((n_sets, n_poses, 4, 4), np.nan)
    count = np.zeros(n_sets, int)
    todo = np.arange(n_sets)
    m = max(4 * n_poses, 32)
    for _attempt in range(20):
        if len(todo) == 0:
            break
        T0 = generate_random_poses(robot, len(todo), rng)
        state = anchor(T0)
        for _ in range(max_rounds):
            pending = count[todo] < n_poses
            if not np.any(pending):
                break
            cand = propose(state, m)  # (S_todo, m, 4, 4)
            ok = robot.in_workspace(cand.reshape(-1, 4, 4)).reshape(len(todo), m)
            ok &= pending[:, None]
            rank = np.cumsum(ok, axis=1) - 1 + count[todo][:, None]
            take = ok & (rank < n_poses)
            si, ci = np.nonzero(take)
            out[todo[si], rank[si, ci]] = cand[si, ci]
            count[todo] += take.sum(axis=1)
        todo = todo[count[todo] < n_poses]
        count[todo] = 0
    if len(todo):
        raise InputError(f"could not generate {n_poses} constrained poses for {len(todo)} sets; "
                           "the workspace or leg limits are too tight for this constraint")
    return out


def generate_random_poses(robot: GoughPlatform, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` unconstrained poses (n, 4, 4) uniform in the workspace box × Euler bounds,
    kept when all legs are within limits (rejection sampling)."""
    ws = robot.workspace
    if ws is None:
        raise InputError(f"robot {robot.name!r} has no workspace; pose generation needs one")
    out = np.empty((0, 4, 4))
    tried = 0
    while len(out) < n:
        m = min(max(4 * (n - len(out)), 64), 200_000)
        T = make_T(rng.uniform(ws.position_min, ws.position_max, (m, 3)), _random_rotations(rng, (m,), ws.max_angle))
        out = np.concatenate([out, T[robot.in_workspace(T)]])
        tried += m
        if tried > 1000 * n + 100_000 and len(out) < 0.001 * tried:
            raise InputError(f"robot {robot.name!r}: fewer than 0.1 % of the poses drawn in the workspace box "
                               f"respect the leg-length limits ({len(out)} of {tried}); shrink the workspace box")
    return out[:n]


def _leg_point(robot, k, T):
    P, R = split_pose(T)
    return P + R @ robot.b[k]


def generate_type1(robot: GoughPlatform, k: int, n_sets: int, n_poses: int, rng: np.random.Generator) -> np.ndarray:
    """Type I pose sets (S, N, 4, 4): leg ``k`` (0-based) keeps one direction per set.

    Per set: a random feasible pose fixes the unit direction ``n`` of leg k;
    poses are ``P_i = a_k + L_i n − R_i b_k`` with ``R_i`` uniform in the Euler
    bounds and ``L_i`` uniform in leg k's length limits, kept if feasible.
    """
    a, b, lim = robot.a[k], robot.b[k], robot.length_limits[k]
    ws = robot.workspace

    def anchor(T0):
        v = _leg_point(robot, k, T0) - a
        return {"n": v / np.linalg.norm(v, axis=-1, keepdims=True)}

    def propose(st, m):
        S = len(st["n"])
        R = _random_rotations(rng, (S, m), ws.max_angle)
        L = rng.uniform(lim[0], lim[1], (S, m))
        P = a + L[..., None] * st["n"][:, None, :] - R @ b
        return make_T(P, R)

    return _fill_sets(robot, n_sets, n_poses, rng, anchor, propose)


def generate_type2(robot: GoughPlatform, k: int, n_sets: int, n_poses: int, rng: np.random.Generator) -> np.ndarray:
    """Type II pose sets: leg ``k`` keeps direction and length (point B_k fixed per set).

    ``P_i = B − R_i b_k`` with ``B`` from a random feasible pose and ``R_i``
    uniform in the Euler bounds.
    """
    b = robot.b[k]
    ws = robot.workspace

    def anchor(T0):
        return {"B": _leg_point(robot, k, T0)}

    def propose(st, m):
        S = len(st["B"])
        R = _random_rotations(rng, (S, m), ws.max_angle)
        return make_T(st["B"][:, None, :] - R @ b, R)

    return _fill_sets(robot, n_sets, n_poses, rng, anchor, propose)


def generate_type3(robot: GoughPlatform, k: int, n_sets: int, n_poses: int, rng: np.random.Generator,
                   max_tilt: float = np.radians(45.0)) -> np.ndarray:
    """Type III pose sets: leg ``k`` keeps its length (per set), direction free.

    ``P_i = a_k + L n_i − R_i b_k`` with ``L`` from a random feasible pose,
    ``n_i`` uniform on the spherical cap of half-angle ``max_tilt`` about the
    base normal and ``R_i`` uniform in the Euler bounds.
    """
    a, b = robot.a[k], robot.b[k]
    ws = robot.workspace
    cmin = np.cos(max_tilt)

    def anchor(T0):
        return {"L": np.linalg.norm(_leg_point(robot, k, T0) - a, axis=-1)}

    def propose(st, m):
        S = len(st["L"])
        cz = rng.uniform(cmin, 1.0, (S, m))
        phi = rng.uniform(0, 2 * np.pi, (S, m))
        sz = np.sqrt(1 - cz**2)
        n = np.stack([sz * np.cos(phi), sz * np.sin(phi), cz], -1)
        R = _random_rotations(rng, (S, m), ws.max_angle)
        return make_T(a + st["L"][:, None, None] * n - R @ b, R)

    return _fill_sets(robot, n_sets, n_poses, rng, anchor, propose)


def add_uniform_noise(T: np.ndarray, rng: np.random.Generator, err_p: float, err_a: float) -> np.ndarray:
    """Uniform noise: each position component ± ``err_p`` [m], each ZYX Euler
    angle ± ``err_a`` [rad] (Daney's protocol, §5 of the digest)."""
    P, R = T[..., :3, 3], T[..., :3, :3]
    Pn = P + rng.uniform(-err_p, err_p, P.shape)
    e = matrix_to_euler_zyx(R) + rng.uniform(-err_a, err_a, P.shape)
    return make_T(Pn, euler_zyx_to_matrix(e))


# ---------------------------------------------------------------- per-leg workflow
@dataclass
class LegDaneyResult:
    """Linear per-leg estimates (SI) and the condition numbers of the systems."""

    leg: int  # 1-based
    method: str  # "3.2" or "3.3"
    a: np.ndarray
    b: np.ndarray
    drho: float | None
    cond: dict

    def to_dict(self) -> dict:
        return {"leg": self.leg, "method": self.method, "a": self.a.tolist(), "b": self.b.tolist(),
                "drho": None if self.drho is None else float(self.drho),
                "condition_numbers": {k: float(v) for k, v in self.cond.items()}}


def calibrate_leg_daney(
    leg: int,
    *,
    type1: tuple[np.ndarray, np.ndarray] | None = None,
    drho_known: float | None = None,
    type2: np.ndarray | None = None,
    type3: np.ndarray | None = None,
    offset_poses: tuple[np.ndarray, np.ndarray] | None = None,
) -> LegDaneyResult:
    """Calibrate one leg (1-based ``leg``) from constrained measurements.

    Method 3.2: ``type1=(T, rho)`` with measured poses (N,4,4) and readings
    (N,) of the clamped leg, and the known offset ``drho_known``.
    Method 3.3: ``type2=T2`` (poses, direction+length fixed), ``type3=T3``
    (poses, length fixed) and, for the offset, ``offset_poses=(T, rho)``
    (any poses with the leg's readings; default: the Type III poses need a
    reading, so ``offset_poses`` is required for Δρ).
    """
    if type1 is not None:
        if drho_known is None:
            raise InputError("method 3.2 (Type I) needs the known offset drho_known (Model 36)")
        T, rho = type1
        P, R = split_pose(T)
        b, a, c = solve_type1(P, R, np.asarray(rho, float) + drho_known)
        return LegDaneyResult(leg, "3.2", a, b, float(drho_known), {"type1": float(c)})
    if type2 is None or type3 is None:
        raise InputError("method 3.3 needs Type II poses (type2) and Type III poses (type3); "
                         "method 3.2 needs type1=(T, rho)")
    P2, R2 = split_pose(type2)
    b, c2 = solve_type2(P2, R2)
    P3, R3 = split_pose(type3)
    a, c3 = solve_type3(P3, R3, b)
    drho = None
    if offset_poses is not None:
        T0, rho0 = offset_poses
        P0, R0 = split_pose(T0)
        drho = float(solve_offset(P0, R0, np.atleast_1d(np.asarray(rho0, float)), a, b))
    return LegDaneyResult(leg, "3.3", a, b, drho, {"type2": float(c2), "type3": float(c3)})


def daney_initial_theta(robot: GoughPlatform, results: list[LegDaneyResult]) -> np.ndarray:
    """Full (42,) parameter vector with the legs in ``results`` replaced by their
    linear estimates (other legs keep the robot's nominal values) — the
    no-guess initial value offered to the nonlinear estimators."""
    th = robot.theta.reshape(6, 7).copy()
    for r in results:
        k = r.leg - 1
        th[k, 0:3] = r.a
        th[k, 3:6] = r.b
        if r.drho is not None:
            th[k, 6] = r.drho
    return th.reshape(-1)
