"""``estcal check``: data hygiene before any fit (:func:`estcal.workflows.check.check_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

__all__ = ["check", "register"]


def check(
    data: Path = typer.Argument(..., help="Dataset CSV (through --map: the file as published)."),
    robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF (.urdf)."),
    root: Optional[str] = typer.Option(None, "--root", help="URDF root link."),
    tip: Optional[str] = typer.Option(None, "--tip", help="URDF tip link."),
    column_map: Optional[Path] = typer.Option(None, "--map", metavar="FILE.yaml",
                                              help="Column map of the data file (docs/dataset.md)."),
    points: Optional[int] = typer.Option(None, "--points", help="Use the first N measured points (x1..zN)."),
    no_outliers: bool = typer.Option(False, "--no-outliers", help="Skip the robust fit and the outlier test."),
    json_path: Optional[Path] = typer.Option(None, "--json", help="Write {\"findings\": [{kind, lines, message}]}."),
) -> None:
    """Name the rows a calibration should not trust, by file line: marker_swap (with the repaired order),
    non_rigid, outlier (studentised residual after a robust fit, Bonferroni), out_of_limits, duplicate_row;
    and repeated_pose (with the repeatability in mm) and unused_column. Exit code 0 whatever is found;
    docs/dataset.md, "Checking a file"."""
    from estcal.base.errors import NumericalRefusal
    from estcal.cli.common import fail, message, refuse, warn_datasets
    from estcal.workflows.check import check_file

    try:
        report, _, ds = check_file(data, robot, root=root, tip=tip, column_map=column_map, points=points,
                                   outliers=not no_outliers)
    except NumericalRefusal as exc:
        refuse(message(exc))
    except (ValueError, KeyError, FileNotFoundError) as exc:
        fail(message(exc))
    warn_datasets([ds])
    n_def = len(report.flagged_lines())
    typer.echo(f"{data}: {ds.n} rows, {len(report.findings)} finding(s), {n_def} row(s) flagged as defects")
    for f in report.findings:
        typer.echo(f"  {f.kind}: {f.message}")
    for n in report.notes:
        typer.echo(f"  ({n})")
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, report.to_dict())


def register(app: typer.Typer) -> None:
    app.command("check")(check)
