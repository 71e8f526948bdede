"""``estcal check``: data hygiene before any fit (:func:`estcal.intake.hygiene.check_data`).

:func:`check_file` loads the robot and the data (through a column map when given) and returns
the :class:`~estcal.intake.hygiene.CheckReport`; :func:`findings_for` is what calibrate,
diagnose, sessions and online run on their data to warn with the same findings, and
:func:`drop_flagged` removes the flagged rows (``--drop-flagged``). Never prints, never exits.
"""
from __future__ import annotations

import warnings

__all__ = ["check_file", "findings_for", "drop_flagged", "screen", "screen_rows", "SCREEN_OUTLIER_MAX_ROWS"]


def _robot_for(robot, data_path, root=None, tip=None, column_map=None, points=None):
    """The robot with one unknown marker per measured point of the file (read through the map)."""
    from estcal.io.columnmap import ColumnMap, load_column_map
    from estcal.io.dataset import measurement_layout
    from estcal.io.robotfile import load_robot

    if not isinstance(robot, (str, bytes)) and hasattr(robot, "joint_names"):
        return robot
    if column_map is not None:
        cmap = column_map if isinstance(column_map, ColumnMap) else load_column_map(column_map)
        k = len(cmap.points) if cmap.points and cmap.rpy is None and cmap.quaternion is None else None
    else:
        k, _, quat = measurement_layout(data_path)
        k = k if k and not quat else None
    k = points if points is not None else k
    return load_robot(robot, root=root, tip=tip, n_markers=k)


def check_file(data, robot, *, root=None, tip=None, column_map=None, points=None, outliers: bool = True,
               level: str = "auto"):
    """All checks of :mod:`estcal.intake.hygiene` on the file ``data`` (CSV; ``column_map``: its column
    map). Returns ``(report, robot, dataset)``."""
    from estcal.intake.hygiene import check_data
    from estcal.io.stream import read_dataset

    rb = _robot_for(robot, data, root, tip, column_map, points)
    ds = read_dataset(data, rb, column_map=column_map)[0]  # bounded memory on any file (streamed when large)
    if points is not None:
        ds = ds.with_points(points)
    return check_data(rb, ds, outliers=outliers, level=level), rb, ds


#: rows above which the data screening of calibrate, diagnose, sessions and online skips the robust
#: fit of the outlier test (``estcal check`` always runs it)
SCREEN_OUTLIER_MAX_ROWS = 5000


def screen(datasets, robot, drop: bool = False) -> list:
    """The data screening of calibrate, diagnose, sessions and online: each dataset's findings warned
    (:func:`findings_for`); with ``drop`` (``--drop-flagged``) the defect rows removed and named in a
    warning. Returns the datasets (the same objects when nothing is dropped)."""
    return screen_rows(datasets, robot, drop)[0]


def screen_rows(datasets, robot, drop: bool = False, warn_dropped: bool = True) -> tuple[list, list]:
    """:func:`screen`, also returning the rows left out: ``(datasets, left_out)``, ``left_out`` one dict per
    row (``file``, ``line``, ``kind``, ``reason``, ``session``: the dataset's index; ``row``: its index in
    that dataset), in file order. ``warn_dropped=False``: the findings of the rows left out are not warned
    one by one (the caller reports them)."""
    from estcal.base.errors import EstcalWarning
    from estcal.intake.hygiene import DEFECTS

    out, left = [], []
    for k, ds in enumerate(datasets):
        big = ds.n > SCREEN_OUTLIER_MAX_ROWS
        report = findings_for(robot, ds, outliers=not big, skip=() if warn_dropped or not drop else DEFECTS)
        if big:
            warnings.warn(f"{ds.where}: {ds.n} rows: no outlier test before the fit (run `estcal check` for it)",
                          EstcalWarning, stacklevel=2)
        if drop:
            full = ds
            ds, lines = drop_flagged(ds, report)
            if lines and warn_dropped:
                shown = ", ".join(str(x) for x in lines[:20]) + (" …" if len(lines) > 20 else "")
                warnings.warn(f"{ds.where}: --drop-flagged: {len(lines)} row(s) left out (lines {shown})",
                              EstcalWarning, stacklevel=2)
            left += [dict(r, session=k) for r in _left_out_rows(full, report, lines)]
        out.append(ds)
    return out, left


def _left_out_rows(ds, report, lines) -> list[dict]:
    """One dict per left-out line: the file, the line, its row in ``ds``, the finding's kind and its reason
    (the finding's message without the leading ``line N:``; a duplicate: the line it copies)."""
    import numpy as np

    from estcal.intake.hygiene import DEFECTS

    row_of = {int(ln): i for i, ln in enumerate(ds.lines)}
    why = {}
    for f in report.findings:
        if f.kind not in DEFECTS:
            continue
        for ln in f.lines:
            text = f.message.split(": ", 1)[1] if f.message.startswith(f"line {ln}: ") else f.message
            if f.kind == "duplicate_row":
                text = "a copy, bit for bit, of an earlier row"
            why.setdefault(int(ln), (f.kind, text.split(" — ")[0]))
    return [{"file": ds.where, "line": int(ln), "row": row_of[int(ln)], "kind": why[int(ln)][0],
             "reason": why[int(ln)][1]} for ln in sorted(np.unique(lines).tolist())]


def findings_for(robot, ds, outliers: bool = True, skip=()):
    """The findings of ``ds`` warned as :class:`~estcal.base.errors.EstcalWarning` (one per finding,
    defects first; not those of the kinds in ``skip``) and returned (the report)."""
    from estcal.base.errors import EstcalWarning
    from estcal.intake.hygiene import check_data

    report = check_data(robot, ds, outliers=outliers)
    for f in report.findings:
        # unused columns are warned when a column map would read them (an orientation fitted without)
        if f.kind not in skip and (f.kind != "unused_column" or f.details.get("map")):
            warnings.warn(f"{ds.where}: {f.kind}: {f.message}", EstcalWarning, stacklevel=2)
    return report


def drop_flagged(ds, report):
    """``ds`` without the rows of the defect findings; ``(dataset, dropped lines)``."""
    import numpy as np

    lines = report.flagged_lines()
    if not lines:
        return ds, []
    keep = ~np.isin(ds.lines, lines)
    out = ds.subset(np.flatnonzero(keep))
    return out, lines
