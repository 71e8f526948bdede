"""``estcal diagnose``: how accurate the robot's model is at new postures, which physical causes it names, and
what stays unexplained.

Runs :func:`estcal.workflows.diagnose.diagnose` (one sparse Bayesian model of the geometry and every effect
of the library, the causes named by evidence, folds and cross-validation; docs/discrepancy.md) and prints
the answer first — the expected error at new postures with its 95 % bound, the named causes with their
gains, what stays unexplained, one figure per validation file — then the details.

JSON (``--json PATH``): ``answer``, ``causes``, ``accuracy`` (``validation``: one entry per file), ``terms``,
``budget``, ``data``, ``model`` (every parameter value, the effects, gravity — the input of ``estcal simulate
--from-fit``).
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
    drop_flagged: bool = drop_flagged_option(True),
    effects: Optional[str] = typer.Option(None, "--effects", help="Comma-separated effect names to consider "
                                                                  "(default: every registered effect); 'none': the "
                                                                  "geometric model alone."),
    noise_pos_mm: Optional[float] = typer.Option(None, "--noise-pos-mm", help="Position noise std per "
                                                 "coordinate (mm; default 0.1 with --known-noise): the rows' weights."),
    noise_rot_mrad: Optional[float] = typer.Option(None, "--noise-rot-mrad", help="Orientation noise std (mrad; "
                                                   "default 1 with --known-noise)."),
    known_noise: bool = known_noise_option("The noise figures are the instrument's (the rows' weights); the "
                                           "model fits the residual's scale either way."),
    old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
    row_sigma_mm: Optional[str] = row_sigma_option(),
    k_folds: int = typer.Option(5, "--folds", help="Cross-validation folds (by posture; by session too with "
                                                   "several sessions)."),
    urdf_masses: bool = typer.Option(True, "--urdf-chain-masses/--no-urdf-chain-masses",
                                     help="For URDF robots, count the links after the last actuated "
                                          "joint (tool, sensor, gripper) in its mass."),
    geometric: str = typer.Option("sparse", "--geometric", help="Geometric parameters: sparse (every identifiable "
                                  "one under a relevance prior; the default) | full (all of them, unpenalised) | "
                                  "joint_offset (the offsets only)."),
    geometric_width_mm: str = typer.Option("auto", "--geometric-width-mm", help="The link frames' relevance "
                                            "priors: the widest prior the evidence search moves a link frame's "
                                            "parameter to, mm for a length and mrad for an angle (e.g. 1 for an "
                                            "arm whose nominal geometry is known to 1 mm / 1 mrad; joint offsets "
                                            "and the tool stay unbounded), or inf (unbounded). Default auto: 1 "
                                            "unless the unbounded model's cross-validated error is lower by more "
                                            "than one standard error."),
    approach_from_order: bool = typer.Option(True, "--approach-from-order/--no-approach-from-order",
                                             help="Infer approach_<joint> columns (the side each joint moved "
                                                  "from into the posture) from the acquisition order — the t "
                                                  "column, else the row order — so that backlash by approach "
                                                  "is a candidate beside backlash by the load. Recorded "
                                                  "approach_<joint> columns are kept."),
    register_zeros: bool = typer.Option(True, "--register-zeros/--no-register-zeros",
                                        help="A --validate file's rows at seen postures register its measuring "
                                             "frame and every joint zero they show moved since training "
                                             "(posture-grouped CV on those rows alone); --no-register-zeros: the "
                                             "frame only."),
    seed: int = typer.Option(0, "--seed", help="Seed of the fold assignment."),
    posture_tol_mrad: float = posture_tol_mrad_option(),
    posture_tol_mm: float = posture_tol_mm_option(),
    budget: bool = typer.Option(True, "--budget/--no-budget", help="Error budget: nested and time-blocked "
                                "cross-validation, the repeatability floor, the 95 % region (docs/discrepancy.md)."),
    json_path: Optional[Path] = json_option("Write the diagnosis as JSON."),
    report: Optional[Path] = report_option("Folder for a report: residual figures (PNG), diagnosis.json, "
                                           "summary.txt and index.html with the tables."),
    save_model: Optional[Path] = save_model_option("Write the model (geometry + the effects it keeps) as a robot "
                                                   "file (.yaml) with a 'calibration:' block; reload it with --robot."),
    former: Optional[str] = typer.Option(None, "--alpha", "--max-effects", "--prior-widths", "--session-frames",
                                         "--prior-criterion", "--residual-model", hidden=True),
) -> None:
    """How accurate the model is at new postures, which physical causes it names, what stays unexplained."""
    from estcal.base.errors import InputError
    from estcal.workflows.diagnose import diagnose as run, width_from_text

    if former is not None:
        raise InputError("this option belonged to the former diagnosis (forward selection, the prior model, the "
                         "residual GP): the default model now keeps every term under a relevance prior and names "
                         "causes by evidence, folds and cross-validation; drop the option (docs/discrepancy.md)")
    noise = with_row_sigma(_noise(noise_pos_mm, noise_rot_mrad, known_noise, old_noise_pos), row_sigma_mm)
    res = run(robot, list(data), validate=list(validate), effects=effects, noise=noise, points=points, root=root,
              tip=tip, urdf_chain_masses=urdf_masses, folds=k_folds, report=report, seed=seed, geometric=geometric,
              approach_from_order=approach_from_order, posture_tol=posture_tol(posture_tol_mrad, posture_tol_mm),
              budget=budget, column_map=column_map, drop_flagged=drop_flagged, register_zeros=register_zeros,
              geometric_width=width_from_text(geometric_width_mm))
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
