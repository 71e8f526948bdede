"""Report of ``estcal diagnose``: verdict, named causes, RMSE table and the residual figures.

:func:`diagnose_report` writes the residual figures of a diagnosis
(:meth:`estcal.discrepancy.diagnose.DiagnosisResult.figures`), ``diagnosis.json``,
``summary.txt`` and the ``index.html`` that shows them with the tables, like the other
commands' reports.
"""
from __future__ import annotations

from pathlib import Path

from estcal.base.atomic import atomic_write_text
from estcal.base.tables import Table

from .figures import save_figure
from .html import Report

__all__ = ["diagnose_report"]

_CAPTIONS = {
    "partial_residuals.png": "Partial joint residuals δq̂_j of the geometric fit against each joint reading: the "
                             "joint-angle error that would explain the residual (trends: gain / compliance; "
                             "periodic: gear harmonics).",
    "vs_gravity_torque.png": "The same partial residuals against the gravity torque of each joint (a line: "
                             "joint compliance).",
    "partial_residuals_extended.png": "Partial joint residuals after adding the named effect(s).",
    "residual_norm.png": "Per-pose RMS residual of the geometric fit against time and tool position (drift, "
                         "thermal, workspace-dependent effects).",
    "spectrum.png": "Amplitude of the harmonics of the partial joint residuals per joint.",
    "budget.png": "Error budget by posture-grouped cross-validation: registration only, the geometric level, the "
                  "named effects and what is left after the residual Gaussian process, with the repeatability "
                  "floor and the predicted RMSE at new postures (docs/real-data.md).",
}


_DPI = {"budget.png": 110}


def diagnose_report(folder, result, title: str = "estcal diagnose", plots: bool = True) -> Report:
    """The report of a :class:`~estcal.discrepancy.diagnose.DiagnosisResult` in ``folder``: its
    residual figures (``plots``), ``diagnosis.json``, ``summary.txt`` and ``index.html``; the file
    names are in ``result.report_files``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for name, fig in (result.figures().items() if plots else ()):
        save_figure(fig, folder / name, dpi=_DPI.get(name, 90))
        files.append(name)
    result.report_files = files + ["diagnosis.json", "summary.txt"]
    result.to_json(folder / "diagnosis.json")
    atomic_write_text(folder / "summary.txt", str(result) + "\n")
    d = result.to_dict()
    rep = Report(folder, title, subtitle=d["verdict"])
    rep.heading("Named causes")
    rows = []
    for c in d["causes"]:
        for n, v in c["parameters"].items():
            rows.append([c["effect"], ", ".join(c["joints"]) or "whole arm", n, v["estimate"], v["std"],
                         c["delta_bic"], c["p_value"], c["explained_fraction"]])
    if rows:
        rep.table(Table("causes", "named causes (parameter values in SI units)",
                        ["effect", "joints", "parameter", "estimate", "± std", "ΔBIC", "p-value",
                         "explained fraction"], rows))
    else:
        rep.text("No cause named.")
    rep.heading("Geometric vs extended model")
    rm, mx = d["rmse_mm"], d["max_mm"]
    rep.table(Table("rmse", "position error (mm): RMSE on the calibration data, by cross-validation and on the "
                            "validation files; max on calibration / validation",
                    ["model", "RMSE train", "RMSE CV", "RMSE validation", "max train", "max validation"],
                    [[k, rm[k]["train"], rm[k]["cv"], rm[k]["validation"], mx[k]["train"], mx[k]["validation"]]
                     for k in ("geometric", "extended")]))
    rep.text(str(result), pre=True)
    pngs = [f for f in result.report_files if f.endswith(".png")]
    if pngs:
        rep.heading("Residual figures")
    for f in pngs:
        rep.image(f, _CAPTIONS.get(f, ""))
    for f in result.report_files:
        if not f.endswith(".png"):
            rep.link(f, f)
    rep.write()
    return rep
