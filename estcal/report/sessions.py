"""Report of ``estcal sessions``: population parameters, between-session variation, new sessions."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from estcal.base.tables import Table, parameter_table

from .html import Report

__all__ = ["sessions_report"]


def sessions_report(folder, run, *, unit, title: str = "estcal sessions", result_dict=None) -> Report:
    """Write the report of a several-session fit (:class:`estcal.workflows.sessions.SessionsRun`)
    into ``folder``: the same numbers as the command prints, in display units (``unit(name) ->
    (unit, factor)``), and a figure of the population estimates (change from the initial value ± 2σ)."""
    from estcal.plots.parameters import parameter_figure

    fit = run.fit
    us = [unit(n) for n in fit.names]
    f = np.array([k for _, k in us])
    pv = fit.robot.params
    nominal = np.array([pv.values[pv.index(n)] for n in fit.names])
    rep = Report(folder, title, subtitle=f"{len(run.names)} sessions, {len(fit.names)} free parameters, "
                                         f"{fit.formulation}: {fit.n_iterations} iterations")
    rep.heading("Population parameters")
    population = SimpleNamespace(names=list(fit.names), nominal=nominal, estimate=fit.estimate, std=fit.std)
    rep.table(parameter_table(population, unit, title="population estimate (display units)"))
    rep.figure("parameters.png", parameter_figure(list(fit.names), (fit.estimate - nominal) * f, fit.std * f,
                                                  [u for u, _ in us]),
               "Population estimate − initial value with its ±2σ bar, one panel per unit.")
    rep.heading("Between-session variation (REML)")
    if fit.vary:
        comps = fit.variance_components()
        rep.table(Table("variance", "between-session std of each varying parameter",
                        ["parameter", "std", "± std err", "unit"],
                        [[v["parameter"], v["std"], v["std_err"], v["unit"]] for v in comps]))
        units = {v["parameter"]: v["unit"] for v in comps}
        rep.table(Table("deviations", "each session's deviation (BLUP)", ["session", *[f"{n} ({units[n]})"
                                                                                        for n in fit.vary]],
                        [[s, *[float(x * 1e3) for x in u]] for s, u in zip(fit.sessions, fit.u)]))
    else:
        rep.text("no parameter varies between sessions")
    if run.scores:
        rep.heading("New sessions")
        rep.table(Table("validation", "new sessions against the 95 % prediction ellipsoids",
                        ["file", "RMSE (mm)", "95 % coverage", "binomial band"],
                        [[k, sc["rmse_mm"], sc["coverage"], f"{sc['band'][0]:.2f}–{sc['band'][1]:.2f}"]
                         for k, sc in run.scores.items()]))
    if result_dict is not None:
        rep.json("result.json", result_dict, "result.json — the same numbers as estcal sessions --json")
    rep.write()
    return rep
