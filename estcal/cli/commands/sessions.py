"""``estcal sessions``: calibration over several sessions with a repeatability model.

Each DATA file is one session (or one file with a ``session`` column holds them
all). The population parameters are shared; the parameters given by ``--vary``
(or chosen by the REML likelihood-ratio test with ``--vary auto``) get one
deviation per session, ``u_s ~ N(0, Q)``, whose variance components Q are
estimated by REML (:mod:`estcal.sessions`, docs/repeatability.md). Prints the
between-session std of every varying parameter (mm / mrad), each session's
deviation, and scores ``--validate`` sessions against the new-session 95 %
prediction ellipsoids (θ covariance + Q). The job is
:func:`estcal.workflows.sessions.sessions`.

JSON (``--json PATH``): ``parameters`` {name: {estimate, std}} (SI), ``vary``,
``variance_components`` [{parameter, std, std_err, unit}] (mm / mrad),
``session_deviations``, ``q`` (SI²), ``s2``, ``vary_selection`` (with ``--vary
auto``), ``validation`` {file: {rmse_mm, rmse_mm_per_point, coverage,
coverage_per_point, band}}, ``recalibration`` (with ``--recalibrate K``).
``--save-model`` writes the population model with a new session's covariance;
``--report DIR`` the tables and a figure as index.html.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (free_option, json_option, known_noise_option, level_option, noise_pos_option,
                                noise_rot_option, points_option, report_option, robot_option, root_option,
                                save_model_option, tip_option, map_option, drop_flagged_option)

__all__ = ["sessions"]


@command("sessions")
def sessions(
    data: list[Path] = typer.Argument(..., help="One CSV per session (or one CSV with a 'session' column)."),
    robot: str = robot_option(),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    points: Optional[int] = points_option(),
    column_map: Optional[Path] = map_option(),
    drop_flagged: bool = drop_flagged_option(),
    level: str = level_option(help="Free set: registration | joint_offset | full (default), identifiable by QR "
                                   "on the stacked sessions."),
    free: Optional[str] = free_option("Explicit free set (names or patterns, comma-separated) instead of --level."),
    vary: str = typer.Option("auto", "--vary", help="Parameters that vary between sessions (comma-separated "
                                                    "names, or patterns matched among the free parameters), "
                                                    "'auto' (REML likelihood-ratio selection among the free "
                                                    "offsets and base) or 'none'."),
    formulation: str = typer.Option("gls", "--formulation", help="gls, gtsam (factor graph) or kalman "
                                                                 "(filterpy); they agree."),
    noise_pos_mm: float = noise_pos_option(0.1),
    noise_rot_mrad: float = noise_rot_option(1.0),
    known_noise: bool = known_noise_option("Trust the noise values (else a variance factor is estimated with Q "
                                           "by REML)."),
    validate: list[Path] = typer.Option([], "--validate", help="New session(s): scored, never used for a "
                                                              "decision."),
    recalibrate: int = typer.Option(0, "--recalibrate", help="With --validate: error on the rest of each "
                                                             "new session after re-measuring k = 0…K poses "
                                                             "(number of poses)."),
    alpha: float = typer.Option(0.01, "--alpha", help="Significance level of the --vary auto selection."),
    json_path: Optional[Path] = json_option("Write the fit as JSON (SI units)."),
    report: Optional[Path] = report_option("Folder for a report: population parameters ±2σ (PNG), between-session "
                                           "variation, session deviations, new-session coverage and index.html."),
    save_model: Optional[Path] = save_model_option("Write the population model as a robot file (.yaml) with a "
                                                   "'calibration:' block whose covariance is a new session's "
                                                   "(θ and the between-session Q); reload it with --robot."),
) -> None:
    """Calibrate several sessions at once, with per-session deviations (repeatability as process noise)."""
    from estcal.methods import NoiseModel
    from estcal.workflows.sessions import sessions as run_sessions

    noise = NoiseModel(position=noise_pos_mm * 1e-3, orientation=noise_rot_mrad * 1e-3, scalar=noise_pos_mm * 1e-3,
                       known=known_noise)
    run = run_sessions(robot, list(data), level=level, free=free, vary=vary, formulation=formulation, noise=noise,
                       validate=list(validate), recalibrate=recalibrate, alpha=alpha, points=points, root=root,
                       tip=tip, column_map=column_map, drop_flagged=drop_flagged)
    _print(run, vary, known_noise)
    out = run.to_dict()
    if json_path:
        from estcal.base.jsonio import write_json

        write_json(json_path, out)
        typer.echo(f"wrote {json_path}")
    if report is not None:
        from estcal.base.units import display_unit
        from estcal.report.sessions import sessions_report

        sessions_report(report, run, unit=lambda n: display_unit(n, run.fit.robot),
                        title=f"estcal sessions — {run.fit.robot.name}", result_dict=out)
        typer.echo(f"report: {report}/index.html")
    if save_model:
        from estcal.workflows.inputs import provenance

        run.fit.save_model(save_model, provenance(robot, root, tip))
        typer.echo(f"wrote {save_model} (load it with --robot {save_model})")


def _print(run, vary, known_noise) -> None:
    import math

    fit = run.fit
    typer.echo(f"estcal sessions: {len(run.names)} sessions ("
               f"{', '.join(f'{n}: {s.n}' for n, s in zip(run.names, run.datasets))} poses), "
               f"{len(fit.names)} free parameters")
    typer.echo(f"{fit.formulation}: {fit.n_iterations} iterations, converged={fit.converged}, "
               f"variance factor s² = {fit.s2:.3g}{' (known noise)' if known_noise else ''}")
    if fit.vary:
        comps = fit.variance_components()
        typer.echo("between-session variation (REML):")
        for v in comps:
            err = f" ± {v['std_err']:.3g}" if math.isfinite(v["std_err"]) else ""
            typer.echo(f"  {v['parameter']:<24} std {v['std']:.4g}{err} {v['unit']}")
        units = {v["parameter"]: v["unit"] for v in comps}
        typer.echo("session deviations:")
        for s, u in zip(fit.sessions, fit.u):
            typer.echo(f"  {s}: " + ", ".join(f"{n} {x * 1e3:+.3f} {units[n]}" for n, x in zip(fit.vary, u)))
    else:
        typer.echo("no parameter varies between sessions" + (" (LR test)" if vary == "auto" else ""))
    for key, sc in run.scores.items():
        typer.echo(f"validate {key}: RMSE {sc['rmse_mm']:.3f} mm, 95 % coverage {sc['coverage']:.2f} "
                   f"(binomial band {sc['band'][0]:.2f}–{sc['band'][1]:.2f})")
        rc = run.recalibration.get(key)
        if rc:
            typer.echo("  re-measuring k poses (covariance rule): " +
                       ", ".join(f"k={k} {e:.3f} mm" for k, e in zip(rc["k"], rc["rmse_mm"])))
