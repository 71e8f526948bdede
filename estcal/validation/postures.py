"""Postures: which measurements were taken at the same robot configuration.

A model scored at a posture it was fitted on shows how well it *remembers*, not
how well it predicts. Real calibration campaigns repeat postures — the same
commanded list in every session, or the same posture twice in one file — so a
row-wise split puts the twin of a held-out row in the training set, and every
cross-validation built on it is optimistic. Here rows are grouped by posture
and every split keeps a posture on one side.

Two rows share a posture when their joint readings agree within a tolerance on
every joint (``tol_rad`` for revolute, ``tol_m`` for prismatic joints; default
1e-3 rad / 1e-3 m — a commanded posture reproduced by the controller typically
agrees to 1e-4, distinct postures of a calibration plan differ by 0.05 or more).
Agreement is taken transitively (connected components of the "agree" graph), so a
chain of near-identical readings is one posture.

Functions
---------
posture_groups(readings, joint_types, tol_rad, tol_m) -> (N,) int labels
grouped_folds(groups, k, rng) -> list of row-index arrays, no posture split
seen_postures(train_readings, test_readings, ...) -> (M,) bool
inside_ranges(train_readings, readings) -> (M,) bool
extrapolation_distance(train_readings, readings) -> (M, n) beyond each joint's training range, in ranges
"""
from __future__ import annotations

import numpy as np

__all__ = ["DEFAULT_TOL_RAD", "DEFAULT_TOL_M", "joint_tolerances", "posture_groups", "grouped_folds",
           "seen_postures", "n_postures", "inside_ranges", "extrapolation_distance"]

#: default agreement of two readings of the same posture (rad for revolute, m for prismatic joints)
DEFAULT_TOL_RAD = 1e-3
DEFAULT_TOL_M = 1e-3


def joint_tolerances(n_joints: int, joint_types=None, tol_rad: float = DEFAULT_TOL_RAD,
                     tol_m: float = DEFAULT_TOL_M) -> np.ndarray:
    """Per-joint tolerance (n,): ``tol_m`` for prismatic joints, ``tol_rad`` otherwise."""
    if tol_rad <= 0 or tol_m <= 0:
        raise ValueError(f"posture tolerances must be positive (got {tol_rad} rad, {tol_m} m)")
    types = list(joint_types) if joint_types is not None else ["revolute"] * n_joints
    if len(types) != n_joints:
        raise ValueError(f"{len(types)} joint types for {n_joints} joint columns")
    return np.array([tol_m if t == "prismatic" else tol_rad for t in types], float)


def posture_groups(readings, joint_types=None, tol_rad: float = DEFAULT_TOL_RAD, tol_m: float = DEFAULT_TOL_M
                   ) -> np.ndarray:
    """Posture label of every row: rows whose readings agree within the tolerance share it.

    Parameters
    ----------
    readings : (N, n) joint readings (rad / m) of every row, of every file and session stacked.
    joint_types : n entries ``"revolute"`` / ``"prismatic"`` (default: all revolute).
    tol_rad, tol_m : agreement on every joint (Chebyshev distance of the readings scaled
        by the per-joint tolerance ≤ 1), taken transitively.

    Returns
    -------
    (N,) int labels 0…G−1, numbered in order of first appearance.

    Uses a k-d tree (``scipy.spatial.cKDTree.query_pairs`` with the max-norm) and the
    connected components of the pairs (``scipy.sparse.csgraph``): O(N log N), no N × N matrix.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    Q = np.asarray(readings, float)
    if Q.ndim != 2:
        raise ValueError(f"readings must be (N, n joints), got shape {Q.shape}")
    N = Q.shape[0]
    if N == 0:
        return np.zeros(0, int)
    if not np.all(np.isfinite(Q)):
        raise ValueError("readings contain NaN or inf: postures cannot be grouped")
    tol = joint_tolerances(Q.shape[1], joint_types, tol_rad, tol_m)
    pairs = cKDTree(Q / tol).query_pairs(1.0 + 1e-12, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])) if len(pairs) else
                       (np.zeros(0), (np.zeros(0, int), np.zeros(0, int))), shape=(N, N))
    _, lab = connected_components(graph, directed=False)
    # renumber in order of first appearance (stable, readable labels)
    _, first = np.unique(lab, return_index=True)
    order = np.argsort(first)
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    return remap[np.unique(lab, return_inverse=True)[1]]


def n_postures(groups) -> int:
    """Number of distinct postures in a label array."""
    return int(len(np.unique(np.asarray(groups))))


def grouped_folds(groups, k: int = 5, rng=0) -> list[np.ndarray]:
    """``k`` test folds (sorted row indices) such that every posture lies in exactly one fold.

    Postures are shuffled with ``rng`` and dealt to the fold with the fewest rows so far
    (largest posture first), so folds stay balanced in rows when postures repeat unevenly.
    ``k`` is capped at the number of postures (``k = G`` is leave-one-posture-out).
    """
    g = np.asarray(groups)
    labels, counts = np.unique(g, return_counts=True)
    G = len(labels)
    if G < 2:
        raise ValueError(f"cross-validation needs at least 2 distinct postures, the data have {G}")
    k = int(min(max(int(k), 2), G))
    perm = np.random.default_rng(rng).permutation(G)
    perm = perm[np.argsort(-counts[perm], kind="stable")]
    load = np.zeros(k, int)
    owner = np.empty(G, int)
    for i in perm:
        f = int(np.argmin(load))
        owner[i] = f
        load[f] += counts[i]
    fold_of_row = owner[np.searchsorted(labels, g)]
    return [np.flatnonzero(fold_of_row == f) for f in range(k)]


def seen_postures(train_readings, test_readings, joint_types=None, tol_rad: float = DEFAULT_TOL_RAD,
                  tol_m: float = DEFAULT_TOL_M) -> np.ndarray:
    """(M,) True where a test row's posture was measured in training (within the tolerance).

    Grouping is done on training and test rows together (transitively), so a test row
    joins a training posture through other rows too.
    """
    A = np.asarray(train_readings, float)
    B = np.asarray(test_readings, float)
    if A.shape[0] == 0:
        return np.zeros(B.shape[0], bool)
    lab = posture_groups(np.vstack([A, B]), joint_types, tol_rad, tol_m)
    return np.isin(lab[A.shape[0]:], lab[: A.shape[0]])


def extrapolation_distance(train_readings, readings) -> np.ndarray:
    """(M, n) how far each joint reading of ``readings`` lies beyond the range the training rows span on that
    joint, in units of that range: ``max(0, q − max_A q, min_A q − q) / (max_A q − min_A q)`` (0 inside; a
    joint the training rows never move counts its distance in its own units). A model's error grows with it
    (docs/real-data.md); :func:`inside_ranges` is ``all(d == 0)``."""
    A = np.asarray(train_readings, float)
    B = np.asarray(readings, float)
    lo, hi = A.min(0), A.max(0)
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.maximum(0.0, np.maximum(B - hi, lo - B)) / span


def inside_ranges(train_readings, readings) -> np.ndarray:
    """(M,) True where every joint reading of a row lies within the range the training rows span on that
    joint (an interpolation); False where at least one joint is outside it (an extrapolation, where a
    model's error grows: docs/real-data.md)."""
    A = np.asarray(train_readings, float)
    B = np.asarray(readings, float)
    return np.all((B >= A.min(0)) & (B <= A.max(0)), axis=1)
