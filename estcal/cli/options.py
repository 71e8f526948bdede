"""The options several subcommands share, declared once (name, unit, help cannot drift apart).

One vocabulary (docs/conventions.md, "One vocabulary"):

* ``--estimator`` names how the parameters are estimated (``lm``, ``gtsam``, ``kalman`` …,
  ``estcal estimators``); ``--measure`` names what was measured (``position``, ``pose``,
  ``points``, ``point-link`` …). ``--method`` meant either, depending on the command: it is
  still accepted, hidden, with a deprecation warning naming the option that replaces it
  (:func:`estimator_and_measure`).
* ``--noise-pos-mm`` / ``--noise-rot-mrad`` are the measurement noise σ (mm / mrad on the
  command line, SI in files and JSON); ``--known-noise`` trusts them as absolute.
* ``--row-sigma-mm COLUMN`` weights every row by its own position σ read from a data column (mm),
  through :class:`estcal.methods.NoiseModel` (``row_sigma``): weighted least squares.
* ``--level`` (``registration`` | ``joint_offset`` | ``full``, default ``full`` everywhere).
* ``--map FILE.yaml`` reads the data files through a column map (the loader's hook,
  docs/dataset.md); commands that read datasets declare it with :func:`map_option`, and those
  that fit them ``--drop-flagged`` (:func:`drop_flagged_option`; ``--drop-flagged/--keep-all`` where
  leaving the flagged rows out is the default, as in ``estcal calibrate``).
* output files: ``--json``, ``--report DIR``, ``--save-model``, ``-o/--output``.

Nothing here imports more than typer: the command modules import this at start-up.
"""
from __future__ import annotations

import typer

__all__ = ["robot_option", "root_option", "tip_option", "points_option", "estimator_option", "measure_option",
           "method_option", "noise_pos_option", "noise_rot_option", "known_noise_option", "level_option",
           "free_option", "validate_option", "json_option", "report_option", "save_model_option", "map_option", "drop_flagged_option",
           "plan_option", "deprecated_option", "estimator_and_measure", "LEVEL_HELP", "DEFAULT_LEVEL",
           "posture_tol_mrad_option", "posture_tol_mm_option", "posture_tol", "row_sigma_option", "with_row_sigma"]

DEFAULT_LEVEL = "full"
LEVEL_HELP = ("Free set: registration | joint_offset | full (default), reduced to an identifiable set by QR on the "
              "calibration data.")
ESTIMATOR_HELP = ("Estimator: lm (default), gauss-newton, iterated-lls, scipy-lm, gtsam, isam2, gtsam-timevarying, "
                  "kalman, ukf, mcmc (`estcal estimators`).")


def robot_option(help: str = "Built-in name (`estcal robots`), robot file (.yaml) or URDF."):
    return typer.Option(..., "--robot", "-r", help=help)


def root_option():
    return typer.Option(None, "--root", help="URDF root link.")


def tip_option():
    return typer.Option(None, "--tip", help="URDF tip link.")


def points_option(help: str = "Use the first N measured points (x1..zN)."):
    return typer.Option(None, "--points", help=help)


def estimator_option(default: str | None = "lm", help: str = ESTIMATOR_HELP):
    return typer.Option(default, "--estimator", help=help)


def measure_option(default: str | None = None, help: str = "What was measured: position, pose, points, point-link, "
                                                           "… (default: from the data's columns)."):
    return typer.Option(default, "--measure", help=help)


def method_option():
    """``--method``/``-m``: the deprecated spelling of ``--estimator`` or ``--measure`` (hidden)."""
    return typer.Option(None, "--method", "-m", hidden=True)


def noise_pos_option(default, extra: str = ""):
    """``--noise-pos-mm``: measurement position noise std per coordinate (mm)."""
    return typer.Option(default, "--noise-pos-mm", help=f"Position noise std per coordinate (mm){extra}.")


def noise_rot_option(default, extra: str = ""):
    """``--noise-rot-mrad``: measurement orientation noise std (mrad)."""
    return typer.Option(default, "--noise-rot-mrad", help=f"Orientation noise std (mrad){extra}.")


def known_noise_option(help: str = "Trust the noise values as absolute (covariance not rescaled by σ0²)."):
    return typer.Option(False, "--known-noise", help=help)


def level_option(default: str | None = DEFAULT_LEVEL, help: str = LEVEL_HELP):
    return typer.Option(default, "--level", help=help)


def free_option(help: str = "Comma-separated parameter names or patterns to estimate (e.g. "
                            "'base_*,marker1_*,offset_*') instead of --level."):
    return typer.Option(None, "--free", help=help)


def validate_option(help: str = "Validation dataset; repeat the option for several, scored in order (never "
                                "used for a decision)."):
    return typer.Option([], "--validate", help=help)


def json_option(help: str = "Write the result as JSON (SI units; the unit in every key name)."):
    return typer.Option(None, "--json", help=help)


def report_option(help: str):
    return typer.Option(None, "--report", help=help)


def save_model_option(help: str = "Write the calibrated robot as a robot file (.yaml) with a 'calibration:' "
                                  "block (provenance, covariance); reload it with --robot."):
    return typer.Option(None, "--save-model", help=help)


def plan_option(what: str = "the plan's poses"):
    """``-o/--output``: poses written as a CSV in estcal's dataset layout (``design``, ``next-pose``)."""
    return typer.Option(None, "--output", "-o", help=f"Write {what} as a CSV in estcal's dataset layout (one "
                                                     f"column per joint, rad / m).")


def map_option():
    """``--map FILE.yaml``: the data files read through a column map (their own column names, units,
    orientation convention; docs/dataset.md) — the workflows pass it to the loader as ``column_map``."""
    return typer.Option(None, "--map", metavar="FILE.yaml",
                        help="Column map of the data files (their column names, units, rpy …): docs/dataset.md.")


def posture_tol_mrad_option():
    """``--posture-tol-mrad``: readings of revolute joints within this agree (one posture; docs/real-data.md)."""
    return typer.Option(1.0, "--posture-tol-mrad", help="Rows whose revolute readings agree within this (mrad) and "
                        "prismatic within --posture-tol-mm are one posture: held out together by every "
                        "cross-validation, 'seen' in a validation.")


def posture_tol_mm_option():
    """``--posture-tol-mm``: the same for prismatic joints (mm)."""
    return typer.Option(1.0, "--posture-tol-mm", help="Prismatic-joint agreement of one posture (mm).")


def posture_tol(mrad: float, mm: float) -> tuple[float, float]:
    """The posture tolerance in SI ``(rad, m)`` from the command line's mrad / mm (positive)."""
    if not (mrad > 0 and mm > 0):
        raise typer.BadParameter(f"posture tolerances must be > 0 (got {mrad} mrad, {mm} mm)")
    return mrad * 1e-3, mm * 1e-3


def drop_flagged_option(default: bool = False):
    """``--drop-flagged``: leave out the rows that the data screening flags (``estcal check``'s defect
    kinds; docs/dataset.md) — their findings are printed as warnings either way. Where that is the
    default (``estcal calibrate``: docs/reliability.md, "Gross errors") the option is the pair
    ``--drop-flagged/--keep-all``, ``--keep-all`` fitting every row."""
    if default:
        return typer.Option(True, "--drop-flagged/--keep-all",
                            help="Leave out (default) the rows flagged by the data screening — readings beyond the "
                                 "joint limits, outliers after a robust fit, swapped or ghost markers, duplicates — "
                                 "and print them first, by file and line, with their residual and the "
                                 "least-squares fit with them; --keep-all fits every row (plain least squares "
                                 "unless --robust). `estcal check` lists them.")
    return typer.Option(False, "--drop-flagged",
                        help="Leave out the rows flagged by the data screening (swapped or ghost markers, outliers, "
                             "readings beyond the limits, duplicates), naming their lines; `estcal check` lists "
                             "them.")


def row_sigma_option():
    """``--row-sigma-mm COLUMN``: each row's position noise σ (mm) read from a column of the data."""
    return typer.Option(None, "--row-sigma-mm", metavar="COLUMN",
                        help="Weight each row by its own position noise σ read from this column of the data, in mm "
                             "(e.g. TIAGo's marker_std_mm): weighted least squares; orientation rows keep their σ.")


def with_row_sigma(noise, column: str | None):
    """``noise`` (a NoiseModel, or None = unknown noise) with the per-row position σ of ``--row-sigma-mm``:
    the column is in mm (``row_sigma_unit_m`` = 1e-3). Unchanged when no column is given."""
    if not column:
        return noise
    from dataclasses import replace

    from estcal.methods import NoiseModel

    return replace(noise if noise is not None else NoiseModel(known=False), row_sigma=column, row_sigma_unit_m=1e-3)


def deprecated_option(old: str):
    """A renamed option, still accepted (hidden) in its old unit; see :func:`estcal.cli.units.resolve`."""
    return typer.Option(None, old, hidden=True)


def estimator_and_measure(method: str | None, estimator: str | None, measure: str | None,
                          means: str = "either") -> tuple[str | None, str | None]:
    """``(estimator, measure)`` with the deprecated ``--method`` folded in, warned about.

    ``means``: what ``--method`` meant in this command — ``"measure"``, ``"estimator"`` or
    ``"either"`` (``calibrate``: dispatched by name; the two name sets are disjoint).
    """
    if method is None:
        return estimator, measure
    import warnings

    from estcal.base.errors import EstcalWarning, InputError

    if means == "either":
        from estcal.estimate.registry import estimator_names
        from estcal.methods import METHODS, get_method

        get_method("position")  # imports the optional method modules, so METHODS is complete
        if method in estimator_names():
            means = "estimator"
        elif method in METHODS:
            means = "measure"
        else:
            raise InputError(f"unknown --method {method!r}: neither a measurement method ({', '.join(sorted(METHODS))}) "
                             f"nor an estimator ({', '.join(estimator_names())}) — use --measure or --estimator")
    new, given = ("--estimator", estimator) if means == "estimator" else ("--measure", measure)
    if given is not None and given != method:
        raise InputError(f"--method {method} (deprecated: {new}) but {new} {given} was also given")
    warnings.warn(f"--method is deprecated; use {new} {method} (docs/conventions.md, 'One vocabulary')",
                  EstcalWarning, stacklevel=2)
    return (method, measure) if means == "estimator" else (estimator, method)
