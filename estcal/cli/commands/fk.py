"""``estcal fk``: forward kinematics of every row of a dataset."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.common import fail, message
from estcal.io.atomic import atomic_write
from estcal.io.jsonio import write_json


def register(app: typer.Typer) -> None:
    @app.command("fk")
    def fk_cmd(
        data: Path = typer.Argument(..., help="Dataset CSV with one column per joint (rad / m)."),
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF (.urdf)."),
        output: Path = typer.Option(..., "--output", "-o", help="CSV to write: x,y,z,qw,qx,qy,qz per row."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        with_joints: bool = typer.Option(False, "--with-joints", help="Also copy the joint columns."),
        markers: bool = typer.Option(False, "--markers", help="Also write the robot's marker points x1,y1,z1,…"),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write a short JSON summary."),
    ) -> None:
        """Tool frame in the world (x,y,z in m; quaternion qw,qx,qy,qz) for every row's joint readings.

        Effects in the robot file are evaluated with the row's t / temperature / payload / approach_<joint>
        columns; a model saved by `estcal diagnose --save-model` re-applies its data preparation (t from the
        file's first row, approach directions from the posture order) as recorded in its calibration block.
        """
        import numpy as np
        from rich.console import Console

        from estcal.effects import effect_context
        from estcal.io.dataset import load_dataset
        from estcal.io.robotfile import load_robot
        from estcal.io.savedmodel import prepare_data
        from estcal.kinematics.transforms import matrix_to_quat

        console = Console()
        try:
            rb = load_robot(robot, root=root, tip=tip)
            ds = load_dataset(data, rb)
            # a saved diagnosis model re-applies the data preparation of its fit (session time, approach
            # directions from the posture order); effect columns become the effects' context
            ds = prepare_data(rb, ds)
            ctx = effect_context(rb, ds)
            rb.kinematics(ds.readings[:1], context={k: np.asarray(v)[:1] if np.ndim(v) else v
                                                    for k, v in ctx.items()}, jacobian=False)  # errors early
        except (ValueError, KeyError, FileNotFoundError) as exc:
            fail(message(exc))
        from estcal.kinematics.chunked import CHUNK, tool_poses

        names = list(rb.joint_names) if with_joints else []
        names += ["x", "y", "z", "qw", "qx", "qy", "qz"]
        want_points = markers and rb.n_markers
        if want_points:
            names += [f"{c}{k + 1}" for k in range(rb.n_markers) for c in "xyz"]
        n = len(ds.readings)
        # written CHUNK rows at a time: memory stays bounded whatever the number of rows
        with atomic_write(output) as fh:
            fh.write(",".join(names) + "\n")
            for a in range(0, n, CHUNK):
                sl = slice(a, min(a + CHUNK, n))
                c = {k: np.asarray(v)[sl] if np.ndim(v) and np.shape(v)[0] == n else v for k, v in ctx.items()}
                k = tool_poses(rb, ds.readings[sl], context=c,
                               fields=("R", "p", "points") if want_points else ("R", "p"))
                cols = ([ds.readings[sl]] if with_joints else []) + [k["p"], matrix_to_quat(k["R"])]
                if want_points:
                    cols.append(k["points"].reshape(sl.stop - sl.start, -1))
                np.savetxt(fh, np.column_stack(cols), delimiter=",", fmt="%.15g")
        console.print(f"{len(ds.readings)} rows -> {output} ({', '.join(names)})")
        for w in ds.warnings:
            typer.echo(f"warning: {data}: {w}", err=True)
        if json_path is not None:
            write_json(json_path, {"rows": int(len(ds.readings)), "robot": rb.name, "input": str(data),
                                   "output": str(output), "columns": names})
