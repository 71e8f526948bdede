"""Column maps: a measured file read as its publisher wrote it (``--map FILE.yaml``).

Real calibration files never use estcal's column names (``docs/dataset.md``). A column map
says, once per source, which file column is which quantity; the file is then read as it
is, converted at the edge (mm → m, deg → rad, roll-pitch-yaw → quaternion) and checked by
the same loader as any dataset::

    joints: {arm_left_1_joint: armL1, torso_1_joint: torso1}  # robot joint: column (omit = same name)
    points: [[x1, y1, z1], [x2, y2, z2]]       # measured points, in order
    orientation: {rpy: [phix1, phiy1, phiz1]}  # R = Rz(y)·Ry(p)·Rx(r); or {quaternion: [qw, qx, qy, qz]}
    units: {length: m, angle: rad}             # mm (cm, in) and deg accepted
    columns: [t, x1, y1, z1, torso1, ...]      # names for a file without a header row
    context: {t: t}                            # t, temperature, payload, approach_<joint>

Roll-pitch-yaw ``[r, p, y]`` is the rotation ``R = Rz(y)·Ry(p)·Rx(r)`` (fixed axes x, y, z;
Pinocchio's ``rpy`` and FIGAROH's files; URDF's ``rpy`` too). A quaternion is scalar-first
(w, x, y, z) in the file's own column names. With an orientation, the single point is the
origin of the measured frame and the file is a full-pose dataset.

Every problem is refused with the line of the map that fixes it: an unknown key, a column
the file does not have, a robot joint left unmapped whose name is not a column either.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError
from estcal.base.textinput import ascii_skeleton, lookalike_note
from estcal.io.columns import CONTEXT_COLUMNS, NUMBERED, QUAT_COLUMNS, DatasetError, is_number

__all__ = ["ColumnMap", "ColumnMapError", "load_column_map", "column_map_from_dict", "apply_column_map",
           "as_column_map"]

_TOP = ("joints", "points", "orientation", "units", "columns", "context")
_LENGTH = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254}
_ANGLE = {"rad": 1.0, "deg": np.pi / 180.0}


class ColumnMapError(InputError):
    """A column map that cannot be applied; the message names the map file and its line."""


@dataclass
class ColumnMap:
    """A parsed column map (module docstring). ``lines`` maps a key path (``("joints", name)``,
    ``("points", i)`` …) to its line in the map file, for messages."""

    joints: dict = field(default_factory=dict)
    points: list = field(default_factory=list)
    rpy: list | None = None
    quaternion: list | None = None
    length: str = "m"
    angle: str = "rad"
    columns: list | None = None
    context: dict = field(default_factory=dict)
    path: str = "<column map>"
    lines: dict = field(default_factory=dict)

    def at(self, *key) -> str:
        """``map.yaml, line 3`` for the most specific known key of ``key``."""
        for i in range(len(key), 0, -1):
            if key[:i] in self.lines:
                return f"{self.path}, line {self.lines[key[:i]]}"
        return self.path

    def to_dict(self) -> dict:
        """The map as its YAML says it (only the keys it sets): ``column_map_from_dict(m.to_dict())``
        reads the same map. An online checkpoint keeps it, so that a resumed run reads its input alike."""
        d: dict = {}
        if self.joints:
            d["joints"] = dict(self.joints)
        if self.points:
            d["points"] = [list(p) for p in self.points]
        if self.rpy is not None or self.quaternion is not None:
            d["orientation"] = {"rpy": list(self.rpy)} if self.rpy is not None else {"quaternion": list(self.quaternion)}
        if (self.length, self.angle) != ("m", "rad"):
            d["units"] = {"length": self.length, "angle": self.angle}
        if self.columns is not None:
            d["columns"] = list(self.columns)
        if self.context:
            d["context"] = dict(self.context)
        return d

    def file_columns(self) -> list[str]:
        """Every file column the map names (the map's own use of the file)."""
        out = list(self.joints.values()) + [c for p in self.points for c in p]
        out += list(self.rpy or []) + list(self.quaternion or []) + list(self.context.values())
        return out


def _compose(text: str, where: str):
    """YAML → (value, {key path: line}) with the line of every mapping key and list item."""
    import yaml

    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f", line {mark.line + 1}" if mark is not None else ""
        raise ColumnMapError(f"{where}{at}: invalid YAML in the column map "
                             f"({' '.join(str(getattr(exc, 'problem', exc)).split())})") from None
    lines: dict = {}

    def walk(n, path):
        if isinstance(n, yaml.MappingNode):
            for k, v in n.value:
                lines[path + (k.value,)] = k.start_mark.line + 1
                walk(v, path + (k.value,))
        elif isinstance(n, yaml.SequenceNode):
            for i, v in enumerate(n.value):
                lines[path + (i,)] = v.start_mark.line + 1
                walk(v, path + (i,))

    if node is not None:
        walk(node, ())
    return yaml.safe_load(text), lines


def as_column_map(column_map) -> ColumnMap | None:
    """A column map from what the user gave: a path of its YAML file, a :class:`ColumnMap`, or the dict
    an online checkpoint keeps (:meth:`ColumnMap.to_dict`); None stays None."""
    if column_map is None or isinstance(column_map, ColumnMap):
        return column_map
    if isinstance(column_map, dict):
        return column_map_from_dict(column_map, "<the checkpoint's column map>")
    return load_column_map(column_map)


def load_column_map(path) -> ColumnMap:
    """Read and check a column map file (structure only; the columns are checked against a data
    file by :func:`apply_column_map`)."""
    from estcal.base.textinput import read_text

    text = read_text(path, "column map", ColumnMapError)
    value, lines = _compose(text, str(path))
    return column_map_from_dict(value, str(path), lines)


def _names(v, where, what, n=None) -> list[str]:
    if not isinstance(v, (list, tuple)) or (n is not None and len(v) != n) \
            or not all(isinstance(c, (str, int, float)) and not isinstance(c, bool) for c in v):
        want = f"a list of {n} column names" if n else "a list of column names"
        raise ColumnMapError(f"{where}: {what} must be {want}, got {v!r}")
    return [str(c) for c in v]


def column_map_from_dict(d, path: str = "<column map>", lines: dict | None = None) -> ColumnMap:
    """A :class:`ColumnMap` from the parsed YAML ``d`` (module docstring)."""
    m = ColumnMap(path=path, lines=dict(lines or {}))
    if d is None:
        d = {}
    if not isinstance(d, dict):
        raise ColumnMapError(f"{path}: a column map is a mapping with keys {', '.join(_TOP)}; got {type(d).__name__}")
    for k in d:
        if k not in _TOP:
            close = difflib.get_close_matches(str(k), _TOP, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ColumnMapError(f"{m.at(k)}: unknown key {k!r}{hint} — a column map has {', '.join(_TOP)}")
    j = d.get("joints") or {}
    if not isinstance(j, dict):
        raise ColumnMapError(f"{m.at('joints')}: joints must map robot joint names to file columns "
                             f"({{arm_1_joint: armR1, …}}), got {j!r}")
    m.joints = {str(k): str(v) for k, v in j.items()}
    pts = d.get("points") or []
    if not isinstance(pts, list):
        raise ColumnMapError(f"{m.at('points')}: points must be a list of [x, y, z] column triples, got {pts!r}")
    m.points = [_names(p, m.at("points", i), f"point {i + 1}", 3) for i, p in enumerate(pts)]
    o = d.get("orientation")
    if o is not None:
        if not isinstance(o, dict) or len(o) != 1 or next(iter(o)) not in ("rpy", "quaternion"):
            raise ColumnMapError(f"{m.at('orientation')}: orientation is {{rpy: [r, p, y]}} or {{quaternion: "
                                 f"[qw, qx, qy, qz]}} (the file's column names), got {o!r}")
        (kind, cols), = o.items()
        if kind == "rpy":
            m.rpy = _names(cols, m.at("orientation", "rpy"), "orientation rpy", 3)
        else:
            m.quaternion = _names(cols, m.at("orientation", "quaternion"), "orientation quaternion", 4)
        if len(m.points) != 1:
            raise ColumnMapError(f"{m.at('orientation')}: an orientation needs exactly one point (the origin of the "
                                 f"measured frame) under points:, the map has {len(m.points)}")
    u = d.get("units") or {}
    if not isinstance(u, dict):
        raise ColumnMapError(f"{m.at('units')}: units is {{length: m, angle: rad}}, got {u!r}")
    for k, v in u.items():
        table = {"length": _LENGTH, "angle": _ANGLE}.get(k)
        if table is None:
            raise ColumnMapError(f"{m.at('units', k)}: unknown unit key {k!r} — units has length and angle")
        if v not in table:
            raise ColumnMapError(f"{m.at('units', k)}: {k} unit {v!r} — use one of {', '.join(table)}")
        setattr(m, k, v)
    cols = d.get("columns")
    if cols is not None:
        m.columns = _names(cols, m.at("columns"), "columns")
        seen = {}
        for i, c in enumerate(m.columns):
            if c in seen:
                raise ColumnMapError(f"{m.at('columns', i)}: column {c!r} named twice in columns: "
                                     f"(positions {seen[c] + 1} and {i + 1})")
            seen[c] = i
    ctx = d.get("context") or {}
    if not isinstance(ctx, dict):
        raise ColumnMapError(f"{m.at('context')}: context maps t, temperature, payload, approach_<joint> to "
                             f"file columns, got {ctx!r}")
    for k in ctx:
        if k not in CONTEXT_COLUMNS and not str(k).startswith("approach_"):
            raise ColumnMapError(f"{m.at('context', k)}: unknown context {k!r} — use t (s), temperature (°C), "
                                 f"payload (kg) or approach_<joint>")
    m.context = {str(k): str(v) for k, v in ctx.items()}
    return m


def _floats(values, table, col: str, mapped: str, cmap: ColumnMap, key) -> np.ndarray:
    """Column ``col`` of the file as numbers; a non-number is refused with the file line and the
    map line that uses the column."""
    out = np.empty(len(values))
    for i, v in enumerate(values):
        v = v.strip()
        try:
            out[i] = float(v)
        except ValueError:
            what = "is empty" if v == "" else f"is {v!r}, not a number"
            raise DatasetError(f"{table.where}, line {table.lines[i]}, column {col!r} ({mapped} by {cmap.at(*key)})"
                               f": value {what}") from None
        if not np.isfinite(out[i]):
            raise DatasetError(f"{table.where}, line {table.lines[i]}, column {col!r} ({mapped} by {cmap.at(*key)})"
                               f": value {v!r} is not finite")
    return out


def headerless(table, cmap: ColumnMap):
    """A :class:`~estcal.base.textinput.CsvTable` read with a header row, re-read as a file without one
    whose columns are named by ``columns:`` (the parsed header becomes the first data row)."""
    from estcal.base.textinput import CsvTable

    first = [h.strip() for h in table.header]
    if first == cmap.columns:
        return table  # the file has the header columns: names (one map serves both kinds of file)
    if not all(is_number(h) for h in first if h):
        raise DatasetError(f"{table.where}, line {table.header_line}: the file has a header row "
                           f"({', '.join(first[:6])}{'…' if len(first) > 6 else ''}) that differs from columns: "
                           f"({cmap.at('columns')}) — remove columns: from the map or make it the file's header")
    rows = [list(table.header)] + [list(r) for r in table.rows]
    lines = [table.header_line] + list(table.lines)
    for r, ln in zip(rows, lines):
        if len(r) != len(cmap.columns):
            raise DatasetError(f"{table.where}, line {ln}: {len(r)} fields but columns: in {cmap.at('columns')} "
                               f"names {len(cmap.columns)}")
    return CsvTable(list(cmap.columns), rows, lines, 0, table.delimiter, table.where)


def _one_column_per_joint(jmap: dict, cmap: ColumnMap, where: str) -> None:
    """Two robot joints read from one file column (``j6: j5``, or ``j6: j5`` while ``j5`` keeps its own
    name) would move both joints together: the fit then absorbs a wrong chain into the geometry
    without any warning. Refused, naming the map line and the column."""
    by_col: dict = {}
    for j, col in jmap.items():
        by_col.setdefault(col, []).append(j)
    for col, joints in by_col.items():
        if len(joints) > 1:
            mapped = [j for j in joints if j in cmap.joints]
            at = cmap.at("joints", mapped[-1]) if mapped else cmap.path
            own = [j for j in joints if j not in cmap.joints]
            how = (f" ({', '.join(repr(j) for j in own)} by its own name)" if own else "")
            many = "both" if len(joints) == 2 else "all"
            raise ColumnMapError(f"{at}: joints {', '.join(repr(j) for j in joints)} are {many} read from column "
                                 f"{col!r} of {where}{how} — every joint needs its own column; map each joint to "
                                 f"the column that holds its readings")


def apply_column_map(table, cmap: ColumnMap, joint_names, joint_types=None):
    """The table ``table`` (:class:`~estcal.base.textinput.CsvTable`) in estcal's columns.

    Returns ``(table, renamed)``: the new table (robot joint names; ``x1…zk`` or ``x,y,z`` +
    ``qw…qz``; context names; SI units) and ``{estcal column: file column}`` for messages.
    Columns the map does not use keep their names, except names the map produces or that the
    loader would take for a measurement. Raises :class:`ColumnMapError` naming the map line."""
    from estcal.base.textinput import CsvTable

    if cmap.columns is not None:
        table = headerless(table, cmap)
    header = [h.strip() for h in table.header]
    where = table.where
    present = set(header)
    names = list(joint_names)
    types = list(joint_types or ["revolute"] * len(names))

    def need(col, *key):
        if col not in present:
            close = difflib.get_close_matches(col, [h for h in header if h], n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            same = [h for h in header if h and ascii_skeleton(h) == ascii_skeleton(col)]
            if same:  # one of the two is typed with look-alike letters of another script
                a = same[0] if not same[0].isascii() else col  # the one typed with look-alike letters
                where_to = "the column name in the file" if a == same[0] else "it in the map"
                hint = (f" — the file's column {same[0]!r} reads the same but {lookalike_note(a, ascii_skeleton(a))}"
                        f" (look-alike letters); retype {where_to}")
                raise ColumnMapError(f"{cmap.at(*key)}: column {col!r} is not in {where}{hint}")
            if header and all(is_number(h) for h in header if h):
                hint += (" — its first line holds numbers: the file has no header row; name its columns with "
                         "columns: [...] in the map")
                raise ColumnMapError(f"{cmap.at(*key)}: column {col!r} is not in {where}{hint}")
            raise ColumnMapError(f"{cmap.at(*key)}: column {col!r} is not in {where}{hint}; its columns are "
                                 f"{header}")

    for j, col in cmap.joints.items():
        if j not in names:
            close = difflib.get_close_matches(j, names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ColumnMapError(f"{cmap.at('joints', j)}: {j!r} is not a joint of the robot{hint}; its joints are "
                                 f"{names}")
        need(col, "joints", j)
    jmap = {}
    for j in names:
        col = cmap.joints.get(j, j)
        if col not in present:
            at = cmap.at("joints") if "joints" in {k[0] for k in cmap.lines} else cmap.path
            unmapped = [n for n in names if n not in cmap.joints and n not in present]
            raise ColumnMapError(f"{at}: robot joint {j!r} is not mapped and {where} has no column of that name — "
                                 f"add `{j}: <column>` under joints: ({len(unmapped)} unmapped: {unmapped}); the "
                                 f"file's columns are {header}")
        jmap[j] = col
    _one_column_per_joint(jmap, cmap, where)
    for i, p in enumerate(cmap.points):
        for c in p:
            need(c, "points", i)
    for kind in ("rpy", "quaternion"):
        for c in getattr(cmap, kind) or []:
            need(c, "orientation", kind)
    for k, c in cmap.context.items():
        need(c, "context", k)
    col = {h: [r[i] if i < len(r) else "" for r in table.rows] for i, h in enumerate(header) if h}
    lu, au = _LENGTH[cmap.length], _ANGLE[cmap.angle]
    out: dict[str, list] = {}
    renamed: dict[str, str] = {}

    def put(name, file_col, scale, key):
        renamed[name] = file_col
        if scale == 1.0:
            out[name] = col[file_col]
        else:
            vals = _floats(col[file_col], table, file_col, f"as {name!r}", cmap, key)
            out[name] = [repr(float(v)) for v in vals * scale]

    for j, typ in zip(names, types):
        put(j, jmap[j], lu if typ == "prismatic" else au, ("joints", j))
    pose = cmap.rpy is not None or cmap.quaternion is not None
    for i, p in enumerate(cmap.points):
        for c, fc in zip("xyz", p):
            put(c if pose else f"{c}{i + 1}", fc, lu, ("points", i))
    if cmap.rpy is not None:
        rpy = [_floats(col[c], table, c, "an rpy angle", cmap, ("orientation", "rpy")) * au for c in cmap.rpy]
        from estcal.kinematics.transforms import matrix_to_quat, rpy_to_matrix

        q = matrix_to_quat(rpy_to_matrix(np.stack(rpy, axis=-1)))
        for i, c in enumerate(QUAT_COLUMNS):
            out[c] = [repr(float(v)) for v in q[:, i]]
            renamed[c] = "/".join(cmap.rpy)
    elif cmap.quaternion is not None:
        for c, fc in zip(QUAT_COLUMNS, cmap.quaternion):
            put(c, fc, 1.0, ("orientation", "quaternion"))
    for k, fc in cmap.context.items():
        put(k, fc, 1.0, ("context", k))
    used = set(cmap.file_columns()) | set(jmap.values())
    measurement = {"x", "y", "z", *QUAT_COLUMNS}
    for h in header:
        if not h or h in used or h in out:
            continue
        if (cmap.points or pose) and (h in measurement or NUMBERED.match(h)):
            continue  # the map defines the measurement: a leftover x2,… would be read as another point
        if cmap.context and h in CONTEXT_COLUMNS:
            continue
        out[h] = col[h]
    new_header = list(out)
    rows = [list(r) for r in zip(*(out[h] for h in new_header))] if table.rows else []
    return CsvTable(new_header, rows, list(table.lines), table.header_line, table.delimiter, where), renamed


def rename_message(msg: str, renamed: dict, cmap: ColumnMap) -> str:
    """A loader message about estcal's column ``c`` rewritten to name the file's column."""
    import re

    def sub(m):
        c = m.group(1)
        fc = renamed.get(c)
        return m.group(0) if fc is None or fc == c else f"column {fc!r} (mapped to {c!r} by {Path(cmap.path).name})"

    return re.sub(r"column '([^']+)'", sub, msg)


# --------------------------------------------------------------------------- what a map would read
_RPY_WORDS = (("roll", "pitch", "yaw"), ("rx", "ry", "rz"), ("phix", "phiy", "phiz"), ("rotx", "roty", "rotz"),
              ("thetax", "thetay", "thetaz"), ("ax", "ay", "az"), ("a", "b", "c"))
_QUAT_WORDS = (("qw", "qx", "qy", "qz"), ("q0", "q1", "q2", "q3"), ("w", "x", "y", "z"))


def _triples(columns, words, sep_ok=True):
    """Groups of ``columns`` named ``<word><suffix>`` (or ``<prefix><word>``) for every word of a set, with
    one shared suffix/prefix: ``phix1, phiy1, phiz1`` → [["phix1", "phiy1", "phiz1"]]."""
    low = {c.lower(): c for c in columns}
    out = []
    for ws in words:
        first = [c for c in low if c.startswith(ws[0]) or c.endswith(ws[0])]
        for c in first:
            for pre, suf in ((c[:len(c) - len(ws[0])], ""), ("", c[len(ws[0]):])):
                if (pre + ws[0] + suf) != c:
                    continue
                group = [low.get(pre + w + suf) for w in ws]
                if all(group) and not any(g in sum(out, []) for g in group):
                    out.append(group)
    return out


def suggest_map(unused, header, points) -> str | None:
    """A column map (one line of YAML) that would read ``unused`` columns of a file whose ``header`` they
    belong to, when they look like a measured orientation: roll-pitch-yaw (``phix1, phiy1, phiz1``,
    ``roll, pitch, yaw``, ``rx, ry, rz`` …) or a quaternion. ``points``: the file's columns of the measured
    position (one [x, y, z] triple), which a pose map names as the frame's origin. None otherwise."""
    if points is None or len(points) != 1:
        return None
    cand = [c for c in unused if c in header]
    pos = "[[" + ", ".join(points[0]) + "]]"
    for group in _triples(cand, _QUAT_WORDS):
        return f"points: {pos}, orientation: {{quaternion: [{', '.join(group)}]}}"
    for group in _triples(cand, _RPY_WORDS):
        return f"points: {pos}, orientation: {{rpy: [{', '.join(group)}]}}"
    return None


def published_map(header, columns) -> str | None:
    """The map of ``docs/maps/`` (in estcal's source tree, when it is there) that reads every column of
    ``columns`` from a file with this ``header`` — e.g. ``docs/maps/ur10.yaml`` for the UR10 file."""
    folder = Path(__file__).resolve().parents[2] / "docs" / "maps"  # the source tree beside the package
    if not folder.is_dir():
        return None
    present = set(header)
    for f in sorted(folder.glob("*.yaml")):
        try:
            m = load_column_map(f)
        except (InputError, OSError):
            continue
        used = set(m.file_columns())
        if m.columns is None and used <= present and set(columns) <= used:
            return f"docs/maps/{f.name}"
    return None
