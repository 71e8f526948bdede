"""Forward kinematics of every row of a dataset: ``estcal fk``.

:func:`fk_file` writes the tool frame in the world (x,y,z in m; quaternion qw,qx,qy,qz) of each
row's joint readings, chunk by chunk (memory bounded whatever the number of rows). Effects in the
robot file are evaluated with the row's context columns; a model saved by ``estcal diagnose
--save-model`` re-applies the data preparation of its fit. When the file has x,y,z (and
qw,qx,qy,qz) columns, the distance of the computed frame from them is returned too.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from estcal.workflows.inputs import check_input_files, input_errors

__all__ = ["Forward", "fk_file"]


@dataclass
class Forward:
    """What :func:`fk_file` wrote: rows, columns, the robot and dataset, and the distance from the
    file's own x,y,z[,q] columns (``position_rms_mm`` … and a ``text`` line), or None."""

    rows: int
    columns: list
    robot: object
    data: object
    against: dict | None

    def to_dict(self, data_path, output) -> dict:
        return {"rows": int(self.rows), "robot": self.robot.name, "input": str(data_path), "output": str(output),
                "columns": self.columns, **({k: v for k, v in self.against.items() if k != "text"}
                                            if self.against else {})}


def fk_file(robot, data, output, *, root=None, tip=None, with_joints: bool = False, markers: bool = False,
            column_map=None) -> Forward:
    """Forward kinematics of every row of the dataset ``data`` written to ``output`` (CSV);
    ``column_map``: the data's column map (docs/dataset.md)."""
    import numpy as np

    from estcal.base.atomic import atomic_write
    from estcal.base.progress import progress
    from estcal.effects import effect_context
    from estcal.io.dataset import load_dataset
    from estcal.io.robotfile import load_robot
    from estcal.io.prepare import prepare_data
    from estcal.kinematics.chunked import CHUNK, tool_poses
    from estcal.kinematics.transforms import matrix_to_quat

    check_input_files([data])
    with input_errors():
        rb = load_robot(robot, root=root, tip=tip)
        ds = load_dataset(data, rb, column_map=column_map)
        # a saved diagnosis model re-applies the data preparation of its fit (session time, approach
        # directions from the posture order); effect columns become the effects' context
        ds = prepare_data(rb, ds)
        ctx = effect_context(rb, ds)
        rb.kinematics(ds.readings[:1], context={k: np.asarray(v)[:1] if np.ndim(v) else v
                                                for k, v in ctx.items()}, jacobian=False)  # errors early
    names = list(rb.joint_names) if with_joints else []
    names += ["x", "y", "z", "qw", "qx", "qy", "qz"]
    want_points = markers and rb.n_markers
    if want_points:
        names += [f"{c}{k + 1}" for k in range(rb.n_markers) for c in "xyz"]
    n = len(ds.readings)
    against = _AgainstFile(rb, ds)
    fields = ("R", "p", "points") if want_points or against.needs_points else ("R", "p")
    with atomic_write(output) as fh, progress(total=-(-n // CHUNK), desc="fk", unit="chunk") as bar:
        fh.write(",".join(names) + "\n")
        for a in range(0, n, CHUNK):
            bar.update(1)
            sl = slice(a, min(a + CHUNK, n))
            c = {k: np.asarray(v)[sl] if np.ndim(v) and np.shape(v)[0] == n else v for k, v in ctx.items()}
            k = tool_poses(rb, ds.readings[sl], context=c, fields=fields)
            against.add(sl, k)
            cols = ([ds.readings[sl]] if with_joints else []) + [k["p"], matrix_to_quat(k["R"])]
            if want_points:
                cols.append(k["points"].reshape(sl.stop - sl.start, -1))
            np.savetxt(fh, np.column_stack(cols), delimiter=",", fmt="%.15g")
    return Forward(n, names, rb, ds, against.result())


class _AgainstFile:
    """Distance of the computed tool frame (or markers) from the file's own x,y,z[,qw..qz] columns.

    Turns `estcal fk` into a check: on a compensated command file it shows where the model (or a URDF
    export, or a true robot) puts the tool relative to the targets; on a dataset, the model's error.
    The point is the tool origin, or the markers when the model has them (docs/dataset.md). Accumulated
    chunk by chunk, like the output.
    """

    def __init__(self, rb, ds):
        self.ds = ds
        self.pose = ds.kind == "pose"
        # measured markers are compared with the model's markers only (a model without markers has
        # nothing to put at x1..zk; a single x,y,z is the tool origin, docs/dataset.md)
        self.active = self.pose or (ds.points is not None and (ds.kind == "position" or
                                                               (ds.kind == "points" and bool(rb.n_markers))))
        self.needs_points = self.active and not self.pose and bool(rb.n_markers)
        self.k = 1 if not self.active or self.pose else \
            min(rb.n_markers or 1, ds.points.shape[1])
        self.sp = self.sr = self.n = 0
        self.mp = self.mr = 0.0

    def add(self, sl, kin) -> None:
        import numpy as np

        from estcal.kinematics.transforms import so3_log

        if not self.active:
            return
        ds = self.ds
        if self.pose:
            dp = np.linalg.norm(kin["p"] - ds.p[sl], axis=1)
            dr = np.linalg.norm(so3_log(ds.R[sl] @ np.swapaxes(kin["R"], 1, 2)), axis=1)
            self.sr += float(np.sum(dr ** 2))
            self.mr = max(self.mr, float(dr.max(initial=0.0)))
        else:
            model = kin["points"] if self.needs_points else kin["p"][:, None, :]
            dp = np.linalg.norm(model[:, :self.k] - ds.points[sl, :self.k], axis=2).ravel()
        self.sp += float(np.sum(dp ** 2))
        self.mp = max(self.mp, float(dp.max(initial=0.0)))
        self.n += len(dp)

    def result(self) -> dict | None:
        if not self.active or not self.n:
            return None
        what = "x,y,z,q" if self.pose else ("x,y,z" if self.k == 1 else f"x1..z{self.k}")
        out = {"position_rms_mm": (self.sp / self.n) ** 0.5 * 1e3, "position_max_mm": self.mp * 1e3}
        text = f"vs the file's {what}: {out['position_rms_mm']:.4g} mm RMS (max {out['position_max_mm']:.4g})"
        if self.pose:
            out.update(orientation_rms_mrad=(self.sr / self.n) ** 0.5 * 1e3, orientation_max_mrad=self.mr * 1e3)
            text += f", {out['orientation_rms_mrad']:.4g} mrad RMS (max {out['orientation_max_mrad']:.4g})"
        out["text"] = text
        return out
