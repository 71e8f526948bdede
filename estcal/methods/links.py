"""Autonomous, planar and distance measurement methods (GECARO eqs. [11]–[20]).

Importing this module registers, next to ``position`` and ``location`` (in
:mod:`estcal.methods.base`), the methods

=========================  =====================================================
name                       rows
=========================  =====================================================
``point-link``             3 per configuration of a group, except the first:
                           same unknown point reached by every member (eq. [12])
``frame-link``             6 per such configuration: same unknown pose (eq. [12])
``plane-known``            1 per configuration: signed distance to a known plane
                           ``a x + b y + c z + 1 = 0`` (eqs. [13]–[15])
``plane-unknown``          same, plane coefficients estimated (``plane_a/b/c``)
``plane-normal-known``     1 per configuration of a group except the first:
                           ``n·(P_j − P_first) = 0`` with a known normal (eqs. [16]–[17])
``plane-normal-unknown``   same, normal estimated (two angles ``normal_u/v``)
``distance``               1 per pair: measured distance between two end points
                           (eqs. [18]–[20])
=========================  =====================================================

Dataset columns (read from :attr:`Dataset.columns`, see ``docs/methods.md``):
``group`` (integer id; rows with the same id reach the same point / pose, or
lie on the same plane), ``pair`` + ``distance`` (metres) for the distance
measure, optional ``plane_a, plane_b, plane_c`` for known planes/normals.

Design choices (documented in ``docs/methods.md``)
--------------------------------------------------
* **Link methods use GECARO's difference form**, not an unknown common point:
  each member j of a group is compared with the group's first member i. The
  predicted quantity is ``P_j − P_i`` (and ``log(R_i R_jᵀ)``), the "measurement"
  is zero, so ``e = P_i − P_j`` and ``H = J_j − J_i`` (eq. [12]). No extra
  unknowns, and the rows are exactly GECARO's observation matrix. Rows of one
  group share member i, so for groups of more than two their errors are
  correlated (coefficient ½); each row's σ is ``√2·σ_position`` (difference of
  two independent configurations). The orientation rows use the exact
  derivative of the rotation logarithm, ``H_rot = J_l⁻¹(δ)(D w_j − w_i)``
  with ``D = R_i R_jᵀ = exp(δ)``, which reduces to ``w_j − w_i`` when the two
  orientations agree (the case eq. [12] linearises about).
* **Plane equation form** uses the signed distance
  ``s = (a P_x + b P_y + c P_z + 1)/‖n‖`` (metres, so ``σ_scalar`` applies):
  eq. [15] divided by ``‖n‖``. For the robot parameters this is a row scaling;
  for ``a, b, c`` the extra term ``−s·n/‖n‖²`` vanishes on the plane. Rank and
  identifiable set are those of eq. [15].
* **Unknown normal**: eq. [16] is homogeneous in ``(a, b, c)``, so only the
  direction is identifiable. It is parameterised by two angles about a *pole*
  frame ``B = [e1 e2 e3]`` (world axes, ``e3`` the axis closest to the initial
  normal): ``n = B·(cos u sin v, −sin u, cos u cos v)``, i.e. ``Ry(v)Rx(u)e3``.
  The pole is chosen once (from the nominal best-fit plane) and kept; since the
  normal is then within 55° of ``e3``, the parameterisation is never singular.
"""
from __future__ import annotations

import numpy as np

from estcal.kinematics.transforms import skew, so3_log

from .base import Method, NoiseModel, Rows, register_method

__all__ = ["PointLink", "FrameLink", "PlaneKnown", "PlaneUnknown", "PlaneNormalKnown", "PlaneNormalUnknown",
           "DistanceMethod", "group_pairs", "distance_pairs", "fit_plane", "so3_left_jacobian_inv"]


# ----------------------------------------------------------------- helpers
def _col(data, name: str, method: str, what: str) -> np.ndarray:
    if name not in data.columns:
        raise ValueError(f"{data.where}: method {method!r} needs a {name!r} column ({what}); "
                         f"the dataset has extra columns {sorted(data.columns)} (see docs/methods.md)")
    return np.asarray(data.columns[name], float)


def _int_ids(values, data, name) -> np.ndarray:
    ids = np.asarray(values, float)
    bad = np.flatnonzero(ids != np.round(ids))
    if bad.size:
        raise ValueError(f"{data.where}, line {data.lines[bad[0]]}, column {name!r}: "
                         f"{ids[bad[0]]:g} is not an integer id")
    return ids.astype(np.int64)


def group_pairs(groups) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)``: every row j compared with the first row i of its group.

    ``groups`` (N,) integer ids; the first row (in dataset order) of each id is the
    reference; singleton groups give no pair. Vectorised (no loop over rows).
    """
    g = np.asarray(groups)
    _, first, inv = np.unique(g, return_index=True, return_inverse=True)
    ref = first[inv.reshape(-1)]
    j = np.flatnonzero(ref != np.arange(g.size))
    return ref[j], j


def _groups_of(data, method: str) -> tuple[np.ndarray, np.ndarray]:
    g = _int_ids(_col(data, "group", method, "rows with the same id reach the same point/pose or plane"),
                 data, "group")
    i, j = group_pairs(g)
    if j.size == 0:
        raise ValueError(f"{data.where}: method {method!r}: every 'group' id occurs once, so there is no "
                         f"pair of configurations to compare (give ≥ 2 rows per group)")
    return i, j


def distance_pairs(data, method: str = "distance") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i, j, D_measured)`` for the distance measure.

    Rows sharing a ``pair`` id form a pair (exactly two rows); ``j`` is the later
    row and ``D`` its ``distance`` value (m). If both rows carry a non-zero,
    different distance, that is an error (ambiguous).
    """
    pid = _int_ids(_col(data, "pair", method, "rows i and j of a pair share an id"), data, "pair")
    dist = _col(data, "distance", method, "measured distance (m) on the second row of each pair")
    ids, counts = np.unique(pid, return_counts=True)
    if np.any(counts != 2):
        bad = ids[np.flatnonzero(counts != 2)[0]]
        lines = data.lines[pid == bad].tolist()
        raise ValueError(f"{data.where}: pair id {bad} occurs on {len(lines)} rows (lines {lines}); "
                         f"each pair needs exactly 2 rows")
    order = np.argsort(pid, kind="stable")
    i, j = order[0::2], order[1::2]
    swap = i > j  # keep dataset order inside a pair: the later row holds the distance
    i[swap], j[swap] = j[swap].copy(), i[swap].copy()
    di, dj = dist[i], dist[j]
    amb = (di != 0) & (di != dj)
    if np.any(amb):
        k = np.flatnonzero(amb)[0]
        raise ValueError(f"{data.where}, lines {data.lines[i[k]]}/{data.lines[j[k]]}: the two rows of pair "
                         f"{pid[i[k]]} carry different distances {di[k]:g} and {dj[k]:g} (put the measured "
                         f"distance on the second row, and the same value or 0 on the first)")
    if np.any(dj <= 0):
        k = np.flatnonzero(dj <= 0)[0]
        raise ValueError(f"{data.where}, line {data.lines[j[k]]}, column 'distance': {dj[k]:g} m is not a "
                         f"positive distance")
    return i, j, dj


def so3_left_jacobian_inv(phi) -> np.ndarray:
    """Inverse left Jacobian of SO(3), (..., 3) -> (..., 3, 3).

    ``exp(c) exp(φ) = exp(φ + J_l⁻¹(φ) c + O(c²))`` with
    ``J_l⁻¹ = I − ½[φ]× + (1/θ² − (1+cos θ)/(2θ sin θ)) [φ]×²`` (Barfoot, eq. 7.83);
    the last coefficient tends to 1/12 at θ → 0 (series used below 1e-4).
    """
    phi = np.asarray(phi, float)
    th = np.linalg.norm(phi, axis=-1)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    coef = np.where(small, 1.0 / 12.0 + th**2 / 720.0,
                    1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    K = skew(phi)
    return np.eye(3) - 0.5 * K + coef[..., None, None] * (K @ K)


def fit_plane(points) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane through (M, 3) points: ``(unit normal, centroid)`` (SVD)."""
    P = np.asarray(points, float)
    if P.shape[0] < 3:
        raise ValueError(f"a plane needs at least 3 points, got {P.shape[0]}")
    m = P.mean(0)
    _, s, Vt = np.linalg.svd(P - m, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        raise ValueError("the points are collinear: no unique best-fit plane")
    return Vt[2], m


def _plane_groups(data) -> np.ndarray:
    """Plane id per row: the ``group`` column, or a single plane 0 when absent."""
    if "group" in data.columns:
        return _int_ids(data.columns["group"], data, "group")
    return np.zeros(data.n, np.int64)


def _known_plane(opt, data, method: str) -> np.ndarray:
    """(N, 3) plane coefficients per row: from the option, else ``plane_a/b/c`` columns."""
    if opt is not None:
        return np.broadcast_to(np.asarray(opt, float).reshape(3), (data.n, 3))
    if all(f"plane_{c}" in data.columns for c in "abc"):
        return np.c_[data.columns["plane_a"], data.columns["plane_b"], data.columns["plane_c"]]
    raise ValueError(f"{data.where}: method {method!r} needs the plane: give it as an option "
                     f"({method}: a=…, b=…, c=… / CLI --plane a,b,c) or as columns plane_a, plane_b, plane_c")


def _coeffs(a, b, c, plane):
    if plane is not None:
        return np.asarray(plane, float).reshape(3)
    if a is None and b is None and c is None:
        return None
    if None in (a, b, c):
        raise ValueError("give all three plane coefficients a, b, c")
    return np.array([a, b, c], float)


def _nominal_points(robot, data):
    return robot.kinematics(data.readings, robot.params.values, data.context, jacobian=False).p


def _extra_names(prefix: str, suffixes, gids) -> dict:
    """{group id: [names]}: ``prefix_s`` for a single group, ``prefix{g}_s`` for several."""
    if len(gids) == 1:
        return {int(gids[0]): [f"{prefix}_{s}" for s in suffixes]}
    return {int(g): [f"{prefix}{int(g)}_{s}" for s in suffixes] for g in gids}


# ----------------------------------------------------------------- link methods
class PointLink(Method):
    """Point (position) link, GECARO eq. [12] rows 1–3.

    Every configuration j of a ``group`` reaches the same (unknown) point as the
    group's first configuration i: ``e = P_i − P_j``, ``H = J_j − J_i`` (position rows,
    world frame). σ = √(σ_i² + σ_j²) per row (√2·σ_position without per-row noise).
    """

    name = "point-link"

    def rows(self, robot, theta, data, noise: NoiseModel, jacobian=True) -> Rows:
        i, j = _groups_of(data, self.name)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        e = (kin.p[i] - kin.p[j]).reshape(-1)
        H = None if not jacobian else (kin.J[j, :3] - kin.J[i, :3]).reshape(-1, robot.n_params)
        m = j.size
        ps = noise.position_sigma(data)  # σ of a difference of two rows: √(σ_i² + σ_j²) (√2·σ when equal)
        return Rows(e, H, np.repeat(np.hypot(ps[i], ps[j]), 3), np.repeat(j, 3), np.zeros(3 * m, int))


class FrameLink(Method):
    """Frame link, GECARO eq. [12]: same pose for every configuration of a group.

    ``e = [P_i − P_j ; log(R_i R_jᵀ)]``; ``H = [J_j − J_i ; J_l⁻¹(δ)(D w_j − w_i)]``
    (exact derivative of the logarithm, see module docstring).
    """

    name = "frame-link"

    def rows(self, robot, theta, data, noise: NoiseModel, jacobian=True) -> Rows:
        i, j = _groups_of(data, self.name)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        D = kin.R[i] @ np.swapaxes(kin.R[j], -1, -2)
        delta = so3_log(D)
        e = np.concatenate([kin.p[i] - kin.p[j], delta], 1).reshape(-1)
        H = None
        if jacobian:
            Hp = kin.J[j, :3] - kin.J[i, :3]
            Hr = so3_left_jacobian_inv(delta) @ (D @ kin.J[j, 3:] - kin.J[i, 3:])
            H = np.concatenate([Hp, Hr], 1).reshape(-1, robot.n_params)
        m = j.size
        ps = noise.position_sigma(data)
        sig = np.sqrt(2.0) * np.tile(np.r_[np.zeros(3), np.full(3, noise.orientation)], m).reshape(m, 6)
        sig[:, :3] = np.hypot(ps[i], ps[j])[:, None]
        sig = sig.reshape(-1)
        return Rows(e, H, sig, np.repeat(j, 6), np.tile(np.r_[0, 0, 0, 1, 1, 1], m))


# ----------------------------------------------------------------- plane, equation form
class _PlaneEquation(Method):
    """Shared rows of the plane equation form (eq. [15] as a signed distance)."""

    def _rows(self, robot, theta, data, noise, jacobian, n, plane_idx):
        """n (N, 3) plane coefficients per row; plane_idx (N, 3) their parameter indices or None."""
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        L = np.linalg.norm(n, axis=1)
        s = (np.einsum("ni,ni->n", n, kin.p) + 1.0) / L
        e = -s
        H = None
        if jacobian:
            H = np.einsum("ni,nip->np", n / L[:, None], kin.J[:, :3])
            if plane_idx is not None:
                dn = kin.p / L[:, None] - (s / L**2)[:, None] * n  # ∂s/∂(a, b, c)
                np.add.at(H, (np.arange(data.n)[:, None], plane_idx), dn)
        N = data.n
        return Rows(e, H, np.full(N, noise.scalar), np.arange(N), np.full(N, 2))


class PlaneKnown(_PlaneEquation):
    """Plane link 1 with a known plane ``a x + b y + c z + 1 = 0`` (GECARO eqs. [13]–[15]).

    Residual: minus the signed distance of the end point to the plane (m),
    ``e = −(a P_x + b P_y + c P_z + 1)/‖(a, b, c)‖``; ``H = (a J_x + b J_y + c J_z)/‖(a, b, c)‖``.

    Parameters
    ----------
    a, b, c or plane=(a, b, c) : plane coefficients (1/m). When omitted, the
        dataset's ``plane_a, plane_b, plane_c`` columns are used (one plane per row).
    """

    name = "plane-known"

    def __init__(self, a=None, b=None, c=None, plane=None):
        self.plane = _coeffs(a, b, c, plane)

    def rows(self, robot, theta, data, noise, jacobian=True) -> Rows:
        n = _known_plane(self.plane, data, self.name)
        return self._rows(robot, theta, data, noise, jacobian, n, None)


class PlaneUnknown(_PlaneEquation):
    """Plane link 1 with unknown plane coefficients, estimated with the robot (eq. [15]).

    Extra parameters ``plane_a, plane_b, plane_c`` (one plane; ``plane{g}_a`` … per
    ``group`` id when several planes), initialised with the plane that best fits the
    end points of the nominal model (GECARO §3.3). A plane through the world origin
    cannot be written ``a x + b y + c z + 1 = 0``; that case is an error.
    """

    name = "plane-unknown"

    def extra_parameters(self, robot, data):
        g = _plane_groups(data)
        gids = np.unique(g)
        names = _extra_names("plane", "abc", gids)
        P = _nominal_points(robot, data)
        out = []
        for gid in gids:
            normal, m = fit_plane(P[g == gid])
            d = float(normal @ m)
            scale = float(np.linalg.norm(P[g == gid] - m, axis=1).max())
            if abs(d) < 1e-3 * max(scale, 1e-3):
                raise ValueError(f"{data.where}: the plane of group {gid} passes (almost) through the world origin "
                                 f"(distance {abs(d):.3g} m); the form a x + b y + c z + 1 = 0 cannot describe it — "
                                 f"use plane-normal-unknown or another world frame")
            out += list(zip(names[int(gid)], (-normal / d).tolist()))
        return out

    def rows(self, robot, theta, data, noise, jacobian=True) -> Rows:
        g = _plane_groups(data)
        names = _extra_names("plane", "abc", np.unique(g))
        idx = {gid: robot.params.indices(nm) for gid, nm in names.items()}
        plane_idx = np.stack([idx[int(x)] for x in np.unique(g)])[np.unique(g, return_inverse=True)[1].reshape(-1)]
        theta = np.asarray(theta, float)
        return self._rows(robot, theta, data, noise, jacobian, theta[plane_idx], plane_idx)


# ----------------------------------------------------------------- plane, normal form
def _pole_frame(normal) -> np.ndarray:
    """Right-handed frame ``B = [e1 e2 e3]`` of world axes, ``e3`` the axis closest to ``normal``."""
    normal = np.asarray(normal, float)
    k = int(np.argmax(np.abs(normal)))
    E = np.eye(3)
    e3 = E[k] * np.sign(normal[k] or 1.0)
    e1 = E[(k + 1) % 3]
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], 1)


def _normal_from_angles(B, u, v):
    """n = B·(cos u sin v, −sin u, cos u cos v) and its derivatives (…, 3)."""
    cu, su, cv, sv = np.cos(u), np.sin(u), np.cos(v), np.sin(v)
    n = np.stack([cu * sv, -su, cu * cv], -1)
    du = np.stack([-su * sv, -cu, -su * cv], -1)
    dv = np.stack([cu * cv, np.zeros_like(u), -cu * sv], -1)
    return tuple(np.einsum("...ij,...j->...i", B, x) for x in (n, du, dv))


class _PlaneNormal(Method):
    def _rows(self, robot, theta, data, noise, jacobian, n, dn=None, idx=None):
        """n (m, 3) unit normal per compared pair; dn (m, 2, 3) ∂n/∂(u, v) with parameter indices idx (m, 2)."""
        i, j = _groups_of(data, self.name)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        dP = kin.p[j] - kin.p[i]
        pred = np.einsum("mi,mi->m", n, dP)
        H = None
        if jacobian:
            H = np.einsum("mi,mip->mp", n, kin.J[j, :3] - kin.J[i, :3])
            if dn is not None:
                np.add.at(H, (np.arange(j.size)[:, None], idx), np.einsum("mki,mi->mk", dn, dP))
        m = j.size
        return Rows(-pred, H, np.full(m, np.sqrt(2.0) * noise.scalar), j, np.full(m, 2))


class PlaneNormalKnown(_PlaneNormal):
    """Plane link 2 with a known normal (GECARO eqs. [16]–[17]).

    For every configuration j of a ``group`` (all rows one plane when there is no
    ``group`` column) compared with the group's first i:
    ``e = −n·(P_j − P_i)``, ``H = n·(J_j − J_i)`` with the unit normal n.

    Parameters
    ----------
    a, b, c / plane / normal : normal direction (any scale; normalised). The
        ``plane_a, plane_b, plane_c`` columns (of row j) are used when omitted.
    """

    name = "plane-normal-known"

    def __init__(self, a=None, b=None, c=None, plane=None, normal=None):
        self.normal = _coeffs(a, b, c, plane if normal is None else normal)

    def rows(self, robot, theta, data, noise, jacobian=True) -> Rows:
        data = _with_default_group(data)
        i, j = _groups_of(data, self.name)
        n = _known_plane(self.normal, data, self.name)[j]
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        return self._rows(robot, theta, data, noise, jacobian, n)


class PlaneNormalUnknown(_PlaneNormal):
    """Plane link 2 with an unknown normal, estimated as two angles (``normal_u, normal_v``).

    ``n = B·(cos u sin v, −sin u, cos u cos v)`` about a pole frame ``B`` chosen from
    the nominal best-fit plane (``pole="x"/"y"/"z"`` or ``"-z"``… forces it). One pair
    of angles per ``group`` id (``normal{g}_u`` … when several planes).
    """

    name = "plane-normal-unknown"

    def __init__(self, pole: str | None = None):
        self.pole = pole
        self._poles: dict = {}

    def _B(self, gid, robot, data, g) -> np.ndarray:
        if self.pole is not None:
            s = -1.0 if self.pole.startswith("-") else 1.0
            v = np.zeros(3)
            v["xyz".index(self.pole[-1])] = s
            return _pole_frame(v)
        if gid not in self._poles:
            normal, _ = fit_plane(_nominal_points(robot, data)[g == gid])
            self._poles[gid] = _pole_frame(normal)
        return self._poles[gid]

    def extra_parameters(self, robot, data):
        data = _with_default_group(data)
        g = _plane_groups(data)
        gids = np.unique(g)
        names = _extra_names("normal", "uv", gids)
        P = _nominal_points(robot, data)
        out = []
        for gid in gids:
            normal, _ = fit_plane(P[g == gid])
            B = self._B(int(gid), robot, data, g)
            nl = B.T @ normal
            nl = nl * np.sign(nl[2] or 1.0)
            u, v = -np.arcsin(np.clip(nl[1], -1, 1)), np.arctan2(nl[0], nl[2])
            out += list(zip(names[int(gid)], [float(u), float(v)]))
        return out

    def rows(self, robot, theta, data, noise, jacobian=True) -> Rows:
        data = _with_default_group(data)
        g = _plane_groups(data)
        gids = np.unique(g)
        names = _extra_names("normal", "uv", gids)
        i, j = _groups_of(data, self.name)
        theta = np.asarray(theta, float)
        gj = g[j]
        idx = np.empty((j.size, 2), int)
        B = np.empty((j.size, 3, 3))
        for gid in gids:  # loop over planes (few), not over rows
            sel = gj == gid
            idx[sel] = robot.params.indices(names[int(gid)])
            B[sel] = self._B(int(gid), robot, data, g)
        n, du, dv = _normal_from_angles(B, theta[idx[:, 0]], theta[idx[:, 1]])
        return self._rows(robot, theta, data, noise, jacobian, n, np.stack([du, dv], 1), idx)


def _with_default_group(data):
    """Plane-normal methods: without a ``group`` column, all rows lie on one plane."""
    if "group" in data.columns:
        return data
    out = data.subset(slice(None))
    out.columns["group"] = np.zeros(data.n)
    return out


# ----------------------------------------------------------------- distance
class DistanceMethod(Method):
    """Distance measure (GECARO eqs. [18]–[20]).

    For a pair (i, j) with measured distance ``D_meas`` (the ``distance`` column
    of row j): ``e = D_meas − D`` with ``D = ‖P_j − P_i‖`` (not squared, so the
    residual is in metres), ``H = (P_j − P_i)ᵀ(J_j − J_i)/D`` — eq. [19] divided by 2D.
    """

    name = "distance"

    def rows(self, robot, theta, data, noise, jacobian=True) -> Rows:
        i, j, Dm = distance_pairs(data, self.name)
        kin = robot.kinematics(data.readings, theta, data.context, jacobian=jacobian)
        dP = kin.p[j] - kin.p[i]
        D = np.linalg.norm(dP, axis=1)
        if np.any(D < 1e-9):
            k = int(np.argmin(D))
            raise ValueError(f"{data.where}, lines {data.lines[i[k]]}/{data.lines[j[k]]}: the two configurations "
                             f"of the pair give the same end point; the distance derivative is undefined")
        H = None
        if jacobian:
            H = np.einsum("mi,mip->mp", dP / D[:, None], kin.J[j, :3] - kin.J[i, :3])
        m = j.size
        return Rows(Dm - D, H, np.full(m, noise.scalar), j, np.full(m, 2))


for _cls in (PointLink, FrameLink, PlaneKnown, PlaneUnknown, PlaneNormalKnown, PlaneNormalUnknown, DistanceMethod):
    register_method(_cls.name, _cls)

#: The nine GECARO method names of Table 2, in the table's column order.
GECARO_METHODS = ("position", "location", "point-link", "frame-link", "plane-known", "plane-unknown",
                  "plane-normal-known", "plane-normal-unknown", "distance")
