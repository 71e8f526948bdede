"""Scores split by posture: rows at postures seen in training vs rows at new postures.

A validation figure is only a prediction figure for rows at postures the model was
not fitted on. :func:`seen_new_scores` reports the two apart; a validation made only
of seen postures is flagged (``only_seen``), because its RMSE measures memory.
"""
from __future__ import annotations

import numpy as np

__all__ = ["rmse_mm", "rmse_se_mm", "seen_new_scores", "validation_split"]


def rmse_mm(errors) -> float | None:
    """RMS (mm) of point-error norms (m), any shape; ``None`` when empty."""
    e = np.asarray(errors, float).reshape(-1)
    return float(np.sqrt(np.mean(e ** 2)) * 1e3) if e.size else None


def rmse_se_mm(errors, groups) -> float | None:
    """Standard error (mm) of :func:`rmse_mm` of ``errors`` (M, k) point-error norms (m) over the postures
    ``groups`` (M,) they were measured at: the postures are the independent units (the rows of one posture share
    its error), so the mean square is a ratio of per-posture sums ``S_g`` over per-posture counts ``n_g`` and its
    variance the ratio estimator's, ``G/(G−1) Σ_g (S_g − MSE·n_g)² / (Σ_g n_g)²`` (Cochran 1977, *Sampling
    Techniques*, §6.4, the clusters' ratio mean), carried to the root by the δ-method, ``se(RMSE) = se(MSE) /
    (2 RMSE)``. ``None`` with fewer than two postures or a zero RMSE.

    The sampling error of the figure itself: a validation of a few dozen postures scores the model to ±10–20 %
    (``experiments/tiago_disjoint.md``), however exact the model's own prediction of it."""
    E = np.asarray(errors, float)
    E = E.reshape(len(E), -1)
    g = np.unique(np.asarray(groups), return_inverse=True)[1].reshape(-1)
    G = int(g.max()) + 1 if g.size else 0
    if G < 2:
        return None
    S = np.bincount(g, weights=np.sum(E ** 2, axis=1), minlength=G)
    n = np.bincount(g, minlength=G) * E.shape[1]
    mse = S.sum() / n.sum()
    if not mse > 0:
        return None
    var = G / (G - 1) * np.sum((S - mse * n) ** 2) / n.sum() ** 2
    return float(np.sqrt(var) / (2.0 * np.sqrt(mse)) * 1e3)


def seen_new_scores(errors, seen, inside=None) -> dict:
    """RMSE of the rows at seen and at new postures.

    Parameters
    ----------
    errors : (M, k) point-error norms (m) of M validation rows, k points each.
    seen : (M,) bool, True where the row's posture was in the training data
        (:func:`estcal.validation.seen_postures`).
    inside : optional (M,) bool, True where a new row lies inside the training joint
        ranges (interpolation) — reported as ``new_inside`` / ``new_outside``.

    Returns
    -------
    ``{"all": {n_rows, rmse_mm}, "seen": {…}, "new": {…}, "only_seen": bool}`` (plus the
    inside/outside split when given); ``rmse_mm`` is ``None`` for an empty part.
    """
    E = np.asarray(errors, float)
    E = E.reshape(len(E), -1)
    seen = np.asarray(seen, bool)

    def part(m):
        return {"n_rows": int(m.sum()), "rmse_mm": rmse_mm(E[m])}

    out = {"all": part(np.ones(len(E), bool)), "seen": part(seen), "new": part(~seen),
           "only_seen": bool(len(E) > 0 and seen.all())}
    if inside is not None:
        ins = np.asarray(inside, bool)
        out["new_inside"] = part(~seen & ins)
        out["new_outside"] = part(~seen & ~ins)
    return out


def validation_split(train_readings, valid_readings, errors, joint_types=None, tol_rad: float = 1e-3,
                     tol_m: float = 1e-3) -> dict:
    """:func:`seen_new_scores` of a validation file against the training rows (all files stacked),
    with the rows inside the training joint ranges marked, and a ``warning`` when every validation
    row is at a seen posture (its RMSE measures memory, not accuracy at new postures)."""
    from .postures import inside_ranges, seen_postures

    A = np.asarray(train_readings, float)
    B = np.asarray(valid_readings, float)
    seen = seen_postures(A, B, joint_types, tol_rad, tol_m)
    inside = inside_ranges(A, B)
    out = seen_new_scores(errors, seen, inside)
    out["warning"] = ("every validation row is at a posture seen in training: this RMSE measures memory, "
                      "not accuracy at new postures") if out["only_seen"] else None
    return out
