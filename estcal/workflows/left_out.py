"""The rows a default calibration left out, and the fit with them (docs/reliability.md, "Gross errors").

``estcal calibrate`` and ``estcal.calibrate`` leave out, by default, the rows that the data screening
of ``estcal check`` flags as defects (:data:`estcal.intake.hygiene.DEFECTS`: readings beyond the joint
limits, outliers of the studentised residual test after a robust fit, swapped or ghost markers, rows
copied bit for bit) and fit the others by the chosen estimator. ``--keep-all`` (``drop_flagged=False``)
fits every row. :func:`left_out_report` says what that choice changed:

* every row left out, by file and line, with the screening's reason and its residual at the fit
  (mm, and mrad for pose data; ``ratio``: over the RMS of the rows kept);
* ``without``: σ0, RMSE on the rows kept and on each validation file of the fit;
* ``with``: the same for plain least squares (``lm``) on every row with the same measure, free set or
  level, selection and noise — what ``--keep-all`` gives with the default estimator — and the largest
  change of a parameter of both fits in standard deviations of the fit (``max_shift_sigma``,
  ``max_shift_parameter``).

It is stored in ``result.extra["left_out"]`` (the JSON's ``left_out``), summarised in one warning and
printed first by ``estcal calibrate`` (:func:`format_left_out`).
"""
from __future__ import annotations

import warnings

import numpy as np

from estcal.base.errors import EstcalWarning

__all__ = ["left_out_report", "format_left_out", "warn_left_out", "LeftOutWarning"]


class LeftOutWarning(EstcalWarning):
    """Rows were left out of a calibration (:func:`warn_left_out`); the command line prints
    :func:`format_left_out` instead."""


def _residuals(robot, theta, ds, rows) -> list[dict]:
    """Residual of each row ``rows`` of ``ds`` at ``theta``: RMS over its points (mm), rotation (mrad)."""
    from estcal.estimate.result import pose_errors

    pos, rot = pose_errors(robot, theta, ds.subset(np.asarray(rows, int)))
    out = []
    for i in range(len(rows)):
        d = {"residual_mm": float(np.sqrt(np.mean(pos[i] ** 2)) * 1e3) if pos is not None else None}
        if rot is not None:
            d["residual_mrad"] = float(rot[i] * 1e3)
        out.append(d)
    return out


def _scores(res, robot, kept, theta=None) -> dict:
    """σ0 and RMSE (mm; mrad for poses) on the rows kept and on each validation file of ``res``."""
    from estcal.estimate.result import accuracy

    theta = res.theta if theta is None else theta
    acc = accuracy(robot, theta, kept)
    out = {"sigma0": float(res.sigma0), "converged": bool(res.converged), "rmse_mm_kept": acc.get("rmse_mm")}
    if "rmse_mrad" in acc:
        out["rmse_mrad_kept"] = acc["rmse_mrad"]
    out["validation_rmse_mm"] = [v.get("after", {}).get("rmse_mm") for v in (res.accuracy or {}).get("validation", [])]
    return out


def left_out_report(left, originals, kept, problem, res, refit) -> dict:
    """What leaving out the rows ``left`` (from :func:`estcal.workflows.check.screen_rows`) changed in the fit
    ``res`` of the rows ``kept`` (module docstring). ``originals``: the datasets before the screening (one per
    session); ``problem``: the fit's problem; ``refit(data)``: plain least squares on ``data`` with the fit's
    free set, noise and validation files (a :class:`~estcal.estimate.result.CalibrationResult`)."""
    from estcal.base.errors import EstcalError

    robot = problem.robot
    rows = []
    for k, ds in enumerate(originals):
        mine = [r for r in left if r["session"] == k]
        if mine:
            for r, e in zip(mine, _residuals(robot, res.theta, ds, [r["row"] for r in mine])):
                rows.append({**{x: r[x] for x in ("file", "line", "kind", "reason")}, **e})
    without = _scores(res, robot, kept)
    for r in rows:
        rms = without["rmse_mm_kept"]
        r["ratio"] = float(r["residual_mm"] / rms) if r["residual_mm"] is not None and rms else None
    out = {"n_rows": int(sum(d.n for d in originals)), "n_left_out": len(rows), "rows": rows, "without": without}
    data = originals[0]
    if len(originals) > 1:
        from estcal.sessions.data import stack_sessions

        data = stack_sessions(originals)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with_all = refit(data)
    except (EstcalError, ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        out["with"] = {"estimator": "lm", "error": " ".join(str(exc).split())[:300]}
        return out
    w = _scores(with_all, robot, kept)
    w["estimator"] = "lm"
    common = [n for n in res.names if n in with_all.names]  # the selection may differ with every row
    if common:
        a = [list(with_all.names).index(n) for n in common]
        b = [list(res.names).index(n) for n in common]
        shift = np.abs(np.asarray(with_all.estimate)[a] - res.estimate[b]) / np.maximum(res.std[b], 1e-300)
        j = int(np.argmax(shift))
        w.update(max_shift_sigma=float(shift[j]), max_shift_parameter=common[j])
    out["with"] = w
    return out


def _rows_text(rows, most: int = 12) -> str:
    """``a.csv line 5, 19; b.csv line 3`` (files in order of appearance)."""
    by = {}
    for r in rows:
        by.setdefault(r["file"], []).append(r["line"])
    parts = []
    for f, lines in by.items():
        shown = ", ".join(str(x) for x in lines[:most]) + (" …" if len(lines) > most else "")
        parts.append(f"{f} line{'s' if len(lines) > 1 else ''} {shown}")
    return "; ".join(parts)


def _fit_text(d) -> str:
    if "error" in d:
        return f"failed ({d['error']})"
    txt = f"σ0 {d['sigma0']:.3g}"
    if d.get("rmse_mm_kept") is not None:
        txt += f", RMSE {d['rmse_mm_kept']:.4g} mm"
        if d.get("rmse_mrad_kept") is not None:
            txt += f" / {d['rmse_mrad_kept']:.4g} mrad"
        txt += " on the rows kept"
    vr = [v for v in d.get("validation_rmse_mm", []) if v is not None]
    if vr:
        txt += f", validation {', '.join(f'{v:.4g}' for v in vr)} mm"
    if not d.get("converged", True):
        txt += " (not converged)"
    return txt


def warn_left_out(rep: dict) -> None:
    """The report in one :class:`LeftOutWarning` (the Python API's signal; the command line prints
    :func:`format_left_out` instead)."""
    kinds = {}
    for r in rep["rows"]:
        kinds[r["kind"]] = kinds.get(r["kind"], 0) + 1
    w = rep.get("with", {})
    moved = f", parameters moved by up to {w['max_shift_sigma']:.3g} σ" if "max_shift_sigma" in w else ""
    warnings.warn(f"{rep['n_left_out']} of {rep['n_rows']} rows left out of the fit, flagged by the data screening "
                  f"({', '.join(f'{n} {k}' for k, n in kinds.items())}): {_rows_text(rep['rows'])}; least squares "
                  f"with them: {_fit_text(w)}{moved} — --keep-all (drop_flagged=False) keeps them",
                  LeftOutWarning, stacklevel=3)


def format_left_out(rep: dict, most: int = 20) -> str:
    """The text block ``estcal calibrate`` prints first: the rows left out, then the fit without and with them."""
    lines = [f"left out: {rep['n_left_out']} of {rep['n_rows']} rows, flagged by the data screening (`estcal check`); "
             f"the fit below is without them, --keep-all fits every row"]
    for r in rep["rows"][:most]:
        res = "—" if r["residual_mm"] is None else f"{r['residual_mm']:.4g} mm"
        if r.get("residual_mrad") is not None:
            res += f" / {r['residual_mrad']:.4g} mrad"
        lines.append(f"  {r['file']} line {r['line']}: residual {res} at this fit — {r['kind']}: {r['reason']}")
    if len(rep["rows"]) > most:
        lines.append(f"  … {len(rep['rows']) - most} more in the JSON (left_out.rows)")
    lines.append(f"  without them (this fit): {_fit_text(rep['without'])}")
    w = rep.get("with", {})
    moved = (f"; parameters differ by up to {w['max_shift_sigma']:.3g} σ ({w['max_shift_parameter']})"
             if "max_shift_sigma" in w else "")
    lines.append(f"  with them (least squares on every row): {_fit_text(w)}{moved}")
    return "\n".join(lines)
