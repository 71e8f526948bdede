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

Resumable: each robot's row is saved as it arrives to ``--results DIR`` (default
``FOLDER/_results``, one ``<robot>.json``, written atomically); rerunning the
same command skips the robots already done with the same options and inputs and
says how many (:mod:`estcal.workflows.fleet_results`). Above
:data:`TABLE_ROWS` robots the table shows the first ones, the failures and the
fleet's medians; every row is in the results folder and ``--json``.

Exit code: 0 when at least one robot was processed (failures are listed, never
fatal — the others are calibrated and saved); 1 with ``--strict`` when any robot
failed; 2 for bad input (no such folder, no robot folders, bad option) or when
every robot failed.

JSON (``--json PATH``): ``n_robots``, ``n_ok``, ``n_failed``, ``n_skipped``, ``results``, ``scheduler``,
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


#: robots listed one per row in the table; a larger fleet shows the first ones and the medians
TABLE_ROWS = 40


def _mm(v) -> str:
    return "—" if v is None else f"{v:.3f}"


def _title(summary, diagnose: bool) -> str:
    n = summary.n_ok + len(summary.failures)
    new = n - summary.n_skipped
    done = "diagnosed" if diagnose else "calibrated"
    head = f"estcal fleet — {summary.n_ok:,} of {n:,} robots {done}"
    if summary.n_skipped:
        head += f" ({summary.n_skipped:,} skipped: done earlier, in {summary.results}/)"
    if not new:
        return head + "; nothing left to run"
    return head + f"; {new:,} run on {summary.scheduler}, {summary.n_workers} worker(s), {summary.wall_s:.1f} s"


def _labels(diagnose: bool) -> tuple[str, str]:
    """The two figures of a row: a diagnosis's registration alone and its model, a calibration's before and after."""
    return ("registration", "model") if diagnose else ("before", "after")


def _medians(rows, before: str, after: str) -> str:
    import statistics

    def med(key):
        v = [r[key] for r in rows if r.get(key) is not None]
        return f"{statistics.median(v):.3f}" if v else "—"

    return (f"medians over {len(rows):,} robots: RMSE {before} {med('rmse_before_mm')} mm, {after} "
            f"{med('rmse_after_mm')} mm; validation {before} {med('validation_rmse_before_mm')} mm, {after} "
            f"{med('validation_rmse_mm')} mm")


def _table(summary, diagnose: bool):
    from rich.table import Table

    t = Table()
    before, after = _labels(diagnose)
    for c, j in (("robot", "left"), ("poses", "right"), (f"RMSE {before} mm", "right"),
                 (f"RMSE {after} mm", "right"), (f"valid. {before} mm", "right"), (f"valid. {after} mm", "right"),
                 ("causes", "left"), ("warnings", "left")):
        t.add_column(c, justify=j)
    shown = summary.rows if len(summary.rows) <= TABLE_ROWS else summary.rows[:TABLE_ROWS // 2]
    for r in shown:
        t.add_row(r["robot"], str(r["poses"]), _mm(r.get("rmse_before_mm")), _mm(r.get("rmse_after_mm")),
                  _mm(r.get("validation_rmse_before_mm")), _mm(r.get("validation_rmse_mm")),
                  ", ".join(r.get("causes") or []) or "—", "; ".join(r.get("warnings") or []) or "—")
    if len(shown) < len(summary.rows):
        t.add_row(f"… {len(summary.rows) - len(shown):,} more", *["…"] * 7)
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
    results: Optional[Path] = typer.Option(None, "--results", help="Folder of the per-robot results, saved "
                                           "as they arrive; a rerun skips the robots done there (default: "
                                           "FOLDER/_results)."),
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
    if results is None and folder.is_dir():
        results = folder / "_results"
    try:
        summary = run_fleet(folder, opts, scheduler=scheduler, n_workers=workers, results=results)
    except OSError as exc:  # e.g. no Dask scheduler at the address
        raise InputError(f"--scheduler {scheduler}: {exc}") from exc
    console = Console(width=160)
    console.print(_title(summary, diagnose), soft_wrap=True)
    console.print(_table(summary, diagnose))
    if len(summary.rows) > TABLE_ROWS:
        b, a = _labels(diagnose)
        console.print(_medians(summary.rows, b, a))
    if summary.results:
        console.print(f"results: {summary.results}/ (one <robot>.json per robot; a rerun skips them)")
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
