"""``estcal compensate``: corrected joint commands from a calibrated (saved) model.

Thin shell around :func:`estcal.workflows.compensate.compensate_file`; the method, the output
columns and the exit codes are documented in docs/compensation.md.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option

__all__ = ["compensate"]


def _lines(lines, k: int = 20) -> str:
    lines = [int(v) for v in lines]
    return ", ".join(map(str, lines[:k])) + (f" … ({len(lines)} in all)" if len(lines) > k else "")


@command("compensate")
def compensate(
    targets: Path = typer.Argument(..., help="CSV of targets: x,y,z (m) [qw,qx,qy,qz] and one column per "
                                             "joint with the nominal program's command (rad / m)."),
    robot: str = typer.Option(..., "--robot", "-r", help="Calibrated model: robot file (.yaml) saved by "
                                                         "calibration, or any robot spec."),
    output: Path = typer.Option(..., "--output", "-o", help="CSV to write: the input rows with the joint "
                                                            "columns replaced by the compensated readings."),
    json_path: Optional[Path] = json_option("Write a JSON report (each key names its unit: _mm, _mrad, and "
                                            "per joint _rad / _m)."),
    tol_mm: float = typer.Option(1e-3, "--tol-mm", help="Largest position residual (mm) of a reachable row."),
    tol_mrad: float = typer.Option(1e-3, "--tol-mrad", help="Largest orientation residual (mrad) of a "
                                                            "reachable row (targets with quaternions)."),
    position_only: bool = typer.Option(False, "--position-only", help="Ignore qw,qx,qy,qz: reach the "
                                                                      "point only."),
    rot_weight_m: float = typer.Option(0.1, "--rot-weight-m", help="Weight of orientation against position "
                                                                   "in the solve, m/rad (metres per radian)."),
    max_iter: int = typer.Option(100, "--max-iter", help="Most Levenberg-Marquardt steps per row."),
    allow_unreachable: bool = typer.Option(False, "--allow-unreachable",
                                           help="Exit 0 even when rows are unreachable (still flagged "
                                                "reachable=0 in the output)."),
) -> None:
    """Joint commands at which the calibrated model (effects included) reaches each target.

    Starts every row from its joint columns (the nominal command fixes the IK branch).
    Adds predicted_error_mm (solve residual), predicted_std_mm (from the model's saved
    covariance, when present) and reachable (1/0). Exit 3 when a row is unreachable.
    """
    import numpy as np
    from rich.console import Console
    from rich.markup import escape

    from estcal.cli.common import warn
    from estcal.workflows.compensate import compensate_file, write_commands
    from estcal.workflows.inputs import warn_datasets

    run = compensate_file(robot, targets, tol_mm=tol_mm, tol_mrad=tol_mrad, position_only=position_only,
                          rot_weight_m=rot_weight_m, max_iter=max_iter)
    warn_datasets([run.data])
    write_commands(run, output, str(targets))
    res, rb = run.result, run.robot
    console = Console(stderr=False, width=120)
    n, ok = len(res.reachable), int(res.reachable.sum())
    shift = run.shift
    jmax = int(np.argmax(shift.max(axis=0)))
    unit = "mm" if rb.joint_types[jmax] == "prismatic" else "mrad"
    console.print(f"{n} rows -> {output}: {ok} reachable within {tol_mm:g} mm"
                  + (f" / {tol_mrad:g} mrad" if res.rot_error_mrad is not None else "")
                  + f" (task point: {'marker 1' if res.task_point == 'marker1' else 'tool origin'}); "
                  f"largest command change {shift[:, jmax].max() * 1e3:.4g} {unit} ({rb.joint_names[jmax]})",
                  soft_wrap=True)
    if res.std_mm is not None:
        console.print(f"predicted position std from the saved covariance ({len(res.covariance_names)} "
                      f"parameters): median {np.median(res.std_mm):.4g} mm, max {res.std_mm.max():.4g} mm")
    else:
        console.print("no calibration covariance in the model: predicted_std_mm omitted")
    for note in run.notes:
        console.print("note: " + escape(note))
    if res.start_outside.any():
        warn(f"starting joints outside the limits (projected) on lines {_lines(res.lines[res.start_outside])}")
    if json_path is not None:
        from estcal.base.jsonio import write_json

        d = run.to_dict()
        d.update(input=str(targets), output=str(output), robot=str(robot))
        write_json(json_path, d)  # strict JSON, atomic
    if ok < n:
        worst = float(res.error_mm[~res.reachable].max())
        level, rows = ("warning" if allow_unreachable else "error"), ("rows" if n - ok > 1 else "row")
        typer.echo(f"{level}: {targets}: {n - ok} {rows} not reachable within tolerance (flagged reachable=0, "
                   f"best-effort joints written), lines {_lines(res.unreachable_lines)}; largest residual "
                   f"{worst:.4g} mm", err=True)
        if not allow_unreachable:
            raise typer.Exit(3)
