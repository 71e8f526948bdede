"""Report of ``estcal online``: estimate ± σ after every row and the innovation tests."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from estcal.base.tables import Table, parameter_table

from .html import Report

__all__ = ["online_report"]

_TEST_ROWS = (("n_steps", "rows tested (after burn-in)"), ("burn_in", "burn-in rows"),
              ("nis_mean_per_row", "NIS per measured row (expected 1)"), ("nis_p_value", "NIS p-value (two-sided)"),
              ("nis_outside_95", "fraction of rows outside the 95 % NIS bounds"),
              ("mean_chi2", "zero-mean χ²"), ("mean_p_value", "zero-mean p-value"),
              ("ljung_box", "Ljung–Box (whiteness)"), ("ljung_box_p_value", "Ljung–Box p-value"),
              ("fires", "model rejected"))


def online_report(folder, names, nominal, trace_estimate, trace_std, nis, dims, tests: dict, *, unit,
                  title: str = "estcal online", result_dict=None) -> Report:
    """Write the report of a row-by-row calibration into ``folder``.

    Parameters
    ----------
    names, nominal : free parameters and their initial values (SI).
    trace_estimate, trace_std : (T, p) estimate and std after each row (SI), as the filter produced them.
    nis, dims : (T,) NIS of each row's innovation and its dimension (the filter's monitor).
    tests : the innovation tests (``InnovationTests.to_dict()``, or ``{"error": msg}``).
    unit : ``unit(name) -> (unit, factor)`` display units.
    """
    from estcal.plots.online import online_history_figure

    X = np.asarray(trace_estimate, float)
    S = np.asarray(trace_std, float)
    nominal = np.asarray(nominal, float)
    us = [unit(n) for n in names]
    f = np.array([k for _, k in us])
    rep = Report(folder, title, subtitle=f"{len(X)} rows, {len(names)} free parameters")
    rep.heading("Final estimate")
    final = SimpleNamespace(names=list(names), nominal=nominal, estimate=X[-1], std=S[-1])
    rep.table(parameter_table(final, unit, title="estimate after the last row (display units)"))
    rep.heading("Innovation tests")
    verdict = ""
    if "error" in tests:
        rep.text(f"innovation tests not run: {tests['error']}")
    else:
        rep.table(Table("innovation", "innovation tests (after burn-in)", ["statistic", "value"],
                        [[lab, tests.get(k)] for k, lab in _TEST_ROWS]))
        verdict = ("MODEL REJECTED (" + ", ".join(tests.get("failed", [])) + ")") if tests.get("fires") \
            else "innovations consistent with the model"
        from estcal.estimate.innovation import InnovationTests

        cause = InnovationTests(**tests).cause
        if cause:
            rep.text(f"{verdict}: {cause}")
    rows = np.arange(1, len(X) + 1)
    rep.figure("online_history.png",
               online_history_figure(rows, (X - nominal) * f, S * f, list(names), [u for u, _ in us], nis, dims,
                                     burn_in=int(tests.get("burn_in", 0) or 0), verdict=verdict),
               "Estimate − initial value (line) ± σ (band) after each row; last panel: NIS of every row with "
               "its χ² 95 % bounds, rows outside circled, burn-in dashed.")
    if result_dict is not None:
        rep.json("result.json", result_dict, "result.json — the same numbers as estcal online --json")
    rep.write()
    return rep
