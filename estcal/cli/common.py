"""Small helpers shared by the subcommands: failing with a clear message, writing JSON.

Exit codes (docs/reliability.md): 0 success, 2 bad input or usage
(:data:`EXIT_INPUT`), 3 numerical refusal — well-formed input the numbers cannot
answer honestly (:data:`EXIT_REFUSED`, use :func:`refuse`). Errors and warnings
go to stderr, results to stdout.
"""
from __future__ import annotations

from pathlib import Path

import typer

from estcal.base.jsonio import write_json

__all__ = ["fail", "message", "refuse", "warn", "write_json", "count_point_columns", "robot_for_data", "EXIT_INPUT",
           "EXIT_REFUSED", "save_model_or_fail", "check_held_out", "check_input_files",
           "warn_datasets"]

EXIT_INPUT = 2
EXIT_REFUSED = 3


_ON_EXIT: list = []


def on_exit(fn) -> None:
    """Run ``fn()`` when the current subcommand ends, however it ends (a lock to release …);
    :func:`estcal.cli.checks.guard` runs them. Also right for in-process runs (tests, notebooks)
    where the process — and with it what the kernel would release — lives on."""
    _ON_EXIT.append(fn)


def run_exit_hooks() -> None:
    while _ON_EXIT:
        fn = _ON_EXIT.pop()
        try:
            fn()
        except Exception:  # noqa: BLE001 - one failing clean-up must not hide the command's outcome
            pass


def fail(msg, code: int = EXIT_INPUT):
    """Print ``error: msg`` to stderr and exit with ``code`` (no traceback)."""
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def message(exc: BaseException) -> str:
    """The text of an exception for ``fail`` (a KeyError's own quotes removed)."""
    if isinstance(exc, KeyError) and exc.args and isinstance(exc.args[0], str):
        return exc.args[0]
    return str(exc)


def refuse(msg):
    """A numerical refusal: ``error: numerical refusal: msg`` to stderr, exit code 3."""
    fail(f"numerical refusal: {msg}", EXIT_REFUSED)


def warn(msg) -> None:
    """``warning: msg`` to stderr (results stay alone on stdout)."""
    typer.echo(f"warning: {msg}", err=True)


def warn_datasets(datasets) -> None:
    """The loader's warnings of each dataset (``Dataset.warnings``), as ``warning: FILE: …`` on stderr."""
    for d in datasets:
        for w in d.warnings:
            warn(f"{d.where}: {w}")


def count_point_columns(path) -> tuple[int, bool, bool]:
    """(k points x1..zk, has x,y,z, has quaternion) from a CSV header (exits with a
    clear message when the file cannot be read as a dataset)."""
    from estcal.io.dataset import DatasetError, measurement_layout

    try:
        return measurement_layout(path)
    except DatasetError as exc:
        fail(exc)


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


def check_distinct_poses(ds, minimum: int = 2) -> None:
    """Refuse (exit 3) a dataset whose rows do not hold ``minimum`` different joint
    configurations: every fit on it would be a fit to one pose, whatever it prints."""
    import numpy as np

    if ds.n == 0 or ds.readings.shape[1] == 0:
        return
    distinct = len(np.unique(ds.readings, axis=0))
    if distinct < minimum:
        what = "all rows have the same joint readings" if distinct == 1 else f"only {distinct} different poses"
        refuse(f"{ds.where}: {what} ({ds.n} rows, lines {ds.lines[0]}–{ds.lines[-1]}) — a calibration needs "
               f"at least {minimum} different poses; measure the robot in other configurations")


def check_input_files(paths, what: str = "dataset", option: str = "") -> None:
    """Fail (exit 2) unless every path is a readable file — before any work, with the message of
    the input layer (:func:`estcal.base.textinput.check_input_file`: folder, missing file,
    standard input, permission)."""
    from estcal.base.textinput import InputError, check_input_file

    for p in paths:
        try:
            check_input_file(p, what, InputError)
        except InputError as exc:
            fail(f"{option} {exc}" if option else str(exc))


def check_held_out(fitted, held_out, role: str = "--validate") -> None:
    """Keep fit and validation data apart: refuse (exit 2) a held-out dataset whose every
    pose is also a fitted pose (the same file given twice, or a copy), and warn, naming
    the lines, when some of its poses are (a validation score on them is a training score).

    ``fitted``: datasets that enter the fit; ``held_out``: datasets scored only. With
    ``role="session"`` the datasets of ``fitted`` are checked against each other instead
    (two sessions that are one measurement).
    """
    import numpy as np

    from estcal.io.dataset import shared_rows

    pairs = ([(a, b) for i, a in enumerate(fitted) for b in fitted[i + 1:]] if role == "session"
             else [(a, b) for b in held_out for a in fitted])
    for a, b in pairs:
        idx = shared_rows(a, b)
        if idx.size == 0:
            continue
        what = (f"session {b.where}" if role == "session" else f"{role} {b.where}")
        if idx.size == b.n:
            fail(f"{what}: all its {b.n} poses are also in {a.where} (the same measurements, bit for bit) — "
                 + ("give each session's own file" if role == "session" else
                    "validation must use poses that were not fitted: give a held-out file"))
        at = b.lines if b.lines is not None else np.arange(b.n) + 2  # header is line 1
        lines = ", ".join(str(int(x)) for x in at[idx[:6]]) + (" …" if idx.size > 6 else "")
        warn(f"{what}: {idx.size} of its {b.n} poses (lines {lines}) are also in {a.where} — "
             + ("they are counted twice" if role == "session" else "their score is a training score, not a validation"))


def save_model_or_fail(result, path, robot_spec, root=None, tip=None) -> str:
    """``result.save_model(path)`` (calibration or diagnosis) with the robot spec in the
    provenance — a file as an absolute path, with the URDF chain's ``root``/``tip``, so that the
    design robot can be found again from anywhere (:func:`estcal.io.savedmodel.design_values`);
    a clear error on failure. Returns the line to print."""
    spec = str(Path(robot_spec).resolve()) if Path(str(robot_spec)).is_file() else robot_spec
    prov = {"robot": spec, **{k: v for k, v in (("root", root), ("tip", tip)) if v}}
    try:
        result.save_model(path, prov)
    except (ValueError, OSError) as exc:
        fail(f"--save-model {path}: {exc}")
    return f"wrote {path} (load it with --robot {path})"
