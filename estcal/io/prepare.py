"""Data prepared for a model: the columns its effects read, and what the saved fit did to its data.

* :func:`with_effect_context` — the ``approach_<joint>`` columns moved into the context, so that
  :class:`~estcal.methods.problem.Problem` passes them to the effects (backlash);
* :func:`derive_approach` — the approach direction of each joint inferred from the posture order;
* :func:`prepare_data` — a dataset prepared for a saved (diagnosed) model as that fit prepared its own
  (``calibration.data_preparation``).
"""
from __future__ import annotations

import numpy as np

__all__ = ["with_effect_context", "derive_approach", "prepare_data"]


def with_effect_context(robot, data):
    """Dataset copy whose ``context`` also carries the columns the robot's effects read
    (e.g. ``approach_<joint>`` for backlash), so :class:`Problem` passes them on."""
    d = data.subset(slice(None))
    for k, v in (data.columns or {}).items():
        if k.startswith("approach_") and k not in d.context:
            d.context[k] = np.asarray(v, float)
    return d


def derive_approach(data, threshold: float = 1e-3):
    """Copy of ``data`` with ``approach_<joint>`` columns inferred from the posture order.

    Static postures recorded one after the other are each reached by moving from
    the previous one, so joint j approached posture i from the side
    ``sign(q_j(i) − q_j(i−1))`` (time order from ``t`` when present, else the row
    order; each session of a ``session`` column on its own). Moves smaller than ``threshold`` (rad or m),
    and the first posture, get 0 (unknown). Existing ``approach_*`` columns are kept. A backlash by approach
    reads them (``δq = −b·sign(approach)``; ``by="auto"`` prefers them to the load's side).
    """
    d = data.subset(slice(None))
    dq = np.zeros_like(d.readings)
    # sessions stacked in one file (a ``session`` column): each has its own sequence, its first posture 0
    lab = d.columns.get("session")
    groups = [np.arange(d.n)] if lab is None else [np.flatnonzero(lab == s) for s in np.unique(lab)]
    t = d.context.get("t")
    for rows in groups:
        order = rows[np.argsort(t[rows], kind="stable")] if t is not None else rows
        dq[order[1:]] = np.diff(d.readings[order], axis=0)
    for j, name in enumerate(d.joint_names):
        key = f"approach_{name}"
        if key in d.columns or key in d.context:
            continue
        a = np.sign(dq[:, j])
        a[np.abs(dq[:, j]) < threshold] = 0.0
        d.columns[key] = a
    return d


def prepare_data(robot, data, preparation: dict | None = None):
    """``data`` prepared for ``robot`` as the fit that saved it prepared its own.

    ``preparation`` (default: the robot's ``calibration.data_preparation``, written for a
    diagnosed model): ``approach_from_order`` — approach columns from the posture order;
    ``session_time`` — ``t`` measured from the first pose of the file, or from its mean time when
    it is ``"centred"`` (a model fitted on several sessions; the absolute time stays in
    ``columns["t_abs"]``); ``time_source`` — ``"row order"`` when the model's time was the row order
    of files without a time column (then ``t`` is the row index here too). Effect columns
    (``approach_<joint>``) are moved into the context in every case.
    """
    if preparation is None:
        preparation = (robot.meta.get("calibration") or {}).get("data_preparation") or {}
    d = derive_approach(data) if preparation.get("approach_from_order") else data
    d = with_effect_context(robot, d)
    if preparation.get("time_source") == "row order":
        d.context["t"] = np.arange(d.n, dtype=float)
    if preparation.get("session_time") and "t" in d.context:
        d.columns["t_abs"] = d.context["t"].copy()
        t = d.context["t"]
        d.context["t"] = t - (t.mean() if preparation["session_time"] == "centred" else t.min())
    return d
