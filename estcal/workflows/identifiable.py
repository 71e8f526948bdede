"""Identifiable (base) parameters of a robot for a measurement: ``estcal identifiable``
(docs/identification.md).

:func:`identifiable` builds the observation matrix of the measurement from random admissible
configurations (``n_poses``, ``seed``; inverse geometric model for the link measurements,
plane-constrained points for the planar ones) or from a dataset (``data``, which also checks its
excitation against random configurations), and runs the priority-ordered QR of GECARO App. III
(:func:`estcal.identify.identify`). A Gough-platform robot file is dispatched to
:func:`estcal.workflows.gough.identifiable_gough`.
"""
from __future__ import annotations

from pathlib import Path

from estcal.base.errors import InputError
from estcal.workflows.inputs import check_input_files, input_errors

__all__ = ["identifiable", "MEASURE_HELP"]

MEASURE_HELP = ("position, pose, point-link, frame-link, plane-known, plane-unknown, plane-normal-known, "
               "plane-normal-unknown, distance (default with --data: from the columns)")


def _plane(text: str | None):
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--plane expects three numbers a,b,c (a x + b y + c z + 1 = 0, 1/m), got {text!r}") from None
    if len(vals) != 3:
        raise ValueError(f"--plane expects three numbers a,b,c, got {len(vals)}")
    if not all(v == v and abs(v) != float("inf") for v in vals) or not any(vals):
        raise ValueError(f"--plane {text}: a, b, c must be finite and not all zero (a x + b y + c z + 1 = 0, 1/m)")
    return vals


def identifiable(robot, measure: str | None = None, data=None, n_poses: int = 60, seed: int = 0,
                 priority=None, free=None, rules: str = "gecaro", pivoting: bool = False, plane: str | None = None,
                 points: int | None = None, root: str | None = None, tip: str | None = None,
                 tau_floor: float = 1e-10, column_map=None):
    """Identifiable, no-effect and regrouped parameters of ``robot`` for ``measure`` — the job of
    ``estcal identifiable``. Returns an :class:`~estcal.identify.IdentifiabilityResult` (or, for a
    Gough platform, its dict). ``column_map``: the column map of ``data`` (docs/dataset.md)."""
    try:
        with input_errors():
            try:
                return _identifiable(robot, measure, data, n_poses, seed, priority, free, rules, pivoting, plane,
                                     points, root, tip, tau_floor, column_map)
            except RuntimeError as exc:  # e.g. no admissible configuration of a link measurement
                raise InputError(str(exc)) from exc
    except InputError as exc:
        msg = str(exc)
        if free is not None and msg.startswith(("unknown parameter", "patterns ")):
            raise InputError(f"--free: {msg}") from exc
        raise


def _identifiable(robot, method, data, n_poses, seed, priority, free, rules, pivoting, plane, points, root, tip,
                  tau_floor, column_map=None):
    from estcal.identify import identify, load_priorities
    from estcal.io.dataset import load_dataset
    from estcal.io.robotfile import load_robot

    from estcal.parallel import is_gough_file

    if is_gough_file(robot):
        from estcal.workflows.gough import identifiable_gough

        return identifiable_gough(robot, data, n_poses=n_poses, seed=seed,
                                  free=None if free is None else [f.strip() for f in free.split(",")])
    rb = load_robot(robot, root=root, tip=tip)
    ds = None
    if method == "location":
        method = "pose"
    if data is not None:
        check_input_files([data])
        ds = load_dataset(data, rb, column_map=column_map)
        k = points if points is not None else (ds.n_points if ds.kind == "points" else None)
        if k and k > 1 and rb.n_markers != k:
            rb = load_robot(robot, root=root, tip=tip, n_markers=k)
        if points is not None:
            ds = ds.with_points(points)
    elif points:
        rb = load_robot(robot, root=root, tip=tip, n_markers=points)
    if method is None and ds is None:
        raise InputError("give --measure (one of " + MEASURE_HELP + ") or --data")
    if method == "points" and ds is None:
        raise ValueError("method 'points' needs --data (several measured points); use position/location for "
                         "random configurations")
    options = {}
    pl = _plane(plane)
    if pl is not None:
        if method not in ("plane-known", "plane-normal-known"):
            raise ValueError("--plane applies to plane-known and plane-normal-known")
        options["plane"] = pl
    gen = {"plane": pl} if (pl is not None and ds is None) else None
    prio = load_priorities(priority) if priority is not None else None
    cands = None if free is None else [f.strip() for f in free.split(",") if f.strip()]
    return identify(rb, method, ds, n_poses=n_poses, seed=seed, priorities=prio, rules=rules, candidates=cands,
                    pivoting=pivoting, method_options=options, generator_options=gen, tau_floor=tau_floor)
