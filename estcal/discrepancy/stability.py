"""Causes that survive a new split: named only when most posture-grouped folds name them too.

On small real files the forward selection of :func:`estcal.discrepancy.diagnose` can name a
different cause for every subset of postures (a gear harmonic on one half, nothing on the
other, a drift on a third): a cause that does not survive a new split is not a cause. The
stability check runs the diagnosis on the training part of every posture-grouped fold (no
posture on both sides) and on all the data, and keeps a cause (effect and joints) only if

* the diagnosis of all the data names it, and
* it is named in more than half of the folds (the count is reported), and
* the model with the kept causes lowers the posture-grouped CV RMSE of the geometric model
  (checked by the caller with :func:`estcal.discrepancy.budget.error_budget`, whose ``named_mm``
  and ``geometric_mm`` are that comparison).

Time runs from the start of each session (``session_time``), so a drift term is zero at
every session's first posture and can never explain an offset between sessions: that is the
repeatability's (between-session) part of the budget.
"""
from __future__ import annotations

import numpy as np

from estcal.validation import grouped_folds, posture_groups

__all__ = ["stable_causes", "cause_key"]


def cause_key(cause) -> str:
    """``effect(joint,…)`` of a named cause (joint-less effects: ``effect(arm)``)."""
    joints = ",".join(cause.joints) if cause.joints else "arm"
    orders = cause.options.get("orders") if getattr(cause, "options", None) else None
    return f"{cause.effect}{list(orders) if orders else ''}({joints})"


def stable_causes(robot, data, *, level: str = "full", k_folds: int = 5, rng=0, groups=None, tol_rad: float = 1e-3,
                  tol_m: float = 1e-3, **diagnose_kw) -> dict:
    """Diagnose ``data`` and every posture-grouped fold's training part; count the causes named.

    Returns ``{"all": [keys named on all data], "counts": {key: folds naming it}, "k_folds": k,
    "kept": [keys named on all data and in > k/2 folds], "effects": [(effect, joints, options)
    of the kept causes, in the order the full diagnosis named them], "diagnosis": the full
    :class:`~estcal.discrepancy.diagnose.DiagnosisResult`}``.
    """
    from estcal.discrepancy.diagnose import diagnose

    kw = {"geometric": level, **diagnose_kw}
    g = posture_groups(data.readings, robot.joint_types, tol_rad, tol_m) if groups is None else np.asarray(groups)
    full = diagnose(robot, data, rng=rng, **kw)
    names = [cause_key(c) for c in full.causes]
    folds = grouped_folds(g, k_folds, rng)
    counts: dict = {}
    for test in folds:
        train = np.setdiff1d(np.arange(data.n), test)
        d = diagnose(robot, data.subset(train), rng=rng, **kw)
        for key in {cause_key(c) for c in d.causes}:
            counts[key] = counts.get(key, 0) + 1
    kept = [n for n in names if counts.get(n, 0) > len(folds) / 2]
    effects = [(c.effect, list(c.joints), dict(c.options or {})) for c in full.causes if cause_key(c) in kept]
    return {"all": names, "counts": counts, "k_folds": len(folds), "kept": kept, "effects": effects,
            "diagnosis": full}
