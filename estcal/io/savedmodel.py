"""Saved models: the identified robot as a robot file with a ``calibration:`` block.

A saved model is the hand-off format of a calibration (``estcal calibrate
--save-model``, :meth:`CalibrationResult.save_model`) or of a diagnosis
(``estcal diagnose --save-model``, :meth:`DiagnosisResult.save_model`): an
ordinary robot file (``estcal_robot: 1``) whose parameters are at their
estimates — named effects included — plus a ``calibration:`` block saying how
it was obtained (docs/robot-file.md, "Saved models")::

    calibration:
      estcal_version: 0.1.0
      date: '2026-11-25T09:14:03+00:00'      # UTC, ISO 8601
      estimator: lm
      data: [{file: train.csv, sha256: 9f2c…, n_poses: 50, role: train},
             {file: valid.csv, sha256: 41aa…, n_poses: 50, role: validation}]
      free: [base_tx, …]                     # names, in the order of covariance
      covariance: [[…], …]                   # SI units (m, rad, 1)
      noise: {position: 5.0e-05, orientation: 0.0005, scalar: 5.0e-05, known: false}
      sigma0: 1.02
      rmse_mm: {train: {before: 4.2, after: 0.078}, validation: [{file: valid.csv, before: 4.1, after: 0.097}]}

``free`` and ``covariance`` are what the compensation and export helpers read
(:func:`estcal.io.robotfile.calibration_covariance`). Loading a saved model
(``--robot model.yaml`` or :func:`estcal.load_robot`) gives the fitted robot:
``estcal fk`` with it reproduces the fit's predictions (for a diagnosed model,
the data preparation the diagnosis applied — session time, approach directions
from the posture order — is recorded in ``data_preparation`` and re-applied by
:func:`estcal.io.prepare.prepare_data`).
"""
from __future__ import annotations

import functools
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from estcal.base.version import __version__

from .integrity import file_sha256
from .robotfile import _plain, load_robot, save_robot

__all__ = ["write_saved_model", "robot_covariance", "design_values", "file_sha256", "data_entry", "calibration_block",
           "save_calibration", "save_diagnosis"]


def design_values(robot):
    """The parameter vector of a saved model with its joint model (geometry, base, tool, offsets,
    gains) back at the *design* values of the robot it was calibrated from (``calibration.robot``),
    markers and effects at their estimates; ``None`` for a robot that is not a saved model, or
    whose design robot cannot be loaded or has other parameters.

    Structural identifiability belongs to the design: at a calibrated geometry, zero lengths and
    right angles are off by the calibration errors, GECARO's priority rules change and regrouped
    parameters become numerically separable with |R_jj| ~ 1e-10 (PUMA 560: 34 "identifiable"
    parameters, condition number 1e16, instead of 30 and 62).
    """
    import numpy as np

    cal = robot.meta.get("calibration") or {}
    spec = cal.get("robot")
    if not isinstance(spec, str) or not spec:
        return None
    try:
        mtime = Path(spec).stat().st_mtime_ns if Path(spec).is_file() else None
    except OSError:
        mtime = None
    design = _design(spec, cal.get("root"), cal.get("tip"), mtime)
    if design is None:
        return None
    nominal_names, nominal_values = design
    pv = robot.params
    names = [n for n, k in zip(pv.names, pv.kinds) if k in ("geometric", "base", "tool", "offset", "gain")]
    index = {n: i for i, n in enumerate(nominal_names)}
    if not names or not all(n in index for n in names):
        return None
    theta = np.array(pv.values, float)
    theta[pv.indices(names)] = nominal_values[[index[n] for n in names]]
    return theta


@functools.lru_cache(maxsize=16)
def _design(spec, root, tip, mtime):
    """``(names, values)`` of the design robot ``spec`` (cached per file version: a URDF takes
    ~0.1 s to parse and the identifiability helpers ask once per call)."""
    try:
        nominal = load_robot(spec, root=root, tip=tip)
    except Exception:  # noqa: BLE001 - a design that cannot be loaded: analyse as given
        return None
    values = design_values(nominal) if nominal.meta.get("calibration") else None
    if values is None:
        values = nominal.params.values
    values = np.array(values, float)
    values.flags.writeable = False  # shared by the cache
    return tuple(nominal.params.names), values


def data_entry(data, role: str) -> dict:
    """``{file, sha256, n_poses, role}`` of a dataset; ``file``/``sha256`` are None for
    in-memory data (no file to hash)."""
    path = getattr(data, "path", None)
    p = Path(path) if path else None
    ok = p is not None and p.is_file()
    return {"file": str(path) if path else None, "sha256": file_sha256(p) if ok else None,
            "n_poses": int(data.n), "role": role}


def _rmse_row(acc: dict, path=None) -> dict:
    """``{before, after}`` RMSE (mm, and mrad for pose data) of one accuracy entry."""
    b, a = acc.get("before", {}), acc.get("after", {})
    row = {} if path is None else {"file": path}
    row.update(before=b.get("rmse_mm"), after=a.get("rmse_mm"))
    if a.get("rmse_mrad") is not None:
        row.update(before_mrad=b.get("rmse_mrad"), after_mrad=a.get("rmse_mrad"))
    return row


def calibration_block(*, estimator: str, train, validation=(), free=(), covariance=None, noise=None,
                      sigma0=None, rmse_mm=None, **extra) -> dict:
    """The ``calibration:`` mapping of a saved model (plain data, SI units).

    ``train`` / ``validation``: datasets (hashed when they come from files); ``free`` and
    ``covariance``: the estimated parameters and their covariance in that order (omitted when
    the covariance is not finite, e.g. an unidentifiable set); ``noise``: a NoiseModel or dict;
    ``extra``: further keys (``level``, ``options``, ``causes`` …) written as given.
    """
    trains = train if isinstance(train, (list, tuple)) else [train]
    # stacked sessions (estcal.sessions.data.stack_sessions) are listed file by file
    trains = [s for d in trains for s in (getattr(d, "sessions", None) or [d])]
    out: dict = {"estcal_version": __version__,
                 "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                 "estimator": estimator,
                 "data": [data_entry(d, "train") for d in trains] + [data_entry(d, "validation")
                                                                      for d in validation]}
    C = None if covariance is None else np.asarray(covariance, float)
    if C is not None and len(free) and np.all(np.isfinite(C)):
        out["free"] = [str(n) for n in free]
        out["covariance"] = C.tolist()
    elif len(free):
        out["free_not_saved"] = "covariance not finite (parameters not identifiable); free/covariance omitted"
    if noise is not None:
        nz = noise.to_dict() if hasattr(noise, "to_dict") else dict(noise)
        out["noise"] = {k: (bool(v) if k == "known" else float(v)) for k, v in nz.items()}
    if sigma0 is not None:
        out["sigma0"] = float(sigma0)
    if rmse_mm is not None:
        out["rmse_mm"] = rmse_mm
    out.update(extra)
    return out


def _finite_or_none(x):
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


def write_saved_model(robot, block: dict, path) -> Path:
    """Write ``robot`` with the ``calibration:`` mapping ``block`` (:func:`calibration_block`) as a robot file."""
    out = robot.copy()  # shallow: the caller's robot keeps its own meta
    out.meta = dict(robot.meta)
    out.meta["calibration"] = _finite_or_none(_plain(block))
    return save_robot(out, path, checksum=True)  # a changed digit or a cut file is refused on loading


def save_calibration(result, path, provenance: dict | None = None) -> Path:
    """Write a :class:`~estcal.estimate.result.CalibrationResult` as a saved model."""
    problem = result.problem
    if problem is None:
        raise ValueError("this CalibrationResult does not know its problem (robot and data); it was not made "
                         "by an estcal estimator — save its robot with estcal.io.robotfile.save_robot")
    robot = result.robot()
    acc = result.accuracy or {}
    rm = {}
    if "train" in acc:
        rm["train"] = _rmse_row(acc["train"])
    if acc.get("validation"):
        rm["validation"] = [_rmse_row(v, v.get("path")) for v in acc["validation"]]
    extra = {k: result.extra[k] for k in ("level", "selection_criterion", "options", "regularize", "measure")
             if k in result.extra}
    if "selection" in result.extra:
        sel = result.extra["selection"]
        extra.setdefault("level", sel.get("level"))
        extra.setdefault("selection_criterion", sel.get("criterion"))
    extra["covariance_source"] = result.covariance_source
    extra["converged"] = bool(result.converged)
    if result.extra.get("left_out"):  # the rows the data screening left out of the fit (not in `train`)
        extra["left_out"] = [{k: r[k] for k in ("file", "line", "kind")} for r in result.extra["left_out"]["rows"]]
    free, C, unknowns = robot_covariance(result)
    if unknowns:
        extra["method_unknowns"] = unknowns
    extra.update(provenance or {})
    block = calibration_block(estimator=result.method, train=[t.data for t in problem.terms],
                              validation=result.validation_data, free=free, covariance=C,
                              noise=problem.terms[0].noise, sigma0=result.sigma0, rmse_mm=rm, **extra)
    return write_saved_model(robot, block, path)


def robot_covariance(result) -> tuple[list, np.ndarray, dict]:
    """``(free, C, unknowns)`` of a :class:`~estcal.estimate.result.CalibrationResult`: the estimated
    robot parameters and their covariance (SI), and ``{name: {estimate, std}}`` of the measurement's
    own unknowns (a plane, a sphere centre …), which are not robot parameters — the covariance kept
    is the robot's part (its marginal)."""
    kinds = dict(zip(result.problem.params.names, result.problem.params.kinds))
    keep = [i for i, n in enumerate(result.names) if kinds.get(n) != "other"]
    unknowns = {result.names[i]: {"estimate": float(result.estimate[i]), "std": float(result.std[i])}
                for i in range(len(result.names)) if i not in keep}
    return [result.names[i] for i in keep], np.asarray(result.covariance, float)[np.ix_(keep, keep)], unknowns


def save_diagnosis(result, path, provenance: dict | None = None) -> Path:
    """Write a :class:`~estcal.discrepancy.result.DiagnosisResult` as a saved model: the diagnosis's model (the
    geometry and the effects it keeps, at the estimate) with its accuracy — the one figure of each question."""
    if result.robot is None:
        raise ValueError("this DiagnosisResult has no robot (it was rebuilt from JSON); run diagnose again")
    m = result.model
    acc = result.accuracy
    rm = {"train": acc.get("train_mm"), "new_postures": {"expected": result.answer.get("expected_mm"),
                                                        "bound95": result.answer.get("bound95_mm"),
                                                        "basis": result.answer.get("basis")}}
    if acc.get("validation"):
        rm["validation"] = [{"file": v["path"], "new_postures": v["rmse_mm"], "n_rows": v["n_new"],
                             "registered": v["registered"]} for v in acc["validation"]]
    prep = m.get("data_preparation") or {}
    extra = {"level": m.get("geometric_level"),
             "causes": [{"effect": c.effect, "joints": list(c.joints),
                         "parameters": {n: {"estimate": v["estimate"], "std": v["std"]}
                                        for n, v in c.parameters.items()},
                         "ln_bf": c.ln_bf, "gain_mm": c.gain_mm} for c in result.causes],
             "verdict": result.verdict,
             "lumped_masses": bool(result.lumped_masses),
             "data_preparation": {"session_time": prep.get("session_time"),
                                  "approach_from_order": bool(prep.get("approach_from_order")),
                                  "time_source": prep.get("time_source", "t column")}}
    extra.update(provenance or {})
    block = calibration_block(estimator="sparse Bayes (diagnose: geometry + the effects the model keeps)",
                              train=result.train_data if isinstance(result.train_data, list) else
                              [result.train_data], validation=result.validation_data,
                              free=result.covariance_names, covariance=result.covariance, noise=result.noise,
                              sigma0=result.sigma0, rmse_mm=rm, **extra)
    return write_saved_model(result.robot, block, path)
