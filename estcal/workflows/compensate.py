"""Corrected joint commands from a calibrated model: ``estcal compensate`` (docs/compensation.md).

:func:`compensate_file` reads a targets CSV (``x,y,z`` in m, optional ``qw,qx,qy,qz``, and one
column per joint with the nominal program's command), solves
:func:`estcal.compensation.compensate` row by row with the model (effects included, each row's
context columns applied) and returns a :class:`CompensationRun`; :func:`write_commands` writes
the input rows with the joint columns replaced and the predicted error / std / reachable columns
added (the other columns unchanged).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estcal.base.errors import InputError, NumericalRefusal
from estcal.workflows.inputs import check_input_files, input_errors

__all__ = ["CompensationRun", "compensate_file", "write_commands", "output_columns"]


@dataclass
class CompensationRun:
    """A compensated targets file: the :class:`~estcal.compensation.core.CompensationResult`, the
    robot, the dataset read (its readings are the nominal commands), the raw header and rows, and
    the notes on effect inputs that fell back to defaults."""

    result: object
    robot: object
    data: object
    header: list
    rows: list
    notes: list = field(default_factory=list)

    @property
    def shift(self) -> np.ndarray:
        """|compensated − nominal| command per row and joint (rad / m)."""
        return np.abs(self.result.readings - self.data.readings)

    def to_dict(self) -> dict:
        """The JSON of ``--json``: the result's figures, each key naming its unit — ``*_mm`` / ``*_mrad``
        for the errors and stds, ``joint_std_median`` and ``readings_changed_max`` per joint with the
        joint's SI unit in the key (``j1_rad``, ``d3_m``)."""
        d = self.result.to_dict()
        units = {j: "m" if t == "prismatic" else "rad" for j, t in zip(self.robot.joint_names, self.robot.joint_types)}
        if "joint_std_median" in d:
            d["joint_std_median"] = {f"{j}_{units[j]}": v for j, v in d["joint_std_median"].items()}
        d["readings_changed_max"] = {f"{j}_{units[j]}": float(v)
                                     for j, v in zip(self.robot.joint_names, self.shift.max(axis=0, initial=0.0))}
        d["notes"] = list(self.notes)
        return d


def _read_raw(path: Path) -> tuple[list[str], list[list[str]]]:
    """Header and data rows as text (blank lines dropped, as load_dataset does), so that the
    columns other than the joints are written back unchanged."""
    from estcal.base.textinput import read_csv
    from estcal.io.dataset import DatasetError

    table = read_csv(path, "targets", DatasetError)  # the input layer: folder, binary, encoding, delimiter
    return table.header, table.rows


def _check_header(targets, header, robot) -> None:
    for h in header:
        if h.startswith("approach_") and h[len("approach_"):] not in robot.joint_names:
            raise InputError(f"{targets}: column {h!r} names unknown joint {h[len('approach_'):]!r}; the model's "
                             f"joints are {robot.joint_names}")
    if not all(c in header for c in "xyz"):
        raise InputError(f"{targets}: missing target columns x,y,z (m, world frame); the file has columns {header}")
    if any(f"{c}1" in header for c in "xyz"):
        raise InputError(f"{targets}: compensate takes one target point per row (x,y,z [qw,qx,qy,qz]), not "
                         f"x1,y1,z1 …")


def _context_notes(robot, ctx) -> list[str]:
    """Say which effect inputs fall back to their defaults (so the user knows what was assumed)."""
    notes, unknown_approach = [], []
    for eff in robot.effects:
        name = getattr(eff, "name", type(eff).__name__)
        if name == "thermal_expansion" and not robot.n_markers:
            notes.append("thermal_expansion acts on marker points; this model has no markers, so the tool "
                         "origin is compensated without it")
        elif name == "thermal_expansion" and "temperature" not in ctx and "t" not in ctx:
            notes.append("thermal_expansion: no temperature column, ΔT = 0 (the reference temperature)")
        by = getattr(eff, "by", "auto")
        if name == "backlash" and by != "load":
            miss = [j for j in eff.joints if f"approach_{j}" not in ctx]
            if miss and by == "approach":
                unknown_approach += miss
            elif miss:
                notes.append(f"backlash: no approach_<joint> column for {', '.join(miss)}; the gravity side "
                             f"sign(τ) is used")
        if name == "joint_compliance" and "payload" not in ctx:
            notes.append(f"joint_compliance: payload {robot.payload_mass:g} kg from the robot file")
    if unknown_approach:
        notes.append(f"backlash by approach of {', '.join(dict.fromkeys(unknown_approach))}: no approach_<joint> "
                     "column, correction 0 (either side as likely)")
    return list(dict.fromkeys(notes))  # one note per kind (an effect may be added once per joint)


def compensate_file(robot, targets, *, tol_mm: float = 1e-3, tol_mrad: float = 1e-3, position_only: bool = False,
                    rot_weight_m: float = 0.1, max_iter: int = 100) -> CompensationRun:
    """Joint commands at which ``robot`` (a calibrated model: spec or object) reaches each target row
    of the CSV ``targets`` — the job of ``estcal compensate``. Every row starts from its joint
    columns (the nominal command fixes the IK branch)."""
    from estcal.compensation import compensate
    from estcal.effects import effect_context
    from estcal.io.dataset import load_dataset
    from estcal.io.prepare import derive_approach
    from estcal.io.robotfile import load_robot
    from estcal.kinematics.transforms import matrix_to_quat

    check_input_files([targets], "targets")
    for opt, v in (("--tol-mm", tol_mm), ("--tol-mrad", tol_mrad), ("--rot-weight-m", rot_weight_m)):
        if not v > 0:
            raise InputError(f"{opt} must be > 0, got {v:g}")
    with input_errors():
        rb = load_robot(robot)
    header, raw = _read_raw(Path(targets))
    _check_header(targets, header, rb)
    with input_errors():
        ds = load_dataset(targets, rb)
    if ds.kind == "pose" and not position_only:
        tgt = np.c_[ds.p, matrix_to_quat(ds.R)]
    else:
        tgt = ds.p if ds.kind == "pose" else ds.points[:, 0]
    derived = _approach_from_order(rb, ds)
    if derived:
        ds = derive_approach(ds)
    ctx = effect_context(rb, ds)
    layer = (rb.meta.get("calibration") or {}).get("residual_model")
    try:
        if layer:  # the saved residual GP: the calibrated model plus its mean reaches the targets
            from estcal.discrepancy.residual import compensate_with_residual, residual_model_from_dict

            res, _ = compensate_with_residual(rb, residual_model_from_dict(layer), tgt, ds.readings, context=ctx,
                                              tol_mm=tol_mm, tol_mrad=tol_mrad, max_iter=max_iter,
                                              rot_weight_m=rot_weight_m, lines=ds.lines)
        else:
            res = compensate(rb, tgt, ds.readings, context=ctx, tol_mm=tol_mm, tol_mrad=tol_mrad,
                             max_iter=max_iter, rot_weight_m=rot_weight_m, lines=ds.lines)
    except np.linalg.LinAlgError as exc:
        raise NumericalRefusal(f"{targets}: numerical failure in the solve ({exc})") from exc
    except ValueError as exc:
        raise InputError(f"{targets}: {exc}") from exc
    notes = _context_notes(rb, ctx)
    if derived:
        notes.insert(0, f"backlash by approach of {', '.join(derived)}: directions from the rows' order, the "
                        "program's order of motion")
    return CompensationRun(res, rb, ds, header, raw, notes)


def _approach_from_order(robot, ds) -> list[str]:
    """The joints of a backlash by approach whose directions the targets do not record, when the model was
    diagnosed with directions from the acquisition order (its ``data_preparation``): the program's rows are
    then its order of motion, as the measured rows were."""
    prep = (robot.meta.get("calibration") or {}).get("data_preparation") or {}
    if not prep.get("approach_from_order"):
        return []
    joints = [j for e in robot.effects if getattr(e, "by", None) == "approach" for j in e.joints]
    return [j for j in dict.fromkeys(joints) if f"approach_{j}" not in ds.columns and f"approach_{j}" not in ds.context]


def output_columns(res) -> list[str]:
    """The columns :func:`write_commands` adds after the input's."""
    extra = ["predicted_error_mm"] + (["predicted_rot_error_mrad"] if res.rot_error_mrad is not None else [])
    if res.std_mm is not None:
        extra += ["predicted_std_mm"] + (["predicted_rot_std_mrad"] if res.rot_std_mrad is not None else [])
    return extra + ["reachable"]


def write_commands(run: CompensationRun, output, where="targets") -> Path:
    """The input rows with the joint columns replaced by the compensated readings (rad / m) and the
    columns of :func:`output_columns` added, written atomically."""
    from estcal.base.atomic import atomic_write

    res, rb = run.result, run.robot
    jidx = {h: i for i, h in enumerate(run.header)}
    extra = output_columns(res)
    for c in extra:
        if c in jidx:
            raise InputError(f"{where}: already has a column {c!r} (is it a compensate output?)")
    with atomic_write(output, newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(run.header + extra)
        for i, row in enumerate(run.rows):
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
    return Path(output)
