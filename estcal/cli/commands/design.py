"""``estcal design``: an optimal measurement plan for a robot, measurement and noise model.

Prints and (``--json PATH``) saves the plan (joint readings), its criterion,
every other criterion, the predicted parameter standard deviations
((JᵀWJ)⁻¹, the covariance the estimators report) and the distribution of the
criterion over random plans of the same size; ``-o plan.csv`` writes the plan's
poses in estcal's dataset column layout (rad / m). The job is
:func:`estcal.workflows.design.design`.

JSON keys: ``robot``, ``measure``, ``sigma_mm``, ``free`` (names), ``criterion``,
``plan`` (:meth:`Plan.to_dict`: ``readings_rad``, ``readings_deg``, ``value``, …),
``criteria`` (all criteria of the plan, ``param_std`` in SI units),
``rho0_mm`` (predicted RMS position error at each test pose), ``test_poses_rad``,
``baseline`` (:meth:`BaselineStats.to_dict`: min/mean/max/percentiles),
``beats_random`` (plan better than the best random plan), ``accuracy_map`` (with ``--accuracy-map N``:
``q``, ``xyz`` (m), ``std`` (m) per pose and a ``summary``; ``--report DIR`` implies ``--accuracy-map 500``).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (deprecated_option, json_option, measure_option, method_option, noise_pos_option,
                                noise_rot_option, plan_option, report_option, robot_option)

__all__ = ["design"]

MEASURE_HELP = "What will be measured: position, pose or points."


def _measure(method, measure) -> str:
    from estcal.cli.options import estimator_and_measure

    return estimator_and_measure(method, None, measure, means="measure")[1] or "position"


def _map_count(accuracy_map, old_map) -> int:
    """``--accuracy-map N``, or the deprecated ``--map N`` (warned): ``--map`` names a column map now."""
    if old_map is None:
        return accuracy_map
    import warnings

    from estcal.base.errors import EstcalWarning, InputError

    if accuracy_map:
        raise InputError("give --accuracy-map or the deprecated --map, not both")
    warnings.warn(f"--map N is deprecated here; use --accuracy-map {old_map} (--map names a column map of the data "
                  f"files, docs/conventions.md)", EstcalWarning, stacklevel=2)
    return old_map


@command("design")
def design(
    robot: str = robot_option(),
    measure: Optional[str] = measure_option(None, MEASURE_HELP),
    method: Optional[str] = method_option(),
    n: int = typer.Option(..., "--n", help="Number of poses m in the plan."),
    criterion: str = typer.Option("D", "--criterion", "-c",
                                  help="D, A, E, G, O1..O5, cond (κ(J)), cond_JtJ, test-pose, test-pose-max."),
    test_pose: Optional[List[str]] = typer.Option(
        None, "--test-pose", help="Test pose 'q1,q2,...' (revolute in deg, prismatic in mm); repeatable. "
                                  "Default (when needed): mid-range of every joint."),
    candidates: Optional[Path] = typer.Option(None, "--candidates",
                                              help="CSV of candidate readings (rad / m; header optional)."),
    degrees: bool = typer.Option(False, "--degrees", help="Candidate CSV revolute columns are in degrees."),
    algorithm: str = typer.Option("fedorov", "--algorithm",
                                  help="greedy, fedorov, detmax (discrete) or continuous."),
    n_candidates: int = typer.Option(2000, "--n-candidates", help="Random candidates when no CSV is given."),
    restarts: int = typer.Option(4, "--restarts", help="Restarts (discrete) / starts (continuous)."),
    sigma_mm: float = noise_pos_option(0.1),
    sigma_rot_mrad: float = noise_rot_option(1.0, ", pose measure"),
    old_sigma: Optional[float] = deprecated_option("--sigma"),
    old_sigma_rot: Optional[float] = deprecated_option("--sigma-rot"),
    free: Optional[str] = typer.Option(None, "--free",
                                       help="Free parameters (comma-separated names/patterns); "
                                            "default: an identifiable subset (offsets first)."),
    random_plans: int = typer.Option(1000, "--random-plans", help="Random plans in the baseline."),
    accuracy_map: int = typer.Option(0, "--accuracy-map", help="Accuracy map: expected position error over N "
                                     "random poses within the joint limits (0 = off)."),
    old_map: Optional[int] = deprecated_option("--map"),
    map_box: Optional[str] = typer.Option(None, "--map-box",
                                          help="Restrict the map to a tool-position box "
                                               "'xmin,ymin,zmin,xmax,ymax,zmax' (mm)."),
    seed: int = typer.Option(0, "--seed"),
    scheduler: str = typer.Option("processes", "--scheduler", help="Where the continuous starts run: "
                                  "serial | processes | local (Dask LocalCluster) | tcp://host:8786."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (processes / local)."),
    output: Optional[Path] = plan_option(),
    json_path: Optional[Path] = json_option("Write the results as JSON."),
    report: Optional[Path] = report_option("Folder for a report: plan, criteria, random-plan histogram, predicted "
                                           "error over the workspace (PNG) and index.html. Implies "
                                           "--accuracy-map 500 unless it is given."),
) -> None:
    """Optimise which poses to measure (plan of m poses) and compare with random plans."""
    from estcal.cli.units import resolve
    from estcal.workflows.design import design as run_design, write_plan

    measure = _measure(method, measure)
    sigma_mm = resolve(sigma_mm, 1.0, old_sigma, "--sigma", "--noise-pos-mm", "mm", 1.0, 0.1)
    sigma_rot_mrad = resolve(sigma_rot_mrad, 1.0, old_sigma_rot, "--sigma-rot", "--noise-rot-mrad", "mrad", 1.0, 1.0)
    n_map = _map_count(accuracy_map, old_map)
    if report is not None and n_map <= 0:
        n_map = 500  # the report's workspace figure needs an accuracy map
    run = run_design(robot, n, measure=measure, criterion=criterion, test_poses=test_pose, candidates=candidates,
                     degrees=degrees, algorithm=algorithm, n_candidates=n_candidates, restarts=restarts,
                     sigma_mm=sigma_mm, sigma_rot_mrad=sigma_rot_mrad, free=free, random_plans=random_plans,
                     accuracy_map=n_map, map_box=map_box, seed=seed, scheduler=scheduler, workers=workers,
                     keep_baseline=report is not None)
    _print(run)
    out = run.to_dict()
    if output is not None:
        write_plan(output, run.plan.readings, run.robot)
        typer.echo(f"wrote {output} ({run.plan.m} poses, rad / m)")
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, out)
        typer.echo(f"wrote {json_path}")
    if report is not None:
        from estcal.base.units import display_unit
        from estcal.design.criteria import larger_is_better
        from estcal.report.design import design_report

        rb = run.robot
        design_report(report, run.model, run.plan, run.criteria, run.baseline, run.accuracy_map, run.rho_mm,
                      run.q_test, larger_is_better=larger_is_better(run.criterion),
                      unit=lambda nm: display_unit(nm, rb), title=f"estcal design — {rb.name}", result_dict=out)
        typer.echo(f"report: {report}/index.html")


def _print(run) -> None:
    from rich.console import Console
    from rich.markup import escape

    from estcal.base.units import display_unit
    from estcal.design.criteria import CRITERIA
    from estcal.workflows.design import format_readings

    console, rb, plan = Console(), run.robot, run.plan
    console.print(f"robot {rb.name}, measure {run.measure}, σ = {run.sigma_mm} mm, {run.model.p} free parameters")
    console.print(f"plan ({plan.method}, m = {plan.m}): {run.criterion} = {plan.value:.6g}   "
                  f"[{CRITERIA[run.criterion][2]}]")
    console.print("joint readings (" + ", ".join(rb.joint_names) + "):")
    for line in format_readings(plan.readings, rb):
        console.print("  " + line)
    console.print(escape(str(run.criteria)))
    if run.rho_mm is not None:
        console.print("predicted RMS position error at the test pose(s) (mm): "
                      + ", ".join(f"{v:.5g}" for v in run.rho_mm))
    console.print("predicted parameter std:")
    for k, v in run.criteria.param_std.items():
        u, f = display_unit(k, rb)
        console.print(f"  {k:<14}{v * f:.4g} {u}")
    console.print(escape(str(run.baseline)))
    if run.accuracy_map is not None:
        console.print(escape(str(run.accuracy_map)))
    console.print(f"optimised plan {'beats' if run.beats_random else 'does NOT beat'} the best of "
                  f"{run.baseline.n_plans} random plans")
