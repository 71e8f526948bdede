"""``estcal compensate``: corrected joint commands from a calibrated (saved) model.

Thin shell around :func:`estcal.compensation.compensate`; the method, the output
columns and the exit codes are documented in docs/compensation.md.
"""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Optional

import typer

from estcal.cli.common import check_input_files, fail, warn


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve() or (a.exists() and b.exists() and a.samefile(b))
    except OSError:
        return False


def _read_raw(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and data rows as text (blank lines dropped, as load_dataset does), so that the
    columns other than the joints are written back unchanged."""
    from estcal.io.dataset import DatasetError
    from estcal.base.textinput import read_csv

    try:  # the input layer: folder, binary, encoding, delimiter (docs/reliability.md)
        table = read_csv(path, "targets", DatasetError)
    except DatasetError as exc:
        fail(str(exc))
    return table.header, table.rows


def register(app: typer.Typer) -> None:
    @app.command("compensate")
    def compensate_cmd(
        targets: Path = typer.Argument(..., help="CSV of targets: x,y,z (m) [qw,qx,qy,qz] and one column per "
                                                 "joint with the nominal program's command (rad / m)."),
        robot: str = typer.Option(..., "--robot", "-r", help="Calibrated model: robot file (.yaml) saved by "
                                                             "calibration, or any robot spec."),
        output: Path = typer.Option(..., "--output", "-o", help="CSV to write: the input rows with the joint "
                                                                "columns replaced by the compensated readings."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write a JSON report."),
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

        from estcal.compensation import compensate
        from estcal.effects import effect_context
        from estcal.base.atomic import atomic_write
        from estcal.io.dataset import DatasetError, load_dataset
        from estcal.io.robotfile import load_robot

        console = Console(stderr=False, width=120)
        check_input_files([targets], "targets")
        # outputs equal to TARGETS or to each other are refused by estcal.cli.checks.guard
        for opt, v in (("--tol-mm", tol_mm), ("--tol-mrad", tol_mrad), ("--rot-weight-m", rot_weight_m)):
            if not v > 0:
                fail(f"{opt} must be > 0, got {v:g}")
        if max_iter < 1:
            fail(f"--max-iter must be an integer ≥ 1, got {max_iter}")
        try:
            rb = load_robot(robot)
        except (ValueError, KeyError, FileNotFoundError) as exc:
            fail(str(exc).strip("'\""))
        for p, opt in ((output, "-o"), (json_path, "--json")):
            if p is not None and _same_file(p, Path(robot)):
                fail(f"{opt} {p} is the robot file; choose another output path (inputs are never overwritten)")
        header, raw = _read_raw(targets)
        for h in header:
            if h.startswith("approach_") and h[len("approach_"):] not in rb.joint_names:
                fail(f"{targets}: column {h!r} names unknown joint {h[len('approach_'):]!r}; the model's joints "
                     f"are {rb.joint_names}")
        if not all(c in header for c in "xyz"):
            fail(f"{targets}: missing target columns x,y,z (m, world frame); the file has columns {header}")
        if any(f"{c}1" in header for c in "xyz"):
            fail(f"{targets}: compensate takes one target point per row (x,y,z [qw,qx,qy,qz]), not x1,y1,z1 …")
        try:
            ds = load_dataset(targets, rb)
        except (DatasetError, FileNotFoundError) as exc:
            fail(str(exc))
        for w in ds.warnings:
            warn(f"{targets}: {w}")
        if ds.kind == "pose" and not position_only:
            tgt = np.c_[ds.p, _quat(ds.R)]
        else:
            tgt = ds.p if ds.kind == "pose" else ds.points[:, 0]
        ctx = effect_context(rb, ds)
        notes = _context_notes(rb, ctx)
        try:
            res = compensate(rb, tgt, ds.readings, context=ctx, tol_mm=tol_mm, tol_mrad=tol_mrad,
                             max_iter=max_iter, rot_weight_m=rot_weight_m, lines=ds.lines)
        except ValueError as exc:
            fail(f"{targets}: {exc}")
        except np.linalg.LinAlgError as exc:
            fail(f"{targets}: numerical failure in the solve ({exc})", code=3)

        jidx = {h: i for i, h in enumerate(header)}
        extra = ["predicted_error_mm"] + (["predicted_rot_error_mrad"] if res.rot_error_mrad is not None else [])
        if res.std_mm is not None:
            extra += ["predicted_std_mm"] + (["predicted_rot_std_mrad"] if res.rot_std_mrad is not None else [])
        extra += ["reachable"]
        for c in extra:
            if c in jidx:
                fail(f"{targets}: already has a column {c!r} (is it a compensate output?)")
        with atomic_write(output, newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(header + extra)
            for i, row in enumerate(raw):
                row = list(row)
                for j, name in enumerate(rb.joint_names):
                    row[jidx[name]] = repr(float(res.readings[i, j]))
                vals = [f"{res.error_mm[i]:.6g}"]
                if res.rot_error_mrad is not None:
                    vals.append(f"{res.rot_error_mrad[i]:.6g}")
                if res.std_mm is not None:
                    vals.append(f"{res.std_mm[i]:.6g}")
                    if res.rot_std_mrad is not None:
                        vals.append(f"{res.rot_std_mrad[i]:.6g}")
                vals.append("1" if res.reachable[i] else "0")
                w.writerow(row + vals)

        n, ok = len(res.reachable), int(res.reachable.sum())
        shift = np.abs(res.readings - ds.readings)
        jmax = int(np.argmax(shift.max(axis=0)))
        unit = "mm" if rb.joint_types[jmax] == "prismatic" else "mrad"
        msg = (f"{n} rows -> {output}: {ok} reachable within {tol_mm:g} mm"
               + (f" / {tol_mrad:g} mrad" if res.rot_error_mrad is not None else "")
               + f" (task point: {'marker 1' if res.task_point == 'marker1' else 'tool origin'}); "
               f"largest command change {shift[:, jmax].max() * 1e3:.4g} {unit} ({rb.joint_names[jmax]})")
        console.print(msg, soft_wrap=True)
        if res.std_mm is not None:
            console.print(f"predicted position std from the saved covariance ({len(res.covariance_names)} "
                          f"parameters): median {np.median(res.std_mm):.4g} mm, max {res.std_mm.max():.4g} mm")
        else:
            console.print("no calibration covariance in the model: predicted_std_mm omitted")
        for note in notes:
            console.print("note: " + escape(note))
        if res.start_outside.any():
            warn(f"starting joints outside the limits (projected) on lines {_lines(res.lines[res.start_outside])}")
        if json_path is not None:
            from estcal.base.jsonio import write_json

            d = res.to_dict()
            d.update(input=str(targets), output=str(output), robot=str(robot), notes=notes,
                     readings_changed_max=float(shift.max()))
            write_json(json_path, d)  # strict JSON, atomic
        if ok < n:
            bad = res.unreachable_lines
            worst = float(res.error_mm[~res.reachable].max())
            level, rows = ("warning" if allow_unreachable else "error"), ("rows" if n - ok > 1 else "row")
            typer.echo(f"{level}: {targets}: {n - ok} {rows} not reachable within tolerance (flagged "
                       f"reachable=0, best-effort joints written), lines {_lines(bad)}; largest residual "
                       f"{worst:.4g} mm", err=True)
            if not allow_unreachable:
                raise typer.Exit(3)


def _quat(R):
    from estcal.kinematics.transforms import matrix_to_quat

    return matrix_to_quat(R)


def _lines(lines, k: int = 20) -> str:
    lines = [int(v) for v in lines]
    return ", ".join(map(str, lines[:k])) + (f" … ({len(lines)} in all)" if len(lines) > k else "")


def _context_notes(robot, ctx) -> list[str]:
    """Say which effect inputs fall back to their defaults (so the user knows what was assumed)."""
    notes = []
    for eff in robot.effects:
        name = getattr(eff, "name", type(eff).__name__)
        if name == "thermal_expansion" and not robot.n_markers:
            notes.append("thermal_expansion acts on marker points; this model has no markers, so the tool "
                         "origin is compensated without it")
        elif name == "thermal_expansion" and "temperature" not in ctx and "t" not in ctx:
            notes.append("thermal_expansion: no temperature column, ΔT = 0 (the reference temperature)")
        if name == "backlash":
            miss = [j for j in eff.joints if f"approach_{j}" not in ctx]
            if miss:
                notes.append(f"backlash: no approach_<joint> column for {', '.join(miss)}; the gravity side "
                             f"sign(τ) is used")
        if name == "joint_compliance" and "payload" not in ctx:
            notes.append(f"joint_compliance: payload {robot.payload_mass:g} kg from the robot file")
    return list(dict.fromkeys(notes))  # one note per kind (an effect may be added once per joint)
