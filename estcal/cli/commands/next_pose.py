"""``estcal next-pose``: the measurement pose that most reduces a criterion of the covariance.

The state file is JSON with keys ``parameters`` (free parameter names),
``estimate`` (SI values) and ``covariance`` (p × p), e.g. written by any
estimator; a :class:`~estcal.estimate.result.CalibrationResult` JSON
(``estcal calibrate --json``) is accepted too. The predicted covariance after
measuring a candidate pose is the Kalman / MAP update
``C⁺ = C − C Hᵀ (H C Hᵀ + R)⁻¹ H C``, evaluated for all candidates at once
(:func:`estcal.workflows.design.next_pose`). ``-o pose.csv`` writes the pose in estcal's
dataset column layout (rad / m).

JSON keys: ``robot``, ``measure``, ``criterion``, ``next`` (:meth:`NextPose.to_dict`:
``readings_rad``, ``readings_deg``, ``value_before``, ``value_after``, ``reduction``,
``predicted_std``), ``test_poses_rad``; with ``--report DIR``: ``accuracy_map`` (``before``, ``after``:
predicted position-error std on the same ``--accuracy-map N`` random poses, see :mod:`estcal.report.design`).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.app import command
from estcal.cli.commands.design import MEASURE_HELP, _map_count, _measure
from estcal.cli.options import (deprecated_option, json_option, measure_option, method_option, noise_pos_option,
                                noise_rot_option, plan_option, report_option, robot_option)

__all__ = ["next_pose"]


@command("next-pose")
def next_pose(
    robot: str = robot_option(),
    state: Path = typer.Option(..., "--state", help="JSON with parameters, estimate, covariance."),
    criterion: Optional[str] = typer.Option(
        None, "--criterion", "-c", help="D, A, E, G, O1..O5, cond, test-pose (default: test-pose when "
                                        "--test-pose is given, else D)."),
    measure: Optional[str] = measure_option(None, MEASURE_HELP),
    method: Optional[str] = method_option(),
    test_pose: Optional[List[str]] = typer.Option(
        None, "--test-pose", help="Test pose 'q1,q2,...' (revolute in deg, prismatic in mm); repeatable."),
    candidates: Optional[Path] = typer.Option(None, "--candidates", help="CSV of candidate readings (rad/m)."),
    degrees: bool = typer.Option(False, "--degrees", help="Candidate CSV revolute columns are in degrees."),
    n_candidates: int = typer.Option(2000, "--n-candidates", help="Random candidate poses when no CSV is "
                                                                  "given."),
    sigma_mm: float = noise_pos_option(0.1),
    sigma_rot_mrad: float = noise_rot_option(1.0, ", pose measure"),
    old_sigma: Optional[float] = deprecated_option("--sigma"),
    old_sigma_rot: Optional[float] = deprecated_option("--sigma-rot"),
    refine: bool = typer.Option(True, "--refine/--no-refine", help="Polish the best candidate locally."),
    seed: int = typer.Option(0, "--seed"),
    output: Optional[Path] = plan_option("the proposed pose"),
    json_path: Optional[Path] = json_option("Write the proposal as JSON."),
    report: Optional[Path] = report_option("Folder for a report: the pose, parameter std before/after, predicted "
                                           "error over the workspace before/after (PNG) and index.html; adds "
                                           "'accuracy_map' to the JSON."),
    accuracy_map: int = typer.Option(500, "--accuracy-map", help="Poses sampled within the joint limits for the "
                                     "report's accuracy map."),
    old_map: Optional[int] = deprecated_option("--map"),
) -> None:
    """Propose the next measurement pose from the current estimate and covariance."""
    from rich.console import Console

    from estcal.cli.units import resolve
    from estcal.workflows.design import format_readings, next_pose as propose, write_plan

    measure = _measure(method, measure)
    sigma_mm = resolve(sigma_mm, 1.0, old_sigma, "--sigma", "--noise-pos-mm", "mm", 1.0, 0.1)
    sigma_rot_mrad = resolve(sigma_rot_mrad, 1.0, old_sigma_rot, "--sigma-rot", "--noise-rot-mrad", "mrad", 1.0, 1.0)
    n_map = _map_count(0, old_map) or accuracy_map
    run = propose(robot, state, criterion=criterion, measure=measure, test_poses=test_pose, candidates=candidates,
                  degrees=degrees, n_candidates=n_candidates, sigma_mm=sigma_mm, sigma_rot_mrad=sigma_rot_mrad,
                  refine=refine, seed=seed, accuracy_map=n_map if report is not None else 0)
    console, rb, nxt = Console(), run.robot, run.next
    console.print(f"robot {rb.name}, measure {run.measure}, {len(run.state.parameters)} parameters in the state")
    console.print("next pose (" + ", ".join(rb.joint_names) + "):")
    console.print("  " + format_readings(nxt.readings, rb)[0])
    console.print(f"{run.criterion}: {nxt.value_before:.6g} -> {nxt.value_after:.6g} "
                  f"({100 * nxt.reduction:.2f} % better, {nxt.n_candidates} candidates"
                  f"{', refined' if nxt.refined else ''})")
    out = run.to_dict()
    if output is not None:
        write_plan(output, nxt.readings, rb)
        console.print(f"wrote {output} (1 pose, rad / m)")
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, out)
        console.print(f"wrote {json_path}")
    if report is not None:
        from estcal.base.units import display_unit
        from estcal.report.design import next_pose_report

        next_pose_report(report, run.model, nxt, run.state, run.maps, unit=lambda nm: display_unit(nm, rb),
                         title=f"estcal next-pose — {rb.name}", result_dict=out)
        console.print(f"report: {report}/index.html")
