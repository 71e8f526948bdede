"""``estcal fleet``: calibrate (or diagnose) every robot of a fleet folder, on one machine or a Dask cluster.

Runs :func:`estcal.scale.fleet.run_fleet`: one task per robot folder (layout in
:mod:`estcal.scale.fleet` and docs/scaling.md), executed by
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

import json
from pathlib import Path
from typing import Optional

import typer

from estcal.cli.common import fail
from estcal.base.units import MILLI
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option, resolve

__all__ = ["register"]


def _mm(v) -> str:
    return "—" if v is None else f"{v:.3f}"


def _table(summary, diagnose: bool):
    from rich.table import Table

    t = Table(title=f"estcal fleet — {summary.n_ok} of {summary.n_ok + len(summary.failures)} robots "
                    f"{'diagnosed' if diagnose else 'calibrated'} ({summary.scheduler}, {summary.n_workers} "
                    f"worker(s), {summary.wall_s:.1f} s)", title_justify="left")
    before, after = ("geometric", "extended") if diagnose else ("before", "after")
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


def register(app: typer.Typer) -> None:
    @app.command("fleet")
    def fleet_cmd(
        folder: Path = typer.Argument(..., help="Fleet folder: one sub-folder per robot (data.csv, optional "
                                                "validate*.csv, robot.yaml/.urdf or one shared at the top)."),
        scheduler: str = typer.Option("serial", "--scheduler", help="serial | processes | local (Dask "
                                      "LocalCluster) | tcp://host:8786 (a running Dask scheduler)."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes for processes/local "
                                              "(default: 2 for local, the CPU count for processes)."),
        level: str = typer.Option("full", "--level", help="registration | joint_offset | full (as estcal "
                                                          "calibrate; reduced to an identifiable set per robot)."),
        estimator: str = typer.Option("lm", "--estimator", help="Estimator name (as estcal calibrate)."),
        diagnose: bool = typer.Option(False, "--diagnose", help="Run estcal diagnose on each robot (named "
                                      "non-geometric causes; the saved model includes them)."),
        noise_pos_mm: float = noise_pos_option(0.1),
        noise_rot_mrad: float = noise_rot_option(1.0),
        old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
        old_noise_rot: Optional[float] = deprecated_option("--noise-rot"),
        known_noise: bool = typer.Option(False, "--known-noise", help="Trust the noise values."),
        save_models: Optional[Path] = typer.Option(None, "--save-models", help="Folder for the saved models "
                                                   "(<robot>.yaml robot files with a calibration: block)."),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 1 when any robot failed."),
        seed: int = typer.Option(0, "--seed", help="Seed of diagnose's cross-validation folds."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the summary as JSON."),
    ) -> None:
        """Calibrate or diagnose every robot of a fleet folder, serially or on a Dask cluster."""
        from rich.console import Console

        from estcal.estimate.levels import LEVELS
        from estcal.estimate.registry import estimator_names
        from estcal.base.atomic import atomic_write_text
        from estcal.base.jsonio import to_jsonable
        from estcal.scale.fleet import FleetError, FleetOptions, run_fleet
        from estcal.scale.runner import check_scheduler

        noise_pos = resolve(noise_pos_mm, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.1)
        noise_rot = resolve(noise_rot_mrad, MILLI, old_noise_rot, "--noise-rot", "--noise-rot-mrad", "rad", 1.0, 1.0)
        try:
            check_scheduler(scheduler)
        except ValueError as exc:
            fail(f"--scheduler: {exc}")
        if level not in LEVELS:
            fail(f"unknown --level {level!r}; choose one of {', '.join(LEVELS)}")
        if estimator not in estimator_names():
            fail(f"unknown --estimator {estimator!r}; choose one of {', '.join(estimator_names())}")
        if workers is not None and workers < 1:
            fail(f"--workers must be ≥ 1, got {workers}")
        opts = FleetOptions(level=level, estimator=estimator, diagnose=diagnose, noise_pos=noise_pos,
                            noise_rot=noise_rot, known_noise=known_noise,
                            save_models=str(save_models) if save_models else None, seed=seed)
        try:  # the files the robots' jobs read are inputs: outputs must not land on them
            from estcal.cli.checks import check_outputs
            from estcal.scale.fleet import discover_fleet

            read = [Path(f) for j in discover_fleet(folder) for f in (j.data, j.robot, *j.validate) if f]
        except FleetError:
            read = []  # no robot folder: run_fleet says so below
        check_outputs({"--json": json_path}, read)
        try:
            summary = run_fleet(folder, opts, scheduler=scheduler, n_workers=workers)
        except FleetError as exc:
            fail(str(exc))
        except OSError as exc:  # e.g. no Dask scheduler at the address
            fail(f"--scheduler {scheduler}: {exc}")
        console = Console(width=160)
        console.print(_table(summary, diagnose))
        for f in summary.failures:
            typer.echo(f"failed: {f['robot']} ({f['inputs']}): {f['error']}", err=True)
        if save_models and summary.n_ok:
            console.print(f"saved models: {save_models}/ ({summary.n_ok} robot files)")
        if json_path:
            atomic_write_text(json_path, json.dumps(to_jsonable(summary.to_dict()), indent=2))
            console.print(f"wrote {json_path}")
        if not summary.n_ok:
            fail(f"no robot of {folder} could be processed ({len(summary.failures)} failures listed above)")
        if strict and summary.failures:
            raise typer.Exit(1)
