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
    """Effect names (a list or comma-separated text) checked against the registered effects."""
    names = split_names(effects, "--effects")
    if names is None:
        return None
    from estcal.effects import EFFECTS

    bad = [e for e in names if e not in EFFECTS]
    if bad:
        raise InputError(f"--effects: unknown effect(s) {bad}; registered: {', '.join(sorted(EFFECTS))}")
    return names


def diagnose(robot, data, *, validate=(), effects=None, noise=None, points: int | None = None, root=None, tip=None,
             urdf_chain_masses: bool = True, column_map=None, drop_flagged: bool = False, k_folds: int = 5, **kw):
    """Diagnose ``robot`` on ``data`` — the job of ``estcal diagnose``.

    Parameters
    ----------
    robot : SerialRobot, built-in name, robot file or URDF; data : a dataset (path or Dataset) or
        a list of them, one per session (fitted together; approach and time per session).
    validate : datasets scored with both models, never used for a decision.
    effects : effect names to try (default: every registered effect, docs/effects.md).
    noise : a :class:`~estcal.methods.NoiseModel` (known: likelihood-ratio and noise-floor tests)
        or None (unknown: F tests).
    urdf_chain_masses : for URDF robots, count the links after the last actuated joint in its mass.
    column_map, drop_flagged : the data's column map; leave out the rows the screening flags
        (:func:`estcal.workflows.check.screen`; their findings are warned either way).
    k_folds, **kw : options of :func:`estcal.discrepancy.diagnose` (``alpha``, ``max_effects``,
        ``geometric``, ``approach_from_order``, ``rng``, ``report`` …); ``geometric="prior"`` runs
        :func:`estcal.discrepancy.prior_model.diagnose_prior` instead (the MAP group-prior model, no
        effect selection; ``effects`` refused); ``geometric="auto"`` runs
        :func:`estcal.discrepancy.prior_model.diagnose_auto` (the level chosen by posture-grouped CV among
        the prior model, preferred, and the levels; with ``effects``, among the levels only).

    Returns a :class:`~estcal.discrepancy.diagnose.DiagnosisResult`.
    """
    from estcal.discrepancy import diagnose as _diagnose
    from estcal.identify.select import UnidentifiableError

    from estcal.discrepancy.residual import RESIDUAL_MODELS

    if kw.get("residual_model") not in (None, *RESIDUAL_MODELS):
        raise InputError(f"--residual-model: unknown {kw['residual_model']!r}; choose one of "
                         f"{', '.join(RESIDUAL_MODELS)}")
    mode = kw.get("geometric", "full")
    mode = "auto+prior" if mode == "auto" and effects is None else mode
    # the prior model's options, and where they apply (with --effects, auto chooses among the levels only)
    for key, flag, where in (("widths", "--prior-widths", ("prior", "auto+prior")),
                             ("criterion", "--prior-criterion", ("prior", "auto+prior")),
                             ("session_frames", "--session-frames", ("prior",))):
        if key in kw and mode not in where:
            raise InputError(f"{flag}: only with --geometric {' or '.join(w.split('+')[0] for w in where)} (without "
                             f"--effects); got --geometric {kw.get('geometric', 'full')}"
                             + (" with --effects" if effects is not None else ""))
    if mode in ("prior", "auto+prior"):  # the MAP group-prior model: loaded only when asked for
        from estcal.discrepancy.prior_model import EFFECTS as PRIOR_EFFECTS
        from estcal.discrepancy.prior_model import SESSION_FRAMES, WIDTH_CHOICES

        if mode == "prior" and effects is not None:
            raise InputError(f"--effects: --geometric prior keeps every {', '.join(PRIOR_EFFECTS)} term the data "
                             "can excite under its prior and selects no effect, so there is nothing to choose "
                             "from; drop --effects, or choose another --geometric (docs/real-data.md, 'A prior "
                             "instead of a level')")
        for key, flag, choices in (("widths", "--prior-widths", WIDTH_CHOICES),
                                   ("criterion", "--prior-criterion", ("evidence+cv", "evidence")),
                                   ("session_frames", "--session-frames", SESSION_FRAMES)):
            if kw.get(key, choices[0]) not in choices:
                raise InputError(f"{flag}: {kw[key]!r} is not a choice; give {' or '.join(choices)}")
        if mode == "prior":
            from estcal.discrepancy.prior_model import diagnose_prior as _diagnose
        else:  # the level choice with the prior model as its preferred candidate
            from estcal.discrepancy.prior_model import diagnose_auto as _diagnose

            kw.pop("geometric")
    items = list(data) if isinstance(data, (list, tuple)) else [data]
    check_input_files([*items, *validate])
    rob, n_markers = robot_for_data(robot, items[0], points, root, tip, column_map)
    if urdf_chain_masses and rob.meta.get("urdf"):
        from estcal.discrepancy.masses import with_urdf_masses

        rob = with_urdf_masses(rob)
    sessions = load_datasets(items, rob, n_markers, column_map)
    vals = load_datasets(validate, rob, n_markers, column_map)
    warn_datasets(sessions + vals)
    cands = check_effects(effects)
    for d in sessions:
        check_distinct_poses(d)
    from estcal.workflows.check import screen

    sessions = screen(sessions, rob, drop_flagged)
    check_held_out(sessions, [], "session")
    check_held_out(sessions, vals)
    spec = str(robot) if isinstance(robot, (str, Path)) and not (root or tip) else None
    kw.setdefault("robot_spec", spec)
    ds = sessions[0] if len(sessions) == 1 else sessions
    report = kw.pop("report", None)
    try:
        with input_errors():
            res = _diagnose(rob, ds, validate=vals, candidates=cands, noise=noise, k_folds=k_folds, **kw)
    except UnidentifiableError as exc:
        where = ", ".join(str(getattr(d, "where", d)) for d in sessions)
        raise NumericalRefusal(f"{where}: {exc} (the geometric fit on {sum(d.n for d in sessions)} poses, and each "
                               f"cross-validation fold of --folds {k_folds}, needs more equations than "
                               f"parameters)") from exc
    if isinstance(robot, (str, Path)):
        res.model["robot_spec"] = str(robot)
    res.model["root"], res.model["tip"] = root, tip
    res.model["urdf_chain_masses"] = bool(urdf_chain_masses and rob.meta.get("urdf"))
    if report is not None:  # the analysis writes no file: figures, diagnosis.json, summary.txt, index.html
        from estcal.report.diagnose import diagnose_report

        where = ", ".join(str(getattr(d, "where", d)) for d in sessions)
        diagnose_report(report, res, title=f"estcal diagnose — {res.robot.name if res.robot else robot}, {where}")
    return res
