"""``estcal import-bag``: a ROS 1 or ROS 2 bag to a dataset CSV (:func:`estcal.workflows.import_bag.import_bag_file`)."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.app import command

__all__ = ["import_bag"]


@command("import-bag")
def import_bag(
    bag: Path = typer.Argument(..., help="ROS 1 .bag file or ROS 2 bag folder."),
    joints: str = typer.Option(..., "--joints", help="sensor_msgs/JointState topic."),
    pose: Optional[str] = typer.Option(None, "--pose", help="Pose topic (PoseStamped, TransformStamped, …)."),
    point: Optional[List[str]] = typer.Option(None, "--point", help="Point topic (PointStamped); repeat for k points."),
    output: Path = typer.Option(..., "--output", "-o", help="Dataset CSV to write (one row per plateau)."),
    tol_mrad: float = typer.Option(1.0, "--tol-mrad", help="Static: joint range over the window (mrad; mm for prismatic)."),
    tol_mm: float = typer.Option(1.0, "--tol-mm", help="Static: measured position range over the window (mm)."),
    window_s: float = typer.Option(0.5, "--window-s", help="Sliding window of the static test (s)."),
    min_duration_s: float = typer.Option(1.0, "--min-duration-s", help="Shortest plateau kept (s)."),
    margin_s: float = typer.Option(0.2, "--margin-s", help="Time dropped at each end of a plateau (s)."),
    offset_s: Optional[float] = typer.Option(None, "--offset-s",
                                             help="Measurement clock − joint clock (s); default: estimated."),
) -> None:
    """One row per static plateau of the joint stream: joints and measurement averaged over the plateau,
    with t_start_robot, t_end_robot, marker_std_mm and joint_std_mrad columns (like the TIAGo files).
    Topics may run at different rates and on clocks offset from each other. docs/dataset.md, "ROS bags"."""
    from estcal.workflows.import_bag import import_bag_file

    out = import_bag_file(bag, output, joints, pose, point or (), tol=tol_mrad * 1e-3, tol_m=tol_mm * 1e-3,
                          window_s=window_s, min_duration_s=min_duration_s, margin_s=margin_s, offset_s=offset_s)
    offs = ", ".join(f"{t}: {o:+.3f} s" for t, o in out.offset_s.items())
    typer.echo(f"{out.n} plateau(s) -> {output} ({', '.join(out.columns)}); clock offsets {offs}")
    for a, b, why in out.skipped:
        typer.echo(f"warning: plateau {a:.3f}–{b:.3f} s skipped: {why}", err=True)

