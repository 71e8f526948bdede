"""Configurations satisfying the constraint of a measurement method (GECARO "Points generation").

GECARO generates, for every method, joint configurations that satisfy the
method's constraint with a numerical inverse geometric model built on the
differential model (§3.2, §4). This module does the same, vectorised: all
targets × all random seeds are solved as one batch of Newton problems.

* :func:`solve_ik` — batched damped least squares (Levenberg/Wampler DLS)
  ``Δr = Jᵀ (J Jᵀ + λ² I)⁻¹ e`` with ``λ² = 10⁻³‖e‖²`` (undamped Newton close to
  the solution, so it converges quadratically to machine precision), steps
  limited to ``max_step``, readings kept inside the joint limits (revolute
  joints with a full-turn range are wrapped, the others clipped).
* :func:`link_data` — groups of configurations reaching the same point
  (``point-link``) or pose (``frame-link``): a random first configuration, then
  the inverse model from ``n_seeds`` random starts; solutions closer than
  ``min_separation`` to the first configuration (or to an already chosen one)
  are rejected. Which inverse-kinematics branches the members use is reported
  by :func:`branch_report` (see ``docs/methods.md``).
* :func:`plane_data` — configurations whose end point lies on a plane.
* :func:`distance_data` — random pairs with their end-point distance.
* :func:`measurement_data` — random configurations with position / pose.
* :func:`generate` — dispatch by method name (used by :mod:`estcal.identify`).

Readings are generated with the parameter vector ``theta`` (default: the
robot's values), i.e. with the "true" robot when simulating.
"""
from __future__ import annotations

import numpy as np

from estcal.io.dataset import Dataset, dataset_from_arrays
from estcal.kinematics.transforms import pose_error, so3_exp

from .links import group_pairs

__all__ = ["solve_ik", "link_data", "plane_data", "distance_data", "measurement_data", "generate",
           "branch_report", "default_plane", "joint_distance"]


# ------------------------------------------------------------------ joint-space helpers
def _reading_map(robot, theta) -> np.ndarray:
    """∂q/∂reading (n, n) of the rigid joint model q = Cj diag(K) Cm r + offset (GECARO eq. [4])."""
    K = theta[robot.gain_idx]
    if robot.coupling is None:
        return np.diag(K)
    Cj, Cm = (np.asarray(c, float) for c in robot.coupling)
    return Cj @ np.diag(K) @ Cm


def _full_turn(robot) -> np.ndarray:
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    return np.array([t == "revolute" for t in robot.joint_types]) & (hi - lo >= 2 * np.pi - 1e-9)


def _project(robot, r) -> np.ndarray:
    """Readings into the joint limits: wrap full-turn revolute joints, clip the others."""
    lo, hi = robot.limits[:, 0], robot.limits[:, 1]
    wrap = _full_turn(robot)
    out = np.clip(r, lo, hi)
    if wrap.any():
        out[:, wrap] = lo[wrap] + np.mod(r[:, wrap] - lo[wrap], 2 * np.pi)
    return out


def joint_distance(robot, r1, r2) -> np.ndarray:
    """Max-norm joint distance (N,): revolute differences wrapped to (−π, π] (rad),
    prismatic differences scaled by π/range (a full-range stroke counts as π)."""
    d = np.asarray(r1, float) - np.asarray(r2, float)
    rev = np.array([t == "revolute" for t in robot.joint_types])
    d[..., rev] = np.angle(np.exp(1j * d[..., rev]))
    span = robot.limits[:, 1] - robot.limits[:, 0]
    d[..., ~rev] = d[..., ~rev] * np.pi / np.maximum(span[~rev], 1e-12)
    return np.abs(d).max(-1)


# ------------------------------------------------------------------ Newton solver
def _residual(kin, mode, target):
    """Constraint residual ``target − current`` (N, m) and its Jacobian w.r.t. the joint values (N, m, n)."""
    if mode == "pose":
        R_t, p_t = target
        return pose_error(R_t, p_t, kin.R, kin.p), kin.J_q
    if mode == "position":
        return target - kin.p, kin.J_q[:, :3]
    if mode == "plane":  # target (N, 3) plane coefficients: signed distance to a x + b y + c z + 1 = 0
        L = np.linalg.norm(target, axis=1)
        s = (np.einsum("ni,ni->n", target, kin.p) + 1.0) / L
        return -s[:, None], np.einsum("ni,nij->nj", target / L[:, None], kin.J_q[:, :3])[:, None, :]
    raise ValueError(f"unknown IK mode {mode!r} (pose, position or plane)")


def solve_ik(robot, r0, target, mode: str = "pose", theta=None, max_iter: int = 100, tol: float = 1e-14,
             max_step: float = 0.3, context=None):
    """Batched numerical inverse geometric model (damped least squares).

    Parameters
    ----------
    robot : SerialRobot
    r0 : (N, n) initial readings (one Newton problem per row).
    target : for ``mode="pose"`` a tuple ``(R (N, 3, 3), p (N, 3))``; ``"position"``: p (N, 3);
        ``"plane"``: (N, 3) coefficients (a, b, c) of ``a x + b y + c z + 1 = 0``.
    theta : parameter vector used (default the robot's values).
    tol : convergence threshold on ‖e‖ (m / rad); a solution is accepted (``ok``) when
        ‖e‖ ≤ 100·tol (1e-12 by default), Newton stops earlier only at tol or when the
        error stops decreasing below 100·tol.

    Returns
    -------
    r : (N, n) readings, within the joint limits; ok : (N,) bool converged;
    err : (N,) final ‖e‖.
    """
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    r = _project(robot, np.array(r0, float, copy=True))
    M = _reading_map(robot, theta)
    N = r.shape[0]
    err = np.full(N, np.inf)
    active = np.ones(N, bool)
    best = np.full(N, np.inf)
    stall = np.zeros(N, int)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        tgt = _take(target, idx, mode)
        kin = robot.kinematics(r[idx], theta, _ctx(context, idx), jacobian=True)
        e, Jq = _residual(kin, mode, tgt)
        Jr = Jq @ M
        ne = np.linalg.norm(e, axis=1)
        err[idx] = ne
        done = ne <= tol
        # Newton cannot go below round-off: stop when the error no longer decreases.
        improved = ne < 0.5 * best[idx]
        stall[idx] = np.where(improved, 0, stall[idx] + 1)
        best[idx] = np.minimum(best[idx], ne)
        done |= (stall[idx] >= 3) & (ne < 1e2 * tol)
        done |= stall[idx] >= 8  # stuck (joint limit, singularity): give up, another seed will do
        active[idx[done]] = False
        keep = ~done
        if not keep.any():
            break
        idx, e, Jr, ne = idx[keep], e[keep], Jr[keep], ne[keep]
        m = e.shape[1]
        A = Jr @ np.swapaxes(Jr, 1, 2) + (1e-3 * ne**2 + 1e-300)[:, None, None] * np.eye(m)
        try:
            y = np.linalg.solve(A, e[..., None])[..., 0]
        except np.linalg.LinAlgError:
            y = np.linalg.lstsq(A.reshape(-1, m), e.reshape(-1), rcond=None)[0].reshape(e.shape)
        dr = np.einsum("nmj,nm->nj", Jr, y)
        big = np.abs(dr).max(1)
        dr *= np.minimum(1.0, max_step / np.maximum(big, 1e-300))[:, None]
        r[idx] = _project(robot, r[idx] + dr)
    kin = robot.kinematics(r, theta, context, jacobian=True)
    e, _ = _residual(kin, mode, target)
    err = np.linalg.norm(e, axis=1)
    # Accept only solutions at round-off level: identifiability analysis of link
    # methods relies on columns that vanish exactly when the constraint holds.
    return r, err <= 1e2 * tol, err


def _take(target, idx, mode):
    if mode == "pose":
        return target[0][idx], target[1][idx]
    return target[idx]


def _ctx(context, idx):
    return None if context is None else {k: np.asarray(v)[idx] for k, v in context.items()}


def _random(robot, n, rng, margin):
    return robot.random_readings(n, rng, margin=margin)


# ------------------------------------------------------------------ link methods
def link_data(robot, n_groups: int, group_size: int = 2, mode: str = "point", rng=0, theta=None,
              n_seeds: int = 16, min_separation: float = 0.5, margin: float = 0.05, max_rounds: int = 6,
              reading_noise: float = 0.0) -> Dataset:
    """Groups of configurations reaching the same point (``mode="point"``) or pose (``"frame"``).

    For each group a random first configuration ``r_i`` (limits shrunk by ``margin``)
    defines the target ``T(r_i, θ)``; the inverse model is solved from ``n_seeds``
    random starts and the converged solutions whose :func:`joint_distance` to
    ``r_i`` and to the members already chosen exceeds ``min_separation`` are kept
    (GECARO requires ``q_j ≠ q_i``; the paper does not say how, this is our rule).
    Groups that do not get ``group_size − 1`` distinct solutions are redrawn
    (up to ``max_rounds`` times). Returns an encoder-only dataset with a ``group``
    column (rows ordered group by group; the first row of a group is its reference).
    """
    if mode not in ("point", "frame"):
        raise ValueError(f"mode must be 'point' or 'frame', got {mode!r}")
    if group_size < 2:
        raise ValueError("group_size must be ≥ 2 (a link needs two configurations)")
    rng = np.random.default_rng(rng)
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    n = robot.n_joints
    groups: list[np.ndarray] = []
    for _ in range(max_rounds):
        need = n_groups - len(groups)
        if need <= 0:
            break
        ri = _random(robot, need, rng, margin)
        kin = robot.kinematics(ri, theta, jacobian=False)
        rep = np.repeat(np.arange(need), n_seeds)
        seeds = _random(robot, need * n_seeds, rng, 0.0)
        target = (kin.R[rep], kin.p[rep]) if mode == "frame" else kin.p[rep]
        sol, ok, _ = solve_ik(robot, seeds, target, "pose" if mode == "frame" else "position", theta)
        ok &= joint_distance(robot, sol, ri[rep]) > min_separation
        sol = sol.reshape(need, n_seeds, n)
        ok = ok.reshape(need, n_seeds)
        for g in range(need):  # selection among a few seeds per group; the solving above is batched
            chosen = [ri[g]]
            for s in np.flatnonzero(ok[g]):
                if all(joint_distance(robot, sol[g, s], c) > min_separation for c in chosen[1:]):
                    chosen.append(sol[g, s])
                if len(chosen) == group_size:
                    groups.append(np.stack(chosen))
                    break
    if len(groups) < n_groups:
        raise RuntimeError(f"{robot.name}: only {len(groups)} of {n_groups} {mode}-link groups found distinct "
                           f"inverse-kinematics solutions within the joint limits; increase n_seeds or lower "
                           f"min_separation ({min_separation})")
    R = np.concatenate(groups[:n_groups])
    if reading_noise:
        R = R + rng.normal(0.0, reading_noise, R.shape)
    gid = np.repeat(np.arange(n_groups), group_size).astype(float)
    return dataset_from_arrays(robot.joint_names, R, columns={"group": gid})


def branch_report(robot, data) -> dict:
    """Which joints change between the members of each group (inverse-kinematics branches).

    Returns ``{"signatures": {"j1,j2,...": count}, "mean_abs_change": {joint: value},
    "changed_fraction": {joint: fraction}}``; a joint counts as changed when its
    (wrapped) reading differs by more than 1e-6 from the group's first member.
    """
    i, j = group_pairs(np.asarray(data.columns["group"]))
    d = data.readings[j] - data.readings[i]
    rev = np.array([t == "revolute" for t in robot.joint_types])
    d[:, rev] = np.angle(np.exp(1j * d[:, rev]))
    changed = np.abs(d) > 1e-6
    sig: dict[str, int] = {}
    for row in changed:
        key = ",".join(nm for nm, c in zip(robot.joint_names, row) if c) or "(none)"
        sig[key] = sig.get(key, 0) + 1
    return {"signatures": dict(sorted(sig.items(), key=lambda kv: -kv[1])),
            "mean_abs_change": {nm: float(v) for nm, v in zip(robot.joint_names, np.abs(d).mean(0))},
            "changed_fraction": {nm: float(v) for nm, v in zip(robot.joint_names, changed.mean(0))}}


# ------------------------------------------------------------------ planes
def default_plane(robot, rng=0, theta=None, direction=(0.2, -0.3, 1.0)) -> np.ndarray:
    """A tilted plane through the middle of the workspace, as ``(a, b, c)`` of ``a x + b y + c z + 1 = 0``.

    Normal along ``direction`` (normalised; tilted so that no world axis is special),
    through the centroid of 200 random end points. If that plane passes within 5 cm
    of the world origin it is shifted by 10 cm along the normal (the equation form
    cannot describe planes through the origin).
    """
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    P = robot.kinematics(robot.random_readings(200, np.random.default_rng(rng), 0.05), theta, jacobian=False).p
    nrm = np.asarray(direction, float) / np.linalg.norm(direction)
    m = P.mean(0)
    d = float(nrm @ m)
    if abs(d) < 0.05:
        d += 0.1 if d >= 0 else -0.1
    return -nrm / d


def plane_data(robot, n: int, plane=None, rng=0, theta=None, margin: float = 0.05, max_rounds: int = 10,
               reading_noise: float = 0.0) -> Dataset:
    """``n`` configurations whose end point lies on ``plane`` (``a x + b y + c z + 1 = 0``).

    Random starts are projected on the plane by the inverse model (one scalar
    constraint, minimum-norm steps). ``plane`` may be one (3,) plane or a list of
    planes; rows are then spread over them and the ``group`` column holds the plane
    index. Columns: ``group``, ``plane_a``, ``plane_b``, ``plane_c``.
    """
    rng = np.random.default_rng(rng)
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    planes = np.atleast_2d(default_plane(robot, rng.integers(1 << 31), theta) if plane is None
                           else np.asarray(plane, float))
    gid = np.arange(n) % planes.shape[0]
    out = np.empty((n, robot.n_joints))
    todo = np.arange(n)
    for _ in range(max_rounds):
        if todo.size == 0:
            break
        r, ok, _ = solve_ik(robot, _random(robot, todo.size, rng, margin), planes[gid[todo]], "plane", theta)
        out[todo[ok]] = r[ok]
        todo = todo[~ok]
    if todo.size:
        raise RuntimeError(f"{robot.name}: {todo.size} of {n} configurations could not be brought onto the plane "
                           f"{planes[gid[todo[0]]].tolist()} within the joint limits — is it inside the workspace?")
    if reading_noise:
        out = out + rng.normal(0.0, reading_noise, out.shape)
    cols = {"group": gid.astype(float), "plane_a": planes[gid, 0], "plane_b": planes[gid, 1],
            "plane_c": planes[gid, 2]}
    return dataset_from_arrays(robot.joint_names, out, columns=cols)


# ------------------------------------------------------------------ distance, classical
def distance_data(robot, n_pairs: int, rng=0, theta=None, margin: float = 0.05, min_distance: float = 0.05,
                  distance_noise: float = 0.0) -> Dataset:
    """Random pairs of configurations and the distance between their end points (m).

    Rows ``2k`` and ``2k+1`` share ``pair = k``; ``distance`` holds the (noisy)
    distance on both rows. Pairs closer than ``min_distance`` are redrawn.
    """
    rng = np.random.default_rng(rng)
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    R = np.empty((0, 2, robot.n_joints))
    D = np.empty(0)
    while R.shape[0] < n_pairs:
        k = 2 * (n_pairs - R.shape[0]) + 4
        r = _random(robot, 2 * k, rng, margin).reshape(k, 2, -1)
        p = robot.kinematics(r.reshape(2 * k, -1), theta, jacobian=False).p.reshape(k, 2, 3)
        d = np.linalg.norm(p[:, 1] - p[:, 0], axis=1)
        good = d >= min_distance
        R = np.concatenate([R, r[good]])
        D = np.concatenate([D, d[good]])
    R, D = R[:n_pairs], D[:n_pairs]
    if distance_noise:
        D = D + rng.normal(0.0, distance_noise, D.shape)
    cols = {"pair": np.repeat(np.arange(n_pairs), 2).astype(float), "distance": np.repeat(D, 2)}
    return dataset_from_arrays(robot.joint_names, R.reshape(2 * n_pairs, -1), columns=cols)


def measurement_data(robot, n: int, kind: str = "position", rng=0, theta=None, margin: float = 0.05,
                     position_noise: float = 0.0, orientation_noise: float = 0.0) -> Dataset:
    """Random configurations with the measured tool position (``kind="position"``, marker 1
    when the robot has markers) or pose (``"location"``), with optional Gaussian noise
    (m; rad as a random rotation vector applied in the world frame)."""
    rng = np.random.default_rng(rng)
    theta = robot.params.values if theta is None else np.asarray(theta, float)
    r = _random(robot, n, rng, margin)
    kin = robot.kinematics(r, theta, jacobian=False)
    if kind == "position":
        p = kin.points[:, 0] if robot.n_markers else kin.p
        return dataset_from_arrays(robot.joint_names, r, points=p + rng.normal(0, position_noise, p.shape)
                                   if position_noise else p)
    if kind in ("location", "pose"):
        p = kin.p + (rng.normal(0, position_noise, kin.p.shape) if position_noise else 0.0)
        Rm = kin.R if not orientation_noise else so3_exp(rng.normal(0, orientation_noise, (n, 3))) @ kin.R
        return dataset_from_arrays(robot.joint_names, r, R=Rm, p=p)
    raise ValueError(f"kind must be 'position' or 'location', got {kind!r}")


def generate(robot, method: str, n: int, rng=0, theta=None, plane=None, group_size: int = 2,
             **kwargs) -> Dataset:
    """Admissible configurations for ``method`` (one of the nine GECARO names), ``n`` configurations.

    ``position``/``location``: ``n`` random configurations; ``point-link``/``frame-link``:
    ``n // group_size`` groups; ``plane-*``: ``n`` configurations on ``plane`` (default
    :func:`default_plane`); ``distance``: ``n // 2`` pairs.
    """
    if method in ("position", "location", "pose"):
        return measurement_data(robot, n, "position" if method == "position" else "location", rng, theta, **kwargs)
    if method in ("point-link", "frame-link"):
        return link_data(robot, max(n // group_size, 1), group_size, method.split("-")[0], rng, theta, **kwargs)
    if method.startswith("plane"):
        return plane_data(robot, n, plane, rng, theta, **kwargs)
    if method == "distance":
        return distance_data(robot, max(n // 2, 1), rng, theta, **kwargs)
    raise ValueError(f"no generator for method {method!r}")
