"""``estcal diagnose``: what the geometric model gets wrong on measured data, and which effect explains it.

Runs :func:`estcal.workflows.diagnose.diagnose` (geometric fit, residual analysis, forward
selection of library effects by BIC / significance test / cross-validation, identifiability by
QR) and prints the named cause(s), the verdict and the RMSE of the geometric and extended models
(train, CV, validation). Robot and data options are those of ``estcal calibrate``; the noise is
unknown (F tests) unless ``--known-noise`` is given (likelihood-ratio and noise-floor tests).

JSON (``--json PATH``): ``causes`` (list of {``effect``, ``joints``,
``parameters`` {name: {estimate, std}}, ``delta_bic``, ``explained_fraction``,
``test``, ``p_value``, …}), ``verdict``, ``rmse_mm`` and ``max_mm``
({``geometric``, ``extended``} × {``train``, ``cv``, ``validation``}),
``analysis`` (noise floor, feature R², spectrum), ``steps`` (selection log),
``model`` (the identified robot: every parameter value, effects, gravity — the
input of ``estcal simulate --from-fit``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (deprecated_option, json_option, known_noise_option, points_option,
                                posture_tol, posture_tol_mm_option, posture_tol_mrad_option, report_option,
                                robot_option, root_option, row_sigma_option, save_model_option, tip_option,
                                validate_option, with_row_sigma, drop_flagged_option, map_option)

__all__ = ["diagnose"]


def _noise(noise_pos_mm, noise_rot_mrad, known, old_noise_pos):
    """The measurement noise of ``diagnose`` (docs/conventions.md, "One vocabulary"): unknown by
    default; ``--known-noise`` trusts ``--noise-pos-mm`` / ``--noise-rot-mrad`` (defaults 0.1 mm /
    1 mrad). A noise given without ``--known-noise`` is still taken as known, as before, with a
    deprecation warning (orientation σ = the position number, as before, unless given)."""
    import warnings

    from estcal.base.errors import EstcalWarning
    from estcal.base.units import MILLI
    from estcal.cli.units import resolve
    from estcal.methods import NoiseModel

    pos = None if noise_pos_mm is None and old_noise_pos is None else \
        resolve(noise_pos_mm or 0.0, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.0)
    rot = None if noise_rot_mrad is None else noise_rot_mrad * MILLI
    if not known:
        if pos is None and rot is None:
            return None
        warnings.warn("a noise without --known-noise is taken as known (as before); write --known-noise — without "
                      "it, a noise will be a relative weight as in every other command (docs/conventions.md, "
                      "'One vocabulary')", EstcalWarning, stacklevel=2)
        pos = pos if pos is not None else 1e-4
        rot = rot if rot is not None else pos
        return NoiseModel(position=pos, orientation=rot, scalar=pos, known=True)
    pos = 1e-4 if pos is None else pos
    rot = 1e-3 if rot is None else rot
    return NoiseModel(position=pos, orientation=rot, scalar=pos, known=True)


@command("diagnose")
def diagnose(
    data: list[Path] = typer.Argument(..., help="Measured dataset(s) (CSV: joint columns + x,y,z / x1..zk / "
                                                "pose); several files are several sessions, fitted together "
                                                "(approach and time per session)."),
    robot: str = robot_option(),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    points: Optional[int] = points_option(),
    validate: list[Path] = validate_option(),
    column_map: Optional[Path] = map_option(),
    drop_flagged: bool = drop_flagged_option(),
    effects: Optional[str] = typer.Option(None, "--effects", help="Comma-separated effect names to try "
                                                                  "(default: every registered effect)."),
    noise_pos_mm: Optional[float] = typer.Option(None, "--noise-pos-mm", help="Position noise std per "
                                                 "coordinate (mm; default 0.1 with --known-noise)."),
    noise_rot_mrad: Optional[float] = typer.Option(None, "--noise-rot-mrad", help="Orientation noise std (mrad; "
                                                   "default 1 with --known-noise)."),
    known_noise: bool = known_noise_option("The noise is known (likelihood-ratio tests, noise-floor test); "
                                           "default unknown (F tests)."),
    old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
    row_sigma_mm: Optional[str] = row_sigma_option(),
    k_folds: int = typer.Option(5, "--folds", help="Cross-validation folds."),
    alpha: float = typer.Option(0.01, "--alpha", help="Family-wise significance level per selection step."),
    max_effects: int = typer.Option(3, "--max-effects", help="Most effects named."),
    urdf_masses: bool = typer.Option(True, "--urdf-chain-masses/--no-urdf-chain-masses",
                                     help="For URDF robots, count the links after the last actuated "
                                          "joint (tool, sensor, gripper) in its mass."),
    geometric: str = typer.Option("full", "--geometric", help="Geometric model: full (every identifiable "
                                  "parameter) | aic (those Akaike's criterion supports) | joint_offset | "
                                  "auto (by posture-grouped CV among prior, preferred, and the three levels) | "
                                  "prior (no selection: the full set and "
                                  "every excitable joint compliance, backlash and link tilt, each under a "
                                  "nominal-centred prior whose width the evidence chooses; docs/real-data.md)."),
    prior_widths: Optional[str] = typer.Option(None, "--prior-widths", help="With --geometric prior or auto: parameter (one "
                                               "width per parameter, automatic relevance determination; the "
                                               "default) | group (one per kind of parameter); docs/real-data.md."),
    session_frames: Optional[str] = typer.Option(None, "--session-frames", help="With --geometric prior and "
                                                 "several sessions: per-session (each further session's measuring "
                                                 "frame registered by the fit; the default) | one (one frame for "
                                                 "all); docs/real-data.md."),
    prior_criterion: Optional[str] = typer.Option(None, "--prior-criterion", help="With --geometric prior or auto: "
                                                  "evidence+cv (the evidence's widths times one multiplier by "
                                                  "leave-one-posture-out CV; the default) | evidence."),
    approach_from_order: bool = typer.Option(False, "--approach-from-order",
                                             help="Infer approach_<joint> columns from the posture order "
                                                  "(backlash by approach direction)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the fold assignment."),
    posture_tol_mrad: float = posture_tol_mrad_option(),
    posture_tol_mm: float = posture_tol_mm_option(),
    budget: bool = typer.Option(True, "--budget/--no-budget", help="Error budget by posture-grouped CV: nominal, "
                                "geometric, named, structured-unnamed (residual GP) and unstructured RMSE, the "
                                "repeatability floor and the predicted RMSE at new postures (docs/real-data.md)."),
    residual_model: Optional[str] = typer.Option(None, "--residual-model", help="gp: keep the residual Gaussian "
                                                 "process as a compensation layer of the recommended model, in the "
                                                 "space whose GP lowers the held-out error most; gp-joints / "
                                                 "gp-cartesian: in that space."),
    json_path: Optional[Path] = json_option("Write the diagnosis as JSON."),
    report: Optional[Path] = report_option("Folder for a report: residual figures (PNG), diagnosis.json, "
                                           "summary.txt and index.html with the tables."),
    save_model: Optional[Path] = save_model_option("Write the identified robot (geometry + named effects) as a "
                                                   "robot file (.yaml) with a 'calibration:' block; reload it "
                                                   "with --robot."),
) -> None:
    """Name the non-geometric cause of the residual of a geometric calibration and measure the gain."""
    from estcal.workflows.diagnose import diagnose as run

    noise = with_row_sigma(_noise(noise_pos_mm, noise_rot_mrad, known_noise, old_noise_pos), row_sigma_mm)
    res = run(robot, list(data), validate=list(validate), effects=effects, noise=noise, points=points, root=root,
              tip=tip, urdf_chain_masses=urdf_masses, k_folds=k_folds, alpha=alpha, max_effects=max_effects,
              report=report, rng=seed, geometric=geometric, approach_from_order=approach_from_order,
              posture_tol=posture_tol(posture_tol_mrad, posture_tol_mm), budget=budget,
              residual_model=residual_model, column_map=column_map, drop_flagged=drop_flagged,
              **({"widths": prior_widths} if prior_widths is not None else {}),
              **({"session_frames": session_frames} if session_frames is not None else {}),
              **({"criterion": prior_criterion} if prior_criterion is not None else {}))
    typer.echo(str(res))
    if report is not None:  # written by the workflow
        typer.echo(f"report: {report}/index.html ({', '.join(res.report_files)})")
    if json_path:
        res.to_json(json_path)
        typer.echo(f"wrote {json_path}")
    if save_model:
        from estcal.workflows.inputs import save_model as save

        save(res, save_model, robot, root, tip)
        typer.echo(f"wrote {save_model} (load it with --robot {save_model})")
