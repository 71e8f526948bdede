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

import difflib
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.textinput import CsvTable, read_csv
from estcal.io.columns import (CONTEXT_COLUMNS, METHOD_COLUMNS, NUMBERED, POSE_COLUMNS, QUAT_COLUMNS, DatasetError,
                               is_number)

__all__ = ["Dataset", "DatasetError", "load_dataset", "write_dataset", "dataset_from_arrays", "dataset_from_table",
           "dataset_from_mapped_table", "shared_rows"]

# allowance of the spread check for unknown marker offsets and calibration errors (m)
SPREAD_SLACK_M = 0.2
#: measured positions that spread less than this fraction of the nominal model's do not follow the joints
#: (a unit mistake makes them larger: mm, cm, inches given as metres)
STILL_RATIO = 0.02


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
    # the file's own column names and {estcal column: file column} when read through a column map
    source_header: list | None = None
    renamed: dict = field(default_factory=dict)
    # estcal's names of the measured coordinates as the file gave them (x,y,z or x1…zk), when read from a table
    coordinates: list | None = None

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
                       list(self.warnings), coordinates=self.coordinates)

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


def _row_keys(ds: Dataset) -> np.ndarray:
    """One opaque key per pose: its readings and measurements, bit for bit."""
    cols = [ds.readings.reshape(ds.n, -1)]
    for a in (ds.points, ds.R, ds.p):
        if a is not None:
            cols.append(np.asarray(a, float).reshape(ds.n, -1))
    M = np.ascontiguousarray(np.hstack(cols), dtype=float) + 0.0  # + 0.0: -0.0 and 0.0 are one value
    return M.view(np.dtype((np.void, M.dtype.itemsize * M.shape[1]))).ravel()


def shared_rows(reference: Dataset, other: Dataset) -> np.ndarray:
    """Indices of the poses of ``other`` that also occur in ``reference`` with identical joint
    readings and identical measurements (bit for bit): rows a held-out file must not share
    with the data that were fitted. Files of different layout share none. Vectorised
    (``np.isin`` on row keys)."""
    if reference.n == 0 or other.n == 0 or reference.kind != other.kind \
            or reference.readings.shape[1] != other.readings.shape[1] \
            or any((a is None) != (b is None) or (a is not None and np.shape(a)[1:] != np.shape(b)[1:])
                   for a, b in ((reference.points, other.points), (reference.R, other.R), (reference.p, other.p))):
        return np.zeros(0, int)
    return np.flatnonzero(np.isin(_row_keys(other), _row_keys(reference)))


def _point_columns(header: list[str]) -> int:
    k = 0
    while all(f"{c}{k + 1}" in header for c in "xyz"):
        k += 1
    return k


def measurement_layout(path) -> tuple[int, bool, bool]:
    """``(k, has_xyz, has_quaternion)`` of a dataset file from its header alone: ``k`` numbered
    points ``x1,y1,z1 … xk,yk,zk``, a single point ``x,y,z``, a quaternion ``qw,qx,qy,qz``.
    Reads the header line only (:func:`estcal.base.textinput.read_csv_header`); raises
    :class:`DatasetError` naming the file."""
    from estcal.base.textinput import read_csv_header

    header = read_csv_header(path, "dataset", DatasetError)
    return (_point_columns(header), all(c in header for c in "xyz"),
            all(c in header for c in ("qw", "qx", "qy", "qz")))


def dataset_from_arrays(joint_names, readings, points=None, R=None, p=None, context=None, columns=None,
                        path=None) -> Dataset:
    """Build a :class:`Dataset` from arrays (kind inferred from what is given).

    Shapes (N poses, n joints, k points; SI units): ``readings`` (N, n) in the order of
    ``joint_names``; ``points`` (N, 3) or (N, k, 3); ``R`` (N, 3, 3) with ``p`` (N, 3) for
    full poses; ``context`` and ``columns`` values (N,). Inconsistent shapes, repeated joint
    names and non-finite readings or measurements raise :class:`DatasetError` naming the
    array and, for values, the first bad pose — the checks the CSV loader makes, for data
    built in Python.
    """
    where = path or "dataset_from_arrays"
    names = list(joint_names)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise DatasetError(f"{where}: joint names repeated: {dup}")
    readings = np.asarray(readings, float)
    if readings.ndim != 2 or readings.shape[1] != len(names):
        raise DatasetError(f"{where}: readings must have shape (N, {len(names)}) — one column per joint of "
                           f"{names} — got {readings.shape}")
    N = readings.shape[0]

    def _check(name, a, tail):
        if a.shape[0] != N or a.shape[1:] != tail:
            want = ", ".join(["N"] + [str(t) for t in tail])
            raise DatasetError(f"{where}: {name} must have shape ({want}) with N = {N} poses, got {a.shape}")
        bad = ~np.isfinite(a.reshape(N, -1)).all(axis=1)
        if bad.any():
            raise DatasetError(f"{where}: {name} of pose {int(np.argmax(bad))} is not finite "
                               f"({int(bad.sum())} pose(s) with NaN or inf)")

    _check("readings", readings, (len(names),))
    given = None if points is None else np.shape(points)  # as the caller wrote it, for the message
    if R is not None:
        kind = "pose"
        R = np.asarray(R, float)
        _check("R", R, (3, 3))
        if p is None:
            raise DatasetError(f"{where}: a full-pose dataset (R given) needs the positions p (N, 3) too")
        points = None if points is None else np.asarray(points, float)
    elif points is not None:
        points = np.asarray(points, float)
        if points.ndim == 2:
            points = points[:, None, :]
        kind = "position" if points.ndim == 3 and points.shape[1] == 1 else "points"
    else:
        kind = "none"
    if points is not None:
        pts = np.asarray(points, float)
        if pts.ndim not in (2, 3) or pts.shape[0] != N or pts.shape[-1] != 3:
            raise DatasetError(f"{where}: points must have shape (N, 3) or (N, k, 3) with N = {N} poses, "
                               f"got {given}")
        points = pts if pts.ndim == 3 else pts[:, None, :]
        _check("points", points, points.shape[1:])
    if p is not None:
        p = np.asarray(p, float)
        _check("p", p, (3,))
    for group, d in (("context", context or {}), ("columns", columns or {})):
        for k, v in d.items():
            if np.shape(v)[:1] != (N,):
                raise DatasetError(f"{where}: {group}[{k!r}] must have one value per pose (N = {N}), "
                                   f"got shape {np.shape(v)}")
    return Dataset(names, readings, kind, points, R, p, dict(context or {}), dict(columns or {}), path=path)


def load_dataset(path, robot=None, joint_names=None, points: int | None = None,
                 check_units: bool = True, column_map=None) -> Dataset:
    """Read a dataset CSV.

    Parameters
    ----------
    path : CSV file with a header row (comma, semicolon or tab separated; UTF-8,
        a byte-order mark is accepted).
    robot : SerialRobot whose ``joint_names`` (and limits and nominal model, for the
        unit and range checks) are used.
    joint_names : alternative to ``robot``.
    points : keep only the first ``points`` measured points (``--points``).
    check_units : reject revolute readings beyond ±4π (degrees?), coordinates beyond
        50 m (millimetres?) and measured positions whose spread disagrees with the
        robot's nominal model (wrong unit or wrong robot; needs ``robot``).

    column_map : a column map (path of its YAML file or a
        :class:`~estcal.io.columnmap.ColumnMap`): the file is read in its publisher's columns,
        units and orientation convention (``--map``; :mod:`estcal.io.columnmap`).

    Every problem raises :class:`DatasetError` naming the file, the line and the
    column (see ``docs/dataset.md``, "Checks and error messages").
    """
    if column_map is not None:
        return _load_mapped(Path(path), column_map, robot, joint_names, points, check_units)
    table = _read_numeric(Path(path)) or read_csv(Path(path), "dataset", DatasetError)
    return dataset_from_table(table, robot, joint_names, points, check_units)


def _load_mapped(path, column_map, robot, joint_names, points, check_units) -> Dataset:
    """:func:`load_dataset` through a column map; the loader's messages name the file's columns."""
    from estcal.io.columnmap import ColumnMap, load_column_map

    cmap = column_map if isinstance(column_map, ColumnMap) else load_column_map(column_map)
    table = read_csv(path, "dataset", DatasetError)
    return dataset_from_mapped_table(table, cmap, robot, joint_names, points, check_units)


def dataset_from_mapped_table(table: CsvTable, cmap, robot=None, joint_names=None, points: int | None = None,
                              check_units: bool = True) -> Dataset:
    """:func:`dataset_from_table` of a table in its publisher's columns, read through the column map
    ``cmap`` (:class:`~estcal.io.columnmap.ColumnMap`): the whole file (``load_dataset(...,
    column_map=)``) or the chunks ``estcal online --map`` streams, with the same checks and messages
    naming the file's columns."""
    from estcal.io.columnmap import ColumnMapError, apply_column_map, rename_message

    names = list(robot.joint_names if robot is not None else (joint_names or []))
    types = list(robot.joint_types) if robot is not None else None
    try:
        mapped, renamed = apply_column_map(table, cmap, names, types)
    except ColumnMapError as exc:
        raise DatasetError(str(exc)) from None
    try:
        ds = dataset_from_table(mapped, robot, joint_names, points, check_units)
    except DatasetError as exc:
        raise DatasetError(rename_message(str(exc), renamed, cmap)) from None
    ds.source_header = [h.strip() for h in (cmap.columns or table.header)]
    ds.renamed = renamed
    ds.warnings = [rename_message(w, renamed, cmap) for w in ds.warnings]
    return ds


def _read_numeric(path):
    """Fast path for large, plain numeric CSV files: numpy's C parser straight from the file
    (memory ≈ the float array; the text path keeps every field as a Python string, ~5 kB per
    row). Used only when the file is a plain UTF-8 table — header on line 1, every field a
    finite number, no blank line, no quote — so that it gives exactly the dataset the text path
    gives; anything else (and every error message) goes through :func:`read_csv`. Returns a
    :class:`CsvTable` carrying the parsed array, or None."""
    from estcal.base.textinput import CsvTable, check_input_file, sniff_delimiter

    try:
        p = check_input_file(path, "dataset", DatasetError)
        if p.stat().st_size < (1 << 20):  # small files: the text path is fast and names every problem
            return None
        with open(p, "rb") as fh:
            first = fh.readline()
            sample = fh.read(1 << 16)
        if first.startswith(b"\xef\xbb\xbf"):
            first = first[3:]
        head = first.decode("utf-8")
        if not head.strip() or head.lstrip().startswith("#") or b'"' in first + sample or b"\r" in sample \
                or b"\n\n" in sample:
            return None
        delim = sniff_delimiter(head)
        header = [h.strip() for h in head.rstrip("\r\n").split(delim)]
        import warnings as _w

        with _w.catch_warnings():
            _w.simplefilter("error")  # empty lines etc. are a warning in numpy: fall back instead
            data = np.loadtxt(p, delimiter=delim, skiprows=1, ndmin=2, encoding="utf-8-sig", dtype=float)
    except (ValueError, UnicodeDecodeError, OSError, Warning):
        return None
    if data.shape[1] != len(header) or not np.all(np.isfinite(data)):
        return None
    return CsvTable(header, None, np.arange(2, 2 + data.shape[0]), 1, delim, str(path), numeric=data)


#: physical range of the context columns (SI / °C): beyond it the column's unit is wrong
TEMPERATURE_RANGE_C = (-90.0, 200.0)
PAYLOAD_MAX_KG = 10_000.0


def _check_context(context: dict, where: str, lines, warnings: list) -> None:
    """Units and range of ``temperature`` (°C), ``payload`` (kg) and ``t`` (s): a Kelvin or
    Fahrenheit temperature, a payload in grams or negative, a time that is not finite are
    refused with the line; a time that runs backwards is a warning (rows out of time order:
    drift and thermal models sort by ``t``)."""
    lo, hi = TEMPERATURE_RANGE_C
    T = context.get("temperature")
    if T is not None and np.any((T < lo) | (T > hi)):
        b = int(np.flatnonzero((T < lo) | (T > hi))[0])
        hint = " (Kelvin? subtract 273.15)" if 200 < T[b] < 600 else ""
        raise DatasetError(f"{where}, line {lines[b]}, column 'temperature': {T[b]:g} is outside "
                           f"[{lo:g}, {hi:g}] °C{hint} — the column is in degrees Celsius")
    m = context.get("payload")
    if m is not None and np.any((m < 0) | (m > PAYLOAD_MAX_KG)):
        b = int(np.flatnonzero((m < 0) | (m > PAYLOAD_MAX_KG))[0])
        why = "a mass cannot be negative" if m[b] < 0 else f"beyond {PAYLOAD_MAX_KG:g} kg (grams?)"
        raise DatasetError(f"{where}, line {lines[b]}, column 'payload': {m[b]:g} kg — {why}; the column is in kg")
    t = context.get("t")
    if t is not None and t.size > 1 and np.any(np.diff(t) < 0):
        b = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
        warnings.append(f"column 't' goes back in time at line {lines[b]} ({t[b - 1]:g} s, then {t[b]:g} s): "
                        f"the rows are not in time order")


def _decimal_hint(txt: str, delimiter: str) -> str:
    if "," in txt and delimiter != ",":
        try:
            float(txt.replace(",", "."))
            return f" (decimal comma? write {txt.replace(',', '.')})"
        except ValueError:
            pass
    return ""


def _suggest_column(name: str, header: list[str]) -> str:
    low = {h.lower(): h for h in header if h}
    if name.lower() in low:
        return f" (column {low[name.lower()]!r} differs only in case: names are case-sensitive, rename it)"
    close = difflib.get_close_matches(name, [h for h in header if h], n=1, cutoff=0.75)
    return f" (did you mean column {close[0]!r}?)" if close else ""


def foreign_joint_columns(header, robot) -> list[str]:
    """Columns that look like joints the robot does not have: actuated joints of its URDF off the
    chain, or names that differ from one of its joints only in their numbers (``j7`` for joints
    ``j1 … j6``; a robot file cut short keeps ``j1 … j3``). They are ignored by the fit: named so
    that a wrong chain or a truncated robot file is seen."""
    names = set(robot.joint_names)
    urdf_joints = set(robot.meta.get("urdf_joints", ()))
    stems = {re.sub(r"\d+", "#", n) for n in names}
    return [h for h in header if h and h not in names and
            (h in urdf_joints or (re.search(r"\d", h) and re.sub(r"\d+", "#", h) in stems))]


def _known_columns(header: list[str], names: list[str]) -> set[str]:
    known = set(names) | set(POSE_COLUMNS) | set(CONTEXT_COLUMNS) | set(METHOD_COLUMNS)
    known |= {f"approach_{j}" for j in names}
    known |= {h for h in header if NUMBERED.match(h)}
    return known


def _check_lookalikes(header: list[str], names: list[str], at: str) -> None:
    """A column whose name is a known one typed with look-alike letters of another script (a Cyrillic
    ``ј`` in ``ј1``) is named as such, instead of "missing column j1" beside a column that reads j1."""
    from estcal.base.textinput import ascii_skeleton, lookalike_note

    known = set(names) | set(POSE_COLUMNS) | set(CONTEXT_COLUMNS) | set(METHOD_COLUMNS)
    for h in header:
        if not h or h.isascii() or h in known:
            continue
        meant = ascii_skeleton(h)
        if meant in known or NUMBERED.match(meant):
            raise DatasetError(f"{at}, column {h!r}: reads like {meant!r} but {lookalike_note(h, meant)} — a "
                               f"look-alike letter (typed on another keyboard layout or pasted); retype the "
                               f"column name")


def _check_header(header: list[str], names: list[str], where: str, line: int) -> list[str]:
    """Structural checks of a header (duplicates, case, partial measurement sets);
    returns warnings (unknown columns that look like misspelt known ones)."""
    at = f"{where}, line {line}"
    _check_lookalikes(header, names, at)
    first: dict[str, int] = {}
    for i, h in enumerate(header):
        if h and h in first:
            raise DatasetError(f"{at}: columns {first[h] + 1} and {i + 1} are both named {h!r} — rename or "
                               f"remove one (estcal would not know which to use)")
        first.setdefault(h, i)
    missing = [j for j in names if j not in first]
    if missing:
        hint = _suggest_column(missing[0], header)
        if len(header) == 1 and (" " in header[0]):
            hint += " — the header has one column: separate the columns with ',', ';' or a tab"
        elif header and all(is_number(h) for h in header if h):
            hint += (" — the first line holds numbers, not column names: the file has no header row; name its "
                     "columns with a column map (columns: [...] in --map FILE.yaml, docs/dataset.md)")
        raise DatasetError(f"{where}: missing joint column(s) {missing}{hint}; the robot's joints are {names}; "
                           f"the file has columns {header}")
    known = _known_columns(header, names)
    known_lower = {k.lower(): k for k in known}
    warnings = []
    for h in header:
        if not h or h in known:
            continue
        if h.lower() in known_lower:
            raise DatasetError(f"{at}, column {h!r}: column names are case-sensitive — rename it to "
                               f"{known_lower[h.lower()]!r}")
        close = difflib.get_close_matches(h, sorted(k for k in known if len(k) >= 3), n=1, cutoff=0.8)
        if close and len(h) >= 3:
            warnings.append(f"column {h!r} is not a column estcal uses and is ignored (did you mean {close[0]!r}?)")
    present = set(header)
    xyz = [c for c in "xyz" if c in present]
    if xyz and len(xyz) < 3:
        raise DatasetError(f"{at}: column(s) {', '.join(xyz)} without {', '.join(c for c in 'xyz' if c not in xyz)}"
                           f" — a measured point needs x, y and z (m)")
    quat = [c for c in QUAT_COLUMNS if c in present]
    if quat and len(quat) < 4:
        raise DatasetError(f"{at}: quaternion column(s) {', '.join(quat)} without "
                           f"{', '.join(c for c in QUAT_COLUMNS if c not in quat)} — a pose needs "
                           f"x,y,z,qw,qx,qy,qz (quaternion scalar-first)")
    if quat and not xyz:
        raise DatasetError(f"{at}: quaternion columns without x, y, z — a pose needs x,y,z,qw,qx,qy,qz")
    idx: dict[int, set] = {}
    for h in header:
        m = NUMBERED.match(h)
        if m:
            idx.setdefault(int(m.group(2)), set()).add(m.group(1))
    if idx:
        for k in sorted(idx):
            if idx[k] != set("xyz"):
                lack = ", ".join(f"{c}{k}" for c in "xyz" if c not in idx[k])
                raise DatasetError(f"{at}: point {k} has no column {lack} — every measured point needs "
                                   f"x{k}, y{k}, z{k} (m)")
        if sorted(idx) != list(range(1, len(idx) + 1)):
            raise DatasetError(f"{at}: measured points are numbered {sorted(idx)} — number them 1, 2, …, "
                               f"{len(idx)} without gaps (x1,y1,z1, x2,…)")
        if xyz and not quat:
            raise DatasetError(f"{at}: both x,y,z and x1,y1,z1… columns — ambiguous measurement; keep x,y,z "
                               f"(one point) or x1…zk (k points)")
    return warnings


def dataset_from_table(table: CsvTable, robot=None, joint_names=None, points: int | None = None,
                       check_units: bool = True) -> Dataset:
    """A :class:`Dataset` from a parsed CSV (:func:`estcal.base.textinput.read_csv`); also
    used for single rows streamed by ``estcal online``, so both get the same checks."""
    from estcal.kinematics.transforms import quat_to_matrix

    where = table.where
    names = list(robot.joint_names if robot is not None else (joint_names or []))
    header = table.header
    warnings = _check_header(header, names, where, table.header_line)
    foreign = foreign_joint_columns(header, robot) if robot is not None else []
    if foreign:
        warnings.append(f"column(s) {', '.join(foreign)} look like joints that the robot {robot.name!r} does not have "
                        f"(its joints: {', '.join(names)}) and are ignored — the wrong chain (--root/--tip) or a "
                        f"robot file cut short?")
    body = table.rows
    numeric = getattr(table, "numeric", None)
    if numeric is not None:  # the fast path (:func:`_read_numeric`): every field already a finite number
        body = []
    elif not body:
        raise DatasetError(f"{where}: header only, no data rows")
    lines = np.asarray(table.lines, int)
    data = numeric if numeric is not None else np.empty((len(body), len(header)))
    for i, r in enumerate(body):
        if len(r) != len(header):
            hint = ""
            if table.delimiter != "," and any("," in v for v in r):
                hint = f" — the file is {table.delimiter_name}-separated; decimal commas?"
            raise DatasetError(f"{where}, line {lines[i]}: {len(r)} fields but the header has {len(header)} "
                               f"(inconsistent column count{hint})")
        for c, v in enumerate(r):
            v = v.strip()
            try:
                data[i, c] = float(v) if v != "" else np.nan
            except ValueError:
                data[i, c] = np.nan  # non-numeric columns are allowed if unused; checked below
    col = {h: data[:, i] for i, h in enumerate(header) if h}
    raw = {h: [r[i] for r in body] for i, h in enumerate(header) if h} if numeric is None else {}

    def need(hs):
        for h in hs:
            bad = np.flatnonzero(~np.isfinite(col[h]))
            if bad.size:
                b = bad[0]
                txt = raw[h][b].strip()
                what = "is empty" if txt == "" else f"is {txt!r}, not a finite number" + _decimal_hint(
                    txt, table.delimiter)
                if txt == h:  # `cat a.csv b.csv`: the second file's header inside the data
                    what += " — the header is repeated here (files concatenated with their headers?); remove it"
                raise DatasetError(f"{where}, line {lines[b]}, column {h!r}: value {what}")

    need(names)
    k = _point_columns(header)
    quat = all(c in header for c in QUAT_COLUMNS)
    single = all(c in header for c in "xyz")
    used = set(names)
    R = p = pts = None
    if single and quat:
        kind = "pose"
        need(list(POSE_COLUMNS))
        p = np.c_[col["x"], col["y"], col["z"]]
        qv = np.c_[col["qw"], col["qx"], col["qy"], col["qz"]]
        nq = np.linalg.norm(qv, axis=1)
        if np.any(np.abs(nq - 1) > 1e-3):
            b = int(np.argmax(np.abs(nq - 1)))
            raise DatasetError(f"{where}, line {lines[b]}: quaternion (qw,qx,qy,qz) has norm {nq[b]:.6f}, "
                               f"expected 1 (scalar-first unit quaternion)")
        R = quat_to_matrix(qv)
        used |= set(POSE_COLUMNS)
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
    readings = np.c_[tuple(col[j] for j in names)] if names else np.zeros((data.shape[0], 0))
    context = {}
    for c in CONTEXT_COLUMNS:
        if c in header:
            need([c])
            context[c] = col[c].copy()
            used.add(c)
    _check_context(context, where, lines, warnings)
    # approach direction of each joint (±1) drives direction-dependent backlash
    for h in header:
        if h.startswith("approach_") and h not in used:
            need([h])
            if not np.all(np.isin(col[h], (-1.0, 1.0))):
                b = int(np.flatnonzero(~np.isin(col[h], (-1.0, 1.0)))[0])
                raise DatasetError(f"{where}, line {lines[b]}, column {h!r}: value {col[h][b]:g} — an approach "
                                   f"direction is +1 or -1 (the sign of the joint's last motion)")
            context[h] = col[h].copy()
            used.add(h)
    if "t" not in context and "t_start_robot" in header and "t_end_robot" in header:
        if np.all(np.isfinite(col["t_start_robot"])) and np.all(np.isfinite(col["t_end_robot"])):
            context["t"] = 0.5 * (col["t_start_robot"] + col["t_end_robot"])
    # Method columns may be partly empty (e.g. ``distance`` only on the second row of a
    # pair): keep them with NaN where empty; drop only columns with no number at all.
    columns = {h: col[h].copy() for h in col if h not in used and np.any(np.isfinite(col[h]))}
    ds = Dataset(names, readings, kind, pts, R, p, context, columns, lines, where, warnings,
                 coordinates=_coord_names(kind, k) if kind != "none" else None)
    if check_units:
        _check_units(ds, robot, _coord_names(kind, k))
    if points is not None:
        ds = ds.with_points(points)
    return ds


def _coord_names(kind: str, k: int) -> list[str]:
    """The columns of the measured coordinates (``k``: numbered points x1…zk of the header, 0 for x,y,z)."""
    return (["x", "y", "z"] if kind == "pose" or (kind == "position" and k == 0) else
            [f"{c}{i + 1}" for i in range(k) for c in "xyz"])


def check_dataset_units(ds: Dataset, robot, header=None, column_map=None) -> None:
    """The unit and range checks of the loader on a dataset assembled from parts of one file (a file read
    in chunks): the same messages (``header``: the file's estcal columns, for the coordinates' names;
    ``column_map``: named in the file's own columns)."""
    k = _point_columns(list(header)) if header is not None else (ds.n_points if ds.kind == "points" else 0)
    try:
        _check_units(ds, robot, _coord_names(ds.kind, k))
    except DatasetError as exc:
        if column_map is None:
            raise
        from estcal.io.columnmap import rename_message

        raise DatasetError(rename_message(str(exc), ds.renamed, column_map)) from None


#: readings beyond ±π a revolute column needs before it is said to look like degrees
DEGREES_MIN_READINGS = 3


def _check_units(ds: Dataset, robot, coord_names=None) -> None:
    """Values that cannot be in estcal's units (radians, metres) or do not fit the robot."""
    if robot is not None:
        for j, (name, typ) in enumerate(zip(robot.joint_names, robot.joint_types)):
            v = ds.readings[:, j]
            lo, hi = robot.limits[j]
            b = int(np.argmax(np.abs(v)))
            at = f"{ds.where}, line {ds.lines[b]}, column {name!r}"
            if typ == "revolute" and abs(v[b]) > 4 * np.pi:
                # degrees are a column's unit: judged on several readings, never on one wild value
                # (a row streamed alone, or one outlier, has its own value as the median)
                if np.count_nonzero(np.abs(v) > np.pi) >= DEGREES_MIN_READINGS and np.median(np.abs(v)) > np.pi \
                        and abs(v[b]) <= 400:
                    raise DatasetError(f"{at}: {v[b]:g} rad is beyond ±4π and the column's typical value "
                                       f"{np.median(np.abs(v)):.3g} is beyond ±π — readings look like degrees; "
                                       f"convert to radians (× π/180)")
                raise DatasetError(f"{at}: {v[b]:g} rad is beyond ±4π (two turns) — not a plausible joint "
                                   f"angle in radians; check this value")
            if typ == "prismatic" and abs(v[b]) > max(1.0, 10 * max(abs(lo), abs(hi))):
                raise DatasetError(f"{at}: {v[b]:g} m for a prismatic joint with limits [{lo:g}, {hi:g}] m — "
                                   f"readings look like millimetres; convert to metres")
            span = hi - lo
            out = np.flatnonzero((v < lo - 0.05 * span) | (v > hi + 0.05 * span))
            if out.size:
                ds.warnings.append(f"{out.size} readings of {name!r} outside its limits [{lo:g}, {hi:g}] "
                                   f"(first at line {ds.lines[out[0]]})")
    coords = ds.points if ds.points is not None else ds.p
    if coords is None or not coords.size:
        return
    a = np.abs(coords).reshape(len(coords), -1)
    if a.max() > 50.0:
        i, c = np.unravel_index(int(np.argmax(a)), a.shape)
        names = list(coord_names or []) or [f"coordinate {c + 1}"] * a.shape[1]
        cname = names[c] if c < len(names) else f"coordinate {c + 1}"
        raise DatasetError(f"{ds.where}, line {ds.lines[i]}, column {cname!r}: measured coordinate "
                           f"{coords.reshape(len(coords), -1)[i, c]:g} m — beyond 50 m, it looks like "
                           f"millimetres; estcal expects metres")
    if robot is not None and ds.n >= 3:
        _check_spread(ds, robot)


def _check_spread(ds: Dataset, robot) -> None:
    """Measured positions must spread like the robot's nominal model says.

    The measurement frame is unknown (registration finds it), but a rigid change of
    frame keeps distances: the median distance between two measured points equals
    that between the predicted tool positions for the same joint readings, up to the
    calibration errors (millimetres) and the unknown marker offsets (a marker at
    distance d from the tool origin changes a distance by at most 2d). A ratio far
    from 1 means a wrong unit (cm, mm, inches) or the wrong robot / joint columns.
    The median keeps a few gross outliers (a wrong row, an unreachable target) from
    raising a false alarm; a whole file in the wrong unit moves it."""
    from scipy.spatial.distance import pdist

    meas = ds.points[:, 0, :] if ds.points is not None else ds.p
    take = np.linspace(0, ds.n - 1, min(ds.n, 400)).astype(int)  # pdist is O(N²): a spread-out subset
    try:
        from estcal.kinematics.chunked import tool_poses

        # the kinematics of the subset only (10⁶ rows: 0.1 s instead of 30 s)
        ctx = {k: np.asarray(v)[take] for k, v in ds.context.items()}
        pred = tool_poses(robot, ds.readings[take], context=ctx, fields=("p",))["p"]
    except (ValueError, KeyError, TypeError):  # effects needing context the file lacks: no check
        return
    sm = float(np.median(pdist(meas[take])))
    sp = float(np.median(pdist(pred)))
    slack = SPREAD_SLACK_M
    if sm < STILL_RATIO * sp:  # no unit is that much larger than the metre: not a unit mistake
        raise DatasetError(
            f"{ds.where}: the measured positions do not move with the joints — they are {sm:.3g} m apart (median "
            f"over pairs of rows) where the nominal model of {robot.name!r} moves the tool {sp:.3g} m for these "
            f"joint readings: a marker on a part the joints do not move (the base, the room), a frozen tracker, or "
            f"the wrong position columns?")
    if sm > 2 * sp + slack or sm < 0.5 * sp - slack:
        ratio = f"{sm / sp:.3g}×" if sp > 0 else "∞×"
        raise DatasetError(
            f"{ds.where}: the measured positions are {sm:.3g} m apart (median over pairs of rows) but the nominal "
            f"model of {robot.name!r} puts these joint readings {sp:.3g} m apart ({ratio}) — wrong unit (mm, cm, "
            f"inches instead of metres) or the wrong robot / joint columns?")


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
    from estcal.base.atomic import atomic_write

    path = Path(path)
    names = list(cols)
    M = np.column_stack([np.asarray(cols[n], float) for n in names])
    with atomic_write(path) as fh:
        np.savetxt(fh, M, delimiter=",", header=",".join(names), comments="", fmt=float_format)
    return path
