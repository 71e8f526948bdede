"""Small helpers shared by the subcommands: failing with a clear message, writing JSON."""
from __future__ import annotations

import csv
from pathlib import Path

import typer

from estcal.io.jsonio import write_json

__all__ = ["fail", "write_json", "count_point_columns", "robot_for_data", "save_model_or_fail"]


def fail(msg: str, code: int = 2):
    """Print ``error: msg`` to stderr and exit with ``code`` (no traceback)."""
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def count_point_columns(path) -> tuple[int, bool, bool]:
    """(k points x1..zk, has x,y,z, has quaternion) from a CSV header."""
    with Path(path).open(newline="") as fh:
        header = [h.strip() for h in next(csv.reader(fh), [])]
    k = 0
    while all(f"{c}{k + 1}" in header for c in "xyz"):
        k += 1
    return k, all(c in header for c in "xyz"), all(c in header for c in ("qw", "qx", "qy", "qz"))


def robot_for_data(spec, data, root=None, tip=None, points=None):
    """Load the robot ``spec`` with one unknown marker per measured point of ``data``
    (``--points N`` keeps the first N); exits with a clear message on bad input.

    Returns ``(robot, n_markers)``; ``n_markers`` is None unless the data are point data."""
    from estcal.io.robotfile import load_robot

    k, _, has_quat = count_point_columns(data)
    n_markers = None
    if k and not has_quat:
        n_markers = points if points is not None else k
        if n_markers > k:
            fail(f"{data}: --points {points} but the file has {k} points (x1..z{k})")
    elif points is not None:
        fail(f"{data}: --points needs x1,y1,z1 … columns")
    try:
        return load_robot(spec, root=root, tip=tip, n_markers=n_markers), n_markers
    except (ValueError, FileNotFoundError, KeyError) as exc:
        fail(str(exc))


def save_model_or_fail(result, path, robot_spec) -> str:
    """``result.save_model(path)`` (calibration or diagnosis) with the robot spec in the
    provenance; a clear error on failure. Returns the line to print."""
    try:
        result.save_model(path, {"robot": robot_spec})
    except (ValueError, OSError) as exc:
        fail(f"--save-model {path}: {exc}")
    return f"wrote {path} (load it with --robot {path})"
