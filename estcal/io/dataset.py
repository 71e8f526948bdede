"""Measurement datasets (CSV with a header), loaded into a :class:`Dataset`.

Columns (SI units; see ``docs/dataset.md``):

* joint readings, one column per joint named by the robot's joint names (rad / m);
* the measurement, one of
  - ``x,y,z`` — one point (the tool origin, or marker 1 when the robot has markers);
  - ``x1,y1,z1,…,xk,yk,zk`` — k points of one rigid body (markers 1..k);
  - ``x,y,z,qw,qx,qy,qz`` — full pose of the tool frame (quaternion scalar-first);
* optional ``t`` (s), ``temperature`` (°C), ``payload`` (kg) and ``approach_<joint>``
  (±1, direction in which the joint approached the pose) — the *context* passed
  to non-geometric effects. When ``t`` is absent
  but ``t_start_robot``/``t_end_robot`` are present (the TIAGo files), ``t`` is
  the middle of that window;
* method columns used by the measurement methods (``group`` for link methods,
  ``distance`` …) and anything else, kept in :attr:`Dataset.columns`; unknown
  extra columns are otherwise ignored.

Loading checks every value and names the file, the CSV line and the column
of the first problem (missing joint column, NaN, text, ragged row, values that
look like degrees or millimetres).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Dataset", "DatasetError", "load_dataset", "write_dataset", "dataset_from_arrays"]

CONTEXT_COLUMNS = ("t", "temperature", "payload")


class DatasetError(ValueError):
    """A dataset problem; the message names the file, line and column."""


@dataclass
class Dataset:
    """Joint readings and measurements of N poses.

    Attributes
    ----------
    readings : (N, n) joint readings (rad / m), columns ordered as ``joint_names``.
    kind : ``"position"``, ``"points"``, ``"pose"`` or ``"none"`` (encoders only, link methods).
    points : (N, k, 3) measured points (k = 1 for ``position``), metres; None for pose-only data.
    R, p : (N, 3, 3), (N, 3) measured tool pose when ``kind == "pose"``.
    context : per-pose arrays ``t`` (s), ``temperature`` (°C), ``payload`` (kg) when present.
    columns : every other numeric column by name.
    lines : (N,) CSV line number of each pose (header is line 1), for messages.
    """

    joint_names: list[str]
    readings: np.ndarray
    kind: str
    points: np.ndarray | None = None
    R: np.ndarray | None = None
    p: np.ndarray | None = None
    context: dict = field(default_factory=dict)
    columns: dict = field(default_factory=dict)
    lines: np.ndarray | None = None
    path: str | None = None
    warnings: list = field(default_factory=list)

    def __post_init__(self):
        if self.lines is None:
            self.lines = np.arange(2, 2 + len(self.readings))

    @property
    def n(self) -> int:
        return int(self.readings.shape[0])

    @property
    def n_points(self) -> int:
        return 0 if self.points is None else int(self.points.shape[1])

    def __len__(self) -> int:
        return self.n

    def subset(self, idx) -> "Dataset":
        """Rows ``idx`` (indices or boolean mask) as a new dataset."""
        idx = np.arange(self.n)[idx]
        take = (lambda a: None if a is None else a[idx])
        return Dataset(list(self.joint_names), self.readings[idx], self.kind, take(self.points), take(self.R),
                       take(self.p), {k: v[idx] for k, v in self.context.items()},
                       {k: v[idx] for k, v in self.columns.items()}, self.lines[idx], self.path,
                       list(self.warnings))

    def with_points(self, k: int) -> "Dataset":
        """Keep the first ``k`` measured points (``--points k``)."""
        if self.points is None or k > self.n_points:
            raise DatasetError(f"{self.path or 'dataset'}: asked for {k} points but it has {self.n_points}")
        out = self.subset(slice(None))
        out.points = self.points[:, :k].copy()
        out.kind = "position" if k == 1 else "points"
        return out

    @property
    def where(self) -> str:
        return self.path or "<in-memory dataset>"

    def __repr__(self) -> str:
        return (f"Dataset({self.where!r}, {self.n} poses, kind={self.kind!r}, points={self.n_points}, "
                f"context={sorted(self.context)})")


def _point_columns(header: list[str]) -> int:
    k = 0
    while all(f"{c}{k + 1}" in header for c in "xyz"):
        k += 1
    return k


def dataset_from_arrays(joint_names, readings, points=None, R=None, p=None, context=None, columns=None,
                        path=None) -> Dataset:
    """Build a :class:`Dataset` from arrays (kind inferred from what is given)."""
    readings = np.asarray(readings, float)
    if R is not None:
        kind = "pose"
        points = None if points is None else np.asarray(points, float)
    elif points is not None:
        points = np.asarray(points, float)
        if points.ndim == 2:
            points = points[:, None, :]
        kind = "position" if points.shape[1] == 1 else "points"
    else:
        kind = "none"
    return Dataset(list(joint_names), readings, kind, points, None if R is None else np.asarray(R, float),
                   None if p is None else np.asarray(p, float), dict(context or {}), dict(columns or {}),
                   path=path)


def load_dataset(path, robot=None, joint_names=None, points: int | None = None,
                 check_units: bool = True) -> Dataset:
    """Read a dataset CSV.

    Parameters
    ----------
    path : CSV file with a header row.
    robot : SerialRobot whose ``joint_names`` (and limits, for the unit check) are used.
    joint_names : alternative to ``robot``.
    points : keep only the first ``points`` measured points (``--points``).
    check_units : reject revolute readings beyond ±4π (degrees?) and coordinates beyond
        50 m (millimetres?).
    """
    from estcal.kinematics.transforms import quat_to_matrix

    path = Path(path)
    where = str(path)
    if not path.exists():
        raise DatasetError(f"{where}: file not found")
    names = list(robot.joint_names if robot is not None else (joint_names or []))
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    rows = [r for r in rows if r and not (len(r) == 1 and not r[0].strip())]
    if not rows:
        raise DatasetError(f"{where}: empty file (expected a header row and data rows)")
    header = [h.strip() for h in rows[0]]
    body = rows[1:]
    if not body:
        raise DatasetError(f"{where}: header only, no data rows")
    missing = [j for j in names if j not in header]
    if missing:
        raise DatasetError(f"{where}: missing joint column(s) {missing}; the robot's joints are {names}; "
                           f"the file has columns {header}")
    data = np.empty((len(body), len(header)))
    for i, r in enumerate(body):
        line = i + 2
        if len(r) != len(header):
            raise DatasetError(f"{where}, line {line}: {len(r)} fields but the header has {len(header)} "
                               f"(inconsistent column count)")
        for c, v in enumerate(r):
            v = v.strip()
            try:
                data[i, c] = float(v) if v != "" else np.nan
            except ValueError:
                data[i, c] = np.nan  # non-numeric columns are allowed if unused; checked below
    col = {h: data[:, i] for i, h in enumerate(header)}
    raw = {h: [r[i] for r in body] for i, h in enumerate(header)}

    def need(hs):
        for h in hs:
            bad = np.flatnonzero(~np.isfinite(col[h]))
            if bad.size:
                b = bad[0]
                txt = raw[h][b].strip()
                what = "is empty" if txt == "" else f"is {txt!r}, not a finite number"
                raise DatasetError(f"{where}, line {b + 2}, column {h!r}: value {what}")

    need(names)
    k = _point_columns(header)
    quat = all(c in header for c in ("qw", "qx", "qy", "qz"))
    single = all(c in header for c in "xyz")
    used = set(names)
    R = p = pts = None
    if single and quat:
        kind = "pose"
        need(["x", "y", "z", "qw", "qx", "qy", "qz"])
        p = np.c_[col["x"], col["y"], col["z"]]
        qv = np.c_[col["qw"], col["qx"], col["qy"], col["qz"]]
        nq = np.linalg.norm(qv, axis=1)
        if np.any(np.abs(nq - 1) > 1e-3):
            b = int(np.argmax(np.abs(nq - 1)))
            raise DatasetError(f"{where}, line {b + 2}: quaternion (qw,qx,qy,qz) has norm {nq[b]:.6f}, expected 1")
        R = quat_to_matrix(qv)
        used |= {"x", "y", "z", "qw", "qx", "qy", "qz"}
    elif k >= 1:
        cols = [f"{c}{i + 1}" for i in range(k) for c in "xyz"]
        need(cols)
        pts = np.stack([np.c_[col[f"x{i + 1}"], col[f"y{i + 1}"], col[f"z{i + 1}"]] for i in range(k)], 1)
        kind = "position" if k == 1 else "points"
        used |= set(cols)
    elif single:
        need(["x", "y", "z"])
        pts = np.c_[col["x"], col["y"], col["z"]][:, None, :]
        kind = "position"
        used |= {"x", "y", "z"}
    else:
        kind = "none"
    readings = np.c_[tuple(col[j] for j in names)] if names else np.zeros((len(body), 0))
    context = {}
    for c in CONTEXT_COLUMNS:
        if c in header:
            need([c])
            context[c] = col[c].copy()
            used.add(c)
    # approach direction of each joint (±1) drives direction-dependent backlash
    for h in header:
        if h.startswith("approach_") and h not in used:
            need([h])
            context[h] = col[h].copy()
            used.add(h)
    if "t" not in context and "t_start_robot" in header and "t_end_robot" in header:
        if np.all(np.isfinite(col["t_start_robot"])) and np.all(np.isfinite(col["t_end_robot"])):
            context["t"] = 0.5 * (col["t_start_robot"] + col["t_end_robot"])
    # Method columns may be partly empty (e.g. ``distance`` only on the second row of a
    # pair): keep them with NaN where empty; drop only columns with no number at all.
    columns = {h: col[h].copy() for h in header if h not in used and np.any(np.isfinite(col[h]))}
    ds = Dataset(names, readings, kind, pts, R, p, context, columns, np.arange(2, len(body) + 2), where)
    if check_units:
        _check_units(ds, robot)
    if points is not None:
        ds = ds.with_points(points)
    return ds


def _check_units(ds: Dataset, robot) -> None:
    if robot is not None:
        for j, (name, typ) in enumerate(zip(robot.joint_names, robot.joint_types)):
            v = ds.readings[:, j]
            if typ == "revolute" and np.abs(v).max() > 4 * np.pi:
                b = int(np.argmax(np.abs(v)))
                raise DatasetError(f"{ds.where}, line {ds.lines[b]}, column {name!r}: {v[b]:g} rad is beyond "
                                   f"±4π — readings look like degrees; convert to radians")
            lo, hi = robot.limits[j]
            span = hi - lo
            out = np.flatnonzero((v < lo - 0.05 * span) | (v > hi + 0.05 * span))
            if out.size:
                ds.warnings.append(f"{out.size} readings of {name!r} outside its limits [{lo:g}, {hi:g}] "
                                   f"(first at line {ds.lines[out[0]]})")
    coords = ds.points if ds.points is not None else ds.p
    if coords is not None and np.abs(coords).max() > 50.0:
        raise DatasetError(f"{ds.where}: measured coordinates reach {np.abs(coords).max():g} m — they look like "
                           f"millimetres; estcal expects metres")


def write_dataset(path, ds: Dataset, extra: dict | None = None, float_format: str = "%.17g") -> Path:
    """Write a dataset CSV in the documented format (joint columns, measurement, context, extra).

    The default format round-trips float64 exactly (identifiability checks on link
    data rely on exactly repeated end points)."""
    from estcal.kinematics.transforms import matrix_to_quat

    cols: dict[str, np.ndarray] = {}
    for j, name in enumerate(ds.joint_names):
        cols[name] = ds.readings[:, j]
    if ds.kind == "pose":
        q = matrix_to_quat(ds.R)
        for i, c in enumerate("xyz"):
            cols[c] = ds.p[:, i]
        for i, c in enumerate(("qw", "qx", "qy", "qz")):
            cols[c] = q[:, i]
    elif ds.kind == "position":
        for i, c in enumerate("xyz"):
            cols[c] = ds.points[:, 0, i]
    elif ds.kind == "points":
        for k in range(ds.n_points):
            for i, c in enumerate("xyz"):
                cols[f"{c}{k + 1}"] = ds.points[:, k, i]
    cols.update(ds.context)
    cols.update(ds.columns)
    cols.update(extra or {})
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(cols)
    M = np.column_stack([np.asarray(cols[n], float) for n in names])
    np.savetxt(path, M, delimiter=",", header=",".join(names), comments="", fmt=float_format)
    return path
