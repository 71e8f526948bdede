"""What the geometric model gets wrong on measured data, and which effect explains it:
``estcal diagnose`` and ``estcal.diagnose`` (docs/discrepancy.md).

:func:`diagnose` loads the robot (with the URDF chain's trailing link masses, by default) and the
datasets, checks them (distinct poses, sessions and validation files kept apart) and runs
:func:`estcal.discrepancy.diagnose`; the result records how to rebuild the robot
(``model["robot_spec"]``, root, tip) for ``estcal simulate --from-fit``.
"""
from __future__ import annotations

from pathlib import Path

from estcal.base.errors import InputError, NumericalRefusal
from estcal.workflows.inputs import (check_distinct_poses, check_held_out, check_input_files, input_errors,
                                     load_datasets, robot_for_data, split_names, warn_datasets)

__all__ = ["diagnose", "check_effects"]


def check_effects(effects) -> list[str] | None:
    """Effect names (a list or comma-separated text) checked against the registered effects; ``"none"`` (or an
    empty list) for none: the geometric model alone, scored like the model with effects."""
    if isinstance(effects, str) and effects.strip().lower() == "none":
        return []
    names = split_names(effects, "--effects")
    if names is None:
        return None
    from estcal.effects import EFFECTS

    bad = [e for e in names if e not in EFFECTS]
    if bad:
        raise InputError(f"--effects: unknown effect(s) {bad}; registered: {', '.join(sorted(EFFECTS))}")
    return names


#: former ``--geometric`` choices and what replaced them
_FORMER_GEOMETRIC = {
    "prior": "the default model (sparse: every term under a relevance prior) replaces it",
    "auto": "the default model (sparse) replaces the choice among levels",
    "aic": "the default model (sparse) keeps the geometric parameters the evidence supports",
}
#: the choices of ``geometric``
GEOMETRIC = ("sparse", "full", "joint_offset")


def width_from_text(text: str):
    """``--geometric-width-mm``'s value as ``geometric_width``: ``auto`` (kept), ``inf`` (None: unbounded) or a
    positive number of mm / mrad (to m / rad); anything else an :class:`InputError` naming the option."""
    t = str(text).strip().lower()
    if t == "auto":
        return "auto"
    try:
        w = float(t)
    except ValueError:
        w = float("nan")
    if not w > 0:
        raise InputError(f"--geometric-width-mm {text}: give auto (the default), inf (unbounded) or a number > 0 "
                         f"(mm for a length, mrad for an angle; e.g. 1)")
    return None if w == float("inf") else w * 1e-3


def diagnose(robot, data, *, validate=(), effects=None, noise=None, points: int | None = None, root=None, tip=None,
             urdf_chain_masses: bool = True, column_map=None, drop_flagged: bool = True, folds: int = 5,
             geometric: str = "sparse", budget: bool = True, seed: int = 0, approach_from_order: bool = True,
             posture_tol=(1e-3, 1e-3), robot_spec=None, report=None, register_zeros: bool = True,
             geometric_width: float | str | None = "auto"):
    """Diagnose ``robot`` on ``data`` — the job of ``estcal diagnose`` and ``estcal.diagnose``.

    Parameters
    ----------
    robot : SerialRobot, built-in name, robot file or URDF; data : a dataset (path or Dataset) or
        a list of them, one per session (fitted together, each session's measuring frame registered).
    validate : datasets scored at their new postures (their frame registered on their rows at seen postures,
        and the joint zeros those rows show moved since training), never used for a decision.
    effects : effect names to consider (default: every registered effect, docs/effects.md).
    noise : a :class:`~estcal.methods.NoiseModel` (the rows' relative weights; its scale is fitted either way).
    urdf_chain_masses : for URDF robots, count the links after the last actuated joint in its mass.
    column_map, drop_flagged : the data's column map; leave out the rows the data screening flags (the
        default, as ``estcal calibrate``'s: readings beyond the limits, outliers after a robust fit, swapped or
        ghost markers, copies — named in the output by file and line; ``False``: every row is fitted).
    folds : cross-validation folds (by posture, and by session with several sessions); seed : their seed.
    geometric : ``sparse`` (default), ``full`` or ``joint_offset`` (:func:`estcal.discrepancy.diagnose`).
    geometric_width : the widest prior standard deviation of a link frame's parameter (m / rad): ``"auto"``
        (the default) 1 mm / 1 mrad unless the unbounded model's cross-validated error is lower by more than one
        standard error; None or ``inf``: unbounded; a number: that bound (docs/discrepancy.md).
    budget : the error budget (nested CV, time-blocked CV, the 95 % region); without it the expected error is
        the model's CV with its all-rows choices (optimistic, said in the answer).
    approach_from_order : approach directions from the acquisition order (default; backlash by approach
        is then a candidate beside backlash by the load).
    posture_tol : ``(tol_rad, tol_m)`` of the posture grouping.
    report : a folder for the report (figures, diagnosis.json, summary.txt, index.html).
    register_zeros : register a validation file's moved joint zeros on its seen rows (default; False: its
        measuring frame only).

    Returns a :class:`~estcal.discrepancy.result.DiagnosisResult`.
    """
    from estcal.discrepancy import diagnose as _diagnose
    from estcal.identify.select import UnidentifiableError

    if geometric in _FORMER_GEOMETRIC:
        raise InputError(f"geometric={geometric!r}: {_FORMER_GEOMETRIC[geometric]}; choose one of "
                         f"{', '.join(GEOMETRIC)} (docs/discrepancy.md)")
    if geometric not in GEOMETRIC:
        raise InputError(f"geometric={geometric!r} is not a choice; choose one of {', '.join(GEOMETRIC)}")
    if geometric_width is not None and geometric_width != "auto":
        w = geometric_width
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not w > 0:
            raise InputError(f"geometric_width must be 'auto' (the default), a positive width in m / rad (1e-3: 1 mm, "
                             f"1 mrad) or None for unbounded priors, got {geometric_width!r}")
        geometric_width = None if geometric_width == float("inf") else float(geometric_width)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise InputError(f"folds must be an integer ≥ 2, got {folds!r}")
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    check_input_files([*items, *validate])
    rob, n_markers = robot_for_data(robot, items[0], points, root, tip, column_map)
    if urdf_chain_masses and rob.meta.get("urdf"):
        from estcal.discrepancy.masses import with_urdf_masses

        rob = with_urdf_masses(rob)
    sessions = load_datasets(items, rob, n_markers, column_map)
    vals = load_datasets(validate, rob, n_markers, column_map)
    warn_datasets(sessions + vals)
    names = check_effects(effects)
    for d in sessions:
        check_distinct_poses(d)
    from estcal.workflows.check import screen_rows

    sessions, left = screen_rows(sessions, rob, drop_flagged, warn_dropped=False)
    check_held_out(sessions, [], "session")
    check_held_out(sessions, vals)
    spec = robot_spec or (str(robot) if isinstance(robot, (str, Path)) and not (root or tip) else None)
    ds = sessions[0] if len(sessions) == 1 else sessions
    try:
        with input_errors():
            res = _diagnose(rob, ds, validate=vals, effects=names, noise=noise, k_folds=folds, rng=seed,
                            geometric=geometric, budget=budget, approach_from_order=approach_from_order,
                            posture_tol=posture_tol, robot_spec=spec, register_zeros=register_zeros,
                            geometric_width=geometric_width)
    except UnidentifiableError as exc:
        where = ", ".join(str(getattr(d, "where", d)) for d in sessions)
        raise NumericalRefusal(f"{where}: {exc} (the fit on {sum(d.n for d in sessions)} poses, and each "
                               f"cross-validation fold of folds={folds}, needs more equations than "
                               f"parameters)") from exc
    if isinstance(robot, (str, Path)):
        res.model["robot_spec"] = str(robot)
    res.model["root"], res.model["tip"] = root, tip
    res.model["urdf_chain_masses"] = bool(urdf_chain_masses and rob.meta.get("urdf"))
    res.data["left_out"] = [{k: r[k] for k in ("file", "line", "kind", "reason")} for r in left]
    res.data["drop_flagged"] = bool(drop_flagged)
    if report is not None:  # the analysis writes no file: figures, diagnosis.json, summary.txt, index.html
        from estcal.report.diagnose import diagnose_report

        where = ", ".join(str(getattr(d, "where", d)) for d in sessions)
        diagnose_report(report, res, title=f"estcal diagnose — {res.robot.name if res.robot else robot}, {where}")
    return res
