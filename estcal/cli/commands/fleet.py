"""``estcal fleet``: calibrate (or diagnose) every robot of a fleet folder, on one machine or a Dask cluster.

Runs :func:`estcal.workflows.fleet.run_fleet`: one task per robot folder (layout in
:mod:`estcal.workflows.fleet` and docs/scaling.md), executed by
:func:`estcal.scale.runner.run_tasks` — ``--scheduler serial | processes |
local | tcp://host:8786``. Prints a summary table (robot, poses, RMSE before /
after on the calibration and validation data in mm, named causes, warnings),
lists the robots that failed with their inputs and error, writes each saved
model to ``--save-models OUTDIR/<robot>.yaml`` (a robot file with a
``calibration:`` block: free names, covariance, provenance) and the summary to
``--json``.

Exit code: 0 when at least one robot was processed (failures are listed, never
fatal — the others are calibrated and saved); 1 with ``--strict`` when any robot
failed; 2 for bad input (no such folder, no robot folders, bad option) or when
every robot failed.

JSON (``--json PATH``): ``n_robots``, ``n_ok``, ``n_failed``, ``scheduler``,
``n_workers``, ``wall_s``, ``options``, ``robots`` (one row per robot:
``robot``, ``poses``, ``n_parameters``, ``rmse_before_mm``, ``rmse_after_mm``,
``validation_rmse_before_mm``, ``validation_rmse_mm``, ``causes``, ``warnings``,
``model``, …) and ``failures`` ({``robot``, ``folder``, ``inputs``, ``error``}).
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (deprecated_option, estimator_option, json_option, known_noise_option, level_option,
                                map_option, noise_pos_option, noise_rot_option)

__all__ = ["fleet"]


def _mm(v) -> str:
    return "—" if v is None else f"{v:.3f}"


def _table(summary, diagnose: bool):
    from rich.table import Table

    t = Table(title=f"estcal fleet — {summary.n_ok} of {summary.n_ok + len(summary.failures)} robots "
                    f"{'diagnosed' if diagnose else 'calibrated'} ({summary.scheduler}, {summary.n_workers} "
                    f"worker(s), {summary.wall_s:.1f} s)", title_justify="left")
    before, after = ("registration", "model") if diagnose else ("before", "after")
    for c, j in (("robot", "left"), ("poses", "right"), (f"RMSE {before} mm", "right"),
                 (f"RMSE {after} mm", "right"), (f"valid. {before} mm", "right"), (f"valid. {after} mm", "right"),
                 ("causes", "left"), ("warnings", "left")):
        t.add_column(c, justify=j)
    for r in summary.rows:
        t.add_row(r["robot"], str(r["poses"]), _mm(r.get("rmse_before_mm")), _mm(r.get("rmse_after_mm")),
                  _mm(r.get("validation_rmse_before_mm")), _mm(r.get("validation_rmse_mm")),
                  ", ".join(r.get("causes") or []) or "—", "; ".join(r.get("warnings") or []) or "—")
    for f in summary.failures:
        t.add_row(f["robot"], "—", "—", "—", "—", "—", "—", f"FAILED: {f['error']}")
    return t


@command("fleet")
def fleet(
    folder: Path = typer.Argument(..., help="Fleet folder: one sub-folder per robot (data.csv, optional "
                                            "validate*.csv, robot.yaml/.urdf or one shared at the top)."),
    scheduler: str = typer.Option("serial", "--scheduler", help="serial | processes | local (Dask "
                                  "LocalCluster) | tcp://host:8786 (a running Dask scheduler)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes for processes/local "
                                          "(default: 2 for local, the CPU count for processes)."),
    level: str = level_option(help="registration | joint_offset | full (default; as estcal calibrate, reduced to "
                                   "an identifiable set per robot)."),
    estimator: str = estimator_option("lm", "Estimator name (as estcal calibrate; `estcal estimators`)."),
    diagnose: bool = typer.Option(False, "--diagnose", help="Run estcal diagnose on each robot (named "
                                  "non-geometric causes; the saved model includes them)."),
    noise_pos_mm: float = noise_pos_option(0.1),
    noise_rot_mrad: float = noise_rot_option(1.0),
    old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
    old_noise_rot: Optional[float] = deprecated_option("--noise-rot"),
    known_noise: bool = known_noise_option("Trust the noise values."),
    save_models: Optional[Path] = typer.Option(None, "--save-models", help="Folder for the saved models "
                                               "(<robot>.yaml robot files with a calibration: block)."),
    strict: bool = typer.Option(False, "--strict", help="Exit with code 1 when any robot failed."),
    seed: int = typer.Option(0, "--seed", help="Seed of diagnose's cross-validation folds."),
    column_map: Optional[Path] = map_option(),
    json_path: Optional[Path] = json_option("Write the summary as JSON."),
) -> None:
    """Calibrate or diagnose every robot of a fleet folder, serially or on a Dask cluster."""
    from rich.console import Console

    from estcal.base.errors import InputError
    from estcal.base.units import MILLI
    from estcal.cli.checks import check_outputs
    from estcal.cli.units import resolve
    from estcal.estimate.levels import LEVELS
    from estcal.estimate.registry import estimator_names
    from estcal.workflows.fleet import FleetOptions, check_scheduler, fleet_inputs, run_fleet

    noise_pos = resolve(noise_pos_mm, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.1)
    noise_rot = resolve(noise_rot_mrad, MILLI, old_noise_rot, "--noise-rot", "--noise-rot-mrad", "rad", 1.0, 1.0)
    check_scheduler(scheduler)
    if level not in LEVELS:
        raise InputError(f"unknown --level {level!r}; choose one of {', '.join(LEVELS)}")
    if estimator not in estimator_names():
        raise InputError(f"unknown --estimator {estimator!r}; choose one of {', '.join(estimator_names())}")
    opts = FleetOptions(level=level, estimator=estimator, diagnose=diagnose, noise_pos=noise_pos,
                        noise_rot=noise_rot, known_noise=known_noise,
                        save_models=str(save_models) if save_models else None, seed=seed,
                        column_map=column_map)
    check_outputs({"--json": json_path}, fleet_inputs(folder))  # outputs never land on a robot's inputs
    try:
        summary = run_fleet(folder, opts, scheduler=scheduler, n_workers=workers)
    except OSError as exc:  # e.g. no Dask scheduler at the address
        raise InputError(f"--scheduler {scheduler}: {exc}") from exc
    console = Console(width=160)
    console.print(_table(summary, diagnose))
    for f in summary.failures:
        typer.echo(f"failed: {f['robot']} ({f['inputs']}): {f['error']}", err=True)
    if save_models and summary.n_ok:
        console.print(f"saved models: {save_models}/ ({summary.n_ok} robot files)")
    if json_path:
        from estcal.base.jsonio import write_json

        write_json(json_path, summary.to_dict())
        console.print(f"wrote {json_path}")
    if not summary.n_ok:
        raise InputError(f"no robot of {folder} could be processed ({len(summary.failures)} failures listed above)")
    if strict and summary.failures:
        raise typer.Exit(1)
