"""``estcal check``: data hygiene before any fit (:func:`estcal.workflows.check.check_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import json_option, map_option, points_option, robot_option, root_option, tip_option

__all__ = ["check"]


@command("check")
def check(
    data: Path = typer.Argument(..., help="Dataset CSV (through --map: the file as published)."),
    robot: str = robot_option(),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    column_map: Optional[Path] = map_option(),
    points: Optional[int] = points_option(),
    no_outliers: bool = typer.Option(False, "--no-outliers", help="Skip the robust fit and the outlier test."),
    json_path: Optional[Path] = json_option("Write {\"findings\": [{kind, lines, message}]}."),
) -> None:
    """Name the rows a calibration should not trust, by file line: marker_swap (with the repaired order),
    non_rigid, outlier (studentised residual after a robust fit, Bonferroni), out_of_limits, duplicate_row;
    and repeated_pose (with the repeatability in mm) and unused_column. Exit code 0 whatever is found;
    docs/dataset.md, "Checking a file"."""
    from estcal.workflows.check import check_file
    from estcal.workflows.inputs import warn_datasets

    report, _, ds = check_file(data, robot, root=root, tip=tip, column_map=column_map, points=points,
                               outliers=not no_outliers)
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

