"""What every job reads, loaded and checked once: robots, datasets, held-out files, saved models.

The faces pass what the user has at hand — a robot name, robot file, URDF or robot object; a
CSV path or a :class:`~estcal.io.dataset.Dataset` — and get loaded objects back, or a typed
error (:class:`~estcal.base.errors.InputError` and its subclasses, exit code 2 on the command
line; :class:`~estcal.base.errors.NumericalRefusal`, exit code 3) whose message names the file,
line, option or parameter. Problems that do not stop the job are ``EstcalWarning``.
"""
from __future__ import annotations

import contextlib
import numbers
import warnings
from pathlib import Path

from estcal.base.errors import EstcalError, EstcalWarning, InputError, NumericalRefusal

__all__ = ["input_errors", "split_names", "check_input_files", "point_layout", "robot_for_data", "load_datasets",
           "robot_and_data", "check_distinct_poses", "check_held_out", "warn_datasets", "save_model",
           "provenance"]


@contextlib.contextmanager
def input_errors(prefix: str = ""):
    """Bad input reported by a lower layer as a plain ``ValueError`` / ``KeyError`` /
    ``FileNotFoundError`` becomes an :class:`InputError` (``prefix`` + its message); the typed
    errors pass unchanged."""
    try:
        yield
    except EstcalError:
        raise
    except (ValueError, KeyError, FileNotFoundError) as exc:
        text = exc.args[0] if isinstance(exc, KeyError) and exc.args and isinstance(exc.args[0], str) else str(exc)
        raise InputError(f"{prefix}{text}") from exc


def split_names(text: str | None, option: str = "--free") -> list[str] | None:
    """``'a, b,c*'`` → ``['a', 'b', 'c*']`` (None stays None; an empty list is refused)."""
    if text is None:
        return None
    if not isinstance(text, str):
        return list(text)
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise InputError(f"{option} is empty")
    return names


def check_input_files(paths, what: str = "dataset", option: str = "") -> None:
    """Every path must be a readable file — checked before any work, with the message of the input
    layer (:func:`estcal.base.textinput.check_input_file`: folder, missing file, standard input,
    permission): a ``DatasetError`` for datasets. Datasets given as objects are skipped."""
    from estcal.base.textinput import check_input_file
    from estcal.io.dataset import DatasetError

    error = DatasetError if what == "dataset" else InputError
    for p in paths:
        if isinstance(p, (str, Path)):
            try:
                check_input_file(p, what, error)
            except InputError as exc:
                raise error(f"{option} {exc}" if option else str(exc)) from None


def point_layout(data, column_map=None) -> tuple[int, bool]:
    """``(k, has_quaternion)`` of a dataset (path: from its header alone, or from its column map;
    ``k`` numbered points ``x1..zk``, 0 if none). A file that cannot be read as a dataset raises
    ``DatasetError``."""
    from estcal.io.dataset import Dataset, measurement_layout

    if column_map is not None and not isinstance(data, Dataset):
        from estcal.io.columnmap import ColumnMap, load_column_map

        with input_errors():
            cmap = column_map if isinstance(column_map, ColumnMap) else load_column_map(column_map)
        pose = cmap.rpy is not None or cmap.quaternion is not None
        return (0 if pose or len(cmap.points) < 1 else len(cmap.points)), pose
    if isinstance(data, Dataset):
        return (data.n_points if data.kind == "points" else 0), data.kind == "pose"
    k, _, has_quat = measurement_layout(data)
    return k, has_quat


def robot_for_data(robot, data, points: int | None = None, root=None, tip=None, column_map=None):
    """The robot (spec or object) with one unknown marker per measured point of ``data`` (path or
    Dataset; ``points``: keep the first N). Returns ``(robot, n_markers)``; ``n_markers`` is None
    unless the data are point data."""
    from estcal.io.dataset import DatasetError
    from estcal.io.robotfile import load_robot

    if points is not None and (isinstance(points, bool) or not isinstance(points, numbers.Integral) or points < 1):
        raise InputError(f"points must be an integer ≥ 1 (the first N measured points), got {points!r}")
    k, has_quat = point_layout(data, column_map)
    n_markers = None
    if k and not has_quat:
        n_markers = points if points is not None else k
        if n_markers > k:
            raise DatasetError(f"{_where(data)}: --points {points} but the file has {k} points (x1..z{k})")
    elif points is not None:
        raise DatasetError(f"{_where(data)}: --points needs x1,y1,z1 … columns")
    if not isinstance(robot, (str, Path)):
        if n_markers is None or getattr(robot, "n_markers", 0) == n_markers:
            return robot, n_markers
    with input_errors():
        return load_robot(robot, root=root, tip=tip, n_markers=n_markers), n_markers


def _where(data) -> str:
    return str(getattr(data, "where", None) or getattr(data, "path", None) or data)


def load_datasets(items, robot, points: int | None = None, column_map=None) -> list:
    """Datasets of ``items`` (paths or Datasets) for ``robot`` (``points``: the first N measured
    points; ``column_map``: the data's column map, docs/dataset.md)."""
    from estcal.io.dataset import Dataset, load_dataset

    out = []
    for d in items:
        if isinstance(d, Dataset):
            out.append(d.with_points(points) if points is not None and d.n_points > points else d)
            continue
        kw = {"column_map": column_map} if column_map is not None else {}
        with input_errors():
            out.append(load_dataset(d, robot, points=points, **kw))
    return out


def robot_and_data(robot, data, validate=(), points: int | None = None, root=None, tip=None, column_map=None):
    """Resolve ``robot`` (spec or object) and ``data`` / ``validate`` (paths or Datasets) together:
    the robot gets one unknown marker per measured point. Returns ``(robot, dataset, [validation])``."""
    check_input_files([data, *validate])
    rob, k = robot_for_data(robot, data, points, root, tip)
    ds, *vals = load_datasets([data, *validate], rob, k, column_map)
    return rob, ds, vals


def check_distinct_poses(ds, minimum: int = 2) -> None:
    """Refuse (:class:`NumericalRefusal`) a dataset whose rows do not hold ``minimum`` different
    joint configurations: every fit on it would be a fit to one pose, whatever it prints."""
    import numpy as np

    if ds.n == 0 or ds.readings.shape[1] == 0:
        return
    distinct = len(np.unique(ds.readings, axis=0))
    if distinct < minimum:
        what = "all rows have the same joint readings" if distinct == 1 else f"only {distinct} different poses"
        raise NumericalRefusal(f"{ds.where}: {what} ({ds.n} rows, lines {ds.lines[0]}–{ds.lines[-1]}) — a "
                               f"calibration needs at least {minimum} different poses; measure the robot in other "
                               f"configurations")


def check_held_out(fitted, held_out, role: str = "--validate") -> None:
    """Keep fit and validation data apart: refuse a held-out dataset whose every pose is also a
    fitted pose (the same file given twice, or a copy), and warn, naming the lines, when some of
    its poses are (a validation score on them is a training score).

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
            raise InputError(f"{what}: all its {b.n} poses are also in {a.where} (the same measurements, bit for "
                             f"bit) — " + ("give each session's own file" if role == "session" else
                                           "validation must use poses that were not fitted: give a held-out file"))
        at = b.lines if b.lines is not None else np.arange(b.n) + 2  # header is line 1
        lines = ", ".join(str(int(x)) for x in at[idx[:6]]) + (" …" if idx.size > 6 else "")
        warnings.warn(f"{what}: {idx.size} of its {b.n} poses (lines {lines}) are also in {a.where} — "
                      + ("they are counted twice" if role == "session" else
                         "their score is a training score, not a validation"), EstcalWarning, stacklevel=2)


def warn_datasets(datasets) -> None:
    """The loader's warnings of each dataset (``Dataset.warnings``) as ``EstcalWarning``s ``FILE: …``."""
    for d in datasets:
        for w in d.warnings:
            warnings.warn(f"{d.where}: {w}", EstcalWarning, stacklevel=2)


def provenance(robot_spec, root=None, tip=None) -> dict:
    """The robot spec for a saved model's provenance — a file as an absolute path, with the URDF
    chain's ``root``/``tip``, so that the design robot can be found again from anywhere
    (:func:`estcal.io.savedmodel.design_values`)."""
    spec = str(Path(robot_spec).resolve()) if Path(str(robot_spec)).is_file() else str(robot_spec)
    return {"robot": spec, **{k: v for k, v in (("root", root), ("tip", tip)) if v}}


def save_model(result, path, robot_spec, root=None, tip=None) -> Path:
    """``result.save_model(path)`` (calibration or diagnosis) with :func:`provenance`; a failure
    is an ``InputError`` naming ``--save-model``."""
    try:
        result.save_model(path, provenance(robot_spec, root, tip))
    except (ValueError, OSError) as exc:
        raise InputError(f"--save-model {path}: {exc}") from exc
    return Path(path)
