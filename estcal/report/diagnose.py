"""Report of ``estcal diagnose``: the answer, the named causes, the accuracy table and the figures.

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
    "partial_residuals.png": "Partial joint residuals δq̂_j of the model's geometry alone (its effects set to "
                             "zero) against each joint reading: the joint-angle error that would explain the "
                             "residual (trends: gain / compliance; periodic: gear harmonics).",
    "vs_gravity_torque.png": "The same partial residuals against the gravity torque of each joint (a line: "
                             "joint compliance).",
    "partial_residuals_extended.png": "Partial joint residuals of the model, its effects included.",
    "residual_norm.png": "Per-pose RMS residual of the geometry alone against time and tool position (drift, "
                         "thermal, workspace-dependent effects).",
    "spectrum.png": "Amplitude of the harmonics of the partial joint residuals per joint.",
    "budget.png": "The error at new postures by cross-validation: registration only, with the geometry, the "
                  "model (nested) and the model by time-blocked folds, with the expected error and the "
                  "repeatability floor (docs/discrepancy.md).",
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
    rep.heading("How accurate")
    a = d["answer"]
    rows = [["expected at new postures", a["expected_mm"], a["basis"]],
            ["95 % of points within", a["bound95_mm"], ""]]
    rows += [[f"validation {v['path']}", v["rmse_mm"], f"{v['n_new']} new-posture rows"
              + (f"; frame registered on {v['n_seen']} rows" if v["registered"] else "")
              + "".join(f"; {z['joint']}'s zero moved {z['display'][0]:+.1f} ± {z['display'][1]:.1f} {z['display'][2]}"
                        for z in v.get("zeros_moved") or [])]
             for v in d["accuracy"].get("validation", [])]
    rep.table(Table("accuracy", "position error at new postures (mm): one figure per question",
                    ["figure", "RMSE (mm)", "basis"], rows))
    rep.heading("Named causes")
    rows = []
    for c in d["causes"]:
        for n, v in c["parameters"].items():
            rows.append([c["effect"], ", ".join(c["joints"]) or "whole arm", n, v["display"][0], v["display"][1],
                         v["display"][2], c["ln_bf"], f"{c['folds']}/{c['k_folds']}", c["gain_mm"],
                         c["explained_fraction"]])
    if rows:
        rep.table(Table("causes", "named causes",
                        ["effect", "joints", "parameter", "estimate", "± std", "unit", "ln B", "folds",
                         "gain at new postures (mm)", "explained fraction"], rows))
    else:
        rep.text("No cause named.")
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
